"""``cdpr_demo``: the live node on the paper's robot beside a scripted controller.

    cdpr_demo [--config PATH] [--duration S] [--amplitude-n N] [--excitation-hz F]
              [--output PNG] [--record MCAP | --no-record] [--json PATH]

Starts ``dynamics_node`` as a child process (``--ros-args --params-file`` the config) and waits
until it is up: its latched ``cable_tensions`` and ``/diagnostics`` received, its subscriptions
to ``pose`` and ``wrench`` in the graph, its ``predicted_displacement`` and ``predicted_pose``
matched by this process's subscriptions. Then it runs a scripted controller as a second
process: the controller waits until its publishers see the node's subscriptions (and the
recorder's), and only then takes its first stamp ``t0`` and starts: a slow circle of the
end-effector (poses at 50 Hz) and a harmonic wrench (1 kHz), ``W(t) = W0 sin(2 pi f t)`` with
``W0`` the config's ``frf.force_n`` and ``frf.moment_nm`` (the moment only for a rigid
platform), scaled by ``--amplitude-n`` to a force of that magnitude (N, same direction).
Stamps are ``t0 + k / rate`` (wall clock, integer nanoseconds).

This process counts the wrenches published and the predictions received (matched by stamp),
waits until the last prediction arrived (or the node is idle), reads the node's pose and
wrench counts from ``/diagnostics``, feeds the inputs it sent through the node's own predictor
twice (:func:`~cdpr_dynamics.cli.demo_results.slack_comparison`: ``node.slack`` aware, the
node's default, and linear; the node's predictions are the one its ``node.slack`` names), says
whether and how long the load slackens a cable and what the slack-aware prediction changed, and
where it does, the largest ``--amplitude-n`` that keeps every cable taut at every pose of the
circle (the dynamic cable forces included), calls ``frequency_response`` (per
unit force along the load, the configured model and ``method=spring``) and writes a PNG: load
and predicted displacement over time, cable tensions with the lowest one, and the FRF |H| (m/N,
log-log) with the platform modes marked. All traffic (inputs, outputs, diagnostics, markers,
service events) is recorded to an MCAP file beside the PNG. Without ROS_DOMAIN_ID it takes a
free domain of its own; discovery stays on localhost unless ROS_AUTOMATIC_DISCOVERY_RANGE says
otherwise. Failures end with one line and a non-zero exit status.
"""
from __future__ import annotations

import argparse
import difflib
import json
import math
import os
import queue
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.cli import interruptible
from cdpr_dynamics.cli.demo_figure import plot
from cdpr_dynamics.cli.demo_plan import (
    controller_main, DemoError, Load, read_config, stamps_ns, Trajectory)
from cdpr_dynamics.cli.demo_results import (
    along, input_sentence, Received, slack_comparison, status_count, TensionEstimate)
from cdpr_dynamics.analysis.config import default_config_path

PROG = 'cdpr_demo'
DEMO_TOPICS = ['pose', 'wrench', 'predicted_displacement', 'predicted_pose', 'cable_tensions',
               '/diagnostics', 'cdpr_markers', 'frequency_response/_service_event']
#: depth of this process's subscriptions to the node's predictions (reliable): a 10 s backlog
#: at 1 kHz, so a busy moment here loses nothing that reached this process
PREDICTION_DEPTH = 10000
#: depth of the recorder's subscriptions (raw, taken in batches)
RECORD_DEPTH = 5000
#: the recorder's advice for an existing file, in cdpr_record's flags (see _own_flags)
RECORDER_ADVICE = 'use --force to replace it'
#: how often the Listener takes what arrived (s)
POLL_S = 0.02


def _round_down(value: float) -> float:
    """``value`` > 0 rounded down to two significant digits."""
    step = 10.0 ** (math.floor(math.log10(value)) - 1)
    return math.floor(value / step) * step


def _environment():
    """Domain, discovery range and log folder: the user's, or isolated ones."""
    from cdpr_dynamics.ros.process import ament_prefix, reserve_domain_id
    reservation = None
    env = dict(os.environ)
    if not env.get('ROS_DOMAIN_ID'):
        reservation = reserve_domain_id(141, 200)
        env['ROS_DOMAIN_ID'] = str(reservation.domain_id)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if not env.get('ROS_LOG_DIR'):
        env['ROS_LOG_DIR'] = tempfile.mkdtemp(prefix='cdpr_demo_log_')
    env['AMENT_PREFIX_PATH'] = ament_prefix()
    env['PYTHONUNBUFFERED'] = '1'
    for name in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_LOG_DIR',
                 'AMENT_PREFIX_PATH'):
        os.environ[name] = env[name]
    return env, reservation


# ------------------------------------------------------------------------------ the plan


class Controller:
    """The controller process, its stdout read line by line in a thread."""

    def __init__(self, command, env):
        self.proc = subprocess.Popen(command, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue = queue.Queue()
        self.stderr: list[str] = []
        self._threads = [
            threading.Thread(target=self._pump, args=(self.proc.stdout, self.lines.put),
                             daemon=True),
            threading.Thread(target=self._pump, args=(self.proc.stderr, self.stderr.append),
                             daemon=True)]
        for thread in self._threads:
            thread.start()

    @staticmethod
    def _pump(stream, put):
        for line in stream:
            put(line.rstrip('\n'))

    def failure(self) -> str:
        lines = [line for line in self.stderr if line.strip()]
        return lines[-1] if lines else f'exit status {self.proc.returncode}'

    def next_json(self, timeout_s: float, what: str) -> dict:
        """The controller's next JSON line; DemoError if it ends or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None:
                    for thread in self._threads:
                        thread.join(1.0)
                    if self.lines.empty():
                        raise DemoError(f'controller failed: {self.failure()}') from None
                elif time.monotonic() > deadline:
                    raise DemoError(f'the controller did not {what} within {timeout_s:g} s')
                continue
            try:
                return json.loads(line)
            except ValueError:
                continue      # not one of its lines (a library's output)

    def wait(self, timeout_s: float) -> int:
        try:
            status = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise DemoError('the controller process did not finish') from None
        for thread in self._threads:
            thread.join(1.0)
        return status


# ---------------------------------------------------------------------------- listening


def arrival_s(info: dict) -> float:
    """When DDS received a message taken with ``take_message`` (its ``received_timestamp``,
    wall clock ns, as the stamps), in s; now where the RMW gives none. A poll takes messages up
    to :data:`POLL_S` after they arrived: this, not the poll, is the time a latency ends."""
    stamp_ns = info.get('received_timestamp') or 0
    return stamp_ns * 1e-9 if stamp_ns > 0 else time.time()


class Listener:
    """Predictions, predicted poses, tensions and diagnostics of the node (predictions keyed
    by stamp, ns).

    The subscriptions belong to ``poll_node``, which no executor spins: DDS queues what
    arrives (reliable, :data:`PREDICTION_DEPTH` deep for the predictions) and a timer of
    ``node`` takes everything waiting every :data:`POLL_S`. One executor wake-up per poll
    instead of one per message: this process's CPU per message received measured 260 us with
    a callback per message and 160 us polled (one run each, 1 kHz predictions and predicted
    poses, a loaded 2-core machine), CPU the node beside it needs.
    """

    def __init__(self, node, poll_node):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, Vector3Stamped
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.cond = threading.Condition()
        self.predictions: dict[int, tuple] = {}   # stamp ns -> (receive s, ux, uy, uz)
        self.poses: dict[int, tuple] = {}         # stamp ns -> (x, y, z, qx, qy, qz, qw)
        self.tensions = []        # (stamp s, tensions...)
        self.diagnostics = []     # (receive monotonic s, statuses)
        deep = QoSProfile(depth=PREDICTION_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        self.subscriptions = {}
        self._handlers = {}
        for cls, topic, handler, qos in (
                (Vector3Stamped, 'predicted_displacement', self._on_prediction, deep),
                (PoseStamped, 'predicted_pose', self._on_pose, deep),
                (JointState, 'cable_tensions', self._on_tensions,
                 QoSProfile(depth=1000, durability=DurabilityPolicy.TRANSIENT_LOCAL)),
                (DiagnosticArray, '/diagnostics', self._on_diagnostics, 100)):
            self.subscriptions[topic] = poll_node.create_subscription(
                cls, topic, handler, qos)
            self._handlers[topic] = handler
        self._timer = node.create_timer(POLL_S, self.poll)

    def poll(self) -> None:
        """Take and handle every message waiting on the subscriptions."""
        for topic, sub in self.subscriptions.items():
            handler = self._handlers[topic]
            while True:
                try:
                    with sub.handle:
                        taken = sub.handle.take_message(sub.msg_type, sub.raw)
                except Exception:  # noqa: BLE001 - destroyed at shutdown
                    break
                if taken is None:
                    break
                handler(*taken)

    def unmatched(self) -> list[str]:
        """The node's outputs this process does not see a publisher of yet."""
        return [name for name, sub in self.subscriptions.items()
                if sub.get_publisher_count() == 0]

    def _on_prediction(self, msg, info):
        now = arrival_s(info)
        v, s = msg.vector, msg.header.stamp
        with self.cond:
            self.predictions[s.sec * 1_000_000_000 + s.nanosec] = (now, v.x, v.y, v.z)
            self.cond.notify_all()

    def _on_pose(self, msg, _info):
        p, q, s = msg.pose.position, msg.pose.orientation, msg.header.stamp
        with self.cond:
            self.poses[s.sec * 1_000_000_000 + s.nanosec] = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
            self.cond.notify_all()

    def _on_tensions(self, msg, _info):
        with self.cond:
            self.tensions.append([msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9]
                                 + list(msg.effort))
            self.cond.notify_all()

    def _on_diagnostics(self, msg, _info):
        from msg_adapters.diagnostics import read_statuses
        statuses = read_statuses(msg)
        if not any(name.endswith(': wrench input') for name in statuses):
            return      # another node's diagnostics
        with self.cond:
            self.diagnostics.append((time.monotonic(), statuses))
            self.cond.notify_all()

    def snapshot(self) -> Received:
        """Copies of what arrived so far (callbacks may still add to the originals)."""
        with self.cond:
            return Received(dict(self.predictions), dict(self.poses), list(self.tensions))

    def wait(self, predicate, timeout_s: float) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout_s)

    def status(self, title: str, since: float = -math.inf) -> dict | None:
        """The latest ``<node>: title`` status received after monotonic time ``since``."""
        for received, statuses in reversed(self.diagnostics):
            if received < since:
                return None
            for name, status in statuses.items():
                if name.endswith(f': {title}'):
                    return status
        return None


def _start_recorder(node, poll_node, path):
    """A Recorder of all the demo's traffic to ``path`` (an existing file is never
    overwritten), or None with --no-record. Its subscriptions belong to ``poll_node``, which
    no executor spins; a timer of ``node`` calls :meth:`Recorder.poll` every :data:`POLL_S`
    (one wake-up per poll, not per message: the demo's CPU during an 8 s run measured 4.0 s
    with the recorder's callbacks, 2.0 s polled, beside the node on 2 cores)."""
    if not path:
        return None
    from cdpr_dynamics.recording.base import RecordingError
    from cdpr_dynamics.recording.recorder import Recorder
    if os.path.lexists(path):
        raise DemoError(f'{path} exists; not overwriting it (give another --record path, or '
                        '--no-record)')
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        recorder = Recorder(poll_node, path, DEMO_TOPICS, qos_depth=RECORD_DEPTH,
                            log_failure=False)
    except (RecordingError, OSError) as exc:
        raise DemoError(_own_flags(str(exc))) from None
    node.create_timer(POLL_S, recorder.poll)
    return recorder


def _own_flags(text: str) -> str:
    """A library's message with its advice in this tool's flags: the recorder's advice
    (:data:`RECORDER_ADVICE`, a flag of ``cdpr_record``) becomes the demo's, which never
    overwrites but takes another path."""
    return text.replace(RECORDER_ADVICE, 'give another --record path, or --no-record')


# ------------------------------------------------------------------------------ results


# ------------------------------------------------------------------------------ the figure


# ------------------------------------------------------------------------------ the run


def _cpu_s(who) -> float:
    """User + system CPU time (s) of this process or of its finished children."""
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _controller_command(args, config: Path, subscribers: int) -> list[str]:
    command = [sys.executable, '-m', 'cdpr_dynamics.cli.demo', '--controller',
               '--subscribers', str(subscribers), '--config', str(config),
               '--duration', repr(args.duration), '--radius', repr(args.radius),
               '--pose-rate', repr(args.pose_rate), '--wrench-rate', repr(args.wrench_rate),
               '--excitation-hz', repr(args.excitation_hz), '--timeout', repr(args.timeout)]
    if args.amplitude_n is not None:
        command += ['--amplitude-n', repr(args.amplitude_n)]
    return command


def _wait_until_up(node, listener, proc, log, log_path, timeout_s: float) -> None:
    """Until the node's latched tensions and diagnostics arrived, its pose and wrench
    subscriptions are in the graph and this process's subscriptions see its outputs."""
    def missing():
        out = [f'its {name} subscription' for name in ('pose', 'wrench')
               if node.count_subscribers(name) == 0]
        out += [f'its {name} publisher' for name in listener.unmatched()]
        if not listener.tensions:
            out.append('a cable_tensions message')
        if not listener.diagnostics:
            out.append('a /diagnostics message')
        return out

    deadline = time.monotonic() + timeout_s
    while not listener.wait(lambda: not missing(), 0.2):
        if proc.poll() is not None:
            log.flush()
            lines = log_path.read_text().strip().splitlines()
            raise DemoError(f'dynamics_node exited with {proc.returncode}: '
                            f'{lines[-1] if lines else "no output"}')
        if time.monotonic() > deadline:
            raise DemoError(f'dynamics_node did not come up within {timeout_s:g} s: missing '
                            f'{", ".join(missing())} (log: {log_path})')


def _wait_for_predictions(listener, last_stamp: int, ended: float, timeout_s: float) -> None:
    """Until the prediction of the last wrench arrived, or the node reports (diagnostics after
    the controller ended, at ``ended``) a second without wrenches: it predicts no more."""
    def done():
        if last_stamp in listener.predictions:
            return True
        status = listener.status('wrench input', since=ended + 1.0)
        return status is not None and float(status['values'].get('rate_hz', 1)) == 0.0
    listener.wait(done, timeout_s)


def _final_status(listener, since: float, predicted: int, timeout_s: float) -> tuple:
    """(wrench input, pose input) statuses of a diagnostics message received after ``since``
    that counts at least the ``predicted`` wrenches received here (the node's counts are
    then final)."""
    def final():
        status = listener.status('wrench input', since)
        return (status_count(status, 'accepted') or -1) >= predicted
    listener.wait(final, timeout_s)
    return listener.status('wrench input'), listener.status('pose input')


def _frf(node, load: Load, timeout_s: float) -> tuple[dict, dict | None, float]:
    """The node's FRF per unit force along the load (configured model, then spring) and the
    first call's time (ms)."""
    from msg_adapters.frf_service import FrequencyResponseError, call_frequency_response
    unit = {f'force_{k}_n': float(v) for k, v in zip('xyz', load.direction)}
    unit.update({f'moment_{k}_nm': 0.0 for k in 'xyz'})
    names = ['frequency_hz'] + [f'{a}_{k}_{u}' for a, u in (('amplitude', 'm'), ('phase', 'rad'))
                                for k in 'xyz']
    try:
        start = time.perf_counter()
        frf = call_frequency_response(node, overrides=unit, timeout_s=timeout_s, spin=False)
        frf_ms = (time.perf_counter() - start) * 1e3
        spring = call_frequency_response(node, names, {**unit, 'method': 'spring'}, timeout_s,
                                         spin=False)
    except FrequencyResponseError as exc:
        raise DemoError(f'frequency_response: {exc}') from None
    return frf, spring, frf_ms


def run(args) -> dict:
    """The demo; returns the summary (also printed, and written to ``args.json``)."""
    from cdpr_dynamics.ros.process import start_node, stop_process

    config = Path(args.config) if args.config else default_config_path()
    settings, options = read_config(config)
    plan = Trajectory(settings, args)
    if args.record and os.path.lexists(args.record):
        raise DemoError(f'{args.record} exists; not overwriting it (give another --record '
                        'path, or --no-record)')
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from msg_adapters.frf_service import frequency_response_client

    env, reservation = _environment()
    log_path = Path(env['ROS_LOG_DIR']) / 'dynamics_node.log'
    log = open(log_path, 'w')
    proc = start_node(config, env, stdout=log, stderr=subprocess.STDOUT)
    controller = recorder = status = spinner = None
    nodes = []
    spinning = threading.Event()
    spinning.set()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)   # Ctrl-C: main's one line
    executor = SingleThreadedExecutor()

    def spin():
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    try:
        node = Node('cdpr_demo', start_parameter_services=False)   # a smaller wait set
        nodes.append(node)
        frequency_response_client(node)   # discovered while the demo runs, not after it
        poll_node = Node('cdpr_demo_listener', start_parameter_services=False)   # not spun
        nodes.append(poll_node)
        executor.add_node(node)
        listener = Listener(node, poll_node)
        spinner = threading.Thread(target=spin, daemon=True)
        spinner.start()
        recorder = _start_recorder(node, poll_node, args.record)
        _wait_until_up(node, listener, proc, log, log_path, args.timeout)
        subscribers = node.count_subscribers('wrench') + (recorder is not None)
        controller = Controller(_controller_command(args, config, subscribers), env)
        start = controller.next_json(args.timeout + 10.0, 'see its subscribers')
        cpu_at_start = _cpu_s(resource.RUSAGE_SELF)
        t0_ns = int(start['t0_ns'])
        print(f'{PROG}: node up on ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]} (log {log_path}); '
              f'controller matched {start["matched"]["wrench"]} subscribers, runs '
              f'{args.duration:g} s', flush=True)
        sent = controller.next_json(args.duration + args.timeout + 5.0, 'finish')
        if controller.wait(10.0) != 0:
            raise DemoError(f'controller failed: {controller.failure()}')
        ended = time.monotonic()
        cpu_during = _cpu_s(resource.RUSAGE_SELF) - cpu_at_start
        published = set(stamps_ns(t0_ns, sent['wrenches'], args.wrench_rate).tolist())
        _wait_for_predictions(listener, max(published), ended, args.timeout)
        frf, spring, frf_ms = _frf(node, plan.load, args.timeout)
        got = listener.snapshot()
        predicted = len(published & got.predictions.keys())
        poses_predicted = len(published & got.poses.keys())
        stray = len(got.predictions.keys() - published)
        wrench_status, pose_status = _final_status(listener, ended, predicted, 3.0)
        if not got.predictions:
            raise DemoError('no predicted_displacement received')
        model = (listener.status('model') or {'values': {}})['values']
        comparison = slack_comparison(settings, options, plan, t0_ns, sent['wrenches'],
                                      sent['poses'])
        tensions = (TensionEstimate(comparison.t_s, comparison.static_n,
                                    comparison.force_linear, settings.tension_min_n)
                    if comparison.t_s.size else 'no wrench the node could predict')
        received = np.array(sorted(got.predictions), dtype=np.int64)
        pred = np.array([got.predictions[s] for s in received])
        latency = (pred[:, 0] - received * 1e-9) * 1e3
        h = along(frf, plan.load.direction)
        peak = int(np.argmax(h))
        result = {
            'method': model.get('method', settings.method), 'dofs': model.get('dofs', '?'),
            'load_force_n': plan.load.force_n.tolist(),
            'load_moment_nm': plan.load.moment_nm.tolist(),
            'excitation_hz': args.excitation_hz, 't0_ns': t0_ns,
            'subscribers_matched_at_start': start['matched'],
            'subscribers_at_first_wrench': sent['subscribers_at_first_wrench'],
            'wrenches_published': sent['wrenches'], 'poses_published': sent['poses'],
            'wrenches_predicted': predicted, 'predicted_poses_received': poses_predicted,
            'predictions_not_of_a_published_wrench': stray,
            'prediction_ratio': predicted / max(sent['wrenches'], 1),
            'node_wrenches_accepted': status_count(wrench_status, 'accepted'),
            'node_wrenches_rejected': status_count(wrench_status, 'rejected'),
            'node_wrenches_late': status_count(wrench_status, 'late'),
            'node_poses_accepted': status_count(pose_status, 'accepted'),
            'node_poses_rejected': status_count(pose_status, 'rejected'),
            'node_poses_late': status_count(pose_status, 'late'),
            'latency_ms_p50': float(np.percentile(latency, 50)),
            'latency_ms_p99': float(np.percentile(latency, 99)),
            'max_displacement_m': float(np.abs(pred[:, 1:]).max()),
            'frf_call_ms': frf_ms,
            'peak_receptance_m_per_n': float(h[peak]),
            'peak_frequency_hz': float(frf['frequency_hz'][peak]),
            'platform_natural_frequencies_hz': np.asarray(
                frf.get('platform_natural_frequencies_hz', [])).tolist(),
            'demo_cpu_s': _cpu_s(resource.RUSAGE_SELF), 'demo_cpu_s_while_controlling': cpu_during,
            'controller_cpu_s': _cpu_s(resource.RUSAGE_CHILDREN),
            'load_average_1min': os.getloadavg()[0],
        }
        lines = [
            f'{result["method"]} model, {result["dofs"]} DOFs; load {plan.load.amplitude_n:g} '
            f'N along {np.round(plan.load.direction, 3).tolist()} at {args.excitation_hz:g} Hz',
            f'wrenches: {sent["wrenches"]} published, {predicted} predicted (received here, '
            f'matched by stamp): {100 * result["prediction_ratio"]:.2f} %',
            input_sentence('wrenches', sent['wrenches'], wrench_status),
            input_sentence('poses', sent['poses'], pose_status)]
        if status_count(wrench_status, 'rejected_infeasible'):
            limit = plan.amplitude_limit_n(settings)
            result['amplitude_limit_n'] = limit
            if limit:
                lines.append(f'wrenches: the cables hold up to {limit:.4g} N along this load '
                             '(both signs, tensions in the box) at 16 poses of the circle: '
                             f'e.g. --amplitude-n {_round_down(0.98 * limit):g}')
        slack_mode = options['node.slack']
        matched = [(s, i) for i, s in enumerate(comparison.stamps.tolist())
                   if s in got.predictions]
        if matched:
            mine = comparison.u_aware if slack_mode == 'aware' else comparison.u_linear
            result['node_vs_local_max_m'] = float(max(
                np.abs(np.asarray(got.predictions[s][1:]) - mine[i]).max() for s, i in matched))
        result.update(slack_mode=slack_mode,
                      slack_fraction=float(comparison.slack.mean()) if matched else 0.0,
                      peak_aware_m=float(np.abs(comparison.u_aware).max(initial=0.0)),
                      peak_linear_m=float(np.abs(comparison.u_linear).max(initial=0.0)))
        lines.append(f'prediction: node.slack = {slack_mode} ('
                     + ('the compression-free model while a cable is slack' if slack_mode ==
                        'aware' else 'linear throughout, only a warning while a cable is slack')
                     + f'); {comparison.sentence()}')
        taut = comparison.taut_amplitude_n(plan.load.amplitude_n)
        result['taut_amplitude_n'] = taut
        if taut is not None and taut < plan.load.amplitude_n:
            limit = min(taut, result.get('amplitude_limit_n') or np.inf)
            lines.append('load: no amplitude keeps every cable taut on this circle' if limit <= 0
                         else 'load: to keep every cable taut at every pose of the circle, '
                         'dynamic tension included: --amplitude-n '
                         f'{_round_down(0.98 * limit):g} (at most {limit:.4g} N)')
        if isinstance(tensions, TensionEstimate):
            low, cable, _ = tensions.lowest
            result.update(lowest_tension_n=low, lowest_tension_cable=cable,
                          slack=bool(tensions.slack.any()),
                          slack_cables=np.flatnonzero(tensions.slack.any(axis=0)).tolist())
            lines.append(f'tensions: {tensions.sentence()}')
        else:
            lines.append(f'tensions: {tensions}')
        lines.append(f'max |u| {result["max_displacement_m"] * 1e3:.3f} mm; stamp -> prediction '
                     f'received p50 {result["latency_ms_p50"]:.2f} ms, p99 '
                     f'{result["latency_ms_p99"]:.2f} ms; FRF call {frf_ms:.0f} ms, largest |H| '
                     f'{h[peak]:.3g} m/N at {frf["frequency_hz"][peak]:.1f} Hz')
        output = Path(args.output)
        plot(output, result, got, plan, frf, spring, tensions, t0_ns, comparison)
        lines.append(f'wrote {output.resolve()}')
        if recorder is not None:
            summary = recorder.close()
            recorder = None
            recorded = {name.lstrip('/'): n for name, n in summary.topics.items()}
            result['recorded'] = recorded
            result['record_path'] = str(Path(args.record).resolve())
            expected = {'wrench': sent['wrenches'], 'pose': sent['poses'],
                        'predicted_displacement': result['node_wrenches_accepted'],
                        'predicted_pose': result['node_wrenches_accepted']}
            parts = [f'{name} {n}' + (f' of {expected[name]}' if expected.get(name) is not None
                                      else '') for name, n in recorded.items()]
            lines.append(f'recorded to {result["record_path"]}: ' + ', '.join(parts)
                         + (f' (stopped early: {summary.error})' if summary.error else ''))
        for line in lines:
            print(f'{PROG}: {line}')
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=1))
    finally:
        if controller is not None and controller.proc.poll() is None:
            stop_process(controller.proc, 5.0)
        if recorder is not None:
            recorder.close()
        status = stop_process(proc)
        spinning.clear()
        if spinner is not None:
            spinner.join(2.0)
        executor.shutdown()
        for each in reversed(nodes):
            each.destroy_node()
        rclpy.try_shutdown()
        log.close()
        if reservation is not None:
            reservation.release()
    if status != 0:
        raise DemoError(f'dynamics_node exited with status {status} (log: {log_path})')
    return result


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors that name only this tool's flags."""

    def error(self, message):
        flags = sorted({s for a in self._actions for s in a.option_strings
                        if s.startswith('--') and a.help != argparse.SUPPRESS})
        unknown = re.findall(r'(--[\w-]+)', message) if 'unrecognized' in message else []
        hint = [m for u in unknown for m in difflib.get_close_matches(u.split('=')[0], flags, 1)]
        advice = f'did you mean {hint[0]}? ' if hint else ''
        self.exit(2, f'{self.prog}: error: {message} ({advice}{self.prog} --help lists the '
                  'options)\n')


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG, description='Live vibration prediction demo: the node, a scripted '
        'controller and a frequency-response client; writes a PNG and an MCAP recording.')
    parser.add_argument('--config', help='ROS 2 parameter YAML (default: the paper robot)')
    parser.add_argument('--duration', type=float, default=8.0, help='controller run (s)')
    parser.add_argument('--output', default='out/cdpr_demo.png', help='PNG to write')
    parser.add_argument('--radius', type=float, default=0.05, help='circle radius (m)')
    parser.add_argument('--pose-rate', type=float, default=50.0, help='poses per second')
    parser.add_argument('--wrench-rate', type=float, default=1000.0, help='wrenches per second')
    parser.add_argument('--amplitude-n', type=float, default=None,
                        help="harmonic force amplitude (N, >= 0) along the config's frf.force_n "
                        '(default: frf.force_n and frf.moment_nm as they are)')
    parser.add_argument('--excitation-hz', type=float, default=5.0,
                        help='harmonic force frequency (Hz)')
    parser.add_argument('--record', default=None,
                        help='MCAP file for all traffic (default: out/cdpr_demo_<time>.mcap '
                        'beside the PNG; an existing file is never overwritten)')
    parser.add_argument('--no-record', action='store_true', help='do not record the traffic')
    parser.add_argument('--json', help='also write the summary (counts) to this JSON file')
    parser.add_argument('--timeout', type=float, default=30.0,
                        help='longest wait for the node, the controller or the service (s)')
    parser.add_argument('--controller', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--subscribers', type=int, default=1, help=argparse.SUPPRESS)
    return parser


def _check_numbers(args) -> str | None:
    """The first bad number as a one-line reason, or None."""
    for flag, value, low in (('--duration', args.duration, 0.0),
                             ('--pose-rate', args.pose_rate, 0.0),
                             ('--wrench-rate', args.wrench_rate, 0.0),
                             ('--timeout', args.timeout, 0.0)):
        if not (math.isfinite(value) and value > low):
            return f'{flag} must be a positive number, got {value:g}'
    if round(args.duration * args.wrench_rate) < 1:
        return f'--duration {args.duration:g} s at --wrench-rate {args.wrench_rate:g} is no wrench'
    for flag, value in (('--amplitude-n', args.amplitude_n), ('--radius', args.radius),
                        ('--excitation-hz', args.excitation_hz)):
        if value is not None and not (math.isfinite(value) and value >= 0):
            return f'{flag} must be a number >= 0, got {value:g}'
    return None


@interruptible(PROG)
def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    bad = _check_numbers(args)
    if bad:
        print(f'{PROG}: error: {bad}', file=sys.stderr)
        return 1
    if args.controller:
        args.config = args.config or str(default_config_path())
        try:
            return controller_main(args)
        except DemoError as exc:
            print(exc, file=sys.stderr)     # the demo says 'controller failed: ...'
            return 1
    if not Path(args.output).suffix:    # the file matplotlib writes: the name and '.png'
        args.output = str(Path(args.output).with_suffix('.png'))
    if args.no_record:
        args.record = None
    elif args.record is None:
        args.record = str(Path(args.output).with_name(
            f'cdpr_demo_{time.strftime("%Y%m%d_%H%M%S")}.mcap'))
    try:
        run(args)
    except DemoError as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 1
    except Exception as exc:  # anything unforeseen: still one line, not a traceback
        text = str(exc).strip().splitlines()
        print(f'{PROG}: error: {type(exc).__name__}: {_own_flags(text[0]) if text else ""}',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
