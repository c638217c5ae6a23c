"""geometry_msgs/PoseStamped <-> position (3,) m and quaternion (4,) qx qy qz qw."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseStamped

from msg_adapters.validation import (InvalidMessage, check_finite, check_frame_id, check_order,
                                     stamp_to_ns)


@dataclass(frozen=True)
class PoseInput:
    """A checked pose: stamp (ns), position (3,) m, unit quaternion (4,) qx qy qz qw."""

    stamp_ns: int
    position_m: np.ndarray
    quaternion: np.ndarray


def read_pose(msg: PoseStamped, frame_id: str, quaternion_tolerance: float = 1e-3,
              last_stamp_ns: int | None = None) -> PoseInput:
    """Check a pose message and convert it; raises :class:`InvalidMessage` with the reason.

    Rejected: a frame other than ``frame_id``, a stamp older than ``last_stamp_ns``, NaN or
    infinite values, a quaternion whose norm is off 1 by more than ``quaternion_tolerance``
    (within it the quaternion is normalised).
    """
    return check_pose(*pose_fields(msg), frame_id, quaternion_tolerance, last_stamp_ns)


def pose_fields(msg: PoseStamped) -> tuple:
    """(stamp ns, frame id, (x, y, z, qx, qy, qz, qw)) of a pose message, unchecked."""
    p, q = msg.pose.position, msg.pose.orientation
    return (stamp_to_ns(msg.header.stamp), msg.header.frame_id,
            (p.x, p.y, p.z, q.x, q.y, q.z, q.w))


def check_pose(stamp_ns: int, received_frame_id: str, values: tuple, frame_id: str,
               quaternion_tolerance: float = 1e-3,
               last_stamp_ns: int | None = None) -> PoseInput:
    """:func:`read_pose` of the fields of :func:`pose_fields` (or the same fields decoded from
    a recording's bytes)."""
    position, quaternion = values[:3], values[3:]
    check_finite(position, 'pose position')
    check_finite(quaternion, 'pose orientation')
    norm = math.sqrt(sum(v * v for v in quaternion))
    if abs(norm - 1.0) > quaternion_tolerance:
        raise InvalidMessage(f'pose orientation is not a unit quaternion: norm {norm:.6g} '
                             f'(tolerance {quaternion_tolerance:g})', 'quaternion')
    check_frame_id(received_frame_id, frame_id, 'pose')
    check_order(stamp_ns, last_stamp_ns, 'pose')
    return PoseInput(stamp_ns, np.array(position), np.array(quaternion) / norm)


def pose_message(position_m, quaternion=(0.0, 0.0, 0.0, 1.0), frame_id: str = 'world',
                 stamp=None) -> PoseStamped:
    """A PoseStamped from arrays (``stamp``: builtin_interfaces/Time, default zero)."""
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    return fill_pose(msg, position_m, quaternion, stamp)


def fill_pose(msg: PoseStamped, position_m, quaternion, stamp=None) -> PoseStamped:
    """Write a pose (and ``stamp`` unless None) into an existing message (reused per topic)."""
    if stamp is not None:
        msg.header.stamp = stamp
    p = msg.pose.position
    p.x, p.y, p.z = float(position_m[0]), float(position_m[1]), float(position_m[2])
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = (float(quaternion[0]), float(quaternion[1]), float(quaternion[2]),
                          float(quaternion[3]))
    return msg
