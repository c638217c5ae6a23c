"""Writing MCAP files: :class:`RecordingWriter` (given messages, no ROS graph) and
:class:`ChunkedFile` (the live recorder's file, which stays readable when writing fails).
"""
from __future__ import annotations

import errno
import fcntl
import glob
import itertools
import os
import resource
import struct
import tempfile
from pathlib import Path
from typing import Mapping

import numpy as np
from mcap.records import MessageIndex

from cdpr_dynamics.recording.base import (
    compression_type, count_chunks, DEFAULT_CHUNK_SIZE, mcap_writer, RecordingError,
    RecordingSummary, temporary_file, type_name_of)
from cdpr_dynamics.recording.cdr import serialize
from msg_adapters import mcap_schema


class RecordingWriter:
    """Writes given messages to a new MCAP file with the recorder's conventions, no ROS graph.

    For tools that make recordings themselves (``cdpr_replay``, the test scenarios): same
    profile, ``ros2msg`` schemas from the installed ``.msg`` files, ``cdr`` channels with
    rosbag2's channel metadata, indexed chunks and the ``rosbag2`` metadata record.

    The file is written under a hidden temporary name in the destination folder
    (``.NAME.partial-XXXX``) and renamed to ``path`` only by :meth:`close`, so a file at
    ``path`` is always complete; :meth:`abort` (or an exception in a ``with`` block) deletes
    the temporary file, :meth:`keep_partial` finishes it under its temporary name. The writer
    holds an exclusive ``flock`` on the temporary file while it writes, so a temporary file
    nobody holds is the leftover of a killed writer (:func:`partial_files`). An existing
    ``path`` is refused unless ``force``, at start and again at the rename. Not thread-safe.
    """

    def __init__(self, path, *, force: bool = False, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = 'none', library: str | None = None):
        self.path = Path(path)
        self._force = force
        compression_type(compression)   # an unknown one fails before any file appears
        folder = self.path.parent
        if not folder.is_dir():
            raise RecordingError(f'cannot write {self.path}: no directory {folder}')
        if self.path.is_dir():
            raise RecordingError(f'cannot write {self.path}: it is a directory')
        if os.path.lexists(self.path) and not force:
            raise RecordingError(
                f'{self.path} exists; not overwriting it (use --force to replace it)')
        fd, self.temp_path = temporary_file(self.path)
        self._stream = None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            self._stream = os.fdopen(fd, 'wb')
            self._writer = mcap_writer(self._stream, chunk_size, compression, library)
        except BaseException as err:   # a write error, or Ctrl-C before any `with` can abort
            try:
                if self._stream is None:
                    os.close(fd)
                else:
                    self._stream.close()
            except OSError:
                pass
            os.unlink(self.temp_path)
            if isinstance(err, OSError):
                raise RecordingError(f'cannot write {self.path}: {err.strerror or err}') from None
            raise
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, dict] = {}
        self._metadata: list[tuple[str, dict]] = []
        self._state = 'open'
        self._appender = MessageAppender(self._writer)
        self.summary: RecordingSummary | None = None

    @property
    def topic_counts(self) -> dict:
        """Topic -> messages written so far."""
        counts = self._appender.counts
        return {name: counts.get(t['channel'], 0) for name, t in self._topics.items()}

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
            offered_qos = qos_from_yaml(offered_qos)
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
                              'hash': type_hash, 'write': self._appender.channel(channel_id)}

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
        entry['write'](data, log_time_ns,
                       log_time_ns if publish_time_ns is None else int(publish_time_ns))

    def channel_writer(self, topic: str):
        """``write(data, log_time_ns, publish_time_ns)`` for CDR bytes on a declared topic, for
        loops that write millions: :meth:`write` without its checks and conversions."""
        self._check_open()
        entry = self._topics.get(topic)
        if entry is None:
            raise RecordingError(f'topic {topic} was not declared with add_topic')
        return entry['write']

    def channel_id(self, topic: str) -> int:
        """The channel of a declared topic, for :meth:`write_many`."""
        self._check_open()
        entry = self._topics.get(topic)
        if entry is None:
            raise RecordingError(f'topic {topic} was not declared with add_topic')
        return entry['channel']

    def write_many(self, channel_ids, datas, log_times, publish_times) -> None:
        """CDR bytes on channels (:meth:`channel_id`) in order: what as many writes of
        :meth:`channel_writer` would do, for a run of messages at once."""
        self._check_open()
        self._appender.many(channel_ids, datas, log_times, publish_times)

    def add_metadata(self, name: str, values: Mapping[str, str], now: bool = False) -> None:
        """A metadata record (string keys and values), written when the file is finished, or
        at once with ``now`` (then a killed writer's partial file holds it too)."""
        self._check_open()
        values = {str(k): str(v) for k, v in values.items()}
        if now:
            self._writer.add_metadata(name, values)
        else:
            self._metadata.append((name, values))

    def keep_partial(self, metadata=()) -> Path:
        """Finish the file (summary, index, the ``metadata`` records: (name, dict) pairs) but
        keep it under its temporary name, e.g. for a later run to continue; its path.
        Afterwards the writer is closed."""
        self._check_open()
        try:
            for name, values in metadata:
                self._writer.add_metadata(name, dict(values))
            self._writer.finish()
            self._stream.close()
        except OSError as err:
            self.abort()
            raise RecordingError(f'cannot write {self.temp_path}: {err.strerror or err}') \
                from None
        self._state = 'kept'
        return self.temp_path

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
                      'type_description_hash': t['hash'],
                      'message_count': self._appender.counts.get(t['channel'], 0)}
                     for name, t in self._topics.items()],
                    *self._appender.time_range)})
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
            chunk_count=count_chunks(self.path), topics=self.topic_counts,
            start_ns=self._appender.time_range[0], end_ns=self._appender.time_range[1])
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


_MESSAGE_HEAD = struct.Struct('<BQHIQQ')   # opcode, record length, channel, sequence, times


class _MessageIndex(MessageIndex):
    """A chunk's message index for one channel, written in one ``struct`` call (the ``mcap``
    record writes two calls per message)."""

    def write(self, stream) -> None:
        count = len(self.records)
        stream.write(struct.pack(f'<BQHI{2 * count}Q', 0x07, 6 + 16 * count, self.channel_id,
                                 16 * count, *itertools.chain.from_iterable(self.records)))


class MessageAppender:
    """Adds messages to an ``mcap`` writer's open chunk: the records, message indexes and
    statistics its ``add_message`` makes, without the record object that costs most of its time.
    It works on the writer's private state (mcap 1.1 to 1.6 have it; the recorder's
    :class:`_WriterState` does too); a sequence number per channel counts its messages from 1."""

    def __init__(self, writer):
        try:
            self._stats = writer._Writer__statistics
            self._chunk = writer._Writer__chunk_builder
            self._finalize = writer._Writer__maybe_finalize_chunk
            self._limit = writer._Writer__chunk_size
            self._chunk.record_writer._buffer.tell
        except AttributeError:
            raise RecordingError('this mcap version is not supported (its writer lacks the '
                                 'state the message appender fills)') from None
        self.counts = self._stats.channel_message_counts

    @property
    def time_range(self) -> tuple[int, int]:
        """Log times (ns) of the first and last message written (0, 0: none)."""
        stats = self._stats
        return ((stats.message_start_time, stats.message_end_time) if stats.message_count
                else (0, 0))

    def channel(self, channel_id: int):
        """``write(data, log_time_ns, publish_time_ns)`` on one channel."""
        stats, chunk, counts = self._stats, self._chunk, self.counts
        finalize, limit, pack = self._finalize, self._limit, _MESSAGE_HEAD.pack

        def write(data: bytes, log_time: int, publish_time: int) -> None:
            if stats.message_count == 0 or log_time < stats.message_start_time:
                stats.message_start_time = log_time
            if log_time > stats.message_end_time:
                stats.message_end_time = log_time
            sequence = counts[channel_id] = counts[channel_id] + 1
            stats.message_count += 1
            if chunk.num_messages == 0 or log_time < chunk.message_start_time:
                chunk.message_start_time = log_time
            if log_time > chunk.message_end_time:
                chunk.message_end_time = log_time
            index = chunk.message_indices.get(channel_id)
            if index is None:
                index = chunk.message_indices[channel_id] = _MessageIndex(channel_id, [])
            buffer = chunk.record_writer._buffer
            index.records.append((log_time, buffer.tell()))
            chunk.num_messages += 1
            buffer.write(pack(0x05, 22 + len(data), channel_id, sequence & 0xFFFFFFFF,
                              log_time, publish_time))
            buffer.write(data)
            if buffer.tell() > limit:
                finalize()
        return write

    def many(self, channel_ids, datas, log_times, publish_times) -> None:
        """Messages in order, as :meth:`channel`'s writes one by one would add them (the same
        records, indexes and chunk boundaries): the record heads of a chunk's share made in
        one array, its records in one buffer write."""
        count = len(datas)
        if not count:
            return
        stats, chunk, counts = self._stats, self._chunk, self.counts
        sizes = np.fromiter(map(len, datas), np.int64, count) + _MESSAGE_HEAD.size
        channels = np.asarray(channel_ids, dtype=np.uint16)
        logs = np.asarray(log_times, dtype=np.uint64)
        publish = np.asarray(publish_times, dtype=np.uint64)
        i = 0
        while i < count:
            buffer = chunk.record_writer._buffer
            ends = buffer.tell() + np.cumsum(sizes[i:])
            stop = i + min(int(np.searchsorted(ends, self._limit, side='right')) + 1,
                           count - i)          # through the record that passes the limit
            ends, part = ends[:stop - i], slice(i, stop)
            heads = np.empty(stop - i, _HEAD_DTYPE)
            heads['opcode'], heads['length'] = 0x05, sizes[part] - 9
            heads['channel'], heads['log'], heads['publish'] = (channels[part], logs[part],
                                                                publish[part])
            sequences = heads['sequence']
            offsets = (ends - sizes[part]).tolist()
            mine = channels[part]
            ids, first = np.unique(mine, return_index=True)
            for channel_id in ids[np.argsort(first)].tolist():    # indexes in order of use
                where = np.flatnonzero(mine == channel_id)
                base = counts[channel_id]
                sequences[where] = (base + 1 + np.arange(where.size)) & 0xFFFFFFFF
                counts[channel_id] = base + where.size
                index = chunk.message_indices.get(channel_id)
                if index is None:
                    index = chunk.message_indices[channel_id] = _MessageIndex(channel_id, [])
                index.records.extend(zip(logs[part][where].tolist(),
                                         [offsets[k] for k in where.tolist()]))
            low, high = int(logs[part].min()), int(logs[part].max())
            if chunk.num_messages == 0 or low < chunk.message_start_time:
                chunk.message_start_time = low
            chunk.message_end_time = max(chunk.message_end_time, high)
            chunk.num_messages += stop - i
            if stats.message_count == 0 or low < stats.message_start_time:
                stats.message_start_time = low
            stats.message_end_time = max(stats.message_end_time, high)
            stats.message_count += stop - i
            raw = heads.tobytes()
            size = _MESSAGE_HEAD.size
            buffer.write(b''.join(itertools.chain.from_iterable(zip(
                [raw[k:k + size] for k in range(0, len(raw), size)], datas[i:stop]))))
            i = stop
            if int(ends[-1]) > self._limit:
                self._finalize()


_HEAD_DTYPE = np.dtype([('opcode', 'u1'), ('length', '<u8'), ('channel', '<u2'),
                        ('sequence', '<u4'), ('log', '<u8'), ('publish', '<u8')])  # packed


def partial_files(path) -> list:
    """The temporary files of writers of ``path`` (``.NAME.partial-*`` beside it) that no
    running writer holds: the leftovers of killed or interrupted ones, newest first."""
    path = Path(path)
    found = []
    for candidate in path.parent.glob(f'.{glob.escape(path.name)}.partial-*'):
        try:
            fd = os.open(candidate, os.O_RDONLY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            continue    # a running writer holds it
        finally:
            os.close(fd)
        found.append(candidate)
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


def qos_from_yaml(text: str) -> list:
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


# ----------------------------------------------------------------------------- the recorder's file
FIRST_CHUNK_BYTES = 16 * 1024   # the first chunk's bound; each next one doubles, to chunk_size
RESERVE_BYTES = 16 * 1024       # margin kept to finish the file, beyond the summary's estimate
_CHUNK_INDEX_BYTES = 96         # a chunk index record, plus 10 per channel
_TOPIC_METADATA_BYTES = 1536    # a topic's share of the rosbag2 metadata record


class _Stream:
    """The file as the ``mcap`` writer sees it: unbuffered, every write whole or an error.

    ``limit`` (bytes, None: none) refuses a write that would end past it, before writing any
    of it (:data:`errno.EFBIG`), so what is below the limit stays free to finish the file."""

    def __init__(self, fd: int):
        self.fd = fd
        self.position = 0
        self.limit = None

    def write(self, data) -> int:
        view = memoryview(data).cast('B')
        if self.limit is not None and self.position + len(view) > self.limit:
            raise OSError(errno.EFBIG, 'File too large (the file-size limit, less the room '
                                       'kept to finish the file)')
        while view:
            written = os.write(self.fd, view)
            self.position += written
            view = view[written:]
        return len(data)

    def tell(self) -> int:
        return self.position

    def flush(self) -> None:
        pass


class _WriterState:
    """What the ``mcap`` writer counts, saved after each whole record written and put back
    after a failed write: the statistics, chunk and metadata indexes of the file on disk.

    These are the writer's private attributes (mcap 1.1 to 1.6 have them); the full-disk tests
    of ``test/test_recording.py`` fail first if a new mcap renames them.
    """

    def __init__(self, writer):
        self._stats = writer._Writer__statistics
        self._chunk = writer._Writer__chunk_builder
        self._records = writer._Writer__record_builder
        self._chunk_indexes = writer._Writer__chunk_indices
        self._metadata_indexes = writer._Writer__metadata_indexes
        self._summary_offsets = writer._Writer__summary_offsets
        self.save()

    @property
    def open_chunk_bytes(self) -> int:
        return self._chunk.count

    def save(self) -> None:
        s = self._stats
        self.saved = (s.message_count, dict(s.channel_message_counts), s.message_start_time,
                      s.message_end_time, s.chunk_count, s.metadata_count,
                      len(self._chunk_indexes), len(self._metadata_indexes))

    def restore(self) -> None:
        s = self._stats
        (s.message_count, counts, s.message_start_time, s.message_end_time, s.chunk_count,
         s.metadata_count, chunks, metadata) = self.saved
        s.channel_message_counts.clear()
        s.channel_message_counts.update(counts)
        del self._chunk_indexes[chunks:]
        del self._metadata_indexes[metadata:]
        del self._summary_offsets[:]
        self._chunk.reset()
        self._records.end()

    @property
    def counts(self) -> dict:
        """Channel id -> messages in the chunks written (as saved)."""
        return dict(self.saved[1])


class ChunkedFile:
    """A recording being written that stays readable when writing fails.

    The ``mcap`` writer (:func:`~cdpr_dynamics.recording.base.mcap_writer`) writes straight to
    the file, so the file ends on a whole record after every call here. Chunks are closed by
    :meth:`flush` or when they reach their bound: :data:`FIRST_CHUNK_BYTES` for the first,
    twice the previous one's for each next, up to ``chunk_size``; so a nearly full disk still
    keeps the first messages.

    Room to finish: beside the file, a reserve of disk (an unlinked file of
    :data:`RESERVE_BYTES` plus the estimated size of the summary, grown as chunks are written);
    under a file-size limit (``ulimit -f``) the file stops that many bytes below it.

    When a write fails (disk full, file-size limit, I/O error), the file is cut back to its last
    whole chunk, :attr:`error` holds the one-line cause and later writes are dropped;
    :meth:`finish` then releases the reserve and writes the summary and footer, so the file is
    complete with every message of its whole chunks (``complete``). If even that fails, the file
    stays cut at the chunk boundary: ``mcap``'s stream reader and
    :func:`~cdpr_dynamics.recording.recovery.recover_recording` read it. Not thread-safe.
    """

    def __init__(self, path, *, force: bool = False, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = 'none'):
        self.path = Path(path)
        self.error: str | None = None
        self.complete = False
        self._chunk_size = int(chunk_size)
        self._bound = min(FIRST_CHUNK_BYTES, self._chunk_size)
        compression_type(compression)
        folder = self.path.parent
        if not folder.is_dir():
            raise RecordingError(f'cannot write {self.path}: no directory {folder}')
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if force else os.O_EXCL)
        try:
            self._fd = os.open(self.path, flags, 0o666)
        except FileExistsError:
            raise RecordingError(
                f'{self.path} exists; not overwriting it (use --force to replace it)') from None
        except OSError as err:
            raise RecordingError(f'cannot write {self.path}: {err.strerror or err}') from None
        self._stream = _Stream(self._fd)
        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        self._size_limit = None if soft == resource.RLIM_INFINITY else int(soft)
        self._reserve = None
        self._reserved = 0
        self._definitions = 0     # bytes of schemas and channels (repeated in the summary)
        try:
            self._reserve = tempfile.TemporaryFile(dir=folder)   # unlinked: freed on exit
            self._writer = mcap_writer(self._stream, self._chunk_size, compression)
            self._state = _WriterState(self._writer)
            self._committed = self._stream.position
            self._grow_reserve()
        except BaseException as err:   # no file is left behind
            self._close_fd()
            os.unlink(self.path)
            if isinstance(err, OSError):
                raise RecordingError(f'cannot write {self.path}: {err.strerror or err} (no '
                                     'room for the start of a recording)') from None
            if isinstance(err, AttributeError):
                raise RecordingError('this mcap version is not supported by the recorder (its '
                                     'writer lacks the state restored after a failed write)'
                                     ) from None
            raise

    # -- state ----------------------------------------------------------------------------

    @property
    def message_count(self) -> int:
        """Messages in the chunks written to the file."""
        return self._state.saved[0]

    @property
    def chunk_count(self) -> int:
        """Chunks written to the file."""
        return self._state.saved[4]

    @property
    def counts(self) -> dict:
        """Channel id -> messages in the chunks written to the file."""
        return self._state.counts

    @property
    def time_range(self) -> tuple[int, int]:
        """Log times (ns) of the first and last message in the chunks written (0, 0: none)."""
        return (self._state.saved[2], self._state.saved[3]) if self.message_count else (0, 0)

    @property
    def bytes(self) -> int:
        """Size of the file so far."""
        return self._stream.position

    # -- writing ----------------------------------------------------------------------------

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        self._definitions += len(data) + len(name) + 32
        return self._call(self._writer.register_schema, name, encoding, data)

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: Mapping[str, str]) -> int:
        self._definitions += len(topic) + 32 + sum(len(k) + len(v) + 8
                                                   for k, v in metadata.items())
        return self._call(self._writer.register_channel, topic, message_encoding, schema_id,
                          dict(metadata))

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int = 0) -> bool:
        """Add one message to the open chunk (closed if it reaches its bound); False once the
        file has failed (the message is dropped)."""
        if self.error is not None:
            return False
        self._call(self._writer.add_message, channel_id, log_time, data, publish_time,
                   sequence)
        if self.error is None and self._state.open_chunk_bytes >= self._bound:
            self.flush()
        return self.error is None

    def flush(self) -> None:
        """Write the open chunk (if it has messages) to the file."""
        if self.error is None:
            self._call(self._writer.flush)

    def _call(self, method, *args):
        if self.error is not None:
            return 0
        start = self._stream.position
        try:
            result = method(*args)
        except OSError as err:
            self._fail(err)
            return 0
        if self._stream.position != start:     # a chunk (or a record) went to the file
            self._state.save()
            self._committed = self._stream.position
            self._bound = min(2 * self._bound, self._chunk_size)
            try:
                self._grow_reserve()
            except OSError as err:
                self._fail(err)
        return result

    def _needed(self) -> int:
        """Bytes to finish the file: the summary (schemas, channels, statistics, one index
        entry per chunk), the rosbag2 metadata record and a margin."""
        channels = self._state._stats.channel_count
        return (RESERVE_BYTES + self._definitions + _TOPIC_METADATA_BYTES * channels
                + (_CHUNK_INDEX_BYTES + 10 * channels) * (self.chunk_count + 1))

    def _grow_reserve(self) -> None:
        needed = self._needed()
        if self._size_limit is not None:
            self._stream.limit = self._size_limit - needed
        if needed > self._reserved:
            size = needed + RESERVE_BYTES
            try:
                os.posix_fallocate(self._reserve.fileno(), 0, size)
            except OSError as err:
                if err.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
                    raise
                os.pwrite(self._reserve.fileno(), bytes(size - self._reserved),
                          self._reserved)   # a file system without fallocate
            self._reserved = size

    def _fail(self, err: OSError) -> None:
        """Keep the whole chunks: cut the file back to the last one, stop writing."""
        self.error = f'cannot write {self.path}: {err.strerror or err}'
        self._state.restore()
        self._cut()

    def _cut(self) -> None:
        """Cut the file back to the end of the last whole record written."""
        end = self._committed
        try:
            os.ftruncate(self._fd, end)
            os.lseek(self._fd, end, os.SEEK_SET)
        except OSError:
            pass
        self._stream.position = end

    # -- finishing --------------------------------------------------------------------------

    def finish(self, metadata=()) -> None:
        """Write the open chunk, the ``metadata`` records ((name, dict) pairs), summary and
        footer, with the reserve released; on a write error, the file of the whole chunks
        (see the class). Idempotent; never raises for a write error (see :attr:`error`)."""
        if self._fd is None:
            return
        self.flush()
        if self._reserve is not None:
            self._reserve.close()
            self._reserve = None
        self._stream.limit = self._size_limit
        if self.error is None:
            try:
                for name, values in metadata:
                    self._writer.add_metadata(name, dict(values))
                self._writer.finish()
                self.complete = True
            except OSError as err:
                self._fail(err)
        if not self.complete:       # after a failure: the whole chunks, no metadata record
            try:
                self._writer.finish()
                self.complete = True
            except OSError:
                self._state.restore()
                self._cut()
        try:
            os.fsync(self._fd)
        except OSError:
            pass
        self._close_fd()

    def _close_fd(self) -> None:
        if self._fd is not None:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = None
        if self._reserve is not None:
            self._reserve.close()
            self._reserve = None
