"""diagnostic_msgs/DiagnosticArray <-> plain statuses (name, level, message, values)."""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from msg_adapters.validation import clip

#: levels as ints (the message constants are ``bytes`` of length 1 in Python).
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}
#: longest text of a diagnostic (message, each value)
MAX_TEXT_CHARS = 1000


def _text(value) -> str:
    if isinstance(value, float):
        return f'{value:.6g}'
    if isinstance(value, (list, tuple)):
        return '; '.join(_text(v) for v in value)
    return str(value)


def status_message(name: str, level: int, message: str, values: dict | None = None,
                   hardware_id: str = '') -> DiagnosticStatus:
    """One DiagnosticStatus; ``values`` become KeyValue pairs (numbers formatted, lists joined).

    Every text is cut to :data:`MAX_TEXT_CHARS` (saying its length), so no input can make a
    diagnostic large (a 1 MB frame id was echoed whole, 34 MB/s at 20 Hz)."""
    return DiagnosticStatus(level=bytes([level]), name=clip(name, MAX_TEXT_CHARS),
                            message=clip(message, MAX_TEXT_CHARS),
                            hardware_id=clip(hardware_id, MAX_TEXT_CHARS),
                            values=[KeyValue(key=clip(str(k), MAX_TEXT_CHARS),
                                             value=clip(_text(v), MAX_TEXT_CHARS))
                                    for k, v in (values or {}).items()])


def diagnostics_message(statuses, stamp=None) -> DiagnosticArray:
    """A DiagnosticArray of ``statuses``."""
    msg = DiagnosticArray()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.status = list(statuses)
    return msg


def level_of(status: DiagnosticStatus) -> int:
    """The level of a status as an int (it is a ``bytes`` of length 1 in Python)."""
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def read_statuses(msg: DiagnosticArray) -> dict[str, dict]:
    """``{name: {'level': int, 'message': str, 'values': {key: value}}}``."""
    return {s.name: {'level': level_of(s), 'message': s.message,
                     'values': {kv.key: kv.value for kv in s.values}} for s in msg.status}
