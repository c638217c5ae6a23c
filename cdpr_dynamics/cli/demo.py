"""``cdpr_demo``: the live node on the paper's robot beside a scripted controller.

    cdpr_demo [--config PATH] [--duration S] [--output PNG] [--record MCAP | --no-record]

Starts ``dynamics_node`` as a child process (``--ros-args --params-file`` the config), then
runs a scripted controller as a second process: a slow circle of the end-effector (poses at
50 Hz) and a harmonic wrench (1 kHz; by default 1500 N along z at 5 Hz, the paper's
time-history load), stamped with the wall clock. This process collects the predicted
displacements and cable tensions, calls ``frequency_response`` (the configured model, and
``method=spring`` as an override), and writes a PNG: wrench and predicted displacement over
time, cable tensions along the path, and the FRF log10|A_z|. All traffic (inputs, outputs,
diagnostics, service events) is recorded to an MCAP file beside the PNG. Without ROS_DOMAIN_ID
it takes a free domain of its own; discovery stays on localhost unless
ROS_AUTOMATIC_DISCOVERY_RANGE says otherwise. Failures end with one line and exit status 1.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.cli import interruptible
from cdpr_dynamics.config import ConfigError, default_config_path, load_settings

DEMO_TOPICS = ['pose', 'wrench', 'predicted_displacement', 'cable_tensions', '/diagnostics',
               'frequency_response/_service_event']


class DemoError(RuntimeError):
    """A demo that cannot go on; the message is one line."""


def _environment(args):
    """Domain, discovery range and log folder: the user's, or isolated ones."""
    from cdpr_dynamics.node_process import ament_prefix, reserve_domain_id
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


class Trajectory:
    """The scripted controller's plan: a circle through the start point, a harmonic force."""

    def __init__(self, settings, args):
        self.centre = settings.initial_position_m
        self.args = args

    def position(self, t: float) -> np.ndarray:
        omega = 2 * np.pi / self.args.duration
        r = self.args.radius
        return self.centre + r * np.array([np.cos(omega * t) - 1.0, np.sin(omega * t), 0.0])

    def force(self, t: float) -> np.ndarray:
        return np.array([0.0, 0.0, self.args.amplitude_n *
                         np.sin(2 * np.pi * self.args.excitation_hz * t)])


def controller_main(args) -> int:
    """The controller process: poses and wrenches paced by the clock from wall time ``t0``.

    Prints one JSON line with what it sent. Stamps are ``t0 + k / rate`` (wall clock).
    """
    import json

    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    from msg_adapters.pose import pose_message
    from msg_adapters.validation import s_to_stamp
    from msg_adapters.wrench import wrench_message

    settings = load_settings(args.config)
    plan = Trajectory(settings, args)
    frame = settings.robot.frame_id
    rclpy.init()
    node = Node('cdpr_demo_controller')
    pose_pub = node.create_publisher(PoseStamped, 'pose', qos_profile_sensor_data)
    wrench_pub = node.create_publisher(WrenchStamped, 'wrench', qos_profile_sensor_data)
    deadline = time.monotonic() + args.timeout
    while (pose_pub.get_subscription_count() == 0 or wrench_pub.get_subscription_count() == 0):
        if time.monotonic() > deadline:
            print('controller: dynamics_node not subscribed to pose and wrench', file=sys.stderr)
            return 1
        rclpy.spin_once(node, timeout_sec=0.05)
    dw, dp = 1.0 / args.wrench_rate, 1.0 / args.pose_rate
    n_w = int(round(args.duration * args.wrench_rate))
    n_p = int(round(args.duration * args.pose_rate))
    sent_w = sent_p = 0
    late = []
    while time.time() < args.t0:
        time.sleep(0.001)
    while sent_w < n_w:
        now = time.time() - args.t0
        while sent_p < n_p and sent_p * dp <= now:
            t = sent_p * dp
            pose_pub.publish(pose_message(plan.position(t), frame_id=frame,
                                          stamp=s_to_stamp(args.t0 + t)))
            sent_p += 1
        while sent_w < n_w and sent_w * dw <= now:
            t = sent_w * dw
            wrench_pub.publish(wrench_message(plan.force(t), frame_id=frame,
                                              stamp=s_to_stamp(args.t0 + t)))
            late.append(time.time() - args.t0 - t)
            sent_w += 1
        time.sleep(0.0002)
    node.destroy_node()
    rclpy.try_shutdown()
    print(json.dumps({'wrenches': sent_w, 'poses': sent_p,
                      'publish_delay_ms_p50': float(np.percentile(late, 50) * 1e3),
                      'publish_delay_ms_p99': float(np.percentile(late, 99) * 1e3)}))
    return 0


class Listener:
    """Predictions, tensions and diagnostics of the node, collected in a background executor."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import Vector3Stamped
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from sensor_msgs.msg import JointState
        self.cond = threading.Condition()
        self.predictions = []     # (stamp s, receive wall time s, ux, uy, uz)
        self.tensions = []        # (stamp s, tensions...)
        self.diagnostics = []
        node.create_subscription(Vector3Stamped, 'predicted_displacement', self._on_prediction,
                                 5000)
        node.create_subscription(JointState, 'cable_tensions', self._on_tensions,
                                 QoSProfile(depth=100,
                                            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    def _on_prediction(self, msg):
        now = time.time()
        v = msg.vector
        with self.cond:
            self.predictions.append((msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                                     now, v.x, v.y, v.z))
            self.cond.notify_all()

    def _on_tensions(self, msg):
        with self.cond:
            self.tensions.append([msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9]
                                 + list(msg.effort))
            self.cond.notify_all()

    def _on_diagnostics(self, msg):
        from msg_adapters.diagnostics import read_statuses
        statuses = read_statuses(msg)
        with self.cond:
            self.diagnostics.append(statuses)
            self.cond.notify_all()

    def wait(self, predicate, timeout_s: float) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout_s)

    def status(self, title: str) -> dict:
        for statuses in reversed(self.diagnostics):
            if f'cdpr_dynamics: {title}' in statuses:
                return statuses[f'cdpr_dynamics: {title}']
        return {'values': {}, 'message': '', 'level': 0}


def _start_recorder(node, path):
    """A Recorder of all the demo's traffic to ``path`` (an existing file is never
    overwritten), or None with --no-record."""
    if not path:
        return None
    from cdpr_dynamics.recording.base import RecordingError
    from cdpr_dynamics.recording.recorder import Recorder
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        return Recorder(node, path, DEMO_TOPICS)
    except (RecordingError, OSError) as exc:
        raise DemoError(str(exc)) from None


def _wait_for_recorder(recorder, node, timeout_s: float) -> None:
    """Until the recorder subscribes to pose and wrench (the controller is connecting)."""
    wanted = {node.resolve_topic_name('pose'), node.resolve_topic_name('wrench')}
    deadline = time.monotonic() + timeout_s
    while not wanted <= recorder.subscribed() and time.monotonic() < deadline:
        time.sleep(0.02)


def _plot(path: Path, settings, listener: Listener, plan: Trajectory, frf: dict,
          spring: dict, t0: float, summary: str) -> None:
    import textwrap

    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    args = plan.args
    pred = np.array(listener.predictions)
    tens = np.array([row for row in listener.tensions if row[0] >= t0 - 1e-6])
    fig, axes = plt.subplots(3, 1, figsize=(10, 11.5))
    ax = axes[0]
    ax.plot(pred[:, 0] - t0, pred[:, 4] * 1e3, lw=0.8, label='u_z (predicted_displacement)')
    ax.set_xlabel('time (s)')
    ax.set_ylabel('predicted displacement u_z (mm)')
    ax.grid(True, alpha=0.3)
    twin = ax.twinx()
    tt = np.linspace(0, args.duration, 4000)
    twin.plot(tt, [plan.force(x)[2] for x in tt], color='0.55', lw=0.6, ls=':',
              label='F_z (wrench)')
    twin.set_ylabel('F_z (N)')
    lines = ax.get_legend_handles_labels()
    more = twin.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], loc='upper right', fontsize=8)
    ax.set_title(f'live prediction: {args.amplitude_n:g} N at {args.excitation_hz:g} Hz along '
                 f'z, {args.wrench_rate:g} wrenches/s, while moving on a '
                 f'{args.radius * 100:g} cm circle (poses at {args.pose_rate:g} Hz)')
    ax = axes[1]
    if tens.size:
        for i in range(1, tens.shape[1]):
            ax.plot(tens[:, 0] - t0, tens[:, i], lw=1.0, label=f'cable {i - 1}')
    ax.set_xlabel('time (s)')
    ax.set_ylabel('cable tension (N)')
    ax.grid(True, alpha=0.3)
    ax.legend(ncol=4, fontsize=8)
    ax.set_title('tension distribution along the path (cable_tensions)')
    ax = axes[2]
    ax.plot(frf['frequency_hz'], frf['log10_amplitude_z'], label=f'{settings.method} (service)')
    if spring:
        ax.plot(spring['frequency_hz'], spring['log10_amplitude_z'], ls='--',
                label='override method=spring')
    natural = frf['natural_frequencies_hz']
    for f in np.unique(np.round(natural[natural <= frf['frequency_hz'][-1]], 2)):
        ax.axvline(f, color='0.75', lw=0.6)
    ax.set_xlabel('frequency (Hz)')
    ax.set_ylabel('log10 |A_z| (m)')
    ax.grid(True, alpha=0.3)
    ax.legend()
    ax.set_title(f'frequency_response at the final pose, {frf["frequency_hz"].size} points '
                 '(grey: natural frequencies)')
    fig.suptitle('\n'.join(textwrap.wrap(summary, 130)), fontsize=8.5)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _controller_command(args, config: Path, t0: float) -> list[str]:
    return [sys.executable, '-m', 'cdpr_dynamics.cli.demo', '--controller-t0', repr(t0),
            '--config', str(config), '--duration', repr(args.duration), '--radius',
            repr(args.radius), '--pose-rate', repr(args.pose_rate), '--wrench-rate',
            repr(args.wrench_rate), '--amplitude-n', repr(args.amplitude_n),
            '--excitation-hz', repr(args.excitation_hz), '--timeout', repr(args.timeout)]


def run(args) -> Path:
    import json

    from cdpr_dynamics.node_process import start_node, stop_process

    config = Path(args.config) if args.config else default_config_path()
    try:
        settings = load_settings(config)
    except ConfigError as exc:
        raise DemoError(str(exc)) from None
    plan = Trajectory(settings, args)
    env, reservation = _environment(args)
    log_path = Path(env['ROS_LOG_DIR']) / 'dynamics_node.log'
    log = open(log_path, 'w')
    proc = start_node(config, env, stdout=log, stderr=subprocess.STDOUT)
    controller = None
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rclpy.node import Node

    from msg_adapters.frf_service import FrequencyResponseError, call_frequency_response

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)   # Ctrl-C: main's one line
    node = Node('cdpr_demo')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    listener = Listener(node)
    spinning = threading.Event()
    spinning.set()

    def spin():
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    recorder = None
    status = None
    try:
        recorder = _start_recorder(node, args.record)

        def node_ready():
            return (node.count_subscribers('wrench') > 0 and node.count_subscribers('pose') > 0
                    and listener.tensions and listener.diagnostics)
        deadline = time.monotonic() + args.timeout
        while not listener.wait(node_ready, 0.2):
            if proc.poll() is not None:
                log.flush()
                lines = log_path.read_text().strip().splitlines()
                raise DemoError(f'dynamics_node exited with {proc.returncode}: '
                                f'{lines[-1] if lines else "no output"}')
            if time.monotonic() > deadline:
                raise DemoError(f'dynamics_node did not come up within {args.timeout:g} s '
                                f'(log: {log_path})')
        t0 = time.time() + 2.0       # the controller's first stamp, once it is connected
        controller = subprocess.Popen(_controller_command(args, config, t0), env=env,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if recorder is not None:     # record the controller's topics from its first message
            _wait_for_recorder(recorder, node, min(5.0, t0 - time.time()))
        print(f'cdpr_demo: node up on ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]} (log {log_path}); '
              f'controller runs {args.duration:g} s')
        try:
            out, err = controller.communicate(timeout=args.duration + args.timeout + 5)
        except subprocess.TimeoutExpired:
            raise DemoError('the controller process did not finish') from None
        if controller.returncode != 0:
            lines = err.strip().splitlines()
            raise DemoError(f'controller failed: {lines[-1] if lines else controller.returncode}')
        sent = json.loads(out.strip().splitlines()[-1])
        n_sent = sent['wrenches']
        listener.wait(lambda: len(listener.predictions) >= n_sent, 3.0)
        try:
            start = time.perf_counter()
            frf = call_frequency_response(node, timeout_s=args.timeout, spin=False)
            frf_ms = (time.perf_counter() - start) * 1e3
            spring = call_frequency_response(node, ['frequency_hz', 'log10_amplitude_z'],
                                             {'method': 'spring'}, args.timeout, spin=False)
        except FrequencyResponseError as exc:
            raise DemoError(f'frequency_response: {exc}') from None
        count = len(listener.diagnostics)
        listener.wait(lambda: len(listener.diagnostics) > count + 1, 3.0)   # fresh statistics
        if not listener.predictions:
            raise DemoError('no predicted_displacement received')
        pred = np.array(listener.predictions)
        latency = (pred[:, 1] - pred[:, 0]) * 1e3
        wrench = listener.status('wrench input')['values']
        model = listener.status('model')['values']
        peak = int(np.argmax(frf['amplitude_z_m']))
        summary = (f'{model.get("method", settings.method)} model, {model.get("dofs", "?")} '
                   f'DOFs: node predicted {wrench.get("accepted", "?")} of {n_sent} '
                   f'wrenches, {len(pred)} received here; max |u_z| '
                   f'{np.abs(pred[:, 4]).max() * 1e3:.3f} mm; stamp -> prediction received '
                   f'p50 {np.percentile(latency, 50):.2f} ms, p99 '
                   f'{np.percentile(latency, 99):.2f} ms; node compute per wrench p50 '
                   f'{float(wrench.get("compute_ms_p50", "nan")):.3f} ms, p99 '
                   f'{float(wrench.get("compute_ms_p99", "nan")):.3f} ms; FRF call '
                   f'{frf_ms:.0f} ms, largest |A_z| {frf["amplitude_z_m"][peak] * 1e3:.3f} mm '
                   f'at {frf["frequency_hz"][peak]:.1f} Hz')
        output = Path(args.output)
        _plot(output, settings, listener, plan, frf, spring, t0, summary)
        print(f'cdpr_demo: {summary}')
        print(f'cdpr_demo: wrote {output.resolve()}')
        if recorder is not None:
            recorder.close()
            recorder = None
            print(f'cdpr_demo: recorded all traffic to {Path(args.record).resolve()}')
    finally:
        if controller is not None and controller.poll() is None:
            stop_process(controller, 5.0)
        if recorder is not None:
            recorder.close()
        status = stop_process(proc)
        spinning.clear()
        spinner.join(2.0)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        log.close()
        if reservation is not None:
            reservation.release()
    if status != 0:
        raise DemoError(f'dynamics_node exited with status {status} (log: {log_path})')
    return output


@interruptible('cdpr_demo')
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='cdpr_demo', description='Live vibration prediction demo: the node, a scripted '
        'controller and a frequency-response client; writes a PNG.')
    parser.add_argument('--config', help='ROS 2 parameter YAML (default: the paper robot)')
    parser.add_argument('--duration', type=float, default=8.0, help='controller run (s)')
    parser.add_argument('--output', default='out/cdpr_demo.png', help='PNG to write')
    parser.add_argument('--radius', type=float, default=0.05, help='circle radius (m)')
    parser.add_argument('--pose-rate', type=float, default=50.0, help='poses per second')
    parser.add_argument('--wrench-rate', type=float, default=1000.0, help='wrenches per second')
    parser.add_argument('--amplitude-n', type=float, default=1500.0,
                        help='harmonic force amplitude along z (N)')
    parser.add_argument('--excitation-hz', type=float, default=5.0,
                        help='harmonic force frequency (Hz)')
    parser.add_argument('--record', default=None,
                        help='MCAP file for all traffic (default: out/cdpr_demo_<time>.mcap '
                        'beside the PNG; an existing file is never overwritten)')
    parser.add_argument('--no-record', action='store_true', help='do not record the traffic')
    parser.add_argument('--timeout', type=float, default=30.0,
                        help='longest wait for the node or the service (s)')
    parser.add_argument('--controller-t0', type=float, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not (args.duration > 0 and args.pose_rate > 0 and args.wrench_rate > 0):
        print('cdpr_demo: error: --duration and the rates must be positive', file=sys.stderr)
        return 1
    if args.controller_t0 is not None:
        args.t0 = args.controller_t0
        args.config = args.config or str(default_config_path())
        return controller_main(args)
    if args.no_record:
        args.record = None
    elif args.record is None:
        args.record = str(Path(args.output).with_name(
            f'cdpr_demo_{time.strftime("%Y%m%d_%H%M%S")}.mcap'))
    try:
        run(args)
    except DemoError as exc:
        print(f'cdpr_demo: error: {exc}', file=sys.stderr)
        return 1
    except Exception as exc:  # anything unforeseen: still one line, not a traceback
        text = str(exc).strip().splitlines()
        print(f'cdpr_demo: error: {type(exc).__name__}: {text[0] if text else ""}',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
