"""ament_python setup for rotavg_ros (also a plain pip-installable package)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "rotavg_ros"
# The top-level folder msg_adapters/ installs as rotavg_ros.msg_adapters (no generic
# top-level module in site-packages).
PACKAGES = [*find_packages(include=[PACKAGE, f"{PACKAGE}.*"]), f"{PACKAGE}.msg_adapters"]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=PACKAGES,
    package_dir={f"{PACKAGE}.msg_adapters": "msg_adapters"},
    package_data={f"{PACKAGE}.ros": ["fastdds_profile.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["numpy", "scipy", "torch", "rosbags", "mcap"],
    extras_require={"bench": ["pycolmap", "gtsam", "matplotlib"]},
    zip_safe=True,
    maintainer="rotavg_ros maintainers",
    maintainer_email="rotavg@example.com",
    description="Filtered-DMF multiple rotation averaging for ROS 2 Jazzy",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "rotavg = rotavg_ros.cli:run",
            "rotavg_node = rotavg_ros.ros.node:main",
        ],
    },
)
