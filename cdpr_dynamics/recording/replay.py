"""Replay a recording's pose and wrench messages through the live core (``cdpr_replay``).

Offline (:func:`replay_offline`): the ``pose`` (PoseStamped) and ``wrench`` (WrenchStamped)
messages of an MCAP file (one written here, or by ``ros2 bag record -s mcap``: the file or its
bag directory; the topics may carry a namespace) go, in log-time order (or header-stamp
order), through :class:`InputHandler` - the checks and the
:class:`~cdpr_dynamics.analysis.live.LivePredictor` calls of ``dynamics_node``'s callbacks - and a
new
MCAP file gets the inputs (their CDR bytes unchanged) plus what the node would have published:

* ``predicted_displacement`` (Vector3Stamped): one per accepted wrench, stamped with the
  wrench's stamp, in ``robot.frame_id``;
* ``cable_tensions`` (JointState, position = length m, effort = tension N): one per accepted
  pose, stamped with the pose's stamp;
* ``/diagnostics`` (DiagnosticArray): one per rejected input, status ``cdpr_dynamics: pose
  input`` (ERROR) or ``cdpr_dynamics: wrench input`` (WARN), message = the reason, values
  ``kind``, ``topic``, ``stamp_ns``.

The outputs sit beside their inputs (``/ns/wrench`` -> ``/ns/predicted_displacement``), with log
and publish time those of the input that caused them. The file has the recorder's schemas and
channel metadata (:class:`cdpr_dynamics.recording.writer.RecordingWriter`), a ``cdpr_replay``
metadata record (input, topics, order, method, parameters) and appears under its name only when
complete.

Live (:func:`replay_live`): republishes the messages on ``pose`` and ``wrench`` (relative
names: ``--ros-args -r __ns:=/robot`` or remapping place them) with the recorded log-time
spacing divided by ``rate``, after waiting for subscribers.

:func:`compare_outputs` matches the predictions of two files by header stamp within a tolerance
(the golden-recording tests).
"""
from __future__ import annotations

import heapq
import io
import itertools
import json
import math
import operator
import struct
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from cdpr_dynamics.analysis.config import (NODE_PARAMETER_BY_NAME, Settings, node_options,
                                           read_params_file, settings_from_params)
from cdpr_dynamics.analysis.live import Checkpoint, LivePredictor, PoseUpdate, same_model
from cdpr_dynamics.recording.base import RecordingError, UndecodableMessage
from cdpr_dynamics.recording.reader import McapFile, read_messages, recording_info, Salvage
from cdpr_dynamics.recording import chunks
from cdpr_dynamics.recording.cdr import serialize
from cdpr_dynamics.recording.writer import partial_files, RecordingWriter
from msg_adapters import diagnostics as diag
from msg_adapters.displacement import read_displacement
from msg_adapters.inputs import InputHandler
from msg_adapters.joint_state import read_tensions, tensions_message
from msg_adapters.mcap_schema import (CdrError, decode_stamped, decode_stamped_run,
                                      encode_stamped, encode_stamped_run)
from msg_adapters.validation import InvalidMessage, ns_to_stamp, stamp_to_ns

POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
WRENCH_TYPE = 'geometry_msgs/msg/WrenchStamped'
DISPLACEMENT_TYPE = 'geometry_msgs/msg/Vector3Stamped'
TENSIONS_TYPE = 'sensor_msgs/msg/JointState'
DIAGNOSTICS_TYPE = 'diagnostic_msgs/msg/DiagnosticArray'
DIAGNOSTICS_TOPIC = '/diagnostics'
NODE_NAME = 'cdpr_dynamics'
HARDWARE_ID = 'cdpr_replay'
ORDERS = ('log', 'stamp')
REPLAY_METADATA = 'cdpr_replay'   # the metadata record naming a replay's input and settings
CHECKPOINT_METADATA = 'cdpr_replay_checkpoint'   # an interrupted replay's state to resume
CHECKPOINT_EVERY = 1024   # input messages between two states kept for a checkpoint
COUNTERS = ('poses', 'wrenches', 'poses_accepted', 'wrenches_accepted', 'rebuilds', 'skipped',
            'first_skipped', 'before_first_pose')    # a summary's counts a checkpoint keeps


class ReplayError(RuntimeError):
    """A replay that cannot be done as asked; the message is one line."""


# ----------------------------------------------------------------------------- the node's inputs


@dataclass(frozen=True)
class NodeOptions:
    """The node-only parameters that shape how inputs are accepted (``node.*``)."""

    pose_tolerance_m: float = NODE_PARAMETER_BY_NAME['node.pose_tolerance_m'].default
    angle_tolerance_rad: float = NODE_PARAMETER_BY_NAME['node.angle_tolerance_rad'].default
    quaternion_tolerance: float = NODE_PARAMETER_BY_NAME['node.quaternion_tolerance'].default
    output_point_m: tuple = tuple(NODE_PARAMETER_BY_NAME['node.output_point_m'].default)
    slack: str = NODE_PARAMETER_BY_NAME['node.slack'].default

    def __post_init__(self):
        """Keep ``output_point_m`` a tuple of floats (hashable, JSON in the metadata)."""
        object.__setattr__(self, 'output_point_m', tuple(float(v) for v in self.output_point_m))

    @classmethod
    def from_params(cls, flat: dict) -> 'NodeOptions':
        """From flat parameters (a params file), validated as the node validates them."""
        options = node_options(flat)
        return cls(**{f.name: options[f'node.{f.name}'] for f in fields(cls)})


def load_replay_config(path=None) -> tuple[Settings, NodeOptions, dict]:
    """Settings, node options and the flat parameters of a ROS 2 params file (default: the
    installed paper config)."""
    from cdpr_dynamics.analysis.config import default_config_path

    flat = read_params_file(path or default_config_path())
    return settings_from_params(flat), NodeOptions.from_params(flat), flat


def rejection_message(what: str, exc: InvalidMessage, topic: str, stamp):
    """The /diagnostics message of one rejected input (``what``: 'pose' or 'wrench')."""
    level = diag.ERROR if what == 'pose' else diag.WARN   # the node's levels for its inputs
    status = diag.status_message(
        f'{NODE_NAME}: {what} input', level, str(exc),
        {'kind': exc.kind, 'topic': topic, 'stamp_ns': stamp_to_ns(stamp)}, HARDWARE_ID)
    return diag.diagnostics_message([status], stamp)


# ----------------------------------------------------------------------------- input topics


def _namespace(topic: str) -> str:
    return topic.rsplit('/', 1)[0]


def _absolute(name: str) -> str:
    return name if name.startswith('/') else '/' + name


def find_input_topics(info, pose_topic: str | None = None,
                      wrench_topic: str | None = None) -> tuple[str, str]:
    """The pose and wrench topics of a recording: the given names, or the one topic named
    ``pose`` (``wrench``), with or without a namespace. Raises :class:`ReplayError`."""
    topics = {name: t.type for name, t in info.topics.items()}
    listing = ', '.join(f'{n} ({t.rsplit("/", 1)[-1]})' for n, t in sorted(topics.items()))
    listing = listing or 'none'

    def pick(given, base, type_name, flag):
        if given:
            name = _absolute(given)
            if name not in topics:
                raise ReplayError(f'{info.path}: no topic {name} (topics: {listing})')
            candidates = [name]
        else:
            candidates = [n for n in topics if n.rsplit('/', 1)[-1] == base]
            if not candidates:
                raise ReplayError(f'{info.path}: no {base} topic ({type_name} on .../{base}); '
                                  f'topics: {listing}; name one with {flag}')
        typed = [n for n in candidates if topics[n] == type_name]
        if not typed:
            name = candidates[0]
            raise ReplayError(f'{info.path}: topic {name} has type {topics[name] or "unknown"}, '
                              f'expected {type_name}')
        if len(typed) > 1:
            raise ReplayError(f'{info.path}: several {base} topics ({", ".join(sorted(typed))}); '
                              f'choose one with {flag}')
        return typed[0]

    return (pick(pose_topic, 'pose', POSE_TYPE, '--pose-topic'),
            pick(wrench_topic, 'wrench', WRENCH_TYPE, '--wrench-topic'))


def resolve_input(path) -> Path:
    """The MCAP file to read: ``path`` itself, or the one ``.mcap`` file of a bag directory
    (what ``ros2 bag record -s mcap`` makes). Raises :class:`ReplayError`."""
    path = Path(path)
    if not path.is_dir():
        return path
    files = sorted(path.glob('*.mcap'))
    if len(files) == 1:
        return files[0]
    if not files:
        raise ReplayError(f'{path} is a directory without an .mcap file')
    raise ReplayError(f'{path} is a bag split into {len(files)} files '
                      f'({", ".join(f.name for f in files[:3])}...): replay them one by one')


def inspect_input(input_path, pose_topic: str | None = None, wrench_topic: str | None = None,
                  allow_incomplete: bool = False):
    """Check an input before replaying it: (RecordingInfo, pose topic, wrench topic, number of
    input messages). Raises :class:`ReplayError` / ``RecordingError`` with one line."""
    info = recording_info(input_path)
    if not info.complete and not allow_incomplete:
        raise ReplayError(f'{info.path}: incomplete MCAP file (no footer or index: cut short, '
                          'or its recorder was killed); --allow-incomplete replays what '
                          'survives')
    if not info.complete and not info.message_count:
        raise ReplayError(f'{info.path}: incomplete MCAP file, and no message survives in it '
                          '(no complete chunk)')
    pose, wrench = find_input_topics(info, pose_topic, wrench_topic)
    total = info.topics[pose].message_count + info.topics[wrench].message_count
    if total == 0 and info.complete:
        raise ReplayError(f'{info.path}: {pose} and {wrench} hold no messages')
    return info, pose, wrench, total


def _input_stream(path, pose, wrench, allow_incomplete: bool):
    """Decoded input messages (RawRecordedMessage) in log-time order, for the live replay."""
    return read_messages(path, {pose: POSE_TYPE, wrench: WRENCH_TYPE}, raw=True,
                         allow_incomplete=allow_incomplete)


# ----------------------------------------------------------------------------- stamp order

#: messages (and bytes of them) sorted in memory at once by ``--order stamp``; a longer input
#: is sorted in runs of this size, kept in temporary files beside the output and merged
RUN_MESSAGES = 100_000
RUN_BYTES = 16 * 1024 * 1024
_RUN_BUFFER = 256 * 1024
_RUN_HEAD = struct.Struct('<qQQHI')     # stamp key, log time, publish time, channel, length
_STAMP = {b'\x00\x01': struct.Struct('<iI'), b'\x00\x00': struct.Struct('>iI')}


def stamp_key(data: bytes) -> int:
    """The header stamp (ns) of a stamped message's CDR bytes; -1 for bytes too short to hold
    one (they are refused later, wherever they sort)."""
    unpack = _STAMP.get(data[:2])
    if unpack is None or len(data) < 12:
        return -1
    sec, nanosec = unpack.unpack_from(data, 4)
    return sec * 1_000_000_000 + nanosec


def _spill(run: list, folder: Path):
    """A sorted run written to an unlinked temporary file in ``folder``."""
    stream = tempfile.TemporaryFile(dir=folder)
    pack = _RUN_HEAD.pack
    buffer = io.BufferedWriter(stream, _RUN_BUFFER)
    for key, log_time, publish_time, channel, data in run:
        buffer.write(pack(key, log_time, publish_time, channel, len(data)))
        buffer.write(data)
    buffer.flush()
    buffer.detach()
    return stream


def _read_run(stream):
    stream.seek(0)
    reader = io.BufferedReader(stream, _RUN_BUFFER)
    unpack, size = _RUN_HEAD.unpack, _RUN_HEAD.size
    try:
        while True:
            head = reader.read(size)
            if not head:
                return
            key, log_time, publish_time, channel, length = unpack(head)
            yield key, log_time, publish_time, channel, reader.read(length)
    finally:
        reader.close()


def by_stamp(batches, folder: Path, batch_size: int = 4096):
    """The messages of ``batches`` ((log time, publish time, channel, bytes) lists) in batches
    sorted by header stamp, then log time, then input order: an external merge sort whose
    memory is a run (:data:`RUN_MESSAGES`, :data:`RUN_BYTES`) whatever the input's length."""
    run, runs, size = [], [], 0
    try:
        for batch in batches:
            run.extend((stamp_key(item[3]), *item) for item in batch)
            size += sum(len(item[3]) for item in batch)
            if len(run) >= RUN_MESSAGES or size >= RUN_BYTES:
                run.sort(key=_stamp_order)
                runs.append(_spill(run, folder))
                run, size = [], 0
        run.sort(key=_stamp_order)
        if runs:
            runs.append(_spill(run, folder))
            run = []
            items = heapq.merge(*map(_read_run, runs), key=_stamp_order)
        else:
            items = iter(run)
        while True:
            batch = [item[1:] for item in itertools.islice(items, batch_size)]
            if not batch:
                return
            yield batch
    finally:
        for stream in runs:
            stream.close()


#: the order of ``--order stamp``: header stamp, then log time (sorts are stable: then input
#: order)
_stamp_order = operator.itemgetter(0, 1)


# ----------------------------------------------------------------------------- offline


def _qos(depth: int, transient_local: bool = False) -> dict:
    """A reliable keep-last publisher QoS as rosbag2 stores it (the node's publishers)."""
    zero = {'sec': 0, 'nsec': 0}
    return {'history': 'keep_last', 'depth': depth, 'reliability': 'reliable',
            'durability': 'transient_local' if transient_local else 'volatile',
            'deadline': dict(zero), 'lifespan': dict(zero), 'liveliness': 'automatic',
            'liveliness_lease_duration': dict(zero), 'avoid_ros_namespace_conventions': False}


@dataclass
class ReplaySummary:
    """What :func:`replay_offline` did."""

    input_path: Path
    output_path: Path
    pose_topic: str
    wrench_topic: str
    order: str
    method: str                 # configured model.method
    elements_per_cable: int
    dofs: int                   # of the model at the end
    poses: int = 0
    wrenches: int = 0
    poses_accepted: int = 0
    wrenches_accepted: int = 0
    rebuilds: int = 0
    rejected: Counter = field(default_factory=Counter)  # 'pose:kind' / 'wrench:kind' -> count
    skipped: int = 0            # input messages that did not decode (skip_bad)
    first_skipped: str = ''     # the first one's error
    salvage: Salvage = field(default_factory=Salvage)   # damage met (allow_incomplete)
    removed_partials: list = field(default_factory=list)  # leftovers of killed replays
    resumed_from: str = ''      # the partial output continued (resume)
    resumed_inputs: int = 0     # inputs it held
    resumed_exactly: bool = False   # from its checkpoint (else its inputs predicted again)
    messages_written: int = 0
    bytes: int = 0
    elapsed_s: float = 0.0
    before_first_pose: int = 0  # wrenches predicted before any pose was accepted

    @property
    def warnings(self) -> list[str]:
        """One line each where the input lacks what the prediction needs: predictions made
        before any pose (at ``robot.initial_position``, where the live node may have had a
        pose the recording missed: one published before the recorder subscribed)."""
        if not self.before_first_pose:
            return []
        where = (f'no pose on {self.pose_topic}' if not self.poses_accepted else
                 f'{self.before_first_pose} of {self.wrenches_accepted} wrench(es) came before '
                 f'the first pose on {self.pose_topic}')
        return [f'{where}: those predictions are at robot.initial_position; if the live node '
                f'had a pose then (one published before the recorder subscribed), the replay '
                f'differs from the live run']

    @property
    def inputs(self) -> int:
        return self.poses + self.wrenches

    @property
    def messages_per_s(self) -> float:
        """Input messages replayed per second (reading, models, writing)."""
        return self.inputs / self.elapsed_s if self.elapsed_s > 0 else float('inf')


def replay_offline(input_path, output_path, settings: Settings, method: str | None = None,
                   progress: Callable[[int, int], None] | None = None, *,
                   elements_per_cable: int | None = None, options: NodeOptions | None = None,
                   force: bool = False, pose_topic: str | None = None,
                   wrench_topic: str | None = None, order: str = 'log',
                   allow_incomplete: bool = False, parameters: dict | None = None,
                   skip_bad: bool = False, resume: bool = False,
                   keep_partial: bool = False) -> ReplaySummary:
    """Replay the pose and wrench messages of ``input_path`` into a new file ``output_path``.

    ``settings`` (e.g. :func:`load_replay_config`), with ``method`` / ``elements_per_cable``
    overriding the configured model; ``options``: the node's input tolerances. ``progress``:
    called as ``progress(done, total)`` with input messages (once a batch). ``order``: 'log'
    (receive time, as the node saw them) or 'stamp' (header stamps). ``parameters``: the flat
    parameters, kept in the output's ``cdpr_replay`` metadata record. ``skip_bad``: input
    messages whose bytes do not decode are counted (``skipped``) and left out, instead of ending
    the replay with an error naming the first. ``allow_incomplete``: replay every intact chunk
    of a cut or damaged file (the damage in ``salvage``).

    The output is written under a hidden temporary name beside ``output_path``
    (``.NAME.partial-XXXX``) and renamed when complete. Such a file left by a killed or
    interrupted replay is removed (and named in ``removed_partials``), unless ``resume``: then
    the replay continues it (its messages are kept, the inputs it holds predicted again without
    being written) and the output equals an uninterrupted replay's. ``keep_partial``: an
    interruption (KeyboardInterrupt) finishes the partial file for a later ``resume`` and raises
    :class:`ReplayInterrupted` naming it. Raises :class:`ReplayError`,
    :class:`~cdpr_dynamics.recording.base.RecordingError` (input or output file) or
    :class:`~cdpr_dynamics.analysis.config.ConfigError` / :class:`AnalysisError` (a model that
    cannot be built at the initial pose), all one line; nothing is left at ``output_path``
    then.
    """
    start = time.perf_counter()
    if order not in ORDERS:
        raise ReplayError(f'unknown order {order!r} (log or stamp)')
    changes = {}
    if method is not None:
        changes['method'] = method
    if elements_per_cable is not None:
        changes['elements_per_cable'] = int(elements_per_cable)
    if changes:
        settings = settings.replace(**changes)
    options = options or NodeOptions()
    input_path, output_path = resolve_input(input_path), Path(output_path)
    if output_path.exists() and input_path.exists() and output_path.samefile(input_path):
        raise ReplayError(f'{output_path} is the input file; write the replay elsewhere')
    info, pose, wrench, total = inspect_input(input_path, pose_topic, wrench_topic,
                                              allow_incomplete)
    predictor = _predictor(settings, options)
    frame_id = settings.robot.frame_id
    handler = InputHandler(predictor, frame_id, options.quaternion_tolerance)
    displacement_topic = f'{_namespace(wrench)}/predicted_displacement'
    predicted_pose_topic = f'{_namespace(wrench)}/predicted_pose'
    tensions_topic = f'{_namespace(pose)}/cable_tensions'
    summary = ReplaySummary(input_path, output_path, pose, wrench, order, settings.method,
                            settings.elements_per_cable, predictor.system.dofs)
    identity = {
        'input': input_path.name, 'pose_topic': pose, 'wrench_topic': wrench,
        'order': order, 'method': settings.method,
        'elements_per_cable': str(settings.elements_per_cable),
        'node_options': json.dumps(options.__dict__, sort_keys=True),
        'parameters': json.dumps(parameters or {}, sort_keys=True, default=str),
        'input_bytes': str(input_path.stat().st_size), 'input_messages': str(total),
        'skip_bad': str(bool(skip_bad))}
    partials = partial_files(output_path)
    source = partials.pop(0) if resume and partials else None
    if resume and source is None:
        raise ReplayError(f'nothing to resume: no partial output of an interrupted replay '
                          f'beside {output_path} (.{output_path.name}.partial-*)')
    if not force and output_path.exists():
        raise RecordingError(f'{output_path} exists; not overwriting it (use --force to '
                             'replace it)')
    for leftover in partials:
        summary.removed_partials.append(f'{leftover} ({leftover.stat().st_size} bytes)')
        leftover.unlink()

    with McapFile(input_path) as mcap, RecordingWriter(output_path, force=force) as writer:
        for name in (pose, wrench):
            writer.add_topic(name, info.topics[name].type, info.topics[name].offered_qos_profiles,
                             info.topics[name].type_hash or None)
        writer.add_topic(displacement_topic, DISPLACEMENT_TYPE, [_qos(10)])
        writer.add_topic(predicted_pose_topic, POSE_TYPE, [_qos(10)])
        writer.add_topic(tensions_topic, TENSIONS_TYPE, [_qos(1, transient_local=True)])
        writer.add_topic(DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE, [_qos(10)])
        writer.add_metadata(REPLAY_METADATA, identity, now=True)
        mute = skip = 0
        if source is not None:
            copied, checkpoint = _copy_partial(source, identity, writer, {pose, wrench})
            summary.resumed_from, summary.resumed_inputs = str(source), copied
            if checkpoint is None:
                mute = copied
            else:
                skip = _restore(checkpoint, summary, handler)
                summary.resumed_exactly = True
            source.unlink()
        salvage = summary.salvage if allow_incomplete else None
        if salvage is not None:
            salvage.damage.extend(mcap.layout.damage)
        batches = mcap.batches({pose, wrench}, salvage)
        if order == 'stamp':
            batches = by_stamp(batches, output_path.parent)
        kept = {}
        try:
            _replay_batches(batches, mcap, summary, handler, writer, options, total, progress,
                            skip_bad, mute, skip, kept)
        except KeyboardInterrupt:
            if not keep_partial:
                raise
            raise ReplayInterrupted(writer.keep_partial(_checkpoint_record(kept, settings,
                                                                           options)),
                                    summary.inputs, total) from None
        written = writer.close()
    summary.dofs = predictor.system.dofs
    summary.messages_written = written.message_count
    summary.bytes = written.bytes
    summary.elapsed_s = time.perf_counter() - start
    return summary


class ReplayInterrupted(KeyboardInterrupt):
    """An interrupted replay whose partial output was kept for ``resume``."""

    def __init__(self, partial: Path, done: int, total: int):
        super().__init__(f'interrupted after {done} of {total} inputs; the partial output '
                         f'{partial} is kept: --resume continues it')
        self.partial, self.done, self.total = partial, done, total


def _copy_partial(source: Path, identity: dict, writer: RecordingWriter,
                  inputs: set) -> tuple[int, dict | None]:
    """Copy what a partial output holds into ``writer``: up to its checkpoint's inputs where it
    has one (an interrupted replay's, :func:`_checkpoint_record`), else up to its last input
    (whose outputs may be cut off); the number of inputs copied and the checkpoint (or None).
    Its chunks are read up to the first damaged one; a partial of another replay (other input,
    settings or order) is refused."""
    with McapFile(source) as part:
        made = part.layout.metadata.get(REPLAY_METADATA)
        if made != identity:
            raise ReplayError(f'{source} is the partial output of a replay of another input '
                              'or with other settings: run without --resume to start over')
        checkpoint = part.layout.metadata.get(CHECKPOINT_METADATA)
        limit = None
        if checkpoint is not None:
            counters = json.loads(checkpoint['counters'])
            limit = counters['poses'] + counters['wrenches']
        contents = []   # (chunk ref) read once to find where to stop, then again to copy
        last = None     # (chunk, message) of the last input, or of the input after the limit
        found = 0
        for ref in part.layout.chunks:
            try:
                content = chunks.read_chunk(part.stream, ref)
            except chunks.ChunkDamage:
                break
            part.channels.update({c.id: c for c in content.channels})
            contents.append(ref)
            topics = [part.channels[c].topic if c in part.channels else None
                      for c in content.channel_ids]
            for k, topic in enumerate(topics):
                if topic in inputs and (limit is None or found <= limit):
                    last = (len(contents) - 1, k)
                    found += 1
        if limit is not None and found == limit:     # nothing after the checkpoint's inputs
            last = (len(contents) - 1, None)
        if limit is not None and found < limit:
            raise ReplayError(f'{source} holds {found} inputs, fewer than its checkpoint\'s '
                              f'{limit}: run without --resume to start over')
        if last is None:
            return 0, None
        copied = 0
        writers = {}
        for number, ref in enumerate(contents[:last[0] + 1]):
            content = chunks.read_chunk(part.stream, ref)
            end = last[1] if number == last[0] and last[1] is not None else len(content.data)
            for k in range(end):
                channel = part.channels.get(content.channel_ids[k])
                if channel is None or channel.topic not in writer.topic_counts:
                    continue
                write = writers.get(channel.topic)
                if write is None:
                    write = writers[channel.topic] = writer.channel_writer(channel.topic)
                write(content.data[k], content.log_times[k], content.publish_times[k])
                copied += channel.topic in inputs
        return copied, checkpoint


def _predictor(settings: Settings, options: NodeOptions) -> LivePredictor:
    """The replay's predictor, as a resumed one is made too."""
    return LivePredictor(settings, options.pose_tolerance_m, options.angle_tolerance_rad,
                         options.slack)


def _checkpoint_record(kept: dict, settings: Settings, options: NodeOptions) -> list:
    """The metadata record of an interrupted replay's last state kept (by
    :func:`_replay_batches`), for ``--resume`` to continue from; none (``[]``)
    where that state cannot be restored bit for bit: a cable slack, or a model that a
    predictor rebuilt at the pose does not reproduce exactly (a warm-started iterative
    statics, auto's choice)."""
    state = kept.get('predictor')
    if state is None:
        return []
    fresh = _predictor(settings, options)
    try:
        fresh.update_pose(state.position_m, rotation=state.rotation, force=True)
    except Exception:  # noqa: BLE001 - no checkpoint then: --resume predicts again
        return []
    if not same_model(fresh, state):
        return []

    def plain(value):
        return value.tolist() if isinstance(value, np.ndarray) else value
    return [(CHECKPOINT_METADATA, {
        'consumed': str(kept['consumed']), 'counters': json.dumps(kept['counters']),
        'clocks': json.dumps(kept['clocks']),
        'state': json.dumps({name: plain(getattr(state, name))
                             for name in Checkpoint.STATE_FIELDS})})]


def _restore(record: dict, summary: ReplaySummary, handler: InputHandler) -> int:
    """Continue from a checkpoint record: the predictor, the stamp clocks and the summary's
    counts as they were; the number of input messages it had consumed."""
    state = json.loads(record['state'])
    arrays = {name: None if state[name] is None or not isinstance(state[name], list)
              else np.array(state[name], dtype=float) for name in Checkpoint.STATE_FIELDS}
    handler.predictor.restore(Checkpoint(
        arrays['position_m'], arrays['rotation'], None, None, arrays['state'], state['t_ns'],
        state['remainder_ns'], arrays['load'], state['load_dofs'], arrays['last_step_load'],
        arrays['slack_forces'], float(state['slack_time_s'])))
    handler.pose_clock.last_ns, handler.wrench_clock.last_ns = json.loads(record['clocks'])
    counters = json.loads(record['counters'])
    for name in COUNTERS:
        setattr(summary, name, counters[name])
    summary.rejected = Counter(counters['rejected'])
    return int(record['consumed'])


#: input messages replayed at once at most (a run: wrenches, and the poses between them that
#: leave the model as it is)
RUN_INPUTS = 4096


def _replay_batches(batches, mcap, summary: ReplaySummary, handler: InputHandler,
                    writer: RecordingWriter, options: NodeOptions, total: int, progress,
                    skip_bad: bool, mute: int = 0, skip: int = 0,
                    kept: dict | None = None) -> None:
    """The loop of :func:`replay_offline`: each input decoded from its bytes (checked against
    its type: :func:`~msg_adapters.mcap_schema.decode_stamped`), through ``handler``, and the
    outputs encoded straight to CDR bytes; nothing is written for the first ``mute`` inputs
    (a resumed replay's output has them already), and the first ``skip`` input messages are
    passed over (a resumed replay restored from its checkpoint). Every CHECKPOINT_EVERY input
    messages, ``kept`` takes the state to resume from (:func:`_checkpoint_record`).

    Runs of inputs that share one model - wrenches, and the poses between them that do not
    move it (:meth:`~msg_adapters.inputs.InputHandler.pose_still`) - go through at once
    (:class:`_Outputs`, :func:`_replay_run`): the same messages as one by one."""
    out = _Outputs(handler, writer, summary, options.output_point_m)
    pose = summary.pose_topic
    routes = {}

    def route(channel_id: int) -> tuple:
        is_pose = mcap.channels[channel_id].topic == pose
        routes[channel_id] = (is_pose, 7 if is_pose else 6, POSE_TYPE if is_pose else WRENCH_TYPE)
        return routes[channel_id]

    index = 0
    for batch in batches:
        position, size = 0, len(batch)
        while position < size:
            log_time, publish_time, channel_id, data = batch[position]
            if skip:
                index += 1
                skip -= 1
                position += 1
                continue
            if kept is not None and not mute and index % CHECKPOINT_EVERY == 0:
                _keep(kept, index, summary, handler)
            is_pose, count, type_name = routes.get(channel_id) or route(channel_id)
            if not (is_pose or mute):
                limit = min(RUN_INPUTS, CHECKPOINT_EVERY - index % CHECKPOINT_EVERY
                            if kept is not None else RUN_INPUTS)
                done = _replay_run(batch, position, limit, channel_id, out,
                                   routes.get, route)
                if done:
                    index += done
                    position += done
                    continue
            index += 1
            position += 1
            try:
                stamp_ns, frame, values = decode_stamped(data, count, type_name)
            except CdrError as err:
                bad = (f'{mcap.path}: cannot decode message {index - 1} (a {type_name} on '
                       f'{pose if is_pose else summary.wrench_topic} at log time '
                       f'{log_time}): {err}')
                if not skip_bad:
                    raise UndecodableMessage(bad) from None
                summary.skipped += 1
                summary.first_skipped = summary.first_skipped or bad
                continue
            if mute:
                mute -= 1
                _predict_quietly(handler, is_pose, stamp_ns, frame, values, summary)
                continue
            records = [(channel_id, data, log_time, publish_time)]
            if is_pose:
                out.pose(stamp_ns, frame, values, log_time, records)
            else:
                out.wrench(stamp_ns, frame, values, log_time, records)
            out.write(records)
        if progress is not None:
            done = summary.inputs + summary.skipped
            progress(done, total)


class _Outputs:
    """What the replay writes for its inputs, as records (channel, CDR bytes, log time,
    publish time) in the order the node would publish them."""

    def __init__(self, handler: InputHandler, writer: RecordingWriter,
                 summary: ReplaySummary, point: tuple):
        self.handler, self.writer, self.summary, self.point = handler, writer, summary, point
        self.predictor = handler.predictor
        self.frame_id = handler.frame_id
        wrench_ns, pose_ns = _namespace(summary.wrench_topic), _namespace(summary.pose_topic)
        self.displacement = writer.channel_id(f'{wrench_ns}/predicted_displacement')
        self.predicted_pose = writer.channel_id(f'{wrench_ns}/predicted_pose')
        self.tensions = writer.channel_id(f'{pose_ns}/cable_tensions')
        self.diagnostics = writer.channel_id(DIAGNOSTICS_TOPIC)
        self._tensions = (None, b'')     # an equilibrium's cable_tensions bytes

    def write(self, records: list) -> None:
        if records:
            self.writer.write_many(*zip(*records))

    def rejected(self, what: str, exc: InvalidMessage, stamp_ns: int, log_time: int,
                 records: list) -> None:
        self.summary.rejected[f'{what}:{exc.kind}'] += 1
        topic = self.summary.pose_topic if what == 'pose' else self.summary.wrench_topic
        records.append((self.diagnostics, serialize(rejection_message(
            what, exc, topic, ns_to_stamp(stamp_ns))), log_time, log_time))

    def pose(self, stamp_ns: int, frame: str, values: tuple, log_time: int,
             records: list, still: bool = False) -> None:
        """A pose through the handler: its cable_tensions or its diagnostic. ``still``: the
        pose is known to leave the model as it is (:meth:`InputHandler.pose_still`), the
        model's own test is not made again."""
        summary = self.summary
        summary.poses += 1
        try:
            update = self.handler.pose_values(stamp_ns, frame, values,
                                              move=_kept if still else None)
        except InvalidMessage as exc:
            self.rejected('pose', exc, stamp_ns, log_time, records)
            return
        summary.poses_accepted += 1
        summary.rebuilds += int(update.rebuilt)
        eq, data = self._tensions
        if eq is not self.predictor.eq:           # only the stamp changes between rebuilds
            eq = self.predictor.eq
            data = serialize(tensions_message(eq.geometry.cable_length_m, eq.tensions.tension_n,
                                              ns_to_stamp(stamp_ns), self.frame_id))
            self._tensions = eq, data
        records.append((self.tensions, _restamped(data, stamp_ns), log_time, log_time))

    def wrench(self, stamp_ns: int, frame: str, values: tuple, log_time: int,
               records: list) -> None:
        """A wrench through the handler alone: its predictions or its diagnostic."""
        summary = self.summary
        summary.wrenches += 1
        try:
            self.handler.wrench_values(stamp_ns, frame, values)
        except InvalidMessage as exc:
            self.rejected('wrench', exc, stamp_ns, log_time, records)
            return
        summary.wrenches_accepted += 1
        summary.before_first_pose += not summary.poses_accepted
        out = self.predictor.prediction(self.point)
        records.append((self.displacement, encode_stamped(stamp_ns, self.frame_id,
                                                          out.displacement_m),
                        log_time, log_time))
        records.append((self.predicted_pose, encode_stamped(
            stamp_ns, self.frame_id, (*out.position_m, *out.quaternion)), log_time, log_time))

    def predictions(self, stamps: np.ndarray, q: np.ndarray) -> tuple[list, list]:
        """The predicted_displacement and predicted_pose bytes of platform states ``q``."""
        displacement, position, quaternion = self.predictor.predictions(q, self.point)
        return (encode_stamped_run(stamps, self.frame_id, displacement),
                encode_stamped_run(stamps, self.frame_id, np.hstack([position, quaternion])))


def _kept(position_m, quaternion=None) -> PoseUpdate:
    """What :meth:`LivePredictor.update_pose` returns for a pose that did not move."""
    return PoseUpdate(False)


def _restamped(data: bytes, stamp_ns: int) -> bytes:
    """The CDR bytes of a message that starts with a Header, its stamp set to ``stamp_ns``
    (as :func:`~msg_adapters.validation.ns_to_stamp` splits it)."""
    stamp = ns_to_stamp(stamp_ns)
    return b''.join((data[:4], _STAMP[data[:2]].pack(stamp.sec, stamp.nanosec), data[12:]))


def _replay_run(batch: list, position: int, limit: int, wrench_channel: int, out: _Outputs,
                known, route) -> int:
    """Replay the run of inputs that starts with the wrench at ``batch[position]``, at most
    ``limit`` messages: wrench messages of one layout
    (:func:`~msg_adapters.mcap_schema.decode_stamped_run`) and, once a pose was accepted,
    the poses between them that leave the model as it is. Their wrenches go through
    :meth:`~msg_adapters.inputs.InputHandler.wrench_run` as far as it takes them and one by
    one where it stops, the poses after them (the model is the same for all), and the records
    are written in input order. The number of messages replayed (0: none, go one by one)."""
    handler, summary = out.handler, out.summary
    end = min(len(batch), position + limit)
    wrenches, poses = [], []          # (place in the run, item); (place, item, fields)
    stop = position
    while stop < end:
        item = batch[stop]
        if item[2] == wrench_channel:
            wrenches.append((stop - position, item))
        else:
            is_pose, count, type_name = known(item[2]) or route(item[2])
            if not (is_pose and summary.poses_accepted):
                break
            try:
                fields = decode_stamped(item[3], count, type_name)
            except CdrError:
                break
            if not handler.pose_still(*fields):
                break
            poses.append((stop - position, item, fields))
        stop += 1
    count, stamps, frame, values = decode_stamped_run([item[3] for _, item in wrenches], 6,
                                                      WRENCH_TYPE)
    if count < 2:
        return 0
    if count < len(wrenches):         # the run ends before the first of another layout
        stop = position + wrenches[count][0]
        wrenches = wrenches[:count]
        poses = [p for p in poses if p[0] < stop - position]
    first_pose = summary.poses_accepted
    outputs = [None] * count          # per wrench: its records after the input, or None
    batched, rows, start = [], [], 0
    while start < count:
        done, q = handler.wrench_run(stamps[start:], frame, values[start:])
        if done:
            batched.append(np.arange(start, start + done))
            rows.append(q)
            start += done
        if start < count:
            outputs[start] = records = []
            out.wrench(int(stamps[start]), frame, tuple(values[start].tolist()),
                       wrenches[start][1][0], records)
            start += 1
    extra = {wrenches[k][0]: records for k, records in enumerate(outputs)
             if records is not None}      # place in the run -> the records after its input
    for place, item, fields in poses:    # they leave the model as it is: after the wrenches
        extra[place] = records = []
        out.pose(*fields, item[0], records, still=True)
    items = batch[position:stop]
    sizes = np.ones(len(items), dtype=np.int64)
    for place, records in extra.items():
        sizes[place] += len(records)
    batched = np.concatenate(batched or [np.zeros(0, dtype=np.int64)])
    places = np.array([wrenches[k][0] for k in batched.tolist()], dtype=np.int64)
    sizes[places] += 2
    starts = np.cumsum(sizes) - sizes
    total = int(sizes.sum())
    channels, logs, publish = (np.empty(total, dtype=np.int64) for _ in range(3))
    datas = np.empty(total, dtype=object)
    logs[starts], publish[starts], channels[starts], inputs = zip(*items)    # the inputs
    datas[starts] = _objects(inputs)
    if len(places):
        displacement, predicted = out.predictions(stamps[batched], np.concatenate(rows))
        at = starts[places]
        for shift, channel, data in ((1, out.displacement, displacement),
                                     (2, out.predicted_pose, predicted)):
            channels[at + shift], logs[at + shift], publish[at + shift] = channel, logs[at], \
                logs[at]
            datas[at + shift] = _objects(data)
        summary.wrenches += len(places)
        summary.wrenches_accepted += len(places)
        summary.before_first_pose += len(places) if not first_pose else 0
    for place, records in extra.items():
        for shift, (channel, data, log_time, publish_time) in enumerate(records, 1):
            at = starts[place] + shift
            channels[at], datas[at], logs[at], publish[at] = channel, data, log_time, publish_time
    out.writer.write_many(channels, datas, logs, publish)
    return stop - position


def _objects(items: list) -> np.ndarray:
    """An object array of ``items`` (bytes: numpy would make them a bytes array)."""
    array = np.empty(len(items), dtype=object)
    array[:] = items
    return array


def _keep(kept: dict, consumed: int, summary: ReplaySummary, handler: InputHandler) -> None:
    """Keep the state after the first ``consumed`` input messages in ``kept`` (one update: a
    Ctrl-C finds the previous state or this one whole)."""
    counters = {name: getattr(summary, name) for name in COUNTERS}
    counters['rejected'] = dict(summary.rejected)
    kept.update(consumed=consumed, counters=counters, predictor=handler.predictor.checkpoint(),
                clocks=(handler.pose_clock.last_ns, handler.wrench_clock.last_ns))


def _predict_quietly(handler: InputHandler, is_pose: bool, stamp_ns: int, frame: str,
                     values: tuple, summary: ReplaySummary) -> None:
    """One input through ``handler``, counted, nothing written (a resumed replay's start)."""
    try:
        if is_pose:
            summary.poses += 1
            update = handler.pose_values(stamp_ns, frame, values)
            summary.poses_accepted += 1
            summary.rebuilds += int(update.rebuilt)
        else:
            summary.wrenches += 1
            handler.wrench_values(stamp_ns, frame, values)
            summary.wrenches_accepted += 1
            summary.before_first_pose += not summary.poses_accepted
    except InvalidMessage as exc:
        summary.rejected[f'{"pose" if is_pose else "wrench"}:{exc.kind}'] += 1


# ----------------------------------------------------------------------------- live


@dataclass
class LiveSummary:
    """What :func:`replay_live` published."""

    pose_topic: str
    wrench_topic: str
    published: int
    total: int
    duration_s: float            # wall time from the first to the last message
    recorded_span_s: float       # log-time span of what was published
    max_late_s: float            # worst lateness against the schedule
    stopped: bool                # interrupted before the end


def replay_live(node, input_path, *, rate: float = 1.0, pose_topic: str | None = None,
                wrench_topic: str | None = None, subscribers: int = 1,
                wait_s: float = 30.0, stop: threading.Event | None = None,
                progress: Callable[[int, int], None] | None = None,
                allow_incomplete: bool = False) -> LiveSummary:
    """Republish the pose and wrench messages of a recording from ``node`` (rclpy).

    Publishes on ``pose`` and ``wrench`` (relative to the node's namespace, remappable) the
    recorded CDR bytes, unchanged (header stamps as recorded), at the recorded log times
    relative to the first one, divided by ``rate``; first waits up to ``wait_s`` until each
    topic has ``subscribers`` subscriptions. ``stop`` (an Event) ends it early. Raises
    :class:`ReplayError` / :class:`~cdpr_dynamics.recording.base.RecordingError`.
    """
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if not (rate > 0.0 and math.isfinite(rate)):
        raise ReplayError(f'--rate must be a positive number, got {rate}')
    stop = stop or threading.Event()
    input_path = resolve_input(input_path)
    _, pose, wrench, total = inspect_input(input_path, pose_topic, wrench_topic, allow_incomplete)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    publishers = {pose: node.create_publisher(PoseStamped, 'pose', qos),
                  wrench: node.create_publisher(WrenchStamped, 'wrench', qos)}
    try:
        deadline = time.monotonic() + wait_s
        while any(p.get_subscription_count() < subscribers for p in publishers.values()):
            if stop.is_set():
                return LiveSummary(publishers[pose].topic_name, publishers[wrench].topic_name,
                                   0, total, 0.0, 0.0, 0.0, True)
            if time.monotonic() > deadline:
                missing = [p.topic_name for p in publishers.values()
                           if p.get_subscription_count() < subscribers]
                raise ReplayError(
                    f'no subscriber on {", ".join(missing)} after {wait_s:g} s (wanted '
                    f'{subscribers}): is dynamics_node running on this ROS_DOMAIN_ID?')
            stop.wait(0.02)
        published, first_log, first_wall, last_log, max_late = 0, None, None, None, 0.0
        wall = time.monotonic()
        for item in _input_stream(input_path, pose, wrench, allow_incomplete):
            if first_log is None:
                first_log, first_wall = item.log_time_ns, time.monotonic()
            due = first_wall + (item.log_time_ns - first_log) * 1e-9 / rate
            now = time.monotonic()
            if due > now and stop.wait(due - now):
                break
            if stop.is_set():
                break
            max_late = max(max_late, time.monotonic() - due)
            publishers[item.topic].publish(item.data)
            published += 1
            last_log = item.log_time_ns
            if progress is not None:
                progress(published, total)
        wall = time.monotonic() - (first_wall if first_wall is not None else wall)
        for publisher in publishers.values():   # reliable subscribers got everything
            publisher.wait_for_all_acked(_duration(2.0))
        return LiveSummary(publishers[pose].topic_name, publishers[wrench].topic_name,
                           published, total, wall,
                           ((last_log or 0) - (first_log or 0)) * 1e-9, max_late,
                           stop.is_set())
    finally:
        for publisher in publishers.values():
            node.destroy_publisher(publisher)


def _duration(seconds: float):
    from rclpy.duration import Duration
    return Duration(nanoseconds=int(seconds * 1e9))


# ----------------------------------------------------------------------------- comparison


@dataclass
class Predictions:
    """The outputs of a replay or of a node recording, keyed by header stamp (ns)."""

    displacement: dict = field(default_factory=dict)    # stamp -> (3,) m
    length: dict = field(default_factory=dict)          # stamp -> (n,) m
    tension: dict = field(default_factory=dict)         # stamp -> (n,) N
    rejected: dict = field(default_factory=dict)        # (what, stamp) -> (kind, reason)
    inputs: set = field(default_factory=set)            # stamps of the inputs


def read_predictions(path, diagnostics_source: str | None = HARDWARE_ID) -> Predictions:
    """Predictions of a file: every topic named ``predicted_displacement`` / ``cable_tensions``
    (any namespace), and the per-input rejections on /diagnostics written by
    ``diagnostics_source`` (None: ignore /diagnostics)."""
    out = Predictions()
    for item in read_messages(path):
        base = item.topic.rsplit('/', 1)[-1]
        msg = item.message
        if item.type == DISPLACEMENT_TYPE and base == 'predicted_displacement':
            out.displacement[stamp_to_ns(msg.header.stamp)] = read_displacement(msg)
        elif item.type == TENSIONS_TYPE and base == 'cable_tensions':
            length, tension = read_tensions(msg)
            out.length[stamp_to_ns(msg.header.stamp)] = length
            out.tension[stamp_to_ns(msg.header.stamp)] = tension
        elif item.type in (POSE_TYPE, WRENCH_TYPE) and base in ('pose', 'wrench'):
            out.inputs.add(stamp_to_ns(msg.header.stamp))
        elif item.type == DIAGNOSTICS_TYPE and diagnostics_source is not None:
            for status in msg.status:
                if status.hardware_id != diagnostics_source:
                    continue
                values = {kv.key: kv.value for kv in status.values}
                what = 'pose' if status.name.endswith('pose input') else 'wrench'
                out.rejected[(what, int(values.get('stamp_ns', -1)))] = (
                    values.get('kind', ''), status.message)
    return out


@dataclass
class Comparison:
    """Result of :func:`compare_outputs`: ``ok`` and the mismatches found, worst first."""

    ok: bool
    problems: list
    worst: dict                  # quantity -> largest |difference| / peak of the reference
    tolerance: dict              # quantity -> absolute tolerance used

    def __str__(self) -> str:
        if self.ok:
            return 'match: ' + ', '.join(f'{k} worst {v:.2g} of peak'
                                         for k, v in self.worst.items())
        return '; '.join(self.problems[:5]) + (
            f' (and {len(self.problems) - 5} more)' if len(self.problems) > 5 else '')


def compare_outputs(reference: Predictions, candidate: Predictions, rtol: float = 1e-6,
                    diagnostics: bool = True, extra_ok: bool = False) -> Comparison:
    """Compare predictions by header stamp: each quantity within ``rtol`` times its peak in
    ``reference`` (|u|, cable length, tension), the same stamps present (``extra_ok``: the
    candidate may have outputs at stamps that are no input of the reference, e.g. a node's
    start-up tensions), and, with ``diagnostics``, the same inputs rejected for the same kind
    of reason."""
    problems = []
    worst, tolerance = {}, {}
    for name in ('displacement', 'length', 'tension'):
        ref, cand = getattr(reference, name), getattr(candidate, name)
        peak = max((float(np.abs(v).max()) for v in ref.values() if np.size(v)), default=0.0)
        atol = rtol * peak if peak > 0 else rtol
        tolerance[name] = atol
        missing = sorted(set(ref) - set(cand))
        extra = sorted(set(cand) - set(ref))
        if extra_ok:
            extra = [s for s in extra if s in reference.inputs]
        if missing:
            problems.append(f'{name}: {len(missing)} of {len(ref)} stamps missing '
                            f'(first {missing[0] * 1e-9:.6f} s)')
        if extra:
            problems.append(f'{name}: {len(extra)} unexpected stamps '
                            f'(first {extra[0] * 1e-9:.6f} s)')
        largest, where = 0.0, None
        for stamp in sorted(set(ref) & set(cand)):
            a, b = np.asarray(ref[stamp]), np.asarray(cand[stamp])
            if a.shape != b.shape:
                problems.append(f'{name} at {stamp * 1e-9:.6f} s: {b.size} values, '
                                f'expected {a.size}')
                continue
            diff = float(np.abs(a - b).max()) if a.size else 0.0
            if not math.isfinite(diff):
                diff = math.inf
            if diff > largest:
                largest, where = diff, stamp
        worst[name] = largest / peak if peak > 0 else largest
        if largest > atol:
            problems.insert(0, f'{name} differs by {largest:.3g} at {where * 1e-9:.6f} s '
                               f'({largest / max(peak, 1e-300):.3g} of the peak {peak:.4g}; '
                               f'tolerance {rtol:g} of the peak)')
    if diagnostics:
        ref_kinds = {k: v[0] for k, v in reference.rejected.items()}
        cand_kinds = {k: v[0] for k, v in candidate.rejected.items()}
        if ref_kinds != cand_kinds:
            gone = sorted(set(ref_kinds.items()) - set(cand_kinds.items()))
            new = sorted(set(cand_kinds.items()) - set(ref_kinds.items()))
            problems.append(f'rejected inputs differ: {len(gone)} no longer rejected as before '
                            f'{gone[:3]}, {len(new)} newly rejected {new[:3]}')
    return Comparison(not problems, problems, worst, tolerance)


def summary_lines(summary: ReplaySummary) -> Iterable[str]:
    """Human-readable lines about a finished offline replay."""
    for leftover in summary.removed_partials:
        yield f'removed {leftover}, the partial output of an interrupted replay'
    if summary.resumed_from:
        how = ('continued from its checkpoint' if summary.resumed_exactly
               else 'predicted again, not rewritten')
        yield (f'resumed {summary.resumed_from}: kept its output of {summary.resumed_inputs} '
               f'inputs ({how})')
    for line in summary.salvage.lines():
        yield f'{summary.input_path}: {line}'
    rejected = ', '.join(f'{k} {v}' for k, v in sorted(summary.rejected.items())) or 'none'
    yield (f'{summary.poses} poses ({summary.poses_accepted} accepted, {summary.rebuilds} '
           f'rebuilds), {summary.wrenches} wrenches ({summary.wrenches_accepted} predictions); '
           f'rejected: {rejected}')
    if summary.skipped:
        yield (f'skipped {summary.skipped} undecodable input message(s); the first: '
               f'{summary.first_skipped}')
    yield (f'{summary.method} model ({summary.dofs} DOFs), {summary.inputs} inputs in '
           f'{summary.elapsed_s:.2f} s ({summary.messages_per_s:.0f} messages/s)')
    yield (f'wrote {summary.messages_written} messages ({summary.bytes} bytes) to '
           f'{summary.output_path.resolve()}')


__all__ = [
    'Comparison', 'InputHandler', 'LiveSummary', 'NodeOptions', 'Predictions', 'ReplayError',
    'ReplayInterrupted',
    'ReplaySummary', 'RecordingError', 'compare_outputs', 'find_input_topics', 'inspect_input',
    'load_replay_config', 'read_predictions', 'rejection_message', 'replay_live',
    'replay_offline', 'resolve_input', 'summary_lines',
]
