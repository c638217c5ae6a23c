"""sensor_msgs/JointState <-> cable lengths (n,) m and tensions (n,) N.

One joint per cable, named ``cable_0`` ... ``cable_{n-1}`` in the order of ``robot.anchors``:
position = cable length (m, chord from attachment to anchor), effort = tension (N); for
``cable_length_offsets`` position = unstretched minus straight length (m), velocity = stretch
rate (m/s), effort = predicted cable force (N).
"""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import JointState


def cable_names(n: int) -> list[str]:
    """Joint names of ``n`` cables."""
    return [f'cable_{i}' for i in range(n)]


def tensions_message(length_m, tension_n, stamp=None, frame_id: str = '') -> JointState:
    """JointState with position = length (m), effort = tension (N); velocity left empty."""
    length = np.asarray(length_m, dtype=float).ravel()
    tension = np.asarray(tension_n, dtype=float).ravel()
    msg = JointState()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.name = cable_names(length.size)
    msg.position = length.tolist()
    msg.effort = tension.tolist()
    return msg


def read_tensions(msg: JointState) -> tuple[np.ndarray, np.ndarray]:
    """(lengths m, tensions N) of a cable_tensions message, in cable order."""
    order = np.argsort([int(name.rsplit('_', 1)[-1]) for name in msg.name])
    return np.asarray(msg.position)[order], np.asarray(msg.effort)[order]


def length_offsets_message(offset_m, stretch_rate_m_s, force_n, stamp=None,
                           frame_id: str = '') -> JointState:
    """``cable_length_offsets``: position = offset (m), velocity = stretch rate (m/s),
    effort = cable force (N), one joint per cable."""
    msg = tensions_message(offset_m, force_n, stamp, frame_id)
    msg.velocity = np.asarray(stretch_rate_m_s, dtype=float).ravel().tolist()
    return msg
