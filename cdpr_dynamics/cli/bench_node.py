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
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.analysis.config import load_settings

FRF_CALL_POINTS = 20000     # the large call of the wrench-path-during-a-call figure
QUIET_S = 5.0               # a wrench count unchanged this long in the node's reports: settled


def _percentiles(seconds) -> dict:
    ms = np.asarray(seconds) * 1e3
    return {'p50_ms': float(np.percentile(ms, 50)), 'p99_ms': float(np.percentile(ms, 99)),
            'max_ms': float(ms.max()), 'n': int(ms.size)}


def compute_per_wrench(settings, n: int = 20000) -> dict:
    """The wrench callback's work without the executor (msg_adapters.inputs.InputHandler:
    checks, feasibility, Newmark to the stamp) and the prediction message, under a 5 Hz force
    along z of 1000 N, or the largest half of it the cables hold both ways (``amplitude_n``:
    a robot that holds less would reject every wrench)."""
    from cdpr_dynamics.analysis.config import NODE_PARAMETER_BY_NAME
    from cdpr_dynamics.analysis.live import LivePredictor
    from msg_adapters.displacement import displacement_message
    from msg_adapters.inputs import InputHandler
    from msg_adapters.validation import s_to_stamp
    from msg_adapters.wrench import wrench_message

    predictor = LivePredictor(settings)
    frame = settings.robot.frame_id
    inputs = InputHandler(predictor, frame,
                          NODE_PARAMETER_BY_NAME['node.quaternion_tolerance'].default)
    amplitude = 1000.0
    while any(predictor.wrench_reason((0.0, 0.0, sign * amplitude)) for sign in (1.0, -1.0)):
        amplitude /= 2.0
        if amplitude < 1e-3:
            return {'error': 'the cables hold no force along z at the initial pose'}
    msgs = [wrench_message([0.0, 0.0, amplitude * np.sin(2 * np.pi * 5 * k * 1e-3)],
                           frame_id=frame, stamp=s_to_stamp(100.0 + k * 1e-3)) for k in range(n)]
    times = []
    for msg in msgs:
        start = time.perf_counter()
        u = inputs.wrench(msg)
        displacement_message(u, frame, msg.header.stamp)
        times.append(time.perf_counter() - start)
    result = _percentiles(times[100:])
    result['method'] = settings.method
    result['dofs'] = predictor.system.dofs
    result['amplitude_n'] = amplitude
    return result


def slack_per_wrench(settings, methods=(('spring', 1), ('fem', 16)), n: int = 4000) -> dict:
    """The wrench callback's work (as :func:`compute_per_wrench`) at 1 kHz under the paper
    demo's load, ``frf.force_n`` (and ``frf.moment_nm``) at 5 Hz, by a ``node.slack: linear``
    and a ``node.slack: aware`` predictor fed the same wrenches in turn: per method the
    linear p50/p99, the aware one's over the wrenches it took while a cable was slack, their
    p50 ratio, and the fraction of wrenches taken slack."""
    from cdpr_dynamics.analysis.config import NODE_PARAMETER_BY_NAME
    from cdpr_dynamics.analysis.live import LivePredictor
    from msg_adapters.displacement import displacement_message
    from msg_adapters.inputs import InputHandler
    from msg_adapters.validation import s_to_stamp
    from msg_adapters.wrench import wrench_message

    frame = settings.robot.frame_id
    tolerance = NODE_PARAMETER_BY_NAME['node.quaternion_tolerance'].default
    results = {}
    for method, elements in methods:
        s = settings.replace(method=method, elements_per_cable=elements)
        handlers = {mode: InputHandler(LivePredictor(s, slack=mode), frame, tolerance)
                    for mode in ('linear', 'aware')}
        key = f'{method}_n{elements}' if method == 'fem' else method
        reason = next(filter(None, (handlers['linear'].predictor.wrench_reason(
            sign * s.frf_force_n, sign * s.frf_moment_nm) for sign in (1.0, -1.0))), '')
        if reason:
            results[key] = {'error': f'frf.force_n not held: {reason}'}
            continue
        seconds = {mode: [] for mode in handlers}
        slack = []
        for k in range(n):
            load = np.sin(2 * np.pi * 5.0 * (k + 1) * 1e-3)
            msg = wrench_message(load * s.frf_force_n, load * s.frf_moment_nm, frame_id=frame,
                                 stamp=s_to_stamp(100.0 + k * 1e-3))
            for mode, inputs in handlers.items():
                start = time.perf_counter()
                u = inputs.wrench(msg)
                displacement_message(u, frame, msg.header.stamp)
                seconds[mode].append(time.perf_counter() - start)
            slack.append(bool(handlers['aware'].predictor.slack_cables))
        warm = 100
        taken = np.asarray(slack[warm:])
        row = {'linear': _percentiles(seconds['linear'][warm:]),
               'aware_slack': _percentiles(np.asarray(seconds['aware'][warm:])[taken]),
               'slack_fraction': float(taken.mean()),
               'force_n': [float(f) for f in s.frf_force_n]}
        row['aware_over_linear_p50'] = row['aware_slack']['p50_ms'] / row['linear']['p50_ms']
        results[key] = row
    return results


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
    from cdpr_dynamics.analysis.pipeline import damping_for, equilibrium, new_tension_solver
    from cdpr_dynamics.dynamics.system import platform_system
    from cdpr_dynamics.analysis.live import newmark_for

    solver = new_tension_solver(settings)
    total = []
    for k in range(n):
        start = time.perf_counter()
        eq = equilibrium(settings, _circle(settings, k, n), None, solver)
        system = platform_system(settings.robot, eq.geometry,
                                 models.build(method, eq.cables, elements))
        newmark_for(system, damping_for(settings, system), settings)    # as the live path
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
    from cdpr_dynamics.analysis.live import LivePredictor

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


PULLEY_KEYS = ('robot.pulley_axes', 'robot.pulley_radii_m', 'cable.winch_side_lengths_m')


def pulley_pose_updates(config, methods=(('spring', 1), ('fem', 16)), n: int = 300) -> dict:
    """Pose updates of the robot of ``config`` (with pulleys and winch-side cable) against the
    same robot without them, interleaved pose by pose along the same circle, per method: the
    p50s and their ratio (pulleys over none)."""
    from cdpr_dynamics.analysis.config import read_params_file, settings_from_params
    from cdpr_dynamics.analysis.live import LivePredictor

    flat = read_params_file(config)
    robots = {'pulleys': settings_from_params(flat),
              'none': settings_from_params({k: v for k, v in flat.items()
                                            if k not in PULLEY_KEYS})}
    results = {}
    for method, elements in methods:
        predictors = {name: LivePredictor(s.replace(method=method, elements_per_cable=elements))
                      for name, s in robots.items()}
        seconds = {name: [] for name in predictors}
        for k in range(n):
            position = _circle(robots['none'], k, n)
            for name, predictor in predictors.items():
                start = time.perf_counter()
                predictor.update_pose(position)
                seconds[name].append(time.perf_counter() - start)
        row = {name: _percentiles(values[10:]) for name, values in seconds.items()}
        row['pulleys_over_none'] = row['pulleys']['p50_ms'] / row['none']['p50_ms']
        results[f'{method}_n{elements}' if method == 'fem' else method] = row
    return results


# ------------------------------------------------------------------------------------ DDS

def _ros_session(tag: str):
    from cdpr_dynamics.ros.process import apply_env, isolated_env, reserve_domain_id
    reservation = reserve_domain_id(141, 200)
    env = isolated_env(reservation.domain_id, Path(tempfile.mkdtemp(prefix=f'cdpr_{tag}_')))
    apply_env(env)
    return reservation, env


def _spin_in_background(node):
    """Spin ``node`` on a daemon thread; the function that stops it and its executor."""
    from rclpy.executors import SingleThreadedExecutor
    executor_ = SingleThreadedExecutor()
    executor_.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [executor_.spin_once(0.05)
                                               for _ in iter(stop.is_set, True)], daemon=True)
    spinner.start()

    def halt() -> None:
        stop.set()
        spinner.join(2.0)
        executor_.shutdown()
    return halt


def dds(config, rates=(1000, 2000, 3000, 5000, 8000), flood_s: float = 3.0,
        latency_s: float = 5.0, frf_call_points: int = FRF_CALL_POINTS) -> dict:
    """Latency and sustained rate over DDS against a dynamics_node child process."""
    import rclpy
    from geometry_msgs.msg import Vector3Stamped, WrenchStamped
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions

    from rcl_interfaces.srv import GetParameters

    from cdpr_dynamics.ros.process import start_child, start_node, stop_process
    from msg_adapters.diagnostics import read_statuses
    from msg_adapters.frf_service import request_message
    from msg_adapters.validation import s_to_stamp, stamp_to_ns
    from msg_adapters.wrench import wrench_message

    reservation, env = _ros_session('bench')
    log = open(Path(env['ROS_LOG_DIR']) / 'node.log', 'w')
    proc = None
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
        halt = _spin_in_background(node)

        def wrench_status(after):
            with cond:
                cond.wait_for(lambda: any('cdpr_dynamics: wrench input' in s
                                          for s in statuses[after:]), 10.0)
                return next(s['cdpr_dynamics: wrench input']['values'] for s in statuses[after:]
                            if 'cdpr_dynamics: wrench input' in s)

        frame = load_settings(config).robot.frame_id
        t0 = 100.0

        def latency(t_start):
            """Wrench -> prediction, published at 200 Hz, stamped 1 ms apart (one Newmark step
            per wrench, as for a 1 kHz controller; the node integrates stamps, not wall-clock
            time)."""
            sent = {}
            period, dt = 1 / 200, 1e-3
            start = time.perf_counter()
            for k in range(int(latency_s * 200)):
                target = start + k * period
                while time.perf_counter() < target:
                    time.sleep(0.0002)
                stamp = s_to_stamp(t_start + k * dt)
                msg = wrench_message([0.0, 0.0, 1000.0 * np.sin(2 * np.pi * 5 * k * dt)],
                                     frame_id=frame, stamp=stamp)
                sent[stamp_to_ns(stamp)] = time.perf_counter()
                pub.publish(msg)
            with cond:
                cond.wait_for(lambda: all(k in received for k in sent), 5.0)
            lat = [received[k] - sent[k] for k in sent if k in received]
            out = _percentiles(lat)
            out['lost'] = len(sent) - len(lat)
            return out

        client = node.create_client(GetParameters, 'frequency_response')

        def during_call(t_start):
            """The latency of wrenches sent while a 20000-point fem_sag 64 FRF call is served
            (200 Hz, as :func:`latency`), against those before it; the longest wait."""
            if not client.wait_for_service(timeout_sec=30.0):
                raise RuntimeError('no frequency_response service')
            request = request_message(['amplitude_z_m'], {'method': 'fem_sag',
                                                          'elements_per_cable': 64,
                                                          'n_points': frf_call_points})
            answered = threading.Event()
            call = {}

            def call_service():
                call['start'] = time.perf_counter()
                future = client.call_async(request)
                future.add_done_callback(lambda _: answered.set())
                answered.wait(600.0)
                call['end'] = time.perf_counter()

            caller = threading.Thread(target=call_service, daemon=True)
            sent, period, dt = {}, 1 / 200, 1e-3
            start = time.perf_counter()
            k = 0
            while not answered.is_set() and time.perf_counter() - start < 600.0:
                if k == 200:            # 1 s of wrenches before the call
                    caller.start()
                while time.perf_counter() < start + k * period:
                    time.sleep(0.0002)
                stamp = s_to_stamp(t_start + k * dt)
                sent[stamp_to_ns(stamp)] = time.perf_counter()
                pub.publish(wrench_message([0.0, 0.0, 100.0], frame_id=frame, stamp=stamp))
                k += 1
            caller.join(5.0)
            with cond:
                cond.wait_for(lambda: all(key in received for key in sent), 5.0)
            inside = [key for key, t in sent.items() if call['start'] <= t <= call['end']]
            before = [key for key, t in sent.items() if t < call['start']]
            arrivals = sorted(received[key] for key in sent if key in received)
            out = {'points': frf_call_points, 'call_s': call['end'] - call['start'],
                   'sent_during_call': len(inside),
                   'lost_during_call': sum(key not in received for key in inside),
                   'lost': sum(key not in received for key in sent),
                   'before': _percentiles([received[key] - sent[key] for key in before
                                           if key in received]),
                   'during': _percentiles([received[key] - sent[key] for key in inside
                                           if key in received] or [np.nan]),
                   'longest_gap_ms': float(np.diff(arrivals).max() * 1e3)}
            out['p50_during_over_before'] = out['during']['p50_ms'] / out['before']['p50_ms']
            return out

        result = {}
        try:
            # the reference: a trivial rclpy echo node (wrench in, Vector3Stamped out)
            echo = start_child([sys.executable, '-m', 'cdpr_dynamics.cli.bench_node', 'echo'],
                               env=env, stdout=log, stderr=subprocess.STDOUT)
            try:
                with cond:
                    if not cond.wait_for(lambda: pub.get_subscription_count() > 0, 30.0):
                        raise RuntimeError('the echo node did not come up')
                result['echo_latency'] = latency(t0)
            finally:
                stop_process(echo)
            proc = start_node(config, env, stdout=log, stderr=subprocess.STDOUT)
            with cond:
                if not cond.wait_for(lambda: pub.get_subscription_count() > 0 and statuses, 30.0):
                    raise RuntimeError('dynamics_node did not come up')
            result['latency'] = latency(t0 + 2 * latency_s)
            result['latency_over_echo'] = {
                key: result['latency'][key] / max(result['echo_latency'][key], 1e-9)
                for key in ('p50_ms', 'p99_ms')}
            result['during_frf_call'] = during_call(t0 + 4 * latency_s)
            values = wrench_status(len(statuses))
            result['node_compute'] = {'p50_ms': float(values['compute_ms_p50']),
                                      'p99_ms': float(values['compute_ms_p99']),
                                      'publish_p50_ms': float(values['publish_ms_p50']),
                                      'publish_p99_ms': float(values['publish_ms_p99'])}
            # sustained rate: floods from a child process
            floods = []
            t_next = max(received) * 1e-9 + 5.0    # > 1 s gap: each flood starts at rest
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
            halt()
            node.destroy_node()
            rclpy.try_shutdown()
            if proc is not None:
                result['node_exit'] = stop_process(proc)
            log.close()
            reservation.release()
        return result
    finally:
        if proc is not None:
            stop_process(proc)      # at once where the block above stopped it
        log.close()
        reservation.release()


def modes_latency(config, parameters: dict | None = None, poses: int = 20,
                  spacing_s: float = 1.0, moving_s: float = 3.0) -> dict:
    """``vibration_modes`` against a dynamics_node child process: (1) ``poses`` poses 5 cm
    apart on a circle, ``spacing_s`` apart (a robot going from station to station): the time
    from publishing each to receiving the table stamped with it (p50/p99, and how many never
    came); (2) poses at 50 Hz for ``moving_s`` (a robot moving on): the tables received while
    it moves, each stamped with one of the poses sent (``foreign_stamps`` counts the others),
    and their age (receipt minus the publishing of the pose they carry)."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import Float64MultiArray

    from cdpr_dynamics.analysis.live import rotated_quaternion
    from cdpr_dynamics.ros.process import start_node, stop_process
    from msg_adapters.arrays import read_table
    from msg_adapters.pose import pose_message
    from msg_adapters.validation import s_to_stamp, stamp_to_ns

    settings = load_settings(config)
    frame = settings.robot.frame_id
    quaternion = rotated_quaternion(settings.initial_rotation, np.zeros(3))
    reservation, env = _ros_session('modes')
    log = open(Path(env['ROS_LOG_DIR']) / 'node.log', 'w')
    proc = start_node(config, env, parameters, stdout=log, stderr=subprocess.STDOUT)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node('cdpr_bench_modes')
    cond = threading.Condition()
    tables = []              # (receipt time, pose stamp ns)

    def on_table(msg):
        now = time.perf_counter()
        with cond:
            tables.append((now, read_table(msg)[2]['pose_stamp_ns']))
            cond.notify_all()

    node.create_subscription(Float64MultiArray, 'vibration_modes', on_table,
                             QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    pub = node.create_publisher(PoseStamped, 'pose', qos_profile_sensor_data)
    halt = _spin_in_background(node)
    sent = {}
    t_stamp = 1000.0

    def send(k: int, count: int) -> int:
        nonlocal t_stamp
        t_stamp += 0.02
        stamp = s_to_stamp(t_stamp)
        sent[stamp_to_ns(stamp)] = time.perf_counter()
        pub.publish(pose_message(_circle(settings, k, count), quaternion, frame, stamp))
        return stamp_to_ns(stamp)

    try:
        with cond:
            if not cond.wait_for(lambda: tables and pub.get_subscription_count() > 0, 60.0):
                raise RuntimeError('dynamics_node did not come up')
        time.sleep(spacing_s)
        latency, missing = [], 0
        for k in range(poses):
            ns = send(k, poses)
            with cond:
                got = cond.wait_for(lambda: any(s == ns for _, s in tables), spacing_s)
                arrival = next((t for t, s in tables if s == ns), None)
            if got and arrival is not None:
                latency.append(arrival - sent[ns])
                time.sleep(max(0.0, spacing_s - (time.perf_counter() - sent[ns])))
            else:
                missing += 1
        with cond:
            before = len(tables)
        start = time.perf_counter()
        moving = []
        k = 0
        while time.perf_counter() - start < moving_s:
            moving.append(send(k, 100))
            k += 1
            time.sleep(max(0.0, start + k * 0.02 - time.perf_counter()))
        end = time.perf_counter()
        time.sleep(1.0)
        with cond:
            during = [(t, s) for t, s in tables[before:] if t <= end]
        known = [(t, s) for t, s in during if s in sent]
        result = {'spacing_s': spacing_s, 'poses': poses, 'missing': missing,
                  'latency': _percentiles(latency or [np.nan]),
                  'moving': {'poses': len(moving), 'tables': len(during),
                             'foreign_stamps': len(during) - len(known),
                             'age': _percentiles([t - sent[s] for t, s in known] or [np.nan])},
                  'node_alive': proc.poll() is None}
    finally:
        halt()
        node.destroy_node()
        rclpy.try_shutdown()
        stop_process(proc)
        log.close()
        reservation.release()
    return result


def recording_throughput(config, rate_hz: float = 5000.0, duration_s: float = 3.0) -> dict:
    """``cdpr_record`` beside a running node while wrenches flood in at ``rate_hz``: messages
    recorded per second and bytes per message (all child processes, one ROS domain)."""
    from cdpr_dynamics.recording.reader import recording_info

    path, sent = _beside_node_and_recorder(
        'record', config, None, ['flood', '--rate', str(rate_hz), '--duration', str(duration_s),
                                 '--frame', load_settings(config).robot.frame_id,
                                 '--subscribers', '2'],       # the node and the recorder
        duration_s + 60)
    info = recording_info(path)
    counts = {name: t.message_count for name, t in info.topics.items()}
    span_s = max((info.end_ns - info.start_ns) * 1e-9, 1e-9)
    return {'wrenches_sent': sent['sent'], 'messages': info.message_count, 'topics': counts,
            'messages_per_s': info.message_count / span_s,
            'bytes_per_message': path.stat().st_size / max(info.message_count, 1),
            'complete': info.complete}


def flood(rate_hz: float, duration_s: float, start_s: float, frame: str = 'world',
          subscribers: int = 1, force_n: float = 1000.0, node_match: bool = False) -> dict:
    """Publish wrenches at ``rate_hz`` for ``duration_s`` (``force_n`` along z at 5 Hz);
    stamps start at ``start_s``, once ``subscribers`` subscriptions (the node, and e.g. a
    recorder) have matched and, with ``node_match``, once dynamics_node's /diagnostics say
    its wrench subscription has matched a publisher (the match is made on each side apart: a
    best-effort message sent before the node's side has matched is lost)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import WrenchStamped
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    from msg_adapters.diagnostics import read_statuses
    from msg_adapters.validation import s_to_stamp
    from msg_adapters.wrench import wrench_message

    rclpy.init()
    node = Node('cdpr_flood')
    pub = node.create_publisher(WrenchStamped, 'wrench', qos_profile_sensor_data)
    node_matched = [not node_match]

    def on_diagnostics(msg):
        status = read_statuses(msg).get('cdpr_dynamics: wrench input')
        if status is not None and int(status['values'].get('publishers', 0)) > 0:
            node_matched[0] = True

    if node_match:
        node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)

    def ready() -> bool:
        return pub.get_subscription_count() >= subscribers and node_matched[0]

    deadline = time.monotonic() + 30.0
    while not ready() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    if not ready():
        unmatched = '' if node_matched[0] else ', dynamics_node matched none'
        raise SystemExit(f'flood: {pub.get_subscription_count()} of {subscribers} subscribers '
                         f'on wrench after 30 s{unmatched}')
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
            msg.wrench.force.z = force_n * np.sin(2 * np.pi * 5.0 * (t - start_s))
            pub.publish(msg)
            sent += 1
        time.sleep(min(period, 0.0005))
    elapsed = time.perf_counter() - start
    node.destroy_node()
    rclpy.try_shutdown()
    return {'sent': sent, 'duration_s': elapsed, 'rate_hz': sent / elapsed,
            'last_stamp_s': start_s + (sent - 1) * period}


def controller(config, wrench_hz: float, pose_hz: float, duration_s: float,
               subscribers: int = 1, start_s: float = 2000.0) -> dict:
    """A controller's traffic: WrenchStamped at ``wrench_hz`` and PoseStamped at ``pose_hz``
    moving along a 5 cm circle (each pose a rebuild), both best effort, stamps 1/rate apart
    from ``start_s``, for ``duration_s``; starts once both topics have ``subscribers``
    subscriptions (the node and a recorder) and ``predicted_displacement`` the others (the
    recorder). Returns the counts sent."""
    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    from cdpr_dynamics.analysis.live import rotated_quaternion
    from msg_adapters.pose import pose_message
    from msg_adapters.validation import s_to_stamp
    from msg_adapters.wrench import wrench_message

    settings = load_settings(config)
    frame = settings.robot.frame_id
    quaternion = rotated_quaternion(settings.initial_rotation, np.zeros(3))
    rclpy.init()
    node = Node('cdpr_controller')
    wrench_pub = node.create_publisher(WrenchStamped, 'wrench', qos_profile_sensor_data)
    pose_pub = node.create_publisher(PoseStamped, 'pose', qos_profile_sensor_data)
    deadline = time.monotonic() + 30.0

    def ready() -> bool:
        """The node and the recorder on both inputs, and the recorder on the node's answers
        (a recorder that subscribes to them late misses the first predictions)."""
        inputs = min(wrench_pub.get_subscription_count(), pose_pub.get_subscription_count())
        answers = node.count_subscribers('predicted_displacement')
        return inputs >= subscribers and answers >= subscribers - 1

    while not ready() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    if not ready():
        raise SystemExit(f'controller: fewer than {subscribers} subscribers on wrench and pose '
                         f'(or {subscribers - 1} on predicted_displacement) after 30 s')
    msg = wrench_message([0.0, 0.0, 0.0], frame_id=frame)
    total = int(round(wrench_hz * duration_s))
    per_pose = max(1, int(round(wrench_hz / pose_hz)))
    sent = {'wrench': 0, 'pose': 0}
    start = time.perf_counter()
    k = 0
    while k < total:
        due = min(total, int((time.perf_counter() - start) * wrench_hz) + 1)
        while k < due:
            t = start_s + k / wrench_hz
            if k % per_pose == 0:
                position = _circle(settings, sent['pose'], 100)
                pose_pub.publish(pose_message(position, quaternion, frame, s_to_stamp(t)))
                sent['pose'] += 1
            msg.header.stamp = s_to_stamp(t)
            msg.wrench.force.z = 1000.0 * np.sin(2 * np.pi * 5.0 * (t - start_s))
            wrench_pub.publish(msg)
            sent['wrench'] += 1
            k += 1
        time.sleep(min(1.0 / wrench_hz, 0.0005))
    elapsed = time.perf_counter() - start
    node.destroy_node()
    rclpy.try_shutdown()
    return {**sent, 'duration_s': elapsed, 'wrench_hz': sent['wrench'] / elapsed,
            'last_stamp_s': start_s + (total - 1) / wrench_hz}


def _beside_node_and_recorder(tag: str, config, parameters, child_args: list,
                              timeout_s: float) -> tuple[Path, dict]:
    """Run ``python -m cdpr_dynamics.cli.bench_node CHILD_ARGS`` (a traffic source) with
    dynamics_node and ``cdpr_record`` beside it, all child processes on one ROS domain of their
    own; once the node's counts have settled in the recording, stop both. The recording's
    path and the JSON line the source printed."""
    from cdpr_dynamics.ros.process import start_node, stop_process

    reservation, env = _ros_session(tag)
    path = Path(env['ROS_LOG_DIR']) / f'{tag}.mcap'
    node = start_node(config, env, parameters, stdout=subprocess.DEVNULL,
                      stderr=subprocess.DEVNULL)
    recorder = None
    try:
        recorder = subprocess.Popen([sys.executable, '-m', 'cdpr_dynamics.cli.record',
                                     '--output', str(path)], env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
        before, start = _cpu_seconds(node, recorder), time.monotonic()
        out = subprocess.run([sys.executable, '-m', 'cdpr_dynamics.cli.bench_node']
                             + child_args, env=env, capture_output=True, text=True,
                             timeout=timeout_s)
        after, elapsed = _cpu_seconds(node, recorder), time.monotonic() - start
        if out.returncode != 0:
            raise RuntimeError((out.stderr or out.stdout).strip().splitlines()[-1])
        sent = json.loads(out.stdout.strip().splitlines()[-1])
        sent['cpu_percent'] = {key: round(100 * (after[key] - before[key]) / elapsed, 1)
                               for key in before if key in after}
        _wait_for_quiet_counts(path, time.time_ns(), sent.get('sent', sent.get('wrench', 0)),
                               60.0)
    finally:
        if recorder is not None:
            stop_process(recorder)
        stop_process(node)
        reservation.release()
    return path, sent


def _cpu_seconds(node, recorder) -> dict:
    """CPU time (user + system, s) used so far by the node and the recorder processes (Linux
    /proc; those it cannot read are left out)."""
    seconds = {}
    for key, proc in (('node', node), ('recorder', recorder)):
        try:
            fields = Path(f'/proc/{proc.pid}/stat').read_text().rsplit(')', 1)[1].split()
        except OSError:
            continue
        seconds[key] = (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    return seconds


def _wait_for_quiet_counts(path: Path, after_ns: int, sent: int, timeout_s: float) -> bool:
    """Until the node's diagnostics in the recording being written at ``path`` (logged after
    ``after_ns``) account for all ``sent`` wrenches (accepted or rejected), or have kept one
    count over QUIET_S (the rest is lost), or the time is up; read as far as its whole chunks
    go (a chunk is closed at least every second). A node starved of CPU can keep one count
    over two reports a second apart and still hold its queue."""
    from cdpr_dynamics.recording.reader import read_messages
    from msg_adapters.diagnostics import read_statuses

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        counts = []                       # (log time, accepted + rejected)
        try:
            for record in read_messages(path, ['/diagnostics'], allow_incomplete=True):
                if record.log_time_ns > after_ns:
                    status = read_statuses(record.message).get('cdpr_dynamics: wrench input')
                    if status is not None:
                        values = status['values']
                        counts.append((record.log_time_ns, int(values.get('accepted', 0))
                                       + int(values.get('rejected', 0))))
        except Exception:  # noqa: BLE001 - the file is being written: read again
            counts = []
        if counts:
            last = counts[-1][1]
            same = [t for t, count in counts if count == last]
            if last >= sent or (same[-1] - same[0]) * 1e-9 >= QUIET_S:
                return True
        time.sleep(0.2)       # the polling period of the file, not a synchronisation
    return False


def controller_rate(config, wrench_hz: float = 1000.0, pose_hz: float = 50.0,
                    duration_s: float = 10.0, parameters: dict | None = None) -> dict:
    """A controller's rates with ``cdpr_record`` beside the node (all child processes, one ROS
    domain): per topic the messages published, recorded, and predicted by the node (its
    /diagnostics counts, read from the recording). ``parameters``: the node's overrides
    (``model.method``, ``node.rebuild``, ...)."""
    from cdpr_dynamics.recording.reader import read_messages, recording_info
    from msg_adapters.diagnostics import read_statuses

    path, sent = _beside_node_and_recorder(
        'controller', config, parameters,
        ['controller', '--config', str(config), '--wrench-hz', str(wrench_hz), '--pose-hz',
         str(pose_hz), '--duration', str(duration_s), '--subscribers', '2'], duration_s + 90)
    info = recording_info(path)
    recorded = {name.lstrip('/'): t.message_count for name, t in info.topics.items()}
    last = {}
    for record in read_messages(path, ['/diagnostics']):
        for name, status in read_statuses(record.message).items():
            last[name.split(': ', 1)[-1]] = status['values']
    wrench_in, pose_in = last.get('wrench input', {}), last.get('pose input', {})
    model = last.get('model', {})
    result = {'wrench_hz': wrench_hz, 'pose_hz': pose_hz, 'duration_s': duration_s,
              'published': {'wrench': sent['wrench'], 'pose': sent['pose']},
              'cpu_percent': sent.get('cpu_percent', {}),
              'recorded': recorded,
              'predicted': int(wrench_in.get('accepted', 0)),
              'poses_accepted': int(pose_in.get('accepted', 0)),
              'rebuilds': int(model.get('rebuilds', 0)),
              'update_ms_p50': float(model.get('update_ms_p50', 'nan')),
              'update_ms_p99': float(model.get('update_ms_p99', 'nan')),
              'method': model.get('method', ''),
              'rebuild': model.get('rebuild', ''),
              'poses_superseded': int(model.get('poses_superseded', 0)),
              'swap_ms_p50': float(model.get('swap_ms_p50', 'nan')),
              'pose_rejected': int(pose_in.get('rejected', 0)),
              'wrench_rejected': int(wrench_in.get('rejected', 0)),
              'last_rejection': {'pose': pose_in.get('last_rejection', ''),
                                 'wrench': wrench_in.get('last_rejection', '')}}
    result['predicted_fraction'] = result['predicted'] / max(1, sent['wrench'])
    # a wrench the cables cannot hold is answered with a rejection, not a prediction
    result['handled_fraction'] = ((result['predicted'] + result['wrench_rejected'])
                                  / max(1, sent['wrench']))
    result['recorded_fraction'] = {
        'wrench': recorded.get('wrench', 0) / max(1, sent['wrench']),
        'pose': recorded.get('pose', 0) / max(1, sent['pose']),
        'predicted_displacement': (recorded.get('predicted_displacement', 0)
                                   / max(1, result['predicted']))}
    return result


def slack_rate(config, rate_hz: float = 1000.0, duration_s: float = 10.0,
               parameters: dict | None = None) -> dict:
    """The paper demo's load over DDS: ``frf.force_n``'s z (1500 N on the paper robot) at 5 Hz
    as wrenches at ``rate_hz`` for ``duration_s``, to the node (``node.slack: aware`` unless
    ``parameters`` say otherwise) with ``cdpr_record`` beside it: wrenches sent, predicted and
    rejected by the node (its /diagnostics counts, from the recording), lost (sent, neither
    predicted nor rejected), predictions recorded, and the node's predicted slack time."""
    from cdpr_dynamics.recording.reader import read_messages, recording_info
    from msg_adapters.diagnostics import read_statuses

    settings = load_settings(config)
    parameters = {'node.slack': 'aware', **(parameters or {})}
    path, sent = _beside_node_and_recorder(
        'slack', config, parameters,
        ['flood', '--rate', str(rate_hz), '--duration', str(duration_s), '--frame',
         settings.robot.frame_id, '--subscribers', '2', '--node-match', '--force-n',
         str(float(settings.frf_force_n[2]))], duration_s + 90)
    recorded = {name.lstrip('/'): t.message_count
                for name, t in recording_info(path).topics.items()}
    last = {}
    for record in read_messages(path, ['/diagnostics']):
        for name, status in read_statuses(record.message).items():
            last[name.split(': ', 1)[-1]] = status['values']
    wrench_in, model = last.get('wrench input', {}), last.get('model', {})
    predicted, rejected = int(wrench_in.get('accepted', 0)), int(wrench_in.get('rejected', 0))
    return {'rate_hz': rate_hz, 'duration_s': duration_s,
            'force_n': float(settings.frf_force_n[2]), 'slack': model.get('slack', ''),
            'method': model.get('method', ''), 'sent': sent['sent'],
            'achieved_send_hz': sent['rate_hz'], 'predicted': predicted, 'rejected': rejected,
            'lost': sent['sent'] - predicted - rejected,
            'recorded_predictions': recorded.get('predicted_displacement', 0),
            'slack_time_s': float(model.get('slack_time_s', 'nan')),
            'compute_ms_p50': float(wrench_in.get('compute_ms_p50', 'nan')),
            'compute_ms_p99': float(wrench_in.get('compute_ms_p99', 'nan')),
            'cpu_percent': sent.get('cpu_percent', {})}


def echo() -> None:
    """The reference of the latency: a trivial rclpy node that answers each ``wrench`` with
    a ``predicted_displacement`` of the same stamp (sensor-data QoS in, depth 10 out), spun
    by rclpy's SingleThreadedExecutor; until SIGINT."""
    import rclpy
    from geometry_msgs.msg import Vector3Stamped, WrenchStamped
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    rclpy.init()
    node = Node('cdpr_echo')
    pub = node.create_publisher(Vector3Stamped, 'predicted_displacement', 10)
    out = Vector3Stamped()

    def on_wrench(msg):
        out.header = msg.header
        pub.publish(out)

    node.create_subscription(WrenchStamped, 'wrench', on_wrench, qos_profile_sensor_data)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def main(argv=None) -> int:
    """``flood``: the wrench publisher of the benchmark and of the flood test; ``controller``:
    a controller's wrenches and moving poses (:func:`controller`)."""
    parser = argparse.ArgumentParser(description='publish wrenches at a rate (tests, cdpr_bench)')
    sub = parser.add_subparsers(dest='command', required=True)
    fl = sub.add_parser('flood', help='publish wrenches at a rate (for tests and benchmarks)')
    fl.add_argument('--rate', type=float, default=5000.0)
    fl.add_argument('--duration', type=float, default=10.0)
    fl.add_argument('--start-s', type=float, default=1000.0)
    fl.add_argument('--frame', default='world')
    fl.add_argument('--subscribers', type=int, default=1)
    fl.add_argument('--force-n', type=float, default=1000.0)
    fl.add_argument('--node-match', action='store_true',
                    help="also wait for dynamics_node's wrench subscription to match")
    co = sub.add_parser('controller', help='publish wrenches and moving poses at rates')
    co.add_argument('--config', required=True)
    co.add_argument('--wrench-hz', type=float, default=1000.0)
    co.add_argument('--pose-hz', type=float, default=50.0)
    co.add_argument('--duration', type=float, default=10.0)
    co.add_argument('--subscribers', type=int, default=1)
    sub.add_parser('echo', help='answer each wrench with a prediction of the same stamp')
    args = parser.parse_args(argv)
    if args.command == 'echo':
        echo()
        return 0
    if args.command == 'controller':
        print(json.dumps(controller(args.config, args.wrench_hz, args.pose_hz, args.duration,
                                    args.subscribers)))
        return 0
    print(json.dumps(flood(args.rate, args.duration, args.start_s, args.frame,
                           args.subscribers, args.force_n, args.node_match)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
