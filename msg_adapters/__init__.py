"""ROS message adapters for ``rotavg_ros``.

* :mod:`rotavg_ros.msg_adapters.inputs`: duck-typed ``TransformStamped`` / ``Odometry`` (rclpy or
  rosbags) to :class:`~rotavg_ros.app.accumulator.EdgeMeasurement` or
  :class:`~rotavg_ros.app.accumulator.Rejection`. Imports no ROS module.
* :mod:`rotavg_ros.msg_adapters.outputs`: solve results to the output messages
  (``TransformStamped`` node-to-world, ``TFMessage``, ``MarkerArray``, ``DiagnosticArray``),
  built once over a message-factory protocol; the back-ends are
  :mod:`rotavg_ros.ros.messages` (rclpy) and :mod:`rotavg_ros.io.bag_messages` (rosbags).
  Imports no ROS module either.

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
