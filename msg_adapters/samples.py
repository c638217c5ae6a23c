"""Measured samples as numbers: geometry_msgs/PoseStamped and sensor_msgs/Imu -> numpy rows."""
from __future__ import annotations

import numpy as np

POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
IMU_TYPE = 'sensor_msgs/msg/Imu'


def stamp_ns(msg) -> int:
    """The header stamp (ns); 0 for an unstamped message."""
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def pose_row(msg) -> np.ndarray:
    """(7,) x y z (m), qx qy qz qw of a PoseStamped."""
    p, q = msg.pose.position, msg.pose.orientation
    return np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=float)


def imu_row(msg) -> np.ndarray:
    """(6,) angular velocity (rad/s) and linear acceleration (m/s^2) of an Imu, turned from
    the IMU's frame into the world frame by its orientation where it reports one (an
    orientation covariance starting with -1, or a zero quaternion, means none)."""
    w, a, q = msg.angular_velocity, msg.linear_acceleration, msg.orientation
    omega = np.array([w.x, w.y, w.z], dtype=float)
    acc = np.array([a.x, a.y, a.z], dtype=float)
    quat = np.array([q.x, q.y, q.z, q.w], dtype=float)
    norm = float(np.linalg.norm(quat))
    if msg.orientation_covariance[0] != -1.0 and abs(norm - 1.0) < 1e-3:
        x, y, z, s = quat / norm
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * s), 2 * (x * z + y * s)],
                        [2 * (x * y + z * s), 1 - 2 * (x * x + z * z), 2 * (y * z - x * s)],
                        [2 * (x * z - y * s), 2 * (y * z + x * s), 1 - 2 * (x * x + y * y)]])
        omega, acc = rot @ omega, rot @ acc
    return np.concatenate([omega, acc])
