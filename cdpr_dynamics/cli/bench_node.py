"""Figures of the live node for ``cdpr_bench``: compute per wrench, pose updates, DDS.

    python -m cdpr_dynamics.cli.bench_node flood --rate HZ --duration S [--start-s T]

(1) the node's compute per wrench, in process: the wrench callback's work
(message check, feasibility, Newmark to the stamp, the prediction message) for the configured
model at 1 kHz stamps; (2) a pose update (tensions QP warm-started + model + refactorisation)
for spring, catenary and fem n = 16 along a slow trajectory; (3) over DDS with the node as a
child process: end-to-end latency wrench published -> prediction received (p50/p99, paced at
200 Hz) and the node's own compute (its diagnostics); (4) the sustained input rate: floods of
increasing rate from a child process, the highest rate the node processes >= 99 % of.

``flood``: publish harmonic wrenches (1000 N along z at 5 Hz) at ``--rate`` for ``--duration``
seconds on this process's ROS domain; print one JSON line with what was sent. Used by the flood
test.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.config import load_settings


def _percentiles(seconds) -> dict:
    ms = np.asarray(seconds) * 1e3
    return {'p50_ms': float(np.percentile(ms, 50)), 'p99_ms': float(np.percentile(ms, 99)),
            'max_ms': float(ms.max()), 'n': int(ms.size)}


def compute_per_wrench(settings, n: int = 20000) -> dict:
    """The wrench callback's work without the executor (msg_adapters.inputs.InputHandler:
    checks, feasibility, Newmark to the stamp) and the prediction message."""
    from cdpr_dynamics.config import NODE_PARAMETER_BY_NAME
    from cdpr_dynamics.live import LivePredictor
    from msg_adapters.displacement import displacement_message
    from msg_adapters.inputs import InputHandler
    from msg_adapters.validation import s_to_stamp
    from msg_adapters.wrench import wrench_message

    predictor = LivePredictor(settings)
    frame = settings.robot.frame_id
    inputs = InputHandler(predictor, frame,
                          NODE_PARAMETER_BY_NAME['node.quaternion_tolerance'].default)
    msgs = [wrench_message([0.0, 0.0, 1000.0 * np.sin(2 * np.pi * 5 * k * 1e-3)], frame_id=frame,
                           stamp=s_to_stamp(100.0 + k * 1e-3)) for k in range(n)]
    times = []
    for msg in msgs:
        start = time.perf_counter()
        u = inputs.wrench(msg)
        displacement_message(u, frame, msg.header.stamp)
        times.append(time.perf_counter() - start)
    result = _percentiles(times[100:])
    result['method'] = settings.method
    result['dofs'] = predictor.system.dofs
    return result


def _circle(settings, k: int, n: int) -> np.ndarray:
    """Point k of n on a 5 cm circle around the initial position (each a rebuild)."""
    angle = 2 * np.pi * k / n
    return settings.initial_position_m + 0.05 * np.array([np.cos(angle), np.sin(angle), 0.0])


def chord_statics_pose_updates(settings, method: str = 'fem_sag', elements: int = 16,
                               n: int = 300) -> dict:
    """The pose update of a sag-aware model linearised at the chord tensions, as the node did
    before the sag-consistent statics (chord QP, model, factorisation): the baseline of the
    statics' cost. Not a state the package uses: the chord tensions do not balance sagged
    cables."""
    from cdpr_dynamics import models
    from cdpr_dynamics.analysis import damping_for, equilibrium, new_tension_solver
    from cdpr_dynamics.dynamics import Newmark, platform_system
    from cdpr_dynamics.live import DENSE_NEWMARK_DOFS

    solver = new_tension_solver(settings)
    total = []
    for k in range(n):
        start = time.perf_counter()
        eq = equilibrium(settings, _circle(settings, k, n), None, solver)
        system = platform_system(settings.robot, eq.geometry,
                                 models.build(method, eq.cables, elements))
        stiffness, mass = system.matrices(dense=system.dofs <= DENSE_NEWMARK_DOFS)
        Newmark(stiffness, mass, damping_for(settings, system), settings.dt_s,
                settings.newmark_alpha, settings.newmark_beta)
        total.append(time.perf_counter() - start)
    result = _percentiles(total[10:])
    result['dofs'] = system.dofs
    return result


def pose_updates(settings, methods=(('spring', 1), ('catenary', 1), ('fem', 16),
                                    ('catenary_exact', 1), ('fem_sag', 16)),
                 n: int = 300) -> dict:
    """Pose update time (tensions + model + factorisation) per method along a slow circle;
    sag-aware models include the sag-consistent statics (warm-started pose to pose), and
    ``fem_sag_n16_chord_statics`` is the same model at the chord tensions for the ratio."""
    from cdpr_dynamics.live import LivePredictor

    results = {}
    for method, elements in methods:
        try:
            s = settings.replace(method=method, elements_per_cable=elements)
            predictor = LivePredictor(s)
        except Exception as exc:  # a model not available in this build
            results[f'{method}'] = {'error': str(exc).splitlines()[0]}
            continue
        total, stages = [], {}
        for k in range(n):
            position = _circle(settings, k, n)
            start = time.perf_counter()
            update = predictor.update_pose(position)
            total.append(time.perf_counter() - start)
            for stage, sec in update.timings_s.items():
                stages.setdefault(stage, []).append(sec)
        key = f'{method}_n{elements}' if method in ('fem', 'fem_sag') else method
        results[key] = _percentiles(total[10:])
        results[key]['dofs'] = predictor.system.dofs
        results[key]['stages_p50_ms'] = {k: float(np.median(v) * 1e3) for k, v in
                                         stages.items()}
    if ('fem_sag', 16) in methods:
        try:
            results['fem_sag_n16_chord_statics'] = chord_statics_pose_updates(settings, n=n)
        except Exception as exc:
            results['fem_sag_n16_chord_statics'] = {'error': str(exc).splitlines()[0]}
    return results


# ------------------------------------------------------------------------------------ DDS

def _ros_session(tag: str):
    from cdpr_dynamics.node_process import apply_env, isolated_env, reserve_domain_id
    reservation = reserve_domain_id(141, 200)
    env = isolated_env(reservation.domain_id, Path(tempfile.mkdtemp(prefix=f'cdpr_{tag}_')))
    apply_env(env)
    return reservation, env


def dds(config, rates=(1000, 2000, 3000, 5000, 8000), flood_s: float = 3.0,
        latency_s: float = 5.0) -> dict:
    """Latency and sustained rate over DDS against a dynamics_node child process."""
    import rclpy
    from geometry_msgs.msg import Vector3Stamped, WrenchStamped
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions

    from cdpr_dynamics.node_process import start_node, stop_process
    from msg_adapters.diagnostics import read_statuses
    from msg_adapters.validation import s_to_stamp, stamp_to_ns
    from msg_adapters.wrench import wrench_message

    reservation, env = _ros_session('bench')
    log = open(Path(env['ROS_LOG_DIR']) / 'node.log', 'w')
    proc = start_node(config, env, stdout=log,
                      stderr=subprocess.STDOUT)
    try:          # from here on a Ctrl-C anywhere still stops the node (its own session)
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)   # Ctrl-C: one line in main
        node = Node('cdpr_bench')
        cond = threading.Condition()
        received, statuses = {}, []

        def on_prediction(msg):
            now = time.perf_counter()
            with cond:
                received[stamp_to_ns(msg.header.stamp)] = now
                cond.notify_all()

        def on_diagnostics(msg):
            with cond:
                statuses.append(read_statuses(msg))
                cond.notify_all()

        node.create_subscription(Vector3Stamped, 'predicted_displacement', on_prediction, 1000)
        node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
        pub = node.create_publisher(WrenchStamped, 'wrench', qos_profile_sensor_data)
        executor_ = SingleThreadedExecutor()
        executor_.add_node(node)
        stop = threading.Event()
        spinner = threading.Thread(target=lambda: [executor_.spin_once(0.05)
                                                   for _ in iter(stop.is_set, True)], daemon=True)
        spinner.start()

        def wrench_status(after):
            with cond:
                cond.wait_for(lambda: any('cdpr_dynamics: wrench input' in s
                                          for s in statuses[after:]), 10.0)
                return next(s['cdpr_dynamics: wrench input']['values'] for s in statuses[after:]
                            if 'cdpr_dynamics: wrench input' in s)

        result = {}
        try:
            with cond:
                if not cond.wait_for(lambda: pub.get_subscription_count() > 0 and statuses, 30.0):
                    raise RuntimeError('dynamics_node did not come up')
            frame = load_settings(config).robot.frame_id
            # latency, published at 200 Hz, stamped 1 ms apart (one Newmark step per wrench, as
            # for a 1 kHz controller; the node integrates stamps, not wall-clock time)
            sent = {}
            t0 = 100.0
            period, dt = 1 / 200, 1e-3
            start = time.perf_counter()
            for k in range(int(latency_s * 200)):
                target = start + k * period
                while time.perf_counter() < target:
                    time.sleep(0.0002)
                stamp = s_to_stamp(t0 + k * dt)
                msg = wrench_message([0.0, 0.0, 1000.0 * np.sin(2 * np.pi * 5 * k * dt)],
                                     frame_id=frame, stamp=stamp)
                sent[stamp_to_ns(stamp)] = time.perf_counter()
                pub.publish(msg)
            with cond:
                cond.wait_for(lambda: len(received) >= len(sent), 5.0)
            lat = [received[k] - sent[k] for k in sent if k in received]
            result['latency'] = _percentiles(lat)
            result['latency']['lost'] = len(sent) - len(lat)
            values = wrench_status(len(statuses))
            result['node_compute'] = {'p50_ms': float(values['compute_ms_p50']),
                                      'p99_ms': float(values['compute_ms_p99']),
                                      'publish_p50_ms': float(values['publish_ms_p50']),
                                      'publish_p99_ms': float(values['publish_ms_p99'])}
            # sustained rate: floods from a child process
            floods = []
            t_next = t0 + latency_s + 5.0          # > 1 s gap: each flood starts at rest
            for rate in rates:
                before = int(wrench_status(len(statuses))['accepted'])
                with cond:
                    got_before = len(received)
                out = subprocess.run([sys.executable, '-m', 'cdpr_dynamics.cli.bench_node',
                                      'flood', '--rate', str(rate), '--duration', str(flood_s),
                                      '--start-s', str(t_next), '--frame', frame], env=env,
                                     capture_output=True,
                                     text=True, timeout=flood_s + 60)
                if out.returncode != 0:
                    raise RuntimeError(out.stderr.strip().splitlines()[-1])
                info = json.loads(out.stdout.strip().splitlines()[-1])
                time.sleep(0.3)   # let the last predictions drain before reading the counters
                after = int(wrench_status(len(statuses))['accepted'])
                processed = after - before
                with cond:
                    got = len(received) - got_before
                floods.append({'rate_hz': rate, 'sent': info['sent'],
                               'achieved_send_hz': info['rate_hz'], 'processed': processed,
                               'processed_fraction': processed / max(1, info['sent']),
                               'processed_hz': processed / info['duration_s'],
                               'bench_received': got, 'node_alive': proc.poll() is None})
                t_next = info['last_stamp_s'] + 2.0
            result['floods'] = floods
            kept = [f['rate_hz'] for f in floods if f['processed_fraction'] >= 0.99]
            result['sustained_rate_hz'] = max(kept) if kept else 0
            result['max_processed_hz'] = max(f['processed_hz'] for f in floods)
        finally:
            stop.set()
            spinner.join(2.0)
            executor_.shutdown()
            node.destroy_node()
            rclpy.try_shutdown()
            result['node_exit'] = stop_process(proc)
            log.close()
            reservation.release()
        return result
    finally:
        stop_process(proc)          # at once where the block above stopped it
        log.close()
        reservation.release()


def recording_throughput(config, rate_hz: float = 5000.0, duration_s: float = 3.0) -> dict:
    """``cdpr_record`` beside a running node while wrenches flood in at ``rate_hz``: messages
    recorded per second and bytes per message (all child processes, one ROS domain)."""
    from cdpr_dynamics.node_process import start_node, stop_process
    from cdpr_dynamics.recording.reader import recording_info

    reservation, env = _ros_session('record')
    folder = Path(env['ROS_LOG_DIR'])
    path = folder / 'bench.mcap'
    node = start_node(config, env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    recorder = None
    try:
        recorder = subprocess.Popen([sys.executable, '-m', 'cdpr_dynamics.cli.record',
                                     '--output', str(path)], env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
        out = subprocess.run([sys.executable, '-m', 'cdpr_dynamics.cli.bench_node', 'flood',
                              '--rate', str(rate_hz), '--duration', str(duration_s), '--frame',
                              load_settings(config).robot.frame_id], env=env,
                             capture_output=True, text=True, timeout=duration_s + 60)
        if out.returncode != 0:
            raise RuntimeError(out.stderr.strip().splitlines()[-1])
        sent = json.loads(out.stdout.strip().splitlines()[-1])
        time.sleep(1.0)            # the node's last predictions reach the recorder
    finally:
        if recorder is not None:
            stop_process(recorder)
        stop_process(node)
        reservation.release()
    info = recording_info(path)
    counts = {name: t.message_count for name, t in info.topics.items()}
    span_s = max((info.end_ns - info.start_ns) * 1e-9, 1e-9)
    return {'wrenches_sent': sent['sent'], 'messages': info.message_count, 'topics': counts,
            'messages_per_s': info.message_count / span_s,
            'bytes_per_message': path.stat().st_size / max(info.message_count, 1),
            'complete': info.complete}


def flood(rate_hz: float, duration_s: float, start_s: float, frame: str = 'world') -> dict:
    """Publish wrenches at ``rate_hz`` for ``duration_s``; stamps start at ``start_s``."""
    import rclpy
    from geometry_msgs.msg import WrenchStamped
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    from msg_adapters.validation import s_to_stamp
    from msg_adapters.wrench import wrench_message

    rclpy.init()
    node = Node('cdpr_flood')
    pub = node.create_publisher(WrenchStamped, 'wrench', qos_profile_sensor_data)
    deadline = time.monotonic() + 10.0
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    if pub.get_subscription_count() == 0:
        raise SystemExit('flood: no subscriber on wrench after 10 s')
    msg = wrench_message([0.0, 0.0, 0.0], frame_id=frame)
    period = 1.0 / rate_hz
    total = int(round(rate_hz * duration_s))
    sent = 0
    start = time.perf_counter()
    while sent < total:
        due = min(total, int((time.perf_counter() - start) / period) + 1)
        while sent < due:
            t = start_s + sent * period
            msg.header.stamp = s_to_stamp(t)
            msg.wrench.force.z = 1000.0 * np.sin(2 * np.pi * 5.0 * (t - start_s))
            pub.publish(msg)
            sent += 1
        time.sleep(min(period, 0.0005))
    elapsed = time.perf_counter() - start
    node.destroy_node()
    rclpy.try_shutdown()
    return {'sent': sent, 'duration_s': elapsed, 'rate_hz': sent / elapsed,
            'last_stamp_s': start_s + (sent - 1) * period}


def main(argv=None) -> int:
    """``flood``: the wrench publisher of the benchmark and of the flood test."""
    parser = argparse.ArgumentParser(description='publish wrenches at a rate (tests, cdpr_bench)')
    sub = parser.add_subparsers(dest='command', required=True)
    fl = sub.add_parser('flood', help='publish wrenches at a rate (for tests and benchmarks)')
    fl.add_argument('--rate', type=float, default=5000.0)
    fl.add_argument('--duration', type=float, default=10.0)
    fl.add_argument('--start-s', type=float, default=1000.0)
    fl.add_argument('--frame', default='world')
    args = parser.parse_args(argv)
    print(json.dumps(flood(args.rate, args.duration, args.start_s, args.frame)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
