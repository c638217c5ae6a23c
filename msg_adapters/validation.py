"""Header checks shared by the adapters: stamps, frame ids, finite numbers.

Every ``read_*`` adapter raises :class:`InvalidMessage` whose text is the one-line reason the
node puts into its diagnostics and its log.
"""
from __future__ import annotations

import math
import time

from builtin_interfaces.msg import Time


class InvalidMessage(ValueError):
    """A message the node cannot use; ``str(exc)`` is the reason, one line."""

    def __init__(self, reason: str, kind: str = 'invalid'):
        super().__init__(reason)
        self.kind = kind  # short category for counters: not_finite, frame, stamp, ...


def clock_ns(clock) -> int:
    """Now (ns) on an rclpy ROSClock: its ROS time where simulated time is active, else the
    system time, read without rclpy's Time object (8-15 us a call)."""
    return clock.now().nanoseconds if clock.ros_time_is_active else time.time_ns()


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds (>= 0) as ``builtin_interfaces/Time``."""
    return Time(sec=int(ns) // 1_000_000_000, nanosec=int(ns) % 1_000_000_000)


def stamp_to_s(stamp) -> float:
    """``builtin_interfaces/Time`` as seconds (float)."""
    return stamp.sec + stamp.nanosec * 1e-9


def s_to_stamp(t_s: float) -> Time:
    """Seconds (>= 0) as ``builtin_interfaces/Time``, rounded to the nanosecond."""
    ns = int(round(t_s * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_to_ns(stamp) -> int:
    """``builtin_interfaces/Time`` as integer nanoseconds (exact ordering)."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


#: longest user string (frame id, request name, parameter value) echoed into a log line or a
#: diagnostic; longer ones are cut, with their length said.
MAX_ECHO_CHARS = 80


def clip(text: str, limit: int = MAX_ECHO_CHARS) -> str:
    """``text`` cut to ``limit`` characters, saying how long it was: 'aaaa... (1048576 chars)'."""
    text = str(text)
    if len(text) <= limit:
        return text
    return f'{text[:limit]}... ({len(text)} chars)'


def check_frame(header, frame_id: str, what: str) -> None:
    """Raise :class:`InvalidMessage` unless ``header.frame_id`` is ``frame_id`` (the frame id
    received is echoed cut to :data:`MAX_ECHO_CHARS`)."""
    check_frame_id(header.frame_id, frame_id, what)


def check_frame_id(received: str, frame_id: str, what: str) -> None:
    """:func:`check_frame` of a frame id already read from its header."""
    if received != frame_id:
        got = clip(repr(received)) if received else 'an empty frame_id'
        raise InvalidMessage(f'{what} in frame {got}, expected {frame_id!r} (robot.frame_id); '
                             'no transform is applied', 'frame')


def check_finite(values, what: str) -> None:
    """Raise :class:`InvalidMessage` if any of ``values`` is NaN or infinite."""
    if not all(math.isfinite(v) for v in values):
        raise InvalidMessage(f'{what} is not finite: {_fmt(values)}', 'not_finite')


def check_order(stamp_ns: int, last_ns: int | None, what: str) -> None:
    """Raise :class:`InvalidMessage` for a stamp older than the last accepted one."""
    if last_ns is not None and stamp_ns < last_ns:
        raise InvalidMessage(f'{what} stamp {stamp_ns * 1e-9:.6f} s is older than the last '
                             f'accepted one ({last_ns * 1e-9:.6f} s): out of order', 'stamp')


def _fmt(values) -> str:
    return '[' + ', '.join(f'{v:.6g}' for v in values) + ']'
