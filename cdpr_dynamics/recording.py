"""Record ROS topics to rosbag2-compatible MCAP files and read them back.

Writing (:class:`Recorder`): subscribes with rclpy (``raw=True``: the CDR bytes as received,
never re-serialised) to the topics asked for, once a publisher of each is discovered, with a QoS
adapted to the publishers' offers as rosbag2 does; writes profile ``ros2``, schemas ``ros2msg``
built from the installed ``.msg`` files, channels ``cdr`` with rosbag2's channel metadata, in
indexed chunks. A chunk is closed when it is full (``chunk_size`` bytes) or when its oldest
message is ``chunk_interval_s`` old, whichever comes first, so a recorder killed outright loses
at most about the last second; :meth:`Recorder.close` writes the summary and index.

Timestamps: ``log_time`` is the receive time on the recorder node's clock; ``publish_time`` the
publisher's send time (the DDS source timestamp, as rosbag2 records it), or the receive time
where the middleware gives none. Header stamps stay in the messages.

:class:`RecordingWriter` writes given messages (no ROS graph) with the same conventions, under
a temporary name renamed on success: for tools that produce recordings (``cdpr_replay``).

Reading (:func:`read_messages`, :func:`recording_info`): files written here or by
``ros2 bag record -s mcap``; every problem is a :class:`RecordingError` with a one-line reason.
"""
from __future__ import annotations

import importlib
import io
import os
import struct
import tempfile
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, NamedTuple

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk, StreamReader
from mcap.writer import CompressionType, IndexType, Writer

from msg_adapters import mcap_schema

try:
    from importlib.metadata import version as _dist_version
    _VERSION = _dist_version('cdpr_dynamics')
except Exception:  # noqa: BLE001 - not installed: a checkout on the path
    _VERSION = '0.1.0'

DEFAULT_CHUNK_SIZE = 768 * 1024  # the MCAP C++ writer's default, used by rosbag2
DEFAULT_CHUNK_INTERVAL_S = 1.0
_TICK_S = 0.1        # how often the chunk age and the ROS graph are checked
_DISCOVERY_S = 0.2
_TAKE_BATCH = 256    # messages taken per callback straight from the subscription


class RecordingError(RuntimeError):
    """A recording that cannot be written or read as asked; the message is one line."""


class RecordedMessage(NamedTuple):
    """One message read back: topic, type name, receive time (ns) and the message."""

    topic: str
    type: str
    log_time_ns: int
    message: Any


class RawRecordedMessage(NamedTuple):
    """One message read back with ``raw=True``: also its send time and its CDR bytes."""

    topic: str
    type: str
    log_time_ns: int
    message: Any
    publish_time_ns: int
    data: bytes


@dataclass
class TopicInfo:
    """A channel of a recording."""

    type: str
    message_count: int
    offered_qos_profiles: str = ''
    type_hash: str = ''


@dataclass
class RecordingInfo:
    """What :func:`recording_info` finds in a file."""

    path: Path
    complete: bool          # footer, summary and chunk index present
    profile: str
    library: str
    message_count: int
    start_ns: int
    end_ns: int
    chunk_count: int
    topics: dict = field(default_factory=dict)   # name -> TopicInfo
    schema_encodings: dict = field(default_factory=dict)  # type -> encoding
    metadata: dict = field(default_factory=dict)  # metadata record name -> dict


@dataclass
class RecordingSummary:
    """What a :class:`Recorder` wrote."""

    path: Path
    message_count: int
    bytes: int
    chunk_count: int
    topics: dict            # resolved name -> messages written (0: never seen)
    start_ns: int
    end_ns: int


# ----------------------------------------------------------------------------- types


def type_name_of(msg_class) -> str:
    """``pkg/msg/Type`` of a generated rclpy message class (``pkg/srv/Srv_Event`` too)."""
    package, namespace = msg_class.__module__.split('.')[:2]
    return f'{package}/{namespace}/{msg_class.__name__}'


def message_class(type_name: str):
    """The rclpy class of a type name; raises :class:`RecordingError` if it is not installed."""
    try:
        package, namespace, name = mcap_schema.split_type_name(type_name)
    except mcap_schema.SchemaError as err:
        raise RecordingError(str(err)) from None
    try:
        module = importlib.import_module(f'{package}.{namespace}')
        if namespace == 'srv':
            for suffix, attr in (('_Event', 'Event'), ('_Request', 'Request'),
                                 ('_Response', 'Response')):
                if name.endswith(suffix):
                    return getattr(getattr(module, name[:-len(suffix)]), attr)
        return getattr(module, name)
    except (ImportError, AttributeError):
        raise RecordingError(f'message type {type_name} is not installed') from None


def _normalise_topics(topics) -> dict:
    if isinstance(topics, str):
        topics = [topics]
    if isinstance(topics, Mapping):
        items = topics.items()
    else:
        items = ((name, None) for name in topics)
    out = {}
    for name, typ in items:
        if typ is not None and not isinstance(typ, str):
            typ = type_name_of(typ)
        out[name] = typ
    return out


# ----------------------------------------------------------------------------- recorder


class _Topic:
    __slots__ = ('name', 'wanted_type', 'type', 'channel_id', 'subscription', 'count',
                 'qos', 'type_hash', 'warned')

    def __init__(self, name: str, wanted_type: str | None):
        self.name = name
        self.wanted_type = wanted_type
        self.type = wanted_type
        self.channel_id = None
        self.subscription = None
        self.count = 0
        self.qos = []
        self.type_hash = ''
        self.warned = False


class Recorder:
    """Records topics of a running node's graph to one MCAP file.

    ``topics``: names (relative names resolve in ``node``'s namespace) mapped to a type name
    or message class, or to ``None`` to take the type the publishers have; a plain list of names
    means ``None`` for each. A topic is subscribed once a publisher of it is seen, so wait for
    ``publisher.get_subscription_count()`` before publishing what must be recorded.

    The node must be spun by an executor (callbacks and timers do the work). Thread-safe;
    :meth:`close` (or leaving a ``with`` block) finishes the file. Existing files are never
    overwritten unless ``force``.
    """

    def __init__(self, node, path, topics, *, force: bool = False,
                 chunk_size: int = DEFAULT_CHUNK_SIZE,
                 chunk_interval_s: float = DEFAULT_CHUNK_INTERVAL_S,
                 compression: str = 'none', qos_depth: int = 100):
        from rclpy.clock import Clock, ClockType

        self._node = node
        self.path = Path(path)
        self._chunk_interval_ns = int(chunk_interval_s * 1e9)
        self._qos_depth = int(qos_depth)
        self._lock = threading.RLock()
        self._closed = False
        self._summary = None
        self._schemas: dict[str, int] = {}
        self._chunk_started_ns = None   # monotonic time of the oldest unwritten message
        self._start_ns = None
        self._end_ns = 0
        self._topics: dict[str, _Topic] = {}
        for name, typ in _normalise_topics(topics).items():
            try:
                resolved = node.resolve_topic_name(name)
            except Exception as err:  # noqa: BLE001 - rclpy's invalid-name exceptions
                raise RecordingError(f'invalid topic name {name!r}: {_reason(err)}') from None
            if typ is not None:
                try:
                    mcap_schema.split_type_name(typ)
                except mcap_schema.SchemaError as err:
                    raise RecordingError(str(err)) from None
            self._topics[resolved] = _Topic(resolved, typ)
        if not self._topics:
            raise RecordingError('no topics to record')

        compressions = {'none': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                        'lz4': CompressionType.LZ4}
        if compression not in compressions:
            raise RecordingError(f'unknown compression {compression!r} (none, zstd, lz4)')
        try:
            if self.path.parent and not self.path.parent.is_dir():
                raise RecordingError(f'cannot write {self.path}: no directory {self.path.parent}')
            self._stream = open(self.path, 'wb' if force else 'xb')
        except FileExistsError:
            raise RecordingError(
                f'{self.path} exists; not overwriting it (use --force to replace it)') from None
        except (IsADirectoryError, PermissionError, OSError) as err:
            raise RecordingError(f'cannot write {self.path}: {err.strerror or err}') from None
        self._writer = Writer(
            self._stream, chunk_size=int(chunk_size), compression=compressions[compression],
            index_types=IndexType.ALL, repeat_channels=True, repeat_schemas=True,
            use_chunking=True, use_statistics=True, use_summary_offsets=True, enable_crcs=True)
        self._writer.start(
            profile=mcap_schema.PROFILE, library=f'cdpr_dynamics {_VERSION} (mcap-python)')
        self._writer.flush()

        self._clock = node.get_clock()
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._last_discovery = 0.0
        self._timer = node.create_timer(_TICK_S, self._on_tick, clock=steady)
        self._discover()

    # -- state ------------------------------------------------------------------------------

    @property
    def message_count(self) -> int:
        """Messages written so far."""
        return sum(t.count for t in self._topics.values())

    @property
    def topic_counts(self) -> dict:
        """Resolved topic name -> messages written so far."""
        return {name: t.count for name, t in self._topics.items()}

    def subscribed(self) -> set:
        """Resolved names of the topics subscribed so far."""
        return {name for name, t in self._topics.items() if t.subscription is not None}

    # -- discovery --------------------------------------------------------------------------

    def _discover(self) -> None:
        """Subscribe to the pending topics that have a publisher now (rosbag2 waits for one
        too: the type and the QoS to ask for come from the publishers)."""
        if self._closed:
            return
        for topic in [t for t in self._topics.values() if t.subscription is None]:
            publishers = self._node.get_publishers_info_by_topic(topic.name)
            types = sorted({p.topic_type for p in publishers})
            if not types:
                continue
            if topic.wanted_type is not None and topic.wanted_type not in types:
                self._warn_once(topic, f'it has type {", ".join(types)}, '
                                       f'expected {topic.wanted_type}')
                continue
            if topic.wanted_type is None and len(types) > 1:
                self._warn_once(topic, f'several types ({", ".join(types)})')
                continue
            type_name = topic.wanted_type or types[0]
            self._subscribe(topic, type_name,
                            [p for p in publishers if p.topic_type == type_name])

    def _warn_once(self, topic: _Topic, reason: str) -> None:
        if not topic.warned:
            topic.warned = True
            self._node.get_logger().warning(f'not recording {topic.name} yet: {reason}')

    def _subscribe(self, topic: _Topic, type_name: str, publishers: list) -> None:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        try:
            cls = message_class(type_name)
            definition = mcap_schema.message_definition(type_name)
        except (RecordingError, mcap_schema.SchemaError) as err:
            self._warn_once(topic, str(err))
            return
        offered = [p.qos_profile for p in publishers]
        reliable = bool(offered) and all(
            q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
        latched = bool(offered) and all(
            q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=self._qos_depth,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                        else DurabilityPolicy.VOLATILE))
        hashes = [str(p.topic_type_hash) for p in publishers]
        hashes = [h for h in hashes if h.startswith('RIHS01_')]
        topic.type = type_name
        topic.qos = [mcap_schema.qos_profile_to_dict(q) for q in offered]
        topic.type_hash = hashes[0] if hashes else mcap_schema.type_hash(type_name)
        with self._lock:
            if self._closed:
                return
            schema_id = self._schemas.get(type_name)
            if schema_id is None:
                schema_id = self._writer.register_schema(
                    name=type_name, encoding=mcap_schema.SCHEMA_ENCODING,
                    data=definition.encode('utf-8'))
                self._schemas[type_name] = schema_id
            topic.channel_id = self._writer.register_channel(
                topic=topic.name, message_encoding=mcap_schema.MESSAGE_ENCODING,
                schema_id=schema_id,
                metadata={'offered_qos_profiles':
                          mcap_schema.offered_qos_profiles_yaml(topic.qos),
                          'topic_type_hash': topic.type_hash})

        def on_message(data, info, topic=topic):
            self._write(topic, data, info)
            self._take_more(topic)

        topic.subscription = self._node.create_subscription(
            cls, topic.name, on_message, qos, raw=True)

    # -- writing ----------------------------------------------------------------------------

    def _write(self, topic: _Topic, data: bytes, info) -> None:
        now = self._clock.now().nanoseconds
        sent = 0
        sequence = 0
        if isinstance(info, Mapping):
            sent = info.get('source_timestamp') or 0
            sequence = info.get('publication_sequence_number') or 0
        with self._lock:
            if self._closed:
                return
            self._writer.add_message(
                channel_id=topic.channel_id, log_time=now, data=data,
                publish_time=sent if sent > 0 else now, sequence=sequence & 0xFFFFFFFF)
            topic.count += 1
            if self._start_ns is None:
                self._start_ns = now
            self._end_ns = max(self._end_ns, now)
            mono = time.monotonic_ns()
            if self._chunk_started_ns is None:
                self._chunk_started_ns = mono
            elif mono - self._chunk_started_ns >= self._chunk_interval_ns:
                self._flush_locked()

    def _take_more(self, topic: _Topic) -> None:
        """Take the messages already waiting on this subscription without a trip through the
        executor (its per-message cost is ~15 times that of writing); bounded, so timers and
        other topics still get their turn."""
        subscription = topic.subscription
        for _ in range(_TAKE_BATCH):
            try:
                with subscription.handle:
                    taken = subscription.handle.take_message(subscription.msg_type, True)
            except Exception:  # noqa: BLE001 - destroyed meanwhile: the executor resumes
                return
            if taken is None:
                return
            self._write(topic, taken[0], taken[1])

    def _flush_locked(self) -> None:
        self._writer.flush()   # closes the open chunk (if it has messages), writes it out
        self._chunk_started_ns = None

    def _on_tick(self) -> None:
        with self._lock:
            if self._closed:
                return
            if (self._chunk_started_ns is not None
                    and time.monotonic_ns() - self._chunk_started_ns >= self._chunk_interval_ns):
                self._flush_locked()
        now = time.monotonic()
        if now - self._last_discovery >= _DISCOVERY_S:
            self._last_discovery = now
            self._discover()

    def flush(self) -> None:
        """Close the open chunk now and hand everything written to the operating system."""
        with self._lock:
            if not self._closed:
                self._flush_locked()

    # -- closing ----------------------------------------------------------------------------

    def close(self) -> RecordingSummary:
        """Stop recording and finish the file (rosbag2 metadata, summary, indexes). Idempotent."""
        with self._lock:
            if self._closed:
                return self._summary
            self._closed = True
        for topic in self._topics.values():
            if topic.subscription is not None:
                try:
                    self._node.destroy_subscription(topic.subscription)
                except Exception:  # noqa: BLE001 - context already shut down
                    pass
        try:
            self._node.destroy_timer(self._timer)
        except Exception:  # noqa: BLE001
            pass
        with self._lock:
            recorded = [t for t in self._topics.values() if t.channel_id is not None]
            self._writer.add_metadata(mcap_schema.ROSBAG2_METADATA_NAME, {
                'serialized_metadata': mcap_schema.rosbag2_serialized_metadata(
                    self.path.name,
                    [{'name': t.name, 'type': t.type, 'offered_qos_profiles': t.qos,
                      'type_description_hash': t.type_hash, 'message_count': t.count}
                     for t in recorded],
                    self._start_ns or 0, self._end_ns)})
            self._writer.finish()
            size = self._stream.tell()
            self._stream.flush()
            os.fsync(self._stream.fileno())
            self._stream.close()
            chunks = _count_chunks(self.path)
            self._summary = RecordingSummary(
                path=self.path, message_count=self.message_count, bytes=size,
                chunk_count=chunks, topics=self.topic_counts,
                start_ns=self._start_ns or 0, end_ns=self._end_ns)
            return self._summary

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _count_chunks(path: Path) -> int:
    try:
        with open(path, 'rb') as stream:
            summary = SeekingReader(stream).get_summary()
        return summary.statistics.chunk_count if summary and summary.statistics else 0
    except Exception:  # noqa: BLE001 - only a figure for the summary
        return 0


# ----------------------------------------------------------------------------- serialisation

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


# ----------------------------------------------------------------------------- file writer


class RecordingWriter:
    """Writes given messages to a new MCAP file with the recorder's conventions, no ROS graph.

    For tools that make recordings themselves (``cdpr_replay``, the test scenarios): same
    profile, ``ros2msg`` schemas from the installed ``.msg`` files, ``cdr`` channels with
    rosbag2's channel metadata, indexed chunks and the ``rosbag2`` metadata record.

    The file is written under a hidden temporary name in the destination folder
    (``.NAME.partial-XXXX``) and renamed to ``path`` only by :meth:`close`, so a file at
    ``path`` is always complete; :meth:`abort` (or an exception in a ``with`` block) deletes
    the temporary file. An existing ``path`` is refused unless ``force``, at start and again at
    the rename. Not thread-safe.
    """

    def __init__(self, path, *, force: bool = False, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = 'none', library: str | None = None):
        import tempfile

        self.path = Path(path)
        self._force = force
        compressions = {'none': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                        'lz4': CompressionType.LZ4}
        if compression not in compressions:
            raise RecordingError(f'unknown compression {compression!r} (none, zstd, lz4)')
        folder = self.path.parent
        if not folder.is_dir():
            raise RecordingError(f'cannot write {self.path}: no directory {folder}')
        if self.path.is_dir():
            raise RecordingError(f'cannot write {self.path}: it is a directory')
        if os.path.lexists(self.path) and not force:
            raise RecordingError(
                f'{self.path} exists; not overwriting it (use --force to replace it)')
        try:
            fd, temp = tempfile.mkstemp(prefix=f'.{self.path.name}.partial-', dir=folder)
        except OSError as err:
            raise RecordingError(f'cannot write {self.path}: {err.strerror or err}') from None
        self.temp_path = Path(temp)
        mask = os.umask(0)
        os.umask(mask)
        os.fchmod(fd, 0o666 & ~mask)   # mkstemp's 0600 would outlive the rename
        self._stream = os.fdopen(fd, 'wb')
        self._writer = Writer(
            self._stream, chunk_size=int(chunk_size), compression=compressions[compression],
            index_types=IndexType.ALL, repeat_channels=True, repeat_schemas=True,
            use_chunking=True, use_statistics=True, use_summary_offsets=True, enable_crcs=True)
        self._writer.start(profile=mcap_schema.PROFILE,
                           library=library or f'cdpr_dynamics {_VERSION} (mcap-python)')
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, dict] = {}
        self._metadata: list[tuple[str, dict]] = []
        self._start_ns = None
        self._end_ns = 0
        self._state = 'open'
        self.summary: RecordingSummary | None = None

    @property
    def topic_counts(self) -> dict:
        """Topic -> messages written so far."""
        return {name: t['count'] for name, t in self._topics.items()}

    def add_topic(self, name: str, type_name: str, offered_qos=(),
                  type_hash: str | None = None) -> None:
        """Declare a topic (absolute name) of ``type_name`` (``pkg/msg/Type`` or a message
        class). ``offered_qos``: the publishers' QoS, as rclpy profiles, dicts of
        :func:`mcap_schema.qos_profile_to_dict` or the YAML text of a channel's
        ``offered_qos_profiles``; ``type_hash`` defaults to the installed type's."""
        self._check_open()
        if not isinstance(type_name, str):
            type_name = type_name_of(type_name)
        if name in self._topics:
            if self._topics[name]['type'] != type_name:
                raise RecordingError(f'topic {name} declared twice with different types')
            return
        try:
            mcap_schema.split_type_name(type_name)
            definition = mcap_schema.message_definition(type_name)
            if type_hash is None:
                type_hash = mcap_schema.type_hash(type_name)
        except mcap_schema.SchemaError as err:
            raise RecordingError(str(err)) from None
        text = None
        if isinstance(offered_qos, str):   # a copied channel keeps its text verbatim
            text = offered_qos or '[]'
            offered_qos = _qos_from_yaml(offered_qos)
        qos = [q if isinstance(q, Mapping) else mcap_schema.qos_profile_to_dict(q)
               for q in offered_qos]
        if text is None:
            text = mcap_schema.offered_qos_profiles_yaml(qos)
        schema_id = self._schemas.get(type_name)
        if schema_id is None:
            schema_id = self._writer.register_schema(
                name=type_name, encoding=mcap_schema.SCHEMA_ENCODING,
                data=definition.encode('utf-8'))
            self._schemas[type_name] = schema_id
        channel_id = self._writer.register_channel(
            topic=name, message_encoding=mcap_schema.MESSAGE_ENCODING, schema_id=schema_id,
            metadata={'offered_qos_profiles': text, 'topic_type_hash': type_hash})
        self._topics[name] = {'type': type_name, 'channel': channel_id, 'qos': qos,
                              'hash': type_hash, 'count': 0, 'sequence': 0}

    def write(self, topic: str, message, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Add one message: CDR ``bytes`` as they are, or an rclpy message (serialised)."""
        self._check_open()
        entry = self._topics.get(topic)
        if entry is None:
            raise RecordingError(f'topic {topic} was not declared with add_topic')
        if isinstance(message, (bytes, bytearray, memoryview)):
            data = bytes(message)
        else:
            data = serialize(message)
        log_time_ns = int(log_time_ns)
        entry['sequence'] += 1
        self._writer.add_message(
            channel_id=entry['channel'], log_time=log_time_ns, data=data,
            publish_time=log_time_ns if publish_time_ns is None else int(publish_time_ns),
            sequence=entry['sequence'] & 0xFFFFFFFF)
        entry['count'] += 1
        self._start_ns = log_time_ns if self._start_ns is None else min(self._start_ns,
                                                                        log_time_ns)
        self._end_ns = max(self._end_ns, log_time_ns)

    def add_metadata(self, name: str, values: Mapping[str, str]) -> None:
        """A metadata record (string keys and values), written when the file is finished."""
        self._check_open()
        self._metadata.append((name, {str(k): str(v) for k, v in values.items()}))

    def close(self) -> RecordingSummary:
        """Finish the file (rosbag2 metadata, summary, index), then give it its name."""
        if self._state == 'closed':
            return self.summary
        self._check_open()
        try:
            for name, values in self._metadata:
                self._writer.add_metadata(name, values)
            self._writer.add_metadata(mcap_schema.ROSBAG2_METADATA_NAME, {
                'serialized_metadata': mcap_schema.rosbag2_serialized_metadata(
                    self.path.name,
                    [{'name': name, 'type': t['type'], 'offered_qos_profiles': t['qos'],
                      'type_description_hash': t['hash'], 'message_count': t['count']}
                     for name, t in self._topics.items()],
                    self._start_ns or 0, self._end_ns)})
            self._writer.finish()
            size = self._stream.tell()
            self._stream.flush()
            os.fsync(self._stream.fileno())
            self._stream.close()
            self._publish()
        except RecordingError:
            self.abort()
            raise
        except OSError as err:
            self.abort()
            raise RecordingError(f'cannot write {self.path}: {err.strerror or err}') from None
        self._state = 'closed'
        self.summary = RecordingSummary(
            path=self.path, message_count=sum(self.topic_counts.values()), bytes=size,
            chunk_count=_count_chunks(self.path), topics=self.topic_counts,
            start_ns=self._start_ns or 0, end_ns=self._end_ns)
        return self.summary

    def _publish(self) -> None:
        """Rename the finished temporary file to ``path`` (no clobbering unless ``force``)."""
        if self._force:
            os.replace(self.temp_path, self.path)
            return
        try:
            os.link(self.temp_path, self.path)   # fails if path appeared meanwhile
        except FileExistsError:
            raise RecordingError(
                f'{self.path} exists; not overwriting it (use --force to replace it)') from None
        except OSError:   # a file system without hard links: check, then rename
            if os.path.lexists(self.path):
                raise RecordingError(f'{self.path} exists; not overwriting it '
                                     '(use --force to replace it)') from None
            os.replace(self.temp_path, self.path)
            return
        os.unlink(self.temp_path)

    def abort(self) -> None:
        """Drop the file being written; nothing appears at ``path``. Idempotent."""
        if self._state != 'open':
            return
        self._state = 'aborted'
        try:
            self._stream.close()
        except OSError:
            pass
        try:
            os.unlink(self.temp_path)
        except OSError:
            pass

    def _check_open(self) -> None:
        if self._state != 'open':
            raise RecordingError(f'{self.path}: writer already {self._state}')

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def _qos_from_yaml(text: str) -> list:
    """The profiles of an ``offered_qos_profiles`` channel metadata text ([] if unreadable)."""
    import yaml

    try:
        profiles = yaml.safe_load(text or '[]')
    except yaml.YAMLError:
        return []
    keys = ('history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan',
            'liveliness', 'liveliness_lease_duration', 'avoid_ros_namespace_conventions')
    if not isinstance(profiles, list):
        return []
    return [p for p in profiles if isinstance(p, Mapping) and all(k in p for k in keys)]


# ----------------------------------------------------------------------------- reading

_MAGIC = b'\x89MCAP0\r\n'


def _open(path) -> tuple[Path, io.BufferedReader]:
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
    head = stream.read(len(_MAGIC))
    if head != _MAGIC:
        stream.close()
        what = 'empty' if not head else 'not an MCAP file (bad magic bytes)'
        raise RecordingError(f'{path}: {what}')
    stream.seek(0)
    return path, stream


def _has_footer(stream) -> bool:
    stream.seek(0, io.SEEK_END)
    size = stream.tell()
    if size < 2 * len(_MAGIC) + 9 + 20:
        return False
    stream.seek(size - len(_MAGIC))
    if stream.read(len(_MAGIC)) != _MAGIC:
        return False
    stream.seek(size - len(_MAGIC) - 29)
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
        raise RecordingError(f'{path}: corrupt MCAP summary ({_reason(err)})') from None


def _reason(err: Exception) -> str:
    text = str(err).strip().splitlines()
    return f'{type(err).__name__}: {text[0]}' if text else type(err).__name__


def _scan(path: Path, stream):
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
        raise RecordingError(f'{path}: corrupt MCAP data ({_reason(err)})') from None


def recording_info(path) -> RecordingInfo:
    """Header, topics, types, counts and time range of a recording.

    A complete file is described from its summary; an incomplete one (killed recorder) from a
    scan of what survives (``complete=False``). Raises :class:`RecordingError`.
    """
    path, stream = _open(path)
    with stream:
        try:
            stream.seek(0)
            header = SeekingReader(stream).get_header()
        except (McapError, struct.error, ValueError) as err:
            raise RecordingError(f'{path}: corrupt MCAP header ({_reason(err)})') from None
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
            for record in _scan(path, stream):
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

    def decode(self, schema, channel, message):
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
            raise RecordingError(
                f'{self._path}: cannot decode a {schema.name if schema else "?"} message on '
                f'{channel.topic} at log time {message.log_time} ({_reason(err)})') from None

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


def _recorded(topic: str, type_name: str, record: Message, message, raw: bool):
    if raw:
        return RawRecordedMessage(topic, type_name, record.log_time, message,
                                  record.publish_time, bytes(record.data))
    return RecordedMessage(topic, type_name, record.log_time, message)


def read_messages(path, topics=None, *, allow_incomplete: bool = False, raw: bool = False
                  ) -> Iterator[RecordedMessage]:
    """Yield (topic, type name, log_time_ns, message) in log-time order.

    ``topics``: None for all, names, or a mapping name -> expected type name (None: any).
    Messages are rclpy message objects where the type is installed (mcap-ros2-support's
    dynamic objects otherwise). Raises :class:`RecordingError` (one line) for a missing, empty,
    non-MCAP, truncated or corrupt file, a topic not in the file, a topic of another type, a
    message that does not decode. ``allow_incomplete=True`` reads a file whose recorder was
    killed: the messages of the chunks written before the cut, in file order. ``raw=True``
    yields :class:`RawRecordedMessage` (publish time and CDR bytes as well), e.g. to copy
    messages into another file unchanged.
    """
    wanted = None if topics is None else _normalise_topics(topics)
    path, stream = _open(path)
    with stream:
        decoders = _Decoders(path)
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
                    raise RecordingError(f'{path}: corrupt MCAP data ({_reason(err)})') from None
                yield _recorded(channel.topic, schema.name if schema else '', message,
                                decoders.decode(schema, channel, message), raw)
            return
        # incomplete file: scan what is there
        info = recording_info(path)
        available = {name: t.type for name, t in info.topics.items()}
        selected = None if wanted is None else _check_topics(path, wanted, available)
        schemas, channels = {}, {}
        stream.seek(0)
        for record in _scan(path, stream):
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
                yield _recorded(channel.topic, schema.name if schema else '', record,
                                decoders.decode(schema, channel, record), raw)


def recover_recording(source, destination, *, force: bool = False) -> int:
    """Rewrite what survives of an incomplete recording as a complete, indexed file.

    Returns the number of messages kept. The source is only read; the destination appears only
    once complete (written under a temporary name in its folder, then renamed), is never the
    source, and an existing one is kept unless ``force``.
    """
    destination = Path(destination)
    if destination.exists() and Path(source).exists() and destination.samefile(source):
        raise RecordingError(f'{destination} is the recording to recover: give another name')
    if destination.exists() and not force:
        raise RecordingError(f'{destination} exists; not overwriting it')
    source, stream = _open(source)
    try:
        fd, temp = tempfile.mkstemp(prefix=f'.{destination.name}.partial-',
                                    dir=destination.parent)
    except OSError as exc:
        stream.close()
        raise RecordingError(f'cannot write {destination}: {exc.strerror or exc}') from None
    try:
        with stream, os.fdopen(fd, 'wb') as out:
            try:
                header = SeekingReader(stream).get_header()
            except (McapError, EndOfFile, ValueError) as exc:
                raise RecordingError(f'{source}: no readable MCAP header ({exc})') from None
            writer = Writer(out, chunk_size=DEFAULT_CHUNK_SIZE,
                            compression=CompressionType.NONE)
            writer.start(profile=header.profile, library=header.library)
            schema_ids, channel_ids = {}, {}
            kept = 0
            stream.seek(0)
            for record in _scan(source, stream):
                if isinstance(record, Schema) and record.id not in schema_ids:
                    schema_ids[record.id] = writer.register_schema(
                        record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channel_ids:
                    channel_ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding,
                        schema_ids.get(record.schema_id, 0), dict(record.metadata))
                elif isinstance(record, Message) and record.channel_id in channel_ids:
                    writer.add_message(channel_ids[record.channel_id], record.log_time,
                                       record.data, record.publish_time, record.sequence)
                    kept += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
            writer.finish()
        if force:
            os.replace(temp, destination)
        else:
            os.link(temp, destination)      # fails if the name appeared meanwhile
            os.unlink(temp)
    except FileExistsError:
        os.unlink(temp)
        raise RecordingError(f'{destination} exists; not overwriting it') from None
    except BaseException:
        if os.path.exists(temp):
            os.unlink(temp)
        raise
    return kept


__all__ = [
    'DEFAULT_CHUNK_INTERVAL_S', 'DEFAULT_CHUNK_SIZE', 'RawRecordedMessage', 'Recorder',
    'RecordedMessage', 'RecordingError', 'RecordingInfo', 'RecordingSummary', 'RecordingWriter',
    'TopicInfo', 'message_class', 'serialize',
    'read_messages', 'recording_info', 'recover_recording', 'type_name_of',
]
