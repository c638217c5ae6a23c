"""CDR bytes of rclpy messages exactly as a DDS publisher sends them (:func:`serialize`)."""
from __future__ import annotations

_CDR_SIZES = {
    'boolean': 1, 'octet': 1, 'char': 1, 'int8': 1, 'uint8': 1, 'wchar': 2,
    'int16': 2, 'uint16': 2, 'short': 2, 'unsigned short': 2,
    'int32': 4, 'uint32': 4, 'long': 4, 'unsigned long': 4, 'float': 4,
    'int64': 8, 'uint64': 8, 'long long': 8, 'unsigned long long': 8, 'double': 8,
}


class _Unsized(Exception):
    """A field whose CDR layout is not worked out here (wide strings, long double)."""


def serialize(message) -> bytes:
    """CDR bytes of an rclpy message exactly as a DDS publisher sends them.

    ``rclpy.serialization.serialize_message`` (rmw_fastrtps, Jazzy) returns the *estimated*
    size: bytes of uninitialised memory after the message where it holds an empty sequence of
    8-byte numbers (``JointState.velocity``), and uninitialised alignment padding. ``rosbags``
    rejects such a message ("CDR message size mismatch") and files would differ run to run.
    Here the buffer is cut to the message's CDR length and the padding zeroed, which is what
    arrives through DDS. Types with wide strings are returned as rclpy gives them.
    """
    from rclpy.serialization import serialize_message

    raw = serialize_message(message)
    pads: list = []
    try:
        end = 4 + _cdr_struct(message, 0, pads)   # 4: the encapsulation header
    except _Unsized:
        return raw
    if end > len(raw):   # never cut into the message itself
        return raw
    data = bytearray(raw[:end])
    for start, stop in pads:
        data[4 + start:4 + stop] = bytes(stop - start)
    return bytes(data)


def _cdr_align(pos: int, size: int, pads: list) -> int:
    aligned = -(-pos // size) * size
    if aligned > pos:
        pads.append((pos, aligned))
    return aligned


def _cdr_struct(message, pos: int, pads: list) -> int:
    fields = message.get_fields_and_field_types()
    if not fields:   # an empty message carries one uint8 ("structure_needs_at_least_one_member")
        return pos + 1
    for name, slot in zip(fields, message.SLOT_TYPES):
        pos = _cdr_field(getattr(message, name), slot, pos, pads)
    return pos


def _cdr_field(value, slot, pos: int, pads: list) -> int:
    """End of a field starting at ``pos`` (offsets from the start of the CDR data)."""
    from rosidl_parser import definition as d

    if isinstance(slot, d.BasicType):
        size = _CDR_SIZES.get(slot.typename)
        if size is None:
            raise _Unsized(slot.typename)
        return _cdr_align(pos, size, pads) + size
    if isinstance(slot, d.AbstractWString):
        raise _Unsized('wstring')
    if isinstance(slot, d.AbstractString):
        return _cdr_align(pos, 4, pads) + 4 + len(value.encode('utf-8')) + 1
    if isinstance(slot, d.NamespacedType):
        return _cdr_struct(value, pos, pads)
    if isinstance(slot, d.AbstractSequence):
        pos = _cdr_align(pos, 4, pads) + 4
    elif not isinstance(slot, d.Array):
        raise _Unsized(type(slot).__name__)
    count = len(value)
    if count == 0:
        return pos
    item = slot.value_type
    if isinstance(item, d.BasicType):
        size = _CDR_SIZES.get(item.typename)
        if size is None:
            raise _Unsized(item.typename)
        return _cdr_align(pos, size, pads) + count * size
    for element in value:
        pos = _cdr_field(element, item, pos, pads)
    return pos
