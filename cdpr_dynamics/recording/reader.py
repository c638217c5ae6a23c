"""Read recordings back: :func:`read_messages` and :func:`recording_info`.

Files written here or by ``ros2 bag record -s mcap``; every problem is a
:class:`~cdpr_dynamics.recording.base.RecordingError` with a one-line reason. A complete file is
read through its summary and index; an incomplete one (a recorder killed outright) by a scan of
the chunks written before the cut (:func:`scan`, also the source of
:mod:`~cdpr_dynamics.recording.recovery`).
"""
from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path
from typing import Callable, Iterator, Mapping

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk, StreamReader

from cdpr_dynamics.recording.base import (
    message_class, normalise_topics, RawRecordedMessage, reason, RecordedMessage,
    RecordingError, RecordingInfo, TopicInfo, UndecodableMessage)
from msg_adapters import mcap_schema

MAGIC = b'\x89MCAP0\r\n'


def open_mcap(path) -> tuple[Path, io.BufferedReader]:
    path = Path(path)
    try:
        stream = open(path, 'rb')
    except FileNotFoundError:
        raise RecordingError(f'{path}: no such file') from None
    except IsADirectoryError:
        raise RecordingError(
            f'{path} is a directory; give the .mcap file inside it') from None
    except OSError as err:
        raise RecordingError(f'{path}: cannot read ({err.strerror or err})') from None
    head = stream.read(len(MAGIC))
    if head != MAGIC:
        stream.close()
        what = 'empty' if not head else 'not an MCAP file (bad magic bytes)'
        raise RecordingError(f'{path}: {what}')
    stream.seek(0)
    return path, stream


def _has_footer(stream) -> bool:
    stream.seek(0, io.SEEK_END)
    size = stream.tell()
    if size < 2 * len(MAGIC) + 9 + 20:
        return False
    stream.seek(size - len(MAGIC))
    if stream.read(len(MAGIC)) != MAGIC:
        return False
    stream.seek(size - len(MAGIC) - 29)
    return stream.read(1) == b'\x02'


_INCOMPLETE = ('incomplete MCAP file (no footer or index: the recorder was killed or the file '
               'was cut short; read_messages(..., allow_incomplete=True) reads what survives)')


def _summary(path: Path, stream):
    """The summary (index) of a complete file, None where there is none; corrupt: an error."""
    if not _has_footer(stream):
        return None
    try:
        stream.seek(0)
        return SeekingReader(stream).get_summary()
    except (McapError, struct.error, ValueError, zlib.error) as err:
        raise RecordingError(f'{path}: corrupt MCAP summary ({reason(err)})') from None


def scan(path: Path, stream):
    """Records of a file read front to back, chunks opened; stops quietly where it is cut."""
    reader = StreamReader(stream, emit_chunks=True)
    try:
        for record in reader.records:
            if isinstance(record, Chunk):
                yield record
                yield from breakup_chunk(record, validate_crc=True)
            else:
                yield record
    except EndOfFile:
        return
    except (McapError, struct.error, ValueError, zlib.error) as err:
        raise RecordingError(f'{path}: corrupt MCAP data ({reason(err)})') from None


def recording_info(path) -> RecordingInfo:
    """Header, topics, types, counts and time range of a recording.

    A complete file is described from its summary; an incomplete one (killed recorder) from a
    scan of what survives (``complete=False``). Raises :class:`RecordingError`.
    """
    path, stream = open_mcap(path)
    with stream:
        try:
            stream.seek(0)
            header = SeekingReader(stream).get_header()
        except (McapError, struct.error, ValueError) as err:
            raise RecordingError(f'{path}: corrupt MCAP header ({reason(err)})') from None
        info = RecordingInfo(path=path, complete=False, profile=header.profile,
                             library=header.library, message_count=0, start_ns=0, end_ns=0,
                             chunk_count=0)
        summary = _summary(path, stream)
        if summary is not None:
            info.complete = True
            stats = summary.statistics
            counts = dict(stats.channel_message_counts) if stats else {}
            info.message_count = stats.message_count if stats else 0
            info.start_ns = stats.message_start_time if stats else 0
            info.end_ns = stats.message_end_time if stats else 0
            info.chunk_count = stats.chunk_count if stats else len(summary.chunk_indexes)
            schemas, channels = summary.schemas, summary.channels
            stream.seek(0)
            for record in SeekingReader(stream).iter_metadata():
                info.metadata[record.name] = dict(record.metadata)
        else:
            schemas, channels, counts = {}, {}, {}
            times = []
            stream.seek(0)
            for record in scan(path, stream):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                    times.append(record.log_time)
                elif isinstance(record, Chunk):
                    info.chunk_count += 1
                elif isinstance(record, Metadata):
                    info.metadata[record.name] = dict(record.metadata)
            info.message_count = sum(counts.values())
            info.start_ns = min(times) if times else 0
            info.end_ns = max(times) if times else 0
        for channel_id, channel in channels.items():
            schema = schemas.get(channel.schema_id)
            type_name = schema.name if schema else ''
            if schema:
                info.schema_encodings[type_name] = schema.encoding
            info.topics[channel.topic] = TopicInfo(
                type=type_name, message_count=counts.get(channel_id, 0),
                offered_qos_profiles=channel.metadata.get('offered_qos_profiles', ''),
                type_hash=channel.metadata.get('topic_type_hash', ''))
        return info


def _check_topics(path: Path, wanted: dict, available: Mapping[str, str]) -> set:
    selected = set()
    for name, typ in wanted.items():
        key = name if name.startswith('/') else '/' + name
        if key not in available:
            there = ', '.join(sorted(available)) or 'none'
            raise RecordingError(f'{path}: no topic {key} (topics: {there})')
        if typ is not None and available[key] != typ:
            raise RecordingError(
                f'{path}: topic {key} has type {available[key]}, expected {typ}')
        selected.add(key)
    return selected


class _Decoders:
    """rclpy classes where the type is installed, mcap-ros2-support's decoder otherwise."""

    def __init__(self, path: Path):
        self._path = path
        self._decoders: dict = {}

    def decode(self, schema, channel, message, index: int):
        """The message object; :class:`UndecodableMessage` naming message ``index`` (0 the
        first read) where its bytes do not decode, :class:`RecordingError` where the topic
        cannot be decoded at all."""
        if channel.message_encoding != mcap_schema.MESSAGE_ENCODING:
            raise RecordingError(
                f'{self._path}: topic {channel.topic} has message encoding '
                f'{channel.message_encoding!r}, not cdr')
        key = channel.schema_id
        decoder = self._decoders.get(key)
        if decoder is None:
            decoder = self._decoders[key] = self._make(schema, channel)
        try:
            return decoder(message.data)
        except RecordingError:
            raise
        except Exception as err:  # noqa: BLE001 - any decoder failure is a corrupt message
            raise UndecodableMessage(
                f'{self._path}: cannot decode message {index} (a '
                f'{schema.name if schema else "?"} on {channel.topic} at log time '
                f'{message.log_time}): {reason(err)}') from None

    def _make(self, schema, channel):
        if schema is None:
            raise RecordingError(f'{self._path}: topic {channel.topic} has no schema')
        try:
            cls = message_class(schema.name)
        except RecordingError:
            cls = None
        if cls is not None:
            from rclpy.serialization import deserialize_message
            return lambda data: deserialize_message(data, cls)
        from mcap_ros2.decoder import DecoderFactory
        decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
        if decoder is None:
            raise RecordingError(
                f'{self._path}: no decoder for {schema.name} ({schema.encoding} schema)')
        return decoder


_BAD = object()   # what a skipped message decodes to


def _recorded(topic: str, type_name: str, record: Message, message, raw: bool):
    if raw:
        return RawRecordedMessage(topic, type_name, record.log_time, message,
                                  record.publish_time, bytes(record.data))
    return RecordedMessage(topic, type_name, record.log_time, message)


def read_messages(path, topics=None, *, allow_incomplete: bool = False, raw: bool = False,
                  on_bad: Callable[[UndecodableMessage], None] | None = None
                  ) -> Iterator[RecordedMessage]:
    """Yield (topic, type name, log_time_ns, message) in log-time order.

    ``topics``: None for all, names, or a mapping name -> expected type name (None: any).
    Messages are rclpy message objects where the type is installed (mcap-ros2-support's
    dynamic objects otherwise). Raises :class:`RecordingError` (one line) for a missing, empty,
    non-MCAP, truncated or corrupt file, a topic not in the file, a topic of another type, a
    message that does not decode. ``allow_incomplete=True`` reads a file whose recorder was
    killed: the messages of the chunks written before the cut, in file order. ``raw=True``
    yields :class:`RawRecordedMessage` (publish time and CDR bytes as well), e.g. to copy
    messages into another file unchanged. ``on_bad``: called with the
    :class:`~cdpr_dynamics.recording.base.UndecodableMessage` of each message whose bytes do not
    decode, which is then skipped (without it, that error is raised); the index it names counts
    the messages read of the selected topics from 0, skipped ones included.
    """
    wanted = None if topics is None else normalise_topics(topics)
    path, stream = open_mcap(path)
    with stream:
        decoders = _Decoders(path)
        index = -1

        def decoded(schema, channel, record):
            try:
                return decoders.decode(schema, channel, record, index)
            except UndecodableMessage as bad:
                if on_bad is None:
                    raise
                on_bad(bad)
                return _BAD
        summary = _summary(path, stream)
        if summary is None and not allow_incomplete:
            raise RecordingError(f'{path}: {_INCOMPLETE}')
        if summary is not None:
            available = {c.topic: (summary.schemas[c.schema_id].name
                                   if c.schema_id in summary.schemas else '')
                         for c in summary.channels.values()}
            selected = None if wanted is None else _check_topics(path, wanted, available)
            stream.seek(0)
            reader = SeekingReader(stream, validate_crcs=True)
            iterator = reader.iter_messages(topics=selected, log_time_order=True)
            while True:
                try:
                    schema, channel, message = next(iterator)
                except StopIteration:
                    return
                except (McapError, struct.error, ValueError, zlib.error, KeyError) as err:
                    raise RecordingError(f'{path}: corrupt MCAP data ({reason(err)})') from None
                index += 1
                value = decoded(schema, channel, message)
                if value is not _BAD:
                    yield _recorded(channel.topic, schema.name if schema else '', message,
                                    value, raw)
            return
        # incomplete file: scan what is there
        info = recording_info(path)
        available = {name: t.type for name, t in info.topics.items()}
        selected = None if wanted is None else _check_topics(path, wanted, available)
        schemas, channels = {}, {}
        stream.seek(0)
        for record in scan(path, stream):
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None:
                    raise RecordingError(
                        f'{path}: message on unknown channel {record.channel_id}')
                if selected is not None and channel.topic not in selected:
                    continue
                schema = schemas.get(channel.schema_id)
                index += 1
                value = decoded(schema, channel, record)
                if value is not _BAD:
                    yield _recorded(channel.topic, schema.name if schema else '', record,
                                    value, raw)
