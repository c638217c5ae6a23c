"""geometry_msgs/Vector3Stamped <-> predicted displacement (3,) m."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Vector3Stamped


def displacement_message(u_m, frame_id: str, stamp) -> Vector3Stamped:
    """The prediction as published: displacement (3,) m in ``frame_id``, input's ``stamp``."""
    msg = Vector3Stamped()
    msg.header.frame_id = frame_id
    return fill_displacement(msg, u_m, stamp)


def fill_displacement(msg: Vector3Stamped, u_m, stamp) -> Vector3Stamped:
    """Write ``u_m`` and ``stamp`` into an existing message (the node reuses one per topic:
    building a message costs more than filling it)."""
    msg.header.stamp = stamp
    v = msg.vector
    v.x, v.y, v.z = float(u_m[0]), float(u_m[1]), float(u_m[2])
    return msg


def read_displacement(msg: Vector3Stamped) -> np.ndarray:
    """Displacement (3,) m of a prediction message."""
    v = msg.vector
    return np.array([v.x, v.y, v.z])
