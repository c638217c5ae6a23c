"""Scripted input scenarios for the paper robot, written as MCAP recordings.

Each scenario is a sequence of ``pose`` (PoseStamped, 20 Hz) and ``wrench`` (WrenchStamped,
200 Hz) messages in ``world``, stamped from :data:`T0_NS` (a wall-clock-like epoch, as a real
recording has); the log time of a message is its stamp (perfect delivery) except where a
scenario sends something late on purpose. Poses sit half a wrench period after the wrenches
(2.5 ms), so no two inputs share a time and the order is the same for every reader.

* ``trajectory_harmonic``: 3 s along a slow closed path (x +-0.2 m, y +-0.1 m, z up to
  +0.1 m, a small yaw) under a harmonic wrench (x 30 N at 3 Hz, z 200 N at 5 Hz).
* ``step_wrench``: 2 s at a fixed pose; the wrench steps from 0 to (40, 0, -250) N at 0.5 s.
* ``infeasible_crossing``: 3 s along x from 0.9 m to 1.2 m and back: beyond ~1.07 m no tension
  distribution in [100, 1000] N holds the platform, so those poses are rejected and the
  predictions go on at the last good pose; an upward 4 Hz wrench of 0 to 40 N (a
  downward one could not be held near the edge and would be rejected too).
* ``invalid_inputs``: 1 s at a fixed pose with every kind of bad input the node must reject
  (another frame, a non-unit quaternion, NaN and infinite values, out-of-order stamps, a wrench
  the cables cannot hold).

    python -m cdpr_dynamics.recording.scenarios --output-dir DIR [--names ...] [--force]
    python -m cdpr_dynamics.recording.scenarios --golden test/data [--force]

The first writes the input recordings; ``--golden`` regenerates the golden recordings of the
replay tests: each input replayed by :func:`cdpr_dynamics.recording.replay.replay_offline` with
:data:`GOLDEN` (the paper config, ``fem`` with 4 elements per cable), exactly what
``cdpr_replay NAME.mcap --output test/data/golden_NAME.mcap --method fem --elements 4``
writes.
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from msg_adapters.mcap_schema import encode_stamped

FRAME = 'world'
T0_NS = 1_700_000_000 * 10**9
POSE_PERIOD_NS = 50_000_000        # 20 Hz
WRENCH_PERIOD_NS = 5_000_000       # 200 Hz
POSE_OFFSET_NS = 2_500_000         # poses between wrenches
QOS = [{'history': 'keep_last', 'depth': 10, 'reliability': 'reliable',
        'durability': 'volatile', 'deadline': {'sec': 0, 'nsec': 0},
        'lifespan': {'sec': 0, 'nsec': 0}, 'liveliness': 'automatic',
        'liveliness_lease_duration': {'sec': 0, 'nsec': 0},
        'avoid_ros_namespace_conventions': False}]
#: how the golden recordings are made (config None: the installed paper_cdpr.yaml)
GOLDEN = {'config': None, 'method': 'fem', 'elements_per_cable': 4}


@dataclass(frozen=True)
class Event:
    """One input: topic (``pose``/``wrench``), log time and stamp (ns), and its values."""

    topic: str
    log_time_ns: int
    stamp_ns: int
    values: tuple            # pose: (x, y, z, qx, qy, qz, qw); wrench: (fx, fy, fz, mx, my, mz)
    frame_id: str = FRAME


def _poses(duration_s: float, path: Callable[[float], tuple]) -> list[Event]:
    n = int(round(duration_s * 1e9 / POSE_PERIOD_NS))
    out = []
    for k in range(n):
        stamp = T0_NS + POSE_OFFSET_NS + k * POSE_PERIOD_NS
        out.append(Event('pose', stamp, stamp, path((stamp - T0_NS) * 1e-9)))
    return out


def _wrenches(duration_s: float, load: Callable[[float], tuple]) -> list[Event]:
    n = int(round(duration_s * 1e9 / WRENCH_PERIOD_NS))
    out = []
    for k in range(n):
        stamp = T0_NS + k * WRENCH_PERIOD_NS
        out.append(Event('wrench', stamp, stamp, load((stamp - T0_NS) * 1e-9)))
    return out


def _yaw(angle: float) -> tuple:
    return (0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2))


def trajectory_harmonic(duration_s: float = 3.0) -> list[Event]:
    def path(t):
        w = 2 * math.pi / 3.0
        return (0.2 * math.sin(w * t), 0.1 * math.sin(2 * w * t),
                1.25 + 0.05 * (1 - math.cos(w * t)), *_yaw(0.05 * math.sin(w * t)))

    def load(t):
        return (30.0 * math.sin(2 * math.pi * 3.0 * t), 0.0,
                200.0 * math.sin(2 * math.pi * 5.0 * t), 0.0, 0.0, 0.0)

    return _poses(duration_s, path) + _wrenches(duration_s, load)


def step_wrench() -> list[Event]:
    def load(t):
        return (40.0, 0.0, -250.0, 0.0, 0.0, 0.0) if t >= 0.5 else (0.0,) * 6

    return _poses(2.0, lambda t: (0.1, -0.05, 1.3, 0.0, 0.0, 0.0, 1.0)) + _wrenches(2.0, load)


def infeasible_crossing() -> list[Event]:
    def path(t):
        x = 0.9 + 0.3 * (1 - abs(t - 1.5) / 1.5)
        return (x, 0.0, 1.25, 0.0, 0.0, 0.0, 1.0)

    return _poses(3.0, path) + _wrenches(
        3.0, lambda t: (0.0, 0.0, 20.0 * (1 - math.cos(2 * math.pi * 4.0 * t)), 0.0, 0.0, 0.0))


def invalid_inputs() -> list[Event]:
    poses = _poses(1.0, lambda t: (0.05, 0.0, 1.25, 0.0, 0.0, 0.0, 1.0))
    wrenches = _wrenches(
        1.0, lambda t: (0.0, 0.0, 100.0 * math.sin(2 * math.pi * 5.0 * t), 0.0, 0.0, 0.0))
    nan, inf = float('nan'), float('inf')

    def change(events, k, **kw):
        events[k] = Event(**{**events[k].__dict__, **kw})

    change(poses, 5, frame_id='map')                                    # another frame
    change(poses, 8, values=(0.05, 0.0, 1.25, 0.0, 0.0, 0.0, 1.01))    # not a unit quaternion
    change(poses, 11, values=(nan, 0.0, 1.25, 0.0, 0.0, 0.0, 1.0))     # not finite
    # sent late: received after pose 14, stamped before it -> out of order
    change(poses, 13, log_time_ns=poses[14].log_time_ns + 1_000_000)
    change(wrenches, 40, frame_id='')                                   # no frame
    change(wrenches, 60, values=(0.0, 0.0, inf, 0.0, 0.0, 0.0))        # not finite
    change(wrenches, 100, values=(0.0, 0.0, 5000.0, 0.0, 0.0, 0.0))    # cables cannot hold it
    change(wrenches, 120, values=(0.0, 0.0, 0.0, nan, 0.0, 0.0))       # NaN moment
    # received after wrench 81, stamped before it -> out of order
    change(wrenches, 80, log_time_ns=wrenches[81].log_time_ns + 1_000_000)
    return poses + wrenches


SCENARIOS: dict[str, Callable[[], list[Event]]] = {
    'trajectory_harmonic': trajectory_harmonic,
    'step_wrench': step_wrench,
    'infeasible_crossing': infeasible_crossing,
    'invalid_inputs': invalid_inputs,
}


def scenario_messages(name: str, **kwargs) -> list[tuple[str, int, object]]:
    """(topic, log time ns, rclpy message) of a scenario, in log-time order (``kwargs``: for
    the scenario function, e.g. ``duration_s`` of ``trajectory_harmonic``)."""
    from builtin_interfaces.msg import Time

    from msg_adapters.pose import pose_message
    from msg_adapters.wrench import wrench_message

    try:
        events = SCENARIOS[name](**kwargs)
    except KeyError:
        raise ValueError(f'unknown scenario {name!r}; known: {", ".join(SCENARIOS)}') from None
    out = []
    for e in sorted(events, key=lambda e: (e.log_time_ns, e.topic)):
        stamp = Time(sec=e.stamp_ns // 10**9, nanosec=e.stamp_ns % 10**9)
        if e.topic == 'pose':
            msg = pose_message(e.values[:3], e.values[3:], e.frame_id, stamp)
        else:
            msg = wrench_message(e.values[:3], e.values[3:], e.frame_id, stamp)
        out.append(('/' + e.topic, e.log_time_ns, msg))
    return out


def write_scenario(name: str, path, force: bool = False, **kwargs):
    """Write the input recording of a scenario; the :class:`RecordingSummary`."""
    from cdpr_dynamics.recording.writer import RecordingWriter

    messages = scenario_messages(name, **kwargs)
    with RecordingWriter(path, force=force) as writer:
        writer.add_topic('/pose', 'geometry_msgs/msg/PoseStamped', QOS)
        writer.add_topic('/wrench', 'geometry_msgs/msg/WrenchStamped', QOS)
        writer.add_metadata('cdpr_scenario', {'name': name, 'frame_id': FRAME,
                                              't0_ns': str(T0_NS)})
        for topic, log_time, msg in messages:
            writer.write(topic, msg, log_time)
        return writer.close()


def long_log_messages(duration_s: float, wrench_hz: float = 1000.0, pose_hz: float = 50.0,
                      hold_s: float = 10.0, frame_id: str = FRAME):
    """(topic, log time ns, CDR bytes) of a long recording, in log-time order, generated
    lazily: ``wrench_hz`` wrenches (a 3 Hz / 5 Hz harmonic load, as ``trajectory_harmonic``)
    and ``pose_hz`` poses of a robot that holds a station for ``hold_s`` seconds, with
    measurement noise below the node's pose tolerance, then moves to the next station of a
    slow circle (one rebuild per station); all in ``frame_id``."""
    wrench_period = round(1e9 / wrench_hz)
    pose_period = round(1e9 / pose_hz)
    n_wrench = int(round(duration_s * 1e9 / wrench_period))
    n_pose = int(round(duration_s * 1e9 / pose_period))
    pose_k = 0
    for k in range(n_wrench + 1):
        t_ns = k * wrench_period
        while pose_k < n_pose and pose_k * pose_period + pose_period // 2 < t_ns:
            pt = pose_k * pose_period + pose_period // 2
            station = math.floor(pt * 1e-9 / hold_s)
            angle = 0.3 * station
            noise = 2e-5 * math.sin(1.7 * pose_k)          # 20 um: below node.pose_tolerance_m
            values = (0.15 * math.cos(angle) + noise, 0.08 * math.sin(angle), 1.25,
                      *_yaw(0.02 * math.sin(angle)))
            yield '/pose', T0_NS + pt, encode_stamped(T0_NS + pt, frame_id, values)
            pose_k += 1
        if k == n_wrench:
            break
        t = t_ns * 1e-9
        values = (30.0 * math.sin(2 * math.pi * 3.0 * t), 0.0,
                  200.0 * math.sin(2 * math.pi * 5.0 * t), 0.0, 0.0, 0.0)
        yield '/wrench', T0_NS + t_ns, encode_stamped(T0_NS + t_ns, frame_id, values)


def write_long_log(path, duration_s: float, force: bool = False, compression: str = 'none',
                   chunk_size: int | None = None, **kwargs):
    """Write :func:`long_log_messages` (``kwargs``: its rates) to ``path`` (``chunk_size``:
    bytes, default the recorder's); the :class:`RecordingSummary`. Memory stays flat whatever
    the duration."""
    from cdpr_dynamics.recording.base import DEFAULT_CHUNK_SIZE
    from cdpr_dynamics.recording.writer import RecordingWriter

    with RecordingWriter(path, force=force, compression=compression,
                         chunk_size=chunk_size or DEFAULT_CHUNK_SIZE) as writer:
        writer.add_topic('/pose', 'geometry_msgs/msg/PoseStamped', QOS)
        writer.add_topic('/wrench', 'geometry_msgs/msg/WrenchStamped', QOS)
        writer.add_metadata('cdpr_scenario', {'name': 'long_log',
                                              'frame_id': kwargs.get('frame_id', FRAME),
                                              't0_ns': str(T0_NS)})
        for topic, log_time, data in long_log_messages(duration_s, **kwargs):
            writer.write(topic, data, log_time)
        return writer.close()


def golden_name(name: str) -> str:
    """File name of a scenario's golden recording."""
    return f'golden_{name}.mcap'


def write_golden(name: str, path, force: bool = False, config=None, method=None,
                 elements_per_cable=None):
    """Input of a scenario replayed with :data:`GOLDEN` (or the given settings) into ``path``;
    the :class:`~cdpr_dynamics.recording.replay.ReplaySummary`."""
    from cdpr_dynamics.recording.replay import load_replay_config, replay_offline

    config = GOLDEN['config'] if config is None else config
    method = method or GOLDEN['method']
    elements = elements_per_cable or GOLDEN['elements_per_cable']
    settings, options, flat = load_replay_config(config)
    flat.update({'model.method': method, 'model.elements_per_cable': elements})
    with tempfile.TemporaryDirectory() as folder:
        source = Path(folder) / f'{name}.mcap'   # the output records this input name
        write_scenario(name, source)
        return replay_offline(source, path, settings, method, elements_per_cable=elements,
                              options=options, force=force, parameters=flat)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='python -m cdpr_dynamics.recording.scenarios',
        description='Write the scripted input scenarios (or the golden replays) as MCAP.')
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument('--output-dir', metavar='DIR', help='write the input recordings here')
    where.add_argument('--golden', metavar='DIR',
                       help='write the golden replays (inputs + predictions) here')
    parser.add_argument('--names', nargs='+', choices=list(SCENARIOS), default=list(SCENARIOS))
    parser.add_argument('--force', action='store_true', help='replace existing files')
    args = parser.parse_args(argv)

    from cdpr_dynamics.analysis.config import ConfigError
    from cdpr_dynamics.recording.base import RecordingError
    from cdpr_dynamics.recording.replay import ReplayError

    folder = Path(args.output_dir or args.golden)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for name in args.names:
            path = folder / (golden_name(name) if args.golden else f'{name}.mcap')
            if args.golden:
                s = write_golden(name, path, args.force)
                rejected = ', '.join(f'{k} {v}' for k, v in sorted(s.rejected.items()))
                print(f'{path}: {s.bytes} bytes, {s.poses} poses, {s.wrenches} wrenches, '
                      f'{s.method} n={s.elements_per_cable} ({s.dofs} DOFs); rejected: '
                      f'{rejected or "none"}')
            else:
                s = write_scenario(name, path, args.force)
                print(f'{path}: {s.bytes} bytes, {s.message_count} messages')
    except (RecordingError, ReplayError, ConfigError, OSError) as exc:
        print(f'scenarios: error: {exc}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
