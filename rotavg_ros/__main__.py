"""``python -m rotavg_ros`` runs the ``rotavg`` command line."""

from rotavg_ros.cli import run

run()
