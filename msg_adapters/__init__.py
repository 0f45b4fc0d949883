"""ROS message adapters for ``rotavg_ros``.

* :mod:`rotavg_ros.msg_adapters.inputs`: duck-typed ``TransformStamped`` / ``Odometry`` (rclpy or
  rosbags) to :class:`~rotavg_ros.app.accumulator.EdgeMeasurement` or
  :class:`~rotavg_ros.app.accumulator.Rejection`. Imports no ROS module.
* :mod:`rotavg_ros.ros.messages`: solve results to rclpy ``TransformStamped`` (node-to-world),
  ``MarkerArray`` and ``DiagnosticArray``. Imported lazily (it needs the rclpy message
  packages), so ``import msg_adapters`` works in a ROS-free environment.

Convention: ``R_i`` is world-to-node; an edge ``(i, j)`` carries ``R_ij ~= R_i R_j^T``, which
is exactly the TF rotation of a transform with ``header.frame_id = i`` and
``child_frame_id = j``.
"""

from rotavg_ros.msg_adapters.inputs import (
    ADAPTER_REASONS,
    NOTE_KEYS,
    AdapterConfig,
    EdgeMeasurement,
    Rejection,
    edge_from_message,
    edge_from_odometry,
    edge_from_transform,
    rotation_weight_from_covariance,
)

__all__ = [
    "ADAPTER_REASONS",
    "NOTE_KEYS",
    "AdapterConfig",
    "EdgeMeasurement",
    "Rejection",
    "edge_from_message",
    "edge_from_odometry",
    "edge_from_transform",
    "rotation_weight_from_covariance",
]
