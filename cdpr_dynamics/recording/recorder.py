"""The recorder node: :class:`Recorder` records topics of a running ROS graph to one MCAP file.

It subscribes with rclpy (``raw=True``: the CDR bytes as received, never re-serialised) to the
topics asked for, once a publisher of each is discovered, with a QoS adapted to the publishers'
offers as rosbag2 does, and writes them through a
:class:`~cdpr_dynamics.recording.writer.ChunkedFile`: indexed chunks closed when full or when
their oldest message is ``chunk_interval_s`` old, whichever comes first, so a recorder killed
outright loses at most about the last second, and a disk that fills leaves a finished file of
every chunk written before.

Messages published before the recorder subscribed are not in the file (DDS delivers a late
subscriber only what transient-local publishers keep): at close the recorder warns, naming the
topic, where a subscribed topic with volatile publishers got no message, or where the first
message of a topic's only publisher was not its first (its publication sequence number says
how many came before; a transient-local publisher delivers only the history it keeps).

Timestamps: ``log_time`` is the receive time on the recorder node's clock; ``publish_time`` the
publisher's send time (the DDS source timestamp, as rosbag2 records it), or the receive time
where the middleware gives none. Header stamps stay in the messages.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Mapping

from cdpr_dynamics.recording.base import (
    DEFAULT_CHUNK_INTERVAL_S, DEFAULT_CHUNK_SIZE, message_class, normalise_topics, reason,
    RecordingError, RecordingSummary)
from cdpr_dynamics.recording.writer import ChunkedFile
from msg_adapters import mcap_schema
from msg_adapters.validation import clock_ns

_TICK_S = 0.1        # how often the chunk age and the ROS graph are checked
_DISCOVERY_S = 0.2
_TAKE_BATCH = 256    # messages taken per callback straight from the subscription
_DRAIN_BATCHES = 64  # at most this many batches per topic taken on close (16384 messages)


class _Topic:
    __slots__ = ('name', 'wanted_type', 'type', 'channel_id', 'subscription', 'count',
                 'qos', 'type_hash', 'warned', 'first_sequence')

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
        self.first_sequence = 0   # publication sequence number of the first message written


#: Depth of each subscription: 1 s of a 1 kHz topic, so a recorder that falls behind for a
#: moment (a chunk written, a busy machine) loses nothing (at 100, 98.9-99.7 % were kept of
#: 1-5 kHz wrench floods beside a busy node).
QOS_DEPTH = 1000


class Recorder:
    """Records topics of a running node's graph to one MCAP file.

    ``topics``: names (relative names resolve in ``node``'s namespace) mapped to a type name
    or message class, or to ``None`` to take the type the publishers have; a plain list of names
    means ``None`` for each. A topic is subscribed once a publisher of it is seen, so wait for
    ``publisher.get_subscription_count()`` before publishing what must be recorded.

    The node must be spun by an executor (callbacks and timers do the work). Thread-safe;
    :meth:`close` (or leaving a ``with`` block) finishes the file. Existing files are never
    overwritten unless ``force``. When a write fails (a full disk), recording stops,
    :attr:`error` says why (one line, logged unless ``log_failure=False``: a tool that says it
    itself) and :meth:`close` finishes the file of
    every whole chunk (:class:`~cdpr_dynamics.recording.writer.ChunkedFile`).
    """

    def __init__(self, node, path, topics, *, force: bool = False,
                 chunk_size: int = DEFAULT_CHUNK_SIZE,
                 chunk_interval_s: float = DEFAULT_CHUNK_INTERVAL_S,
                 compression: str = 'none', qos_depth: int = QOS_DEPTH,
                 log_failure: bool = True):
        from rclpy.clock import Clock, ClockType

        self._node = node
        self.path = Path(path)
        self.error: str | None = None
        self._log_failure = log_failure
        self._chunk_interval_ns = int(chunk_interval_s * 1e9)
        self._qos_depth = int(qos_depth)
        self._lock = threading.RLock()
        self._closed = False
        self._summary = None
        self._schemas: dict[str, int] = {}
        self._chunk_started_ns = None   # monotonic time of the oldest unwritten message
        self._topics: dict[str, _Topic] = {}
        for name, typ in normalise_topics(topics).items():
            try:
                resolved = node.resolve_topic_name(name)
            except Exception as err:  # noqa: BLE001 - rclpy's invalid-name exceptions
                raise RecordingError(f'invalid topic name {name!r}: {reason(err)}') from None
            if typ is not None:
                try:
                    mcap_schema.split_type_name(typ)
                except mcap_schema.SchemaError as err:
                    raise RecordingError(str(err)) from None
            self._topics[resolved] = _Topic(resolved, typ)
        if not self._topics:
            raise RecordingError('no topics to record')

        self._file = ChunkedFile(self.path, force=force, chunk_size=chunk_size,
                                 compression=compression)

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
        if self._closed or self.error is not None:
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
                schema_id = self._file.register_schema(
                    type_name, mcap_schema.SCHEMA_ENCODING, definition.encode('utf-8'))
                self._schemas[type_name] = schema_id
            topic.channel_id = self._file.register_channel(
                topic.name, mcap_schema.MESSAGE_ENCODING, schema_id,
                {'offered_qos_profiles': mcap_schema.offered_qos_profiles_yaml(topic.qos),
                 'topic_type_hash': topic.type_hash})
            self._check_file()

        def on_message(data, info, topic=topic):
            self._write(topic, data, info)
            self._take_more(topic)

        topic.subscription = self._node.create_subscription(
            cls, topic.name, on_message, qos, raw=True)

    # -- writing ----------------------------------------------------------------------------

    def _write(self, topic: _Topic, data: bytes, info) -> None:
        """One message: log time = when the middleware received it (its message info, the
        system clock), so that a recorder polled in batches or lagging behind logs arrival,
        not its own take; the node's ROS time where that is simulated, the take's system time
        where the middleware gives no reception time."""
        sent = received = sequence = 0
        if isinstance(info, Mapping):
            sent = info.get('source_timestamp') or 0
            received = info.get('received_timestamp') or 0
            sequence = info.get('publication_sequence_number') or 0
        clock = self._clock
        now = received if received > 0 and not clock.ros_time_is_active else clock_ns(clock)
        with self._lock:
            if self._closed:
                return
            chunks = self._file.chunk_count
            if not self._file.add_message(topic.channel_id, now, data,
                                          sent if sent > 0 else now, sequence & 0xFFFFFFFF):
                self._check_file()
                return
            if topic.count == 0:
                topic.first_sequence = sequence
            topic.count += 1
            mono = time.monotonic_ns()
            if self._file.chunk_count != chunks:    # closed by its size: nothing unwritten
                self._chunk_started_ns = None
            elif self._chunk_started_ns is None:
                self._chunk_started_ns = mono
            elif mono - self._chunk_started_ns >= self._chunk_interval_ns:
                self._flush_locked()

    def _take_more(self, topic: _Topic) -> int:
        """Take the messages already waiting on this subscription without a trip through the
        executor (its per-message cost is ~15 times that of writing); bounded, so timers and
        other topics still get their turn. How many it took."""
        subscription = topic.subscription
        for count in range(_TAKE_BATCH):
            try:
                with subscription.handle:
                    taken = subscription.handle.take_message(subscription.msg_type, True)
            except Exception:  # noqa: BLE001 - destroyed meanwhile: the executor resumes
                return count
            if taken is None:
                return count
            self._write(topic, taken[0], taken[1])
        return _TAKE_BATCH

    def _flush_locked(self) -> None:
        self._file.flush()   # closes the open chunk (if it has messages), writes it out
        self._chunk_started_ns = None
        self._check_file()

    def _check_file(self) -> None:
        """After a failed write: stop recording (the file keeps its whole chunks)."""
        if self._file.error is not None and self.error is None:
            self.error = self._file.error
            if not self._log_failure:
                return
            self._node.get_logger().error(
                f'{self.error}; recording stopped, the file keeps '
                f'{self._file.message_count} messages in {self._file.chunk_count} chunks')

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

    def poll(self) -> None:
        """For a recorder whose node no executor spins (its callbacks and timer never run):
        take everything waiting on each subscription, close an old chunk, discover new
        publishers. Called every few tens of ms (queues deep enough for the gap), it wakes its
        thread once per call instead of once per message (``cdpr_demo`` does this). Up to
        ``_TAKE_BATCH`` messages per topic and call."""
        for topic in list(self._topics.values()):
            if topic.subscription is not None and not self._closed:
                self._take_more(topic)
        self._on_tick()

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
        # what reached the subscriptions before the stop is the user's: write it first (a
        # subscriber that lagged holds up to its queue depth; bounded by _DRAIN_BATCHES)
        for topic in list(self._topics.values()):
            if topic.subscription is not None:
                for _ in range(_DRAIN_BATCHES):
                    if self._take_more(topic) < _TAKE_BATCH:
                        break
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
            self._file.flush()
            counts = self._file.counts      # what the file holds (all, unless a write failed)
            start_ns, end_ns = self._file.time_range
            recorded = [t for t in self._topics.values() if t.channel_id is not None]
            self._file.finish([(mcap_schema.ROSBAG2_METADATA_NAME, {
                'serialized_metadata': mcap_schema.rosbag2_serialized_metadata(
                    self.path.name,
                    [{'name': t.name, 'type': t.type, 'offered_qos_profiles': t.qos,
                      'type_description_hash': t.type_hash,
                      'message_count': counts.get(t.channel_id, 0)} for t in recorded],
                    start_ns, end_ns)})])
            self._check_file()
            topics = {name: counts.get(t.channel_id, 0) if t.channel_id is not None else 0
                      for name, t in self._topics.items()}
            self._summary = RecordingSummary(
                path=self.path, message_count=sum(topics.values()), bytes=self._file.bytes,
                chunk_count=self._file.chunk_count, topics=topics, start_ns=start_ns,
                end_ns=end_ns, complete=self._file.complete, error=self.error,
                warnings=tuple(self._missed()))
        for line in self._summary.warnings:
            self._node.get_logger().warning(line)
        return self._summary

    def _missed(self):
        """One line per subscribed topic whose early messages the file may lack."""
        for t in self._topics.values():
            if t.subscription is None:
                continue                      # no publisher appeared: nothing was missed
            latched = bool(t.qos) and all(q['durability'] == 'transient_local' for q in t.qos)
            kept = ' (its publishers keep only their last messages for late subscribers)' \
                if latched else ''
            if t.count == 0 and not latched:    # a latched history would have been delivered
                yield (f'{t.name}: no message recorded although it has a publisher; one it '
                       f'published before the recorder subscribed is not in the file')
            elif len(t.qos) == 1 and t.first_sequence > 1:
                yield (f'{t.name}: the first {t.first_sequence - 1} message(s) of its publisher '
                       f'came before the recorder subscribed and are not in the file{kept}')

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
