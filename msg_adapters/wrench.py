"""geometry_msgs/WrenchStamped <-> force (3,) N and moment (3,) N m."""
from __future__ import annotations

from dataclasses import dataclass
from math import isfinite

from geometry_msgs.msg import WrenchStamped

from msg_adapters.validation import check_finite, check_frame_id, check_order, stamp_to_ns


@dataclass(frozen=True)
class WrenchInput:
    """A checked wrench: stamp (ns), force (3,) N, moment (3,) N m about the centroid (tuples
    of floats: the consumers copy them into arrays of their own, one numpy call fewer per
    wrench)."""

    stamp_ns: int
    force_n: tuple
    moment_nm: tuple


def read_wrench(msg: WrenchStamped, frame_id: str,
                last_stamp_ns: int | None = None) -> WrenchInput:
    """Check a wrench message and convert it; raises :class:`InvalidMessage` with the reason.

    Rejected: NaN or infinite values, a frame other than ``frame_id`` (the wrench is taken in
    the robot frame, no transform is applied), a stamp older than ``last_stamp_ns``.
    """
    return check_wrench(*wrench_fields(msg), frame_id, last_stamp_ns)


def wrench_fields(msg: WrenchStamped) -> tuple:
    """(stamp ns, frame id, (fx, fy, fz, mx, my, mz)) of a wrench message, unchecked."""
    w = msg.wrench
    f, m = w.force, w.torque
    header = msg.header
    return stamp_to_ns(header.stamp), header.frame_id, (f.x, f.y, f.z, m.x, m.y, m.z)


def check_wrench(stamp_ns: int, received_frame_id: str, values: tuple, frame_id: str,
                 last_stamp_ns: int | None = None) -> WrenchInput:
    """:func:`read_wrench` of the fields of :func:`wrench_fields` (or the same fields decoded
    from a recording's bytes)."""
    if not all(map(isfinite, values)):       # the common case in one C loop, no generator
        check_finite(values, 'wrench')
    check_frame_id(received_frame_id, frame_id, 'wrench')
    check_order(stamp_ns, last_stamp_ns, 'wrench')
    return WrenchInput(stamp_ns, values[:3], values[3:])


def wrench_message(force_n, moment_nm=(0.0, 0.0, 0.0), frame_id: str = 'world',
                   stamp=None) -> WrenchStamped:
    """A WrenchStamped from arrays (``stamp``: builtin_interfaces/Time, default zero)."""
    msg = WrenchStamped()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    w = msg.wrench
    w.force.x, w.force.y, w.force.z = map(float, force_n)
    w.torque.x, w.torque.y, w.torque.z = map(float, moment_nm)
    return msg
