"""Read recordings back: :func:`read_messages` and :func:`recording_info`.

Files written here or by ``ros2 bag record -s mcap``; every problem is a
:class:`~cdpr_dynamics.recording.base.RecordingError` with a one-line reason. A complete file is
read through its summary and index; an incomplete one (a recorder killed outright) or a damaged
one by a scan (:class:`McapFile`, also the source of :mod:`~cdpr_dynamics.recording.recovery`
and of ``cdpr_replay``'s batches), a damaged chunk costing that chunk only.
"""
from __future__ import annotations

import io
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Mapping

from mcap.exceptions import McapError
from mcap.reader import SeekingReader

from cdpr_dynamics.recording import chunks
from cdpr_dynamics.recording.base import (
    message_class, normalise_topics, RawRecordedMessage, reason, RecordedMessage,
    RecordingError, RecordingInfo, TopicInfo, UndecodableMessage)
from msg_adapters import mcap_schema


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
    head = stream.read(len(chunks.MAGIC))
    if head != chunks.MAGIC:
        stream.close()
        what = 'empty' if not head else 'not an MCAP file (bad magic bytes)'
        raise RecordingError(f'{path}: {what}')
    stream.seek(0)
    return path, stream


_INCOMPLETE = ('incomplete MCAP file (no footer or index: the recorder was killed or the file '
               'was cut short; read_messages(..., allow_incomplete=True) reads what survives)')
#: most chunks whose log times overlap that are merged into log-time order at once; a file whose
#: chunks overlap more (none of the writers here makes one) is read in file order beyond it
MAX_OVERLAPPING_CHUNKS = 64


@dataclass
class Salvage:
    """What a damaged file cost a read: the damage to its structure, the chunks lost (one line
    each) and the messages on channels whose definition was in a lost chunk."""

    damage: list = field(default_factory=list)
    lost_chunks: list = field(default_factory=list)
    orphans: int = 0
    chunks_read: int = 0

    def __bool__(self) -> bool:
        return bool(self.damage or self.lost_chunks or self.orphans)

    def lines(self) -> list:
        """One line per kind of damage, for a tool's summary."""
        out = list(self.damage)
        if self.lost_chunks:
            out.append(f'{len(self.lost_chunks)} damaged chunk(s) skipped: '
                       + '; '.join(self.lost_chunks[:3])
                       + (f' (and {len(self.lost_chunks) - 3} more)'
                          if len(self.lost_chunks) > 3 else ''))
        if self.orphans:
            out.append(f'{self.orphans} message(s) skipped on channels defined only in a '
                       'damaged chunk')
        return out


class McapFile:
    """An MCAP file read chunk by chunk (:mod:`~cdpr_dynamics.recording.chunks`): a complete
    file through its chunk index, an incomplete or damaged one by a scan. Schemas and channels
    grow as chunks define them. Use as a context manager (closes the file)."""

    def __init__(self, path):
        self.path, self.stream = open_mcap(path)
        try:
            self.header = SeekingReader(self.stream).get_header()
            self.layout = chunks.layout(self.stream)
        except (McapError, struct.error, ValueError, EOFError) as err:
            self.stream.close()
            raise RecordingError(f'{self.path}: corrupt MCAP header ({reason(err)})') from None
        except BaseException:
            self.stream.close()
            raise
        self.schemas = dict(self.layout.schemas)
        self.channels = dict(self.layout.channels)

    @property
    def complete(self) -> bool:
        """Summary and chunk index present and sound."""
        return self.layout.indexed

    def close(self) -> None:
        self.stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def incomplete_error(self) -> RecordingError:
        """The error for reading this (incomplete or damaged) file as a complete one."""
        if self.layout.damage:
            return RecordingError(f'{self.path}: damaged MCAP file ({self.layout.damage[0]}; '
                                  'allow_incomplete / --allow-incomplete reads the intact '
                                  'chunks)')
        return RecordingError(f'{self.path}: {_INCOMPLETE}')

    def contents(self, refs=None, salvage: Salvage | None = None):
        """(ChunkRef, ChunkContent) of each chunk of ``refs`` (default: all, in file order);
        a damaged chunk raises :class:`RecordingError` or, with ``salvage``, is counted there
        and skipped."""
        for ref in self.layout.chunks if refs is None else refs:
            try:
                content = chunks.read_chunk(self.stream, ref)
            except chunks.ChunkDamage as err:
                if salvage is None:
                    raise RecordingError(f'{self.path}: corrupt MCAP data ({err}; '
                                         'allow_incomplete / --allow-incomplete reads the '
                                         'intact chunks)') from None
                salvage.lost_chunks.append(str(err))
                continue
            if salvage is not None:
                salvage.chunks_read += 1
            for schema in content.schemas:
                self.schemas.setdefault(schema.id, schema)
            for channel in content.channels:
                self.channels.setdefault(channel.id, channel)
            yield ref, content

    def definitions(self, salvage: Salvage | None = None) -> None:
        """Read every chunk for its schemas and channels (a file without a summary has them
        in its chunks only)."""
        if not self.complete:
            for _ in self.contents(salvage=salvage):
                pass

    def topics(self) -> dict:
        """Topic -> type name of the channels known."""
        return {c.topic: (self.schemas[c.schema_id].name if c.schema_id in self.schemas
                          else '') for c in self.channels.values()}

    def batches(self, wanted=None, salvage: Salvage | None = None):
        """Lists of (log time, publish time, channel id, bytes) in log-time order (chunks
        whose log times overlap merged, up to :data:`MAX_OVERLAPPING_CHUNKS` at once), of the
        topics in ``wanted`` (None: all); memory: the chunks of one overlap at a time."""
        keep: dict = {}

        def kept(channel_id) -> bool | None:
            known = keep.get(channel_id)
            if known is None and channel_id in self.channels:
                known = keep[channel_id] = (wanted is None
                                            or self.channels[channel_id].topic in wanted)
            return known

        order = sorted(self.layout.chunks, key=lambda r: (r.start_ns, r.number))
        group, group_end = [], None
        for ref in order + [None]:
            if ref is not None and group and ref.start_ns < group_end \
                    and len(group) < MAX_OVERLAPPING_CHUNKS:
                group.append(ref)
                group_end = max(group_end, ref.end_ns)
                continue
            if group:
                batch = []
                for _, content in self.contents(group, salvage):
                    for item in zip(content.log_times, content.publish_times,
                                    content.channel_ids, content.data):
                        wanted_here = kept(item[2])
                        if wanted_here:
                            batch.append(item)
                        elif wanted_here is None:
                            if salvage is None:
                                raise RecordingError(
                                    f'{self.path}: message on unknown channel {item[2]}')
                            salvage.orphans += 1
                batch.sort(key=_log_time)
                yield batch
            if ref is not None:
                group, group_end = [ref], ref.end_ns


def _log_time(item) -> int:
    return item[0]


def recording_info(path) -> RecordingInfo:
    """Header, topics, types, counts and time range of a recording.

    A complete file is described from its summary; an incomplete or damaged one (killed
    recorder) from a scan of what survives (``complete=False``, ``damage`` says what was
    lost). Raises :class:`RecordingError`.
    """
    with McapFile(path) as mcap:
        info = RecordingInfo(path=mcap.path, complete=mcap.complete,
                             profile=mcap.header.profile, library=mcap.header.library,
                             message_count=0, start_ns=0, end_ns=0,
                             chunk_count=len(mcap.layout.chunks))
        info.metadata = dict(mcap.layout.metadata)
        stats = mcap.layout.statistics
        if mcap.complete:
            counts = dict(stats.channel_message_counts) if stats else {}
            info.message_count = stats.message_count if stats else 0
            info.start_ns = stats.message_start_time if stats else 0
            info.end_ns = stats.message_end_time if stats else 0
        else:
            salvage = Salvage(list(mcap.layout.damage))
            counts, start, end = {}, None, None
            for _, content in mcap.contents(salvage=salvage):
                for channel_id in content.channel_ids:
                    counts[channel_id] = counts.get(channel_id, 0) + 1
                if content.log_times:
                    low, high = min(content.log_times), max(content.log_times)
                    start = low if start is None else min(start, low)
                    end = high if end is None else max(end, high)
            info.message_count = sum(counts.values())
            info.start_ns, info.end_ns = start or 0, end or 0
            info.damage = salvage.lines()
            info.chunk_count -= len(salvage.lost_chunks)
        for channel_id, channel in mcap.channels.items():
            schema = mcap.schemas.get(channel.schema_id)
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
    """rclpy classes where the type is installed, mcap-ros2-support's decoder otherwise; the
    bytes checked against the channel's schema first (:func:`mcap_schema.cdr_checker`), since
    neither decoder notices bytes of another type that are long enough."""

    def __init__(self, path: Path):
        self._path = path
        self._decoders: dict = {}

    def decode(self, schema, channel, data, log_time: int, index: int):
        """The message object; :class:`UndecodableMessage` naming message ``index`` (0 the
        first read) where its bytes do not decode, :class:`RecordingError` where the topic
        cannot be decoded at all."""
        key = channel.id
        decoder = self._decoders.get(key)
        if decoder is None:
            decoder = self._decoders[key] = self._make(schema, channel)
        try:
            return decoder(data)
        except RecordingError:
            raise
        except Exception as err:  # noqa: BLE001 - any decoder failure is a corrupt message
            raise UndecodableMessage(
                f'{self._path}: cannot decode message {index} (a '
                f'{schema.name if schema else "?"} on {channel.topic} at log time '
                f'{log_time}): {reason(err)}') from None

    def _make(self, schema, channel):
        if channel.message_encoding != mcap_schema.MESSAGE_ENCODING:
            raise RecordingError(
                f'{self._path}: topic {channel.topic} has message encoding '
                f'{channel.message_encoding!r}, not cdr')
        if schema is None:
            raise RecordingError(f'{self._path}: topic {channel.topic} has no schema')
        check = schema_check(schema)
        try:
            cls = message_class(schema.name)
        except RecordingError:
            cls = None
        if cls is not None:
            from rclpy.serialization import deserialize_message

            def decode(data):
                check(data)
                return deserialize_message(data, cls)
            return decode
        from mcap_ros2.decoder import DecoderFactory
        decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
        if decoder is None:
            raise RecordingError(
                f'{self._path}: no decoder for {schema.name} ({schema.encoding} schema)')

        def decode_dynamic(data):
            check(data)
            return decoder(data)
        return decode_dynamic


def schema_check(schema):
    """``check(data)`` raising :class:`~msg_adapters.mcap_schema.CdrError` for bytes that are
    not a message of the schema's type (no check where the schema text cannot be parsed: the
    decoder then has the last word)."""
    try:
        text = bytes(schema.data).decode('utf-8')
        count = mcap_schema.stamped_values_count(schema.name, text)
        if count is not None:
            name = schema.name.rsplit('/', 1)[-1]
            return lambda data: mcap_schema.decode_stamped(data, count, name)
        return mcap_schema.cdr_checker(schema.name, text)
    except (mcap_schema.SchemaError, UnicodeDecodeError, ValueError):
        return lambda data: None


_BAD = object()   # what a skipped message decodes to


def _check_selected(mcap: McapFile, wanted) -> set | None:
    if wanted is None:
        return None
    return _check_topics(mcap.path, wanted, mcap.topics())


def read_messages(path, topics=None, *, allow_incomplete: bool = False, raw: bool = False,
                  on_bad: Callable[[UndecodableMessage], None] | None = None,
                  salvage: Salvage | None = None) -> Iterator[RecordedMessage]:
    """Yield (topic, type name, log_time_ns, message) in log-time order.

    ``topics``: None for all, names, or a mapping name -> expected type name (None: any).
    Messages are rclpy message objects where the type is installed (mcap-ros2-support's
    dynamic objects otherwise). Raises :class:`RecordingError` (one line) for a missing, empty,
    non-MCAP, truncated or corrupt file, a topic not in the file, a topic of another type, a
    message that does not decode (bytes that are not one message of the channel's schema).
    ``allow_incomplete=True`` reads what survives of a file whose recorder was killed or
    whose bytes are damaged: every intact chunk (the damage is counted in ``salvage``, a
    :class:`Salvage`, where given). ``raw=True`` yields :class:`RawRecordedMessage`
    (publish time and CDR bytes as well), e.g. to copy messages into another file unchanged.
    ``on_bad``: called with the :class:`~cdpr_dynamics.recording.base.UndecodableMessage` of
    each message whose bytes do not decode, which is then skipped (without it, that error is
    raised); the index it names counts the messages read of the selected topics from 0,
    skipped ones included. Memory stays bounded whatever the file's length.
    """
    wanted = None if topics is None else normalise_topics(topics)
    with McapFile(path) as mcap:
        if not mcap.complete and not allow_incomplete:
            raise mcap.incomplete_error()
        if allow_incomplete and salvage is None:
            salvage = Salvage()
        if salvage is not None:
            salvage.damage.extend(mcap.layout.damage)
        if wanted is not None:
            mcap.definitions(Salvage() if allow_incomplete else None)
        selected = _check_selected(mcap, wanted)
        decoders = _Decoders(mcap.path)
        index = -1
        for batch in mcap.batches(selected, salvage):
            for log_time, publish_time, channel_id, data in batch:
                channel = mcap.channels[channel_id]
                schema = mcap.schemas.get(channel.schema_id)
                index += 1
                try:
                    value = decoders.decode(schema, channel, data, log_time, index)
                except UndecodableMessage as bad:
                    if on_bad is None:
                        raise
                    on_bad(bad)
                    continue
                type_name = schema.name if schema else ''
                if raw:
                    yield RawRecordedMessage(channel.topic, type_name, log_time, value,
                                             publish_time, bytes(data))
                else:
                    yield RecordedMessage(channel.topic, type_name, log_time, value)
