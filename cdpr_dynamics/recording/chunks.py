"""MCAP files chunk by chunk: the list of chunks, each chunk's messages, damage kept local.

:func:`layout` finds a file's chunks from its chunk index, or by a linear scan where the file has
no summary (a killed recorder) or a damaged one; the scan steps over unreadable bytes to the
next chunk record whose header is consistent. :func:`read_chunk` decompresses one chunk, checks
its CRC and splits its records; a damaged chunk raises :class:`ChunkDamage` and costs that chunk
only. Records are parsed with ``struct`` straight from the chunk's bytes (the ``mcap`` library's
record objects cost several microseconds a message).
"""
from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass, field

from mcap import stream_reader as mcap_stream   # its zstandard and lz4 (None if missing)
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Metadata, Schema

MAGIC = b'\x89MCAP0\r\n'
OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06
OP_METADATA, OP_DATA_END = 0x0C, 0x0F
_OPCODES = frozenset(range(0x01, 0x10))
_RECORD = struct.Struct('<BQ')
_CHUNK_HEAD = struct.Struct('<QQQII')    # start, end, uncompressed size, CRC, compression length
_MESSAGE = struct.Struct('<HIQQ')        # channel, sequence, log time, publish time
_COMPRESSIONS = ('', 'zstd', 'lz4')
_SCAN_BLOCK = 1 << 20
_ERRORS = (McapError, struct.error, ValueError, zlib.error, KeyError, EOFError,
           UnicodeDecodeError)


class ChunkDamage(ValueError):
    """A chunk that cannot be read; the message says why (one line)."""


@dataclass(frozen=True)
class ChunkRef:
    """Where a chunk record is: its number in file order, offset and record length (bytes),
    and the log-time range its header states (ns)."""

    number: int
    offset: int
    length: int
    start_ns: int
    end_ns: int


@dataclass
class Layout:
    """What :func:`layout` finds: chunks in file order, the schemas, channels and metadata
    records known before reading the chunks (all of them from a summary; those outside chunks
    from a scan), and the damage met (one line each)."""

    indexed: bool                    # chunks from a valid chunk index
    chunks: list = field(default_factory=list)
    schemas: dict = field(default_factory=dict)
    channels: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    statistics: object = None
    damage: list = field(default_factory=list)
    cut_at: int | None = None        # offset of the record a cut file ends inside


@dataclass
class ChunkContent:
    """The records of one chunk: messages as parallel lists, in file order, and the schemas
    and channels the chunk defines."""

    channel_ids: list
    log_times: list
    publish_times: list
    data: list
    schemas: list
    channels: list


def _size(stream) -> int:
    stream.seek(0, io.SEEK_END)
    return stream.tell()


def _read_at(stream, offset: int, n: int) -> bytes:
    stream.seek(offset)
    return stream.read(n)


def _chunk_header_ok(stream, offset: int, length: int, head: bytes | None = None) -> bool:
    """A chunk record at ``offset`` of ``length`` content bytes whose inner lengths add up."""
    head = head if head is not None else _read_at(stream, offset + 9, _CHUNK_HEAD.size + 4)
    if len(head) < _CHUNK_HEAD.size:
        return False
    _, _, _, _, clen = _CHUNK_HEAD.unpack_from(head)
    if clen > 4:
        return False
    rest = _read_at(stream, offset + 9 + _CHUNK_HEAD.size, clen + 8)
    if len(rest) < clen + 8:
        return False
    try:
        compression = rest[:clen].decode('ascii')
    except UnicodeDecodeError:
        return False
    (records,) = struct.unpack_from('<Q', rest, clen)
    return (compression in _COMPRESSIONS
            and _CHUNK_HEAD.size + clen + 8 + records == length)


def _ref(stream, number: int, offset: int, length: int) -> ChunkRef:
    start, end, _, _, _ = _CHUNK_HEAD.unpack(_read_at(stream, offset + 9, _CHUNK_HEAD.size))
    return ChunkRef(number, offset, length, start, end)


def _from_summary(stream, size: int) -> Layout | None:
    """The layout from the summary, None where it is missing, unreadable or points elsewhere
    than at chunk records (the damage is then named by the caller's scan)."""
    if size < 2 * len(MAGIC) + 29 or _read_at(stream, size - len(MAGIC), 8) != MAGIC:
        return None
    footer = _read_at(stream, size - len(MAGIC) - 29, 29)
    if footer[0] != OP_FOOTER:
        return None
    summary_start, _, crc = struct.unpack_from('<QQI', footer, 9)
    if summary_start and crc:
        if not 0 < summary_start < size - len(MAGIC) - 29:
            raise ValueError(f'summary start {summary_start} is outside the file')
        summary = _read_at(stream, summary_start, size - len(MAGIC) - 29 - summary_start)
        if zlib.crc32(footer[:-4], zlib.crc32(summary)) != crc:
            raise ValueError('summary CRC mismatch')
    stream.seek(0)
    summary = SeekingReader(stream, validate_crcs=True).get_summary()
    if summary is None:
        return None
    out = Layout(True, schemas=dict(summary.schemas), channels=dict(summary.channels),
                 statistics=summary.statistics)
    indexes = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    for number, index in enumerate(indexes):
        offset, length = index.chunk_start_offset, index.chunk_length
        head = _read_at(stream, offset, 9)
        if (len(head) != 9 or offset + length > size
                or _RECORD.unpack(head) != (OP_CHUNK, length - 9)
                or not _chunk_header_ok(stream, offset, length - 9)):
            return None
        out.chunks.append(_ref(stream, number, offset, length))
    if summary.statistics and summary.statistics.chunk_count != len(out.chunks):
        return None
    stream.seek(0)
    for record in SeekingReader(stream).iter_metadata():
        out.metadata[record.name] = dict(record.metadata)
    return out


def _find_chunk(stream, start: int, size: int) -> int | None:
    """Offset of the next chunk record at or after ``start`` whose header is consistent."""
    position = start
    while position < size:
        block = _read_at(stream, position, _SCAN_BLOCK + 9)
        at = block.find(bytes([OP_CHUNK]))
        while 0 <= at < _SCAN_BLOCK:
            offset = position + at
            if at + 9 <= len(block):
                _, length = _RECORD.unpack_from(block, at)
                if offset + 9 + length <= size and _chunk_header_ok(stream, offset, length):
                    return offset
            at = block.find(bytes([OP_CHUNK]), at + 1)
        position += _SCAN_BLOCK
    return None


def _scan(stream, size: int, damage: list) -> Layout:
    """The layout by reading record headers front to back (chunk bodies are skipped);
    unreadable stretches are stepped over to the next consistent chunk record."""
    out = Layout(False, damage=damage)
    position, previous, previous_checked = len(MAGIC), None, True
    while position + 9 <= size:
        head = _read_at(stream, position, 9)
        opcode, length = _RECORD.unpack(head)
        end = position + 9 + length
        sound = opcode in _OPCODES and end <= size
        if sound and opcode == OP_CHUNK:
            sound = _chunk_header_ok(stream, position, length)
        if not sound:
            if opcode == 0 and not any(_read_at(stream, position, 4096)):
                damage.append(f'zeros from byte {position} to the end (the file was '
                              'preallocated or cut)')   # a cut file: nothing more to find
                break
            restart = position + 1 if previous_checked or previous is None else previous + 1
            found = _find_chunk(stream, restart, size)
            if found is None and opcode in _OPCODES and end > size:
                out.cut_at = position    # a file cut short (a killed writer): not damage
                break
            stop = found if found is not None else size
            damage.append(f'bytes {restart}-{stop} unreadable (a damaged record; what it held '
                          'is lost)' + ('' if found is not None else ', nothing readable after '
                                        'them'))
            if found is None:
                break
            position, previous, previous_checked = found, None, True
            continue
        if opcode == OP_CHUNK:
            out.chunks.append(_ref(stream, len(out.chunks), position, 9 + length))
        elif opcode in (OP_SCHEMA, OP_CHANNEL, OP_METADATA):
            try:
                record = _record(opcode, _read_at(stream, position + 9, length))
            except _ERRORS:
                record = None    # a definition also sits in the summary, if any
            if isinstance(record, Schema):
                out.schemas[record.id] = record
            elif isinstance(record, Channel):
                out.channels[record.id] = record
            elif isinstance(record, Metadata):
                out.metadata[record.name] = dict(record.metadata)
        elif opcode in (OP_DATA_END, OP_FOOTER):
            break
        previous, previous_checked = position, opcode == OP_CHUNK
        position = end
    return out


def _record(opcode: int, content: bytes):
    stream = ReadDataStream(io.BytesIO(content))
    if opcode == OP_SCHEMA:
        return Schema.read(stream)
    if opcode == OP_CHANNEL:
        return Channel.read(stream)
    return Metadata.read(stream)


def layout(stream) -> Layout:
    """Chunks, definitions and metadata of an MCAP file (``stream`` opened for reading, its
    magic already checked): from the summary where it is sound, else by a scan, the reason
    recorded in :attr:`Layout.damage` where the file has a summary that cannot be used."""
    size = _size(stream)
    damage = []
    try:
        found = _from_summary(stream, size)
    except _ERRORS as err:
        found = None
        damage.append(f'summary unreadable ({type(err).__name__}: '
                      f'{str(err).strip().splitlines()[0] if str(err).strip() else ""}); '
                      'chunks found by a scan')
    if found is not None:
        return found
    if not damage and _read_at(stream, size - len(MAGIC), 8) == MAGIC:
        damage.append('the chunk index does not match the chunks (a chunk header or the index '
                      'is damaged); chunks found by a scan')
    return _scan(stream, size, damage)


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == '':
        return data
    if compression == 'zstd':
        if mcap_stream.zstandard is None:
            raise ChunkDamage('zstd compression, but zstandard is not installed')
        return mcap_stream.zstandard.decompress(data, size)
    if mcap_stream.lz4 is None:
        raise ChunkDamage('lz4 compression, but lz4 is not installed')
    return mcap_stream.lz4.decompress(data)


def read_chunk(stream, ref: ChunkRef) -> ChunkContent:
    """The records of one chunk; :class:`ChunkDamage` (one line) where it cannot be read:
    decompression fails, the CRC of its records does not match, a record overruns it."""
    raw = _read_at(stream, ref.offset, ref.length)
    if len(raw) != ref.length:
        raise ChunkDamage(f'chunk {ref.number} at byte {ref.offset}: cut short')
    try:
        _, _, size, crc, clen = _CHUNK_HEAD.unpack_from(raw, 9)
        compression = raw[9 + _CHUNK_HEAD.size:9 + _CHUNK_HEAD.size + clen].decode('ascii')
        begin = 9 + _CHUNK_HEAD.size + clen + 8
        data = _decompress(compression, raw[begin:], size)
    except ChunkDamage as err:
        raise ChunkDamage(f'chunk {ref.number} at byte {ref.offset}: {err}') from None
    except Exception as err:  # noqa: BLE001 - any decompressor failure is a damaged chunk
        raise ChunkDamage(f'chunk {ref.number} at byte {ref.offset}: cannot decompress '
                          f'({type(err).__name__}: {_first(err)})') from None
    if len(data) != size:
        raise ChunkDamage(f'chunk {ref.number} at byte {ref.offset}: {len(data)} bytes of '
                          f'records, its header says {size}')
    if crc and zlib.crc32(data) != crc:
        raise ChunkDamage(f'chunk {ref.number} at byte {ref.offset}: CRC mismatch (its '
                          'records are damaged)')
    return split_records(data, ref)


def _first(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else ''


def split_records(data: bytes, ref: ChunkRef) -> ChunkContent:
    """Split a chunk's decompressed records (``ref`` names the chunk in errors)."""
    out = ChunkContent([], [], [], [], [], [])
    channel_ids, log_times, publish_times, payloads = (
        out.channel_ids, out.log_times, out.publish_times, out.data)
    unpack_record, unpack_message = _RECORD.unpack_from, _MESSAGE.unpack_from
    position, total = 0, len(data)
    try:
        while position < total:
            opcode, length = unpack_record(data, position)
            start = position + 9
            position = start + length
            if position > total:
                raise ChunkDamage('a record overruns the chunk')
            if opcode == OP_MESSAGE:
                channel, _, log_time, publish_time = unpack_message(data, start)
                channel_ids.append(channel)
                log_times.append(log_time)
                publish_times.append(publish_time)
                payloads.append(data[start + 22:position])
            elif opcode == OP_SCHEMA:
                out.schemas.append(_record(opcode, data[start:position]))
            elif opcode == OP_CHANNEL:
                out.channels.append(_record(opcode, data[start:position]))
    except _ERRORS as err:
        raise ChunkDamage(f'chunk {ref.number} at byte {ref.offset}: malformed records '
                          f'({type(err).__name__}: {_first(err)})') from None
    return out
