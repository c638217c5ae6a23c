"""geometry_msgs/Vector3Stamped <-> predicted displacement (3,) m."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Vector3Stamped


def displacement_message(u_m, frame_id: str, stamp) -> Vector3Stamped:
    """The prediction as published: displacement (3,) m in ``frame_id``, input's ``stamp``."""
    msg = Vector3Stamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.vector.x, msg.vector.y, msg.vector.z = (float(u_m[0]), float(u_m[1]), float(u_m[2]))
    return msg


def read_displacement(msg: Vector3Stamped) -> np.ndarray:
    """Displacement (3,) m of a prediction message."""
    v = msg.vector
    return np.array([v.x, v.y, v.z])
