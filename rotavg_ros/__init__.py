"""rotavg_ros: filtered-DMF multiple rotation averaging for ROS 2.

Conventions throughout: ``R_i`` is the world-to-node rotation of node i and an edge
``(i, j)`` carries ``R_ij ~= R_i R_j^T`` (the orientation of frame j expressed in frame i).
"""

__version__ = "0.1.0"
