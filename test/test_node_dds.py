"""dynamics_node under real DDS, as its own process (the installed console script).

Each node runs isolated: a ROS domain id of its own (locked, see cdpr_dynamics.ros.process),
localhost-only discovery, its own ROS_LOG_DIR. The test process publishes poses and wrenches,
receives predictions, tensions and diagnostics, calls the service and changes parameters; every
number is checked against the library called directly: a mirror LivePredictor fed the inputs the
node should accept (predictions and tensions must agree to rounding), a fresh equilibrium (the
tension QP), K^-1 f for a constant wrench, frf_arrays and cdpr_analyze's JSON for the service.

Traffic recording: every node's topics and service events are recorded to
test_output/test_node_dds/<harness>.mcap (or $CDPR_RECORD_DIR) with cdpr_dynamics.recording;
the folder is removed when every test of the module passed (kept with CDPR_KEEP_TEST_OUTPUT).
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped, WrenchStamped
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import JointState
from visualization_msgs.msg import MarkerArray

from cdpr_dynamics.analysis.pipeline import AnalysisError, build_system, equilibrium, frf_arrays
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.recording.reader import recording_info
from cdpr_dynamics.ros.node import nodes_named
from cdpr_dynamics.ros.parameters import NODE_NAME
from cdpr_dynamics.ros.process import (isolated_env, reserve_domain_id, rss_kib, start_node,
                                       stop_process)
from msg_adapters.diagnostics import ERROR, OK, WARN, read_statuses
from msg_adapters.displacement import read_displacement
from msg_adapters.frf_service import (ARRAYS, FrequencyResponseError, call_frequency_response,
                                      request_message, unpack_response)
from msg_adapters.joint_state import read_tensions
from msg_adapters.pose import pose_message
from msg_adapters.validation import s_to_stamp, stamp_to_ns
from msg_adapters.wrench import wrench_message
from conftest import cpu_seconds, installed, wait_until

pytestmark = pytest.mark.ros   # nodes, DDS, worker processes, signals

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / 'config' / 'paper_cdpr.yaml'
RIGID = REPO / 'test' / 'data' / 'rigid_cdpr.yaml'
SUSPENDED = REPO / 'config' / 'suspended_3cable.yaml'
TIMEOUT_S = 15.0
START_S = 1000.0          # simulated time of the first input
NAN, INF = float('nan'), float('inf')


RECORD_DIR = Path(os.environ.get('CDPR_RECORD_DIR') or
                  Path(__file__).resolve().parents[1] / 'test_output' / 'test_node_dds')
RECORDED_TOPICS = ['pose', 'wrench', 'predicted_displacement', 'cable_tensions', '/diagnostics',
                   'frequency_response/_service_event', '/parameter_events', 'cdpr_markers']


def _recorder(node, name: str):
    """A cdpr_dynamics.recording.recorder.Recorder of all the traffic of one node under test."""
    from cdpr_dynamics.recording import recorder
    RECORD_DIR.mkdir(parents=True, exist_ok=True)
    return recorder.Recorder(node, RECORD_DIR / f'{name}.mcap', RECORDED_TOPICS, force=True)


class Harness:
    """One dynamics_node process and a test node talking to it; a mirror of its state."""

    def __init__(self, params_file, log_dir: Path, name: str, parameters=None):
        self.name = name
        self.reservation = reserve_domain_id(1, 140)       # a domain per node under test
        self.env = env = isolated_env(self.reservation.domain_id, log_dir / name)
        self.context = context = rclpy.Context()
        rclpy.init(context=context, domain_id=self.reservation.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.settings = load_settings(params_file)
        self.frame = self.settings.robot.frame_id
        self.mirror = LivePredictor(self.settings)
        self.t_ns = int(START_S * 1e9)
        self.log_path = log_dir / f'{name}.log'
        self._log = open(self.log_path, 'w')
        self.proc = start_node(params_file, env, parameters, stdout=self._log,
                               stderr=subprocess.STDOUT)
        self.cond = threading.Condition()
        self.predictions: dict[int, np.ndarray] = {}
        self.rejected_stamps: list[int] = []
        self.prediction_count = 0
        self.tensions: list[JointState] = []
        self.diagnostics: list[dict] = []
        self.node = Node(f'test_{name}', context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(Vector3Stamped, 'predicted_displacement',
                                      self._on_prediction, 1000)
        self.poses: dict[int, tuple] = {}
        self.node.create_subscription(PoseStamped, 'predicted_pose', self._on_pose, 1000)
        self.node.create_subscription(JointState, 'cable_tensions', self._on_tensions, latched)
        self.markers: list[MarkerArray] = []
        self.node.create_subscription(MarkerArray, 'cdpr_markers', self._on_markers, latched)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)
        self.pose_pub = self.node.create_publisher(PoseStamped, 'pose', qos_profile_sensor_data)
        self.wrench_pub = self.node.create_publisher(WrenchStamped, 'wrench',
                                                     qos_profile_sensor_data)
        self.set_client = self.node.create_client(SetParameters, 'cdpr_dynamics/set_parameters')
        self.frf_client = self.node.create_client(GetParameters, 'frequency_response')
        self.recorder = _recorder(self.node, name)
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()
        ready = self.wait(lambda: (self.wrench_pub.get_subscription_count() > 0
                                   and self.pose_pub.get_subscription_count() > 0
                                   and self.tensions and self.diagnostics), TIMEOUT_S)
        if not ready or not self.frf_client.wait_for_service(timeout_sec=TIMEOUT_S):
            self.close()
            raise RuntimeError(f'dynamics_node did not come up: {self.log_tail()}')

    # -- plumbing ---------------------------------------------------------------------------

    def _spin(self):
        while rclpy.ok(context=self.executor.context) and not self._closed:
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # shutting down
                break

    _closed = False

    def _on_pose(self, msg):
        p, o = msg.pose.position, msg.pose.orientation
        with self.cond:
            self.poses[stamp_to_ns(msg.header.stamp)] = (np.array([p.x, p.y, p.z]),
                                                         np.array([o.x, o.y, o.z, o.w]))
            self.cond.notify_all()

    def _on_prediction(self, msg):
        with self.cond:
            self.predictions[stamp_to_ns(msg.header.stamp)] = read_displacement(msg)
            self.prediction_count += 1
            self.cond.notify_all()

    def _on_tensions(self, msg):
        with self.cond:
            self.tensions.append(msg)
            self.cond.notify_all()

    def _on_markers(self, msg):
        with self.cond:
            self.markers.append(msg)
            self.cond.notify_all()

    def _on_diagnostics(self, msg):
        with self.cond:
            self.diagnostics.append(read_statuses(msg))
            self.cond.notify_all()

    def wait(self, predicate, timeout_s=TIMEOUT_S) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout_s)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_tail(self) -> str:
        self._log.flush()
        return ' | '.join(self.log_path.read_text().strip().splitlines()[-5:])

    def close(self) -> int:
        status = stop_process(self.proc)
        if self.recorder is not None:
            self.recorder.close()
        self._closed = True
        self._spinner.join(5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.reservation.release()
        self._log.close()
        return status

    # -- inputs -----------------------------------------------------------------------------

    def next_stamp(self, dt_s: float):
        self.t_ns += int(round(dt_s * 1e9))
        return s_to_stamp(self.t_ns * 1e-9)

    def wrench(self, force, moment=(0.0, 0.0, 0.0), dt_s=0.005, frame=None, stamp=None):
        """Send a wrench the node must accept; return its prediction, checked on the mirror."""
        stamp = stamp or self.next_stamp(dt_s)
        key = stamp_to_ns(stamp)
        frame = self.frame if frame is None else frame
        self.wrench_pub.publish(wrench_message(force, moment, frame, stamp))
        assert self.wait(lambda: key in self.predictions), \
            f'no prediction for the wrench at {key * 1e-9:.3f} s; alive={self.alive()}'
        expected = self.mirror.advance(key, force, moment)
        np.testing.assert_allclose(self.predictions[key], expected, rtol=1e-9, atol=1e-15)
        return self.predictions[key]

    def bad_wrench(self, force, moment=(0.0, 0.0, 0.0), frame=None, stamp=None, words='',
                   level=WARN):
        """Send a wrench the node must reject; check the diagnostics carry the reason."""
        stamp = stamp or self.next_stamp(0.005)
        count = len(self.diagnostics)
        frame = self.frame if frame is None else frame
        self.wrench_pub.publish(wrench_message(force, moment, frame, stamp))
        self.expect_status('wrench input', level, words, since=count)
        self.rejected_stamps.append(stamp_to_ns(stamp))

    def pose(self, position, quaternion=(0.0, 0.0, 0.0, 1.0), dt_s=0.005):
        """Send a pose the node must accept; return (lengths, tensions) it publishes."""
        stamp = self.next_stamp(dt_s)
        self.pose_pub.publish(pose_message(position, quaternion, self.frame, stamp))
        assert self.wait(lambda: any(m.header.stamp == stamp for m in self.tensions)), \
            f'no cable_tensions for the pose {position}; alive={self.alive()}'
        self.mirror.update_pose(position, quaternion=np.asarray(quaternion) /
                                np.linalg.norm(quaternion))
        msg = next(m for m in reversed(self.tensions) if m.header.stamp == stamp)
        lengths, tensions = read_tensions(msg)
        np.testing.assert_allclose(tensions, self.mirror.eq.tensions.tension_n, rtol=1e-9)
        np.testing.assert_allclose(lengths, self.mirror.eq.geometry.cable_length_m, rtol=1e-12)
        return lengths, tensions

    def bad_pose(self, position, quaternion=(0.0, 0.0, 0.0, 1.0), frame=None, stamp=None,
                 words='', model=False):
        """Send a pose the node must reject; ``model``: the model rejects it, not the adapter
        (the mirror then goes through the same failure, e.g. a failed QP that drops its warm
        start)."""
        stamp = stamp or self.next_stamp(0.005)
        count = len(self.diagnostics)
        frame = self.frame if frame is None else frame
        self.pose_pub.publish(pose_message(position, quaternion, frame, stamp))
        self.expect_status('pose input', ERROR, words, since=count)
        assert not any(m.header.stamp == stamp for m in self.tensions)
        if model:
            with pytest.raises(AnalysisError, match=words):
                self.mirror.update_pose(position, quaternion=quaternion)

    def expect_status(self, title, level, words, since=0):
        """Wait for a diagnostics status ``cdpr_dynamics: title`` at ``level`` with ``words``."""
        name = f'cdpr_dynamics: {title}'

        def seen():
            return any(name in d and d[name]['level'] == level and words in d[name]['message']
                       for d in self.diagnostics[since:])
        assert self.wait(seen), (f'no {title} status at level {level} with {words!r}; last: '
                                 f'{self.diagnostics[-1].get(name)}; alive={self.alive()}')
        assert self.alive()

    def status(self, title, since=None) -> dict:
        """The next diagnostics status ``title`` published after now."""
        count = len(self.diagnostics) if since is None else since
        name = f'cdpr_dynamics: {title}'
        assert self.wait(lambda: any(name in d for d in self.diagnostics[count:]))
        return next(d[name] for d in self.diagnostics[count:] if name in d)

    def fresh_status(self, title) -> dict:
        """A status ``title`` built after everything the node published so far: the second
        one from now (the node builds a message under its lock and publishes it outside, so
        the first may predate an input whose answer has already arrived)."""
        self.status(title)
        return self.status(title)

    # -- service and parameters -------------------------------------------------------------

    def frf(self, names=None, overrides=None):
        return call_frequency_response(self.node, names, overrides, TIMEOUT_S, spin=False)

    def frf_raw(self, names):
        request = GetParameters.Request(names=list(names))
        future = self.frf_client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        assert done.wait(TIMEOUT_S)
        return unpack_response(request, future.result())

    def set_parameters(self, **values):
        """Set node parameters (``model__method='spring'`` for model.method); the results."""
        params = []
        for key, value in values.items():
            name = key.replace('__', '.')
            if isinstance(value, str):
                pv = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
            elif isinstance(value, bool):
                pv = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
            elif isinstance(value, int):
                pv = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
            elif isinstance(value, float):
                pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
            else:
                pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY,
                                    double_array_value=[float(v) for v in value])
            params.append(ParameterMsg(name=name, value=pv))
        assert self.set_client.wait_for_service(timeout_sec=TIMEOUT_S)
        future = self.set_client.call_async(SetParameters.Request(parameters=params))
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        assert done.wait(TIMEOUT_S)
        return future.result().results


# ------------------------------------------------------------------------------- fixtures

@pytest.fixture(scope='module')
def ros(tmp_path_factory, request):
    """This process localhost-only, logs in a temporary folder; each Harness (node under test
    and the test's rclpy context) then takes a ROS domain of its own. The recordings of the
    module are removed at its end if no test failed."""
    failed_before = request.session.testsfailed
    log_dir = tmp_path_factory.mktemp('ros_log')
    env = isolated_env(0, log_dir)
    patch = pytest.MonkeyPatch()
    for name in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_LOG_DIR', 'AMENT_PREFIX_PATH'):
        patch.setenv(name, env[name])
    for name in ('ROS_LOCALHOST_ONLY', 'ROS_STATIC_PEERS'):
        patch.delenv(name, raising=False)
    yield {'log_dir': log_dir}
    patch.undo()
    if request.session.testsfailed == failed_before and not os.environ.get(
            'CDPR_KEEP_TEST_OUTPUT') and not os.environ.get('CDPR_RECORD_DIR'):
        shutil.rmtree(RECORD_DIR, ignore_errors=True)


@pytest.fixture(scope='module')
def paper(ros):
    """dynamics_node on the paper's robot, shared by the tests of this module in order."""
    harness = Harness(PAPER, ros['log_dir'], 'paper')
    yield harness
    status = harness.close()
    assert status == 0, f'dynamics_node exited with {status}: {harness.log_tail()}'


def crossing_pairs(settings, position, rotation, clearance_m=1e-3) -> dict:
    """Cable pairs (i, j) whose straight cables pass within ``clearance_m`` of each other
    between their ends, with the gap (m): the least-squares closest points of the two lines,
    kept where both lie on the cables (independent of the node's segment-distance code)."""
    anchors = settings.robot.anchors_m
    ends = np.asarray(position, float) + settings.robot.attachments_m @ np.asarray(rotation).T
    pairs = {}
    for i in range(len(anchors)):
        for j in range(i + 1, len(anchors)):
            di, dj = anchors[i] - ends[i], anchors[j] - ends[j]
            (u, v), *_ = np.linalg.lstsq(np.column_stack([di, -dj]), ends[j] - ends[i],
                                         rcond=None)
            gap = float(np.linalg.norm(ends[i] + u * di - ends[j] - v * dj))
            if 0.0 <= u <= 1.0 and 0.0 <= v <= 1.0 and gap < clearance_m:
                pairs[(i, j)] = gap
    return pairs


def library_tensions(settings, position, quaternion=(0, 0, 0, 1)):
    rot = Rotation.from_quat(quaternion).as_matrix()
    return equilibrium(settings, np.asarray(position, float), rot)


# ---------------------------------------------------------------------------------- tests

def test_starts_at_the_initial_pose(paper):
    msg = paper.tensions[0]
    lengths, tensions = read_tensions(msg)
    eq = library_tensions(paper.settings, paper.settings.initial_position_m)
    np.testing.assert_allclose(tensions, eq.tensions.tension_n, rtol=1e-7, atol=1e-6)
    np.testing.assert_allclose(lengths, eq.geometry.length_m, rtol=1e-12)
    assert list(msg.name) == [f'cable_{i}' for i in range(8)]
    model = paper.status('model')
    assert model['values']['method'] == 'fem' and model['values']['dofs'] == '363'
    assert model['values']['qp_status'] == 'solved'
    assert 'heavy damping' in model['values']['warnings']     # the paper's C = 0.05 M + 0.05 K
    # Irvine's lambda^2 per cable: straight fem's ~1.7 % sag error is within the paper
    # file's model.tolerance of 2 %, so no sag warning (test_model_warnings_reach_the_log
    # has one at 1 %)
    sag = [float(v) for v in model['values']['sag_parameter'].split(';')]
    np.testing.assert_allclose(sag, [0.1989] * 4 + [0.0169] * 4, atol=1e-4)
    assert paper.settings.tolerance == 0.02 and 'sag:' not in model['values']['warnings']


def test_markers_at_start_and_on_rebuild(paper):
    """cdpr_markers is latched at start (the cables end at the library's anchors and
    attachments) and republished on a rebuild with the new pose, same namespaces and ids."""
    assert paper.wait(lambda: paper.markers), 'no cdpr_markers from the node at start'
    first = paper.markers[-1]
    keys = [(m.ns, m.id, m.type) for m in first.markers]
    n = paper.settings.robot.n_cables
    assert keys[:n] == [('cables', i, 4) for i in range(n)]
    assert all(m.frame_locked and m.header.frame_id == paper.frame for m in first.markers)
    end = [(np.array([m.points[0].x, m.points[0].y, m.points[0].z]),
            np.array([m.points[-1].x, m.points[-1].y, m.points[-1].z])) for m in first.markers[:n]]
    eq = library_tensions(paper.settings, paper.settings.initial_position_m)
    np.testing.assert_allclose([e[1] for e in end], paper.settings.robot.anchors_m, atol=1e-9)
    np.testing.assert_allclose([e[0] for e in end],
                               eq.geometry.position_m + eq.geometry.lever_m, atol=1e-9)
    count = len(paper.markers)
    target = paper.settings.initial_position_m + np.array([0.05, 0.0, 0.0])
    paper.pose(target.tolist())
    assert paper.wait(lambda: any(
        abs(m.markers[n + 1].pose.position.x - target[0]) < 1e-12 for m in paper.markers[count:]
    )), 'no cdpr_markers at the new pose after a rebuild'
    assert [(m.ns, m.id, m.type) for m in paper.markers[-1].markers] == keys
    # a wrench moves the arrow (within a diagnostics tick), to marker_scale x the prediction
    paper.wrench([0.0, 0.0, 500.0])
    u = paper.wrench([0.0, 0.0, 500.0], dt_s=0.05)      # zero-order hold: the first one held

    def arrow_at(msg, expected):
        tail, tip = msg.markers[-1].points
        return np.allclose([tip.x - tail.x, tip.y - tail.y, tip.z - tail.z], expected,
                           rtol=1e-9, atol=1e-15)
    assert np.linalg.norm(u) > 1e-6
    assert paper.wait(lambda: arrow_at(paper.markers[-1], 100.0 * u)), 'arrow not updated'
    paper.pose(paper.settings.initial_position_m.tolist())


def test_all_traffic_is_recorded(paper):
    """Inputs, outputs, diagnostics and service events of the node land in its MCAP file."""
    paper.pose(paper.settings.initial_position_m.tolist())
    paper.wrench([0.0, 0.0, 10.0])
    paper.frf(['natural_frequencies_hz'])

    def recorded():
        paper.recorder.flush()
        info = recording_info(RECORD_DIR / 'paper.mcap')
        return {name.lstrip('/'): t.message_count for name, t in info.topics.items()}
    wanted = [t.lstrip('/') for t in RECORDED_TOPICS[:6]]
    assert paper.wait(lambda: all(recorded().get(t, 0) > 0 for t in wanted)), recorded()


def test_tensions_follow_the_pose(paper):
    for position in ([0.1, 0.05, 1.3], [-0.3, 0.2, 1.0], [0.0, 0.0, 1.25]):
        lengths, tensions = paper.pose(position)
        eq = library_tensions(paper.settings, position)      # a fresh QP, no warm start
        np.testing.assert_allclose(tensions, eq.tensions.tension_n, rtol=1e-6, atol=1e-4)
        np.testing.assert_allclose(lengths, eq.geometry.length_m, rtol=1e-12)
    rebuilds = int(paper.fresh_status('model')['values']['rebuilds'])
    paper.pose([0.0, 0.0, 1.25 + 5e-5])                      # within node.pose_tolerance_m
    paper.pose([0.0, 0.0, 1.25])
    assert int(paper.fresh_status('model')['values']['rebuilds']) == rebuilds   # none rebuilt


def test_constant_wrench_converges_to_static_deflection(paper):
    position = [0.1, -0.05, 1.2]
    paper.pose(position)
    force = np.array([50.0, -30.0, 800.0])
    for _ in range(200):                                      # 1 s, a wrench every 5 ms
        u = paper.wrench(force)
    eq = library_tensions(paper.settings, position)
    stiffness = build_system(paper.settings, eq).static_stiffness()
    np.testing.assert_allclose(u, np.linalg.solve(stiffness, force), rtol=1e-4, atol=1e-12)
    stats = paper.status('wrench input')['values']
    assert float(stats['compute_ms_p50']) > 0.0    # reported (its size is cdpr_bench's business)
    # the node's side of the match: the test's publishers, one per input
    assert stats['publishers'] == '1' == paper.status('pose input')['values']['publishers']


def test_frequency_response_matches_the_library(paper):
    paper.pose([0.2, 0.1, 1.3])
    arrays = paper.frf()
    expected = frf_arrays(paper.settings, build_system(paper.settings, paper.mirror.eq))
    arrays_of_model = [n for n in ARRAYS if not isinstance(expected[n], str)]
    assert list(arrays) == arrays_of_model          # a point mass: no rotation arrays
    for name in arrays_of_model:
        np.testing.assert_allclose(arrays[name], expected[name], rtol=1e-9, err_msg=name)
    _, reasons = paper.frf_raw(['rotation_x_rad', 'mode_platform_fraction'])
    assert reasons == {'rotation_x_rad': expected['rotation_x_rad']}
    platform = expected['platform_natural_frequencies_hz']
    # refreshed after the rebuild (by the worker, or by this call's answer)
    assert paper.wait(lambda: any(
        abs(float(d['cdpr_dynamics: model']['values']['lowest_platform_mode_hz']) - platform[0])
        < 1e-4 * platform[0] for d in paper.diagnostics[-3:] if 'cdpr_dynamics: model' in d))
    calls = paper.status('frequency_response')['values']
    again = paper.frf(['amplitude_z_m'])                     # same state: from the cache
    np.testing.assert_array_equal(again['amplitude_z_m'], arrays['amplitude_z_m'])
    after = paper.status('frequency_response')['values']
    assert int(after['cache_hits']) == int(calls['cache_hits']) + 1


def test_frequency_response_equals_cdpr_analyze(paper, tmp_path):
    analyze = installed('cdpr_analyze')
    paper.pose(paper.settings.initial_position_m.tolist())   # cdpr_analyze's pose
    arrays = paper.frf()
    out = tmp_path / 'analyze.json'
    run = subprocess.run([str(analyze), '--config', str(PAPER), '--json', str(out),
                          '--duration', '0.01'], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    doc = json.loads(out.read_text())
    assert doc['method'] == 'fem'
    frf = doc['frf']
    amplitude, phase = np.array(frf['amplitude_m']), np.array(frf['phase_rad'])
    np.testing.assert_allclose(arrays['frequency_hz'], frf['frequency_hz'], rtol=1e-12)
    for axis, name in enumerate('xyz'):
        np.testing.assert_allclose(arrays[f'amplitude_{name}_m'], amplitude[:, axis],
                                   rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(arrays['phase_z_rad'], phase[:, 2], atol=1e-6)
    n = arrays['natural_frequencies_hz'].size
    np.testing.assert_allclose(arrays['natural_frequencies_hz'],
                               doc['natural_frequencies_hz'][:n], rtol=1e-6)
    np.testing.assert_allclose(doc['tensions_n'], read_tensions(paper.tensions[-1])[1],
                               rtol=1e-6, atol=1e-4)


def test_frequency_response_overrides_and_reasons(paper):
    overrides = {'method': 'spring', 'n_points': 50, 'f_max_hz': 20.0, 'force_x_n': 100.0}
    arrays = paper.frf(['frequency_hz', 'amplitude_x_m', 'amplitude_z_m'], overrides)
    settings = paper.settings.replace(method='spring', n_points=50, f_max_hz=20.0,
                                      frf_force_n=np.array([100.0, 0.0, 1500.0]))
    expected = frf_arrays(settings, build_system(settings, paper.mirror.eq))
    assert arrays['frequency_hz'].size == 50
    for name in arrays:
        np.testing.assert_allclose(arrays[name], expected[name], rtol=1e-9, err_msg=name)

    got, reasons = paper.frf_raw(['frequency_hz', 'no_such_array', 'n_points=20'])
    assert got['frequency_hz'].size == 20
    assert reasons['no_such_array'].startswith("unknown array 'no_such_array'")
    for names, words in ((['amplitude_z_m', 'colour=red'], "unknown override 'colour'"),
                         (['amplitude_z_m', 'n_points=0'], 'outside [1'),
                         (['amplitude_z_m', 'method=bogus'], 'must be one of'),
                         (['amplitude_z_m', 'f_min_hz=30', 'f_max_hz=10'], 'exceeds'),
                         (['amplitude_z_m', 'n_points=500000'], 'node.frf_max_points'),
                         (['amplitude_z_m', 'method=dsm', 'n_points=3'], '')):
        got, reasons = paper.frf_raw(names)
        if words:
            assert words in reasons['amplitude_z_m'], reasons
        else:
            assert 'amplitude_z_m' in got or 'amplitude_z_m' in reasons
    with pytest.raises(FrequencyResponseError, match="unknown array 'nope'"):
        paper.frf(['nope'])
    with pytest.raises(FrequencyResponseError,
                       match=r'no_frf not available after 0.5 s: no server matched'):
        call_frequency_response(paper.node, timeout_s=0.5, service='no_frf', spin=False)
    assert paper.alive()
    paper.frf(['amplitude_z_m'])
    paper.expect_status('frequency_response', OK, 'calls')


def test_wrenches_are_served_during_a_long_frf_call(paper):
    """A large FRF call (fem_sag 64) runs in the node's worker process: wrenches sent while it
    is served are all predicted, and agree with the mirror; the answer is the library's."""
    overrides = {'method': 'fem_sag', 'elements_per_cable': 64, 'n_points': 4000}
    request = request_message(['amplitude_z_m'], overrides)
    answered = threading.Event()
    future = paper.frf_client.call_async(request)
    future.add_done_callback(lambda _: answered.set())
    during = []
    while not answered.is_set() and len(during) < 2000:
        during.append(paper.wrench([0.0, 0.0, 50.0 * (len(during) % 7)], dt_s=0.01))
    assert answered.wait(300.0), 'no answer to the large call'
    # served while the call was pending: each paper.wrench() waited for its own prediction
    assert len(during) >= 5, f'only {len(during)} wrenches were answered during the call'
    arrays, reasons = unpack_response(request, future.result())
    assert not reasons, reasons
    settings = paper.settings.replace(method='fem_sag', elements_per_cable=64, n_points=4000)
    expected = frf_arrays(settings, build_system(settings, paper.mirror.eq))
    np.testing.assert_allclose(arrays['amplitude_z_m'], expected['amplitude_z_m'], rtol=1e-8)
    paper.expect_status('frequency_response', OK, 'calls')


def test_frequency_response_answers_in_request_order(paper):
    """Calls answered at once (a refusal, a cached result) wait behind a call being computed:
    one client gets its answers in the order it asked."""
    paper.frf(['amplitude_z_m'])                           # cached from here on
    requests = [request_message(['amplitude_z_m'], {'n_points': 3000, 'f_max_hz': 33.0}),
                request_message(['amplitude_z_m'], {'n_points': 0}),
                request_message(['amplitude_z_m']),
                request_message(['frequency_hz'], {'n_points': 7})]
    order, lock = [], threading.Lock()
    futures = []
    for index, request in enumerate(requests):
        future = paper.frf_client.call_async(request)
        future.add_done_callback(lambda _, i=index: (lock.acquire(), order.append(i),
                                                     lock.release()))
        futures.append(future)
    wait_until(lambda: len(order) == len(requests), 120.0, 'four answers')
    assert order == [0, 1, 2, 3]
    sizes = [unpack_response(r, f.result()) for r, f in zip(requests, futures)]
    assert sizes[0][0]['amplitude_z_m'].size == 3000
    assert 'outside [1' in sizes[1][1]['amplitude_z_m']
    assert sizes[2][0]['amplitude_z_m'].size == paper.settings.n_points
    assert sizes[3][0]['frequency_hz'].size == 7


@pytest.mark.parametrize('force, moment, frame, old, words', [
    ([NAN, 0.0, 0.0], [0.0, 0.0, 0.0], None, False, 'wrench is not finite'),
    ([0.0, 0.0, 0.0], [0.0, INF, 0.0], None, False, 'wrench is not finite'),
    ([0.0, 0.0, 100.0], [0.0, 0.0, 0.0], 'tool0', False, "in frame 'tool0'"),
    ([0.0, 0.0, 100.0], [0.0, 0.0, 0.0], '', False, 'empty frame_id'),
    ([0.0, 0.0, 100.0], [0.0, 0.0, 0.0], None, True, 'out of order'),
    ([0.0, 0.0, -5000.0], [0.0, 0.0, 0.0], None, False, 'outside the feasible set'),
], ids=['nan-force', 'inf-moment', 'other-frame', 'empty-frame', 'out-of-order',
        'infeasible'])
def test_bad_wrench_is_rejected_and_the_node_carries_on(paper, force, moment, frame, old,
                                                        words):
    paper.pose([0.05, 0.0, 1.25])
    paper.wrench([0.0, 0.0, 300.0])
    stamp = s_to_stamp((paper.t_ns - 2_000_000) * 1e-9) if old else None
    paper.bad_wrench(force, moment, frame, stamp, words)
    for _ in range(5):                                       # still predicting, correctly
        paper.wrench([0.0, 20.0, 300.0])
    assert paper.rejected_stamps[-1] not in paper.predictions


@pytest.mark.parametrize('position, quaternion, frame, old, words', [
    ([NAN, 0.0, 1.25], (0, 0, 0, 1), None, False, 'position is not finite'),
    ([0.0, 0.0, 1.25], (0, 0, INF, 1), None, False, 'orientation is not finite'),
    ([0.0, 0.0, 1.25], (0, 0, 0.5, 1.2), None, False, 'not a unit quaternion'),
    ([0.0, 0.0, 1.25], (0, 0, 0, 1), 'map', False, "in frame 'map'"),
    ([0.0, 0.0, 1.25], (0, 0, 0, 1), None, True, 'out of order'),
    ([1.25, 1.25, 2.5], (0, 0, 0, 1), None, False, 'zero length'),
    ([0.0, 0.0, 2.4], (0, 0, 0, 1), None, False, 'infeasible tension distribution'),
], ids=['nan-position', 'inf-quaternion', 'non-unit-quaternion', 'other-frame',
        'out-of-order', 'on-an-anchor', 'infeasible-tensions'])
def test_bad_pose_is_rejected_and_the_node_carries_on(paper, position, quaternion, frame,
                                                      old, words):
    paper.pose([0.1, 0.1, 1.2])
    stamp = s_to_stamp((paper.t_ns - 2_000_000) * 1e-9) if old else None
    model = words in ('zero length', 'infeasible tension distribution')
    paper.bad_pose(position, quaternion, frame, stamp, words, model)
    paper.wrench([0.0, 0.0, 500.0])                          # still at the last good pose
    paper.pose([0.0, 0.1, 1.3])                              # and a good pose is taken
    paper.wrench([0.0, 0.0, 500.0])
    paper.expect_status('pose input', OK, 'accepted')


def test_stamps_never_latch_the_node(paper):
    """Issue 14, findings 1-2, through DDS and the node's own clock: a wrench or pose stamped in
    2038 is rejected and later inputs are taken; stamp 0 is rejected with the reason; a clock
    jump back of 10 minutes restarts the stream with a warning, the state carried on."""
    from builtin_interfaces.msg import Time
    paper.pose([0.0, 0.05, 1.25])
    paper.wrench([0.0, 0.0, 300.0])
    paper.bad_wrench([0.0, 0.0, 300.0], stamp=s_to_stamp(2_145_000_000.0),
                     words='ahead of the node clock')
    paper.wrench([0.0, 0.0, 300.0])                          # taken: no latch
    paper.bad_wrench([0.0, 0.0, 300.0], stamp=Time(), words='unstamped (stamp 0)')
    paper.bad_pose([0.05, 0.05, 1.25], stamp=s_to_stamp(2_145_000_000.0),
                   words='ahead of the node clock')
    paper.pose([0.0, 0.06, 1.25])                            # the model is not frozen
    paper.t_ns -= 600 * 1_000_000_000                         # the controller restarted
    paper.mirror.rebase_time()
    paper.pose([0.0, 0.05, 1.25])                            # the pose stream restarts too
    count = len(paper.diagnostics)
    paper.wrench([0.0, 0.0, 300.0])                          # the mirror restarts alike
    paper.expect_status('wrench input', WARN, 'wrench clock jumped back 599.9', since=count)
    for _ in range(5):
        paper.wrench([0.0, 0.0, 300.0])


def test_runtime_parameter_changes(paper):
    paper.pose([0.0, 0.0, 1.25])
    results = paper.set_parameters(model__method='spring')
    assert results[0].successful, results[0].reason
    paper.mirror.set_settings(paper.settings.replace(method='spring'))
    model = paper.fresh_status('model')['values']
    assert model['method'] == 'spring' and model['dofs'] == '3'
    for _ in range(20):
        paper.wrench([0.0, 0.0, 1000.0])                     # the spring model predicts now
    spring = paper.settings.replace(method='spring')
    np.testing.assert_allclose(paper.frf(['amplitude_z_m'])['amplitude_z_m'],
                               frf_arrays(spring, build_system(spring, paper.mirror.eq))
                               ['amplitude_z_m'], rtol=1e-9)

    rejected = [
        (dict(model__method='bogus'), 'must be one of'),
        (dict(model__elements_per_cable=0), ''),             # outside the descriptor's range
        (dict(frf__f_min_hz=50.0), 'exceeds frf.f_max_hz'),
        (dict(model__method='dsm'), 'no finite matrices'),   # a model invalid for the state
        (dict(tension__min_n=0.0), 'no valid model for this pose'),
        (dict(robot__anchors=[0.0] * 24), 'read-only'),
        (dict(cable__area_m2='thick'), ''),                  # wrong type
    ]
    for change, words in rejected:
        result = paper.set_parameters(**change)[0]
        assert not result.successful, change
        assert words in result.reason, (change, result.reason)
    assert paper.status('model')['values']['method'] == 'spring'
    paper.wrench([0.0, 0.0, 1000.0])                         # unchanged by the rejections

    assert paper.set_parameters(use_sim_time=False)[0].successful      # not ours: left alone
    assert paper.set_parameters(node__pose_tolerance_m=2e-4)[0].successful
    results = paper.set_parameters(model__method='fem', damping__stiffness_factor=0.001)
    assert all(r.successful for r in results)
    paper.mirror.set_settings(paper.settings.replace(damping_stiffness_factor=0.001))
    for _ in range(20):
        paper.wrench([0.0, 0.0, 1000.0])
    results = paper.set_parameters(damping__stiffness_factor=0.05, node__pose_tolerance_m=1e-4)
    assert all(r.successful for r in results)
    paper.mirror.set_settings(paper.settings)
    assert paper.fresh_status('model')['values']['method'] == 'fem'


def test_model_warnings_reach_the_log(ros):
    """The model's warnings reach the log a user watches, not only /diagnostics: all at start,
    not again while their kinds stay the same (a rebuild at a nearby pose), and again when the
    set changes (another model)."""
    node = Harness(PAPER, ros['log_dir'], 'warnlog', {'model.method': 'spring',
                                                      'model.tolerance': 0.01})
    try:
        def log() -> str:
            node._log.flush()
            return node.log_path.read_text()
        wait_until(lambda: 'model: sag:' in log(), TIMEOUT_S, 'the sag warning in the log')
        moved = node.settings.initial_position_m + np.array([0.03, 0.0, 0.0])
        rebuilds = int(node.fresh_status('model')['values']['rebuilds'])
        node.pose(moved.tolist())             # a rebuild whose warnings are of the same kinds
        status = node.fresh_status('model')
        assert int(status['values']['rebuilds']) == rebuilds + 1, status
        assert 'sag: ' in status['values']['warnings'], status
        assert log().count('model: sag:') == 1, log()
        before = len(log())
        assert node.set_parameters(model__method='catenary_exact')[0].successful
        status = node.fresh_status('model')
        assert status['message'].startswith('catenary_exact'), status
        if ': ' in status['message']:         # another set of warnings: logged, the first one
            first = status['message'].split(': ', 1)[1][:60]
            wait_until(lambda: f'model: {first}' in log()[before:], TIMEOUT_S, first)
        else:
            wait_until(lambda: 'model: no warnings any more (' in log()[before:], TIMEOUT_S,
                       'the warnings cleared in the log')
        assert log().count('model: sag:') == 1, log()
    finally:
        assert node.close() == 0


def test_rigid_platform_inputs(ros):
    rigid = Harness(RIGID, ros['log_dir'], 'rigid')
    try:
        assert rigid.status('model')['values']['dofs'] == '174'
        turned = Rotation.from_euler('z', 45, degrees=True)
        crossing = crossing_pairs(rigid.settings, [0.0, 0.0, 1.25], turned.as_matrix())
        assert set(crossing) == {(0, 2), (0, 3)}   # both cross within 1e-15 m of each other
        since = len(rigid.diagnostics)
        rigid.bad_pose([0.0, 0.0, 1.25], turned.as_quat(), words='cross', model=True)
        # which of the tied pairs is named depends on rounding: one of them, with its own gap
        message = next(d['cdpr_dynamics: pose input']['message'] for d in rigid.diagnostics[since:]
                       if 'cross' in d.get('cdpr_dynamics: pose input', {}).get('message', ''))
        named = re.search(r'cables (\d+) and (\d+) cross: ([\d.]+) mm apart', message)
        assert named, message
        pair = (int(named[1]), int(named[2]))
        assert pair in crossing, message
        assert float(named[3]) == round(crossing[pair] * 1e3, 1), message
        small = Rotation.from_euler('xyz', [1.0, -0.5, 2.0], degrees=True).as_quat()
        rigid.pose([0.05, -0.02, 1.3], small)
        eq = library_tensions(rigid.settings, [0.05, -0.02, 1.3], small)
        np.testing.assert_allclose(read_tensions(rigid.tensions[-1])[1], eq.tensions.tension_n,
                                   rtol=1e-6, atol=1e-4)
        for _ in range(40):
            rigid.wrench([10.0, 0.0, 100.0], [1.0, -2.0, 0.5])
        want = rigid.mirror.prediction()          # the predicted pose, beside the displacement
        key = rigid.t_ns
        assert rigid.wait(lambda: key in rigid.poses), 'no predicted_pose'
        position, quaternion = rigid.poses[key]
        np.testing.assert_allclose(position, want.position_m, rtol=1e-9, atol=1e-12)
        assert (Rotation.from_quat(quaternion) * Rotation.from_quat(want.quaternion).inv()
                ).magnitude() < 1e-9
        assert Rotation.from_quat(quaternion).magnitude() > 1e-7       # it turned
        arrays = rigid.frf(['rotation_y_rad', 'amplitude_z_m'], {'moment_y_nm': 5.0})
        assert arrays['rotation_y_rad'].max() > 0
        rigid.bad_wrench([0.0, 0.0, 0.0], [0.0, 0.0, 500.0], words='outside the feasible set')
        rigid.wrench([10.0, 0.0, 100.0], [1.0, -2.0, 0.5])
    finally:
        assert rigid.close() == 0


def test_an_underactuated_robot_hanging_below_its_pulleys(ros):
    """Three cables over pulleys hold a 6-DOF platform whose centre of mass hangs below it: a
    pose that is not an equilibrium is taken, warned with its distance and analysed at the
    equilibrium with its cable lengths (tensions, lengths, predictions and the service as the
    library gives them there)."""
    hang = Harness(SUSPENDED, ros['log_dir'], 'suspended')
    try:
        since = len(hang.diagnostics)
        hang.pose([0.05, -0.03, 1.0])                     # tensions and lengths as the mirror's
        held = hang.mirror.eq.balance
        assert held.far and held.distance_m > 1e-3
        hang.expect_status('model', WARN, 'not an equilibrium', since=since)
        status = hang.fresh_status('model')
        assert any(f'{held.distance_m:.4g} m' in text for text in status['values'].values()) \
            or f'{held.distance_m:.4g} m' in status['message'], status
        for _ in range(20):
            hang.wrench([2.0, 0.0, 0.0])                  # each as the mirror predicts it
        arrays = hang.frf(['amplitude_x_m', 'platform_natural_frequencies_hz'])
        expected = frf_arrays(hang.settings, build_system(hang.settings, hang.mirror.eq))
        for name, values in arrays.items():
            np.testing.assert_allclose(values, expected[name], rtol=1e-9, err_msg=name)
        # a pendulum's swing: the lowest mode is slow (gravity holds it, not the cables)
        assert expected['platform_natural_frequencies_hz'][0] < 2.0
    finally:
        assert hang.close() == 0


@pytest.mark.parametrize('method,parameters,words', [
    ('bogus', None, ('model.method', 'bogus')),
    ('fem', {'node.service_introspection': 'bogus'}, ('node.service_introspection', 'bogus')),
])
def test_bad_configuration_exits_with_one_line(ros, tmp_path, method, parameters, words):
    bad = tmp_path / 'bad.yaml'
    bad.write_text(PAPER.read_text().replace('method: fem', f'method: {method}'))
    with reserve_domain_id(1, 140) as domain:
        env = isolated_env(domain.domain_id, tmp_path / 'log')
        proc = start_node(bad, env, parameters, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 1
    lines = err.decode().strip().splitlines()
    assert len(lines) == 1 and all(w in lines[0] for w in words), lines


def test_two_nodes_of_one_name_both_warn_and_a_refusing_newcomer_ends(ros, tmp_path):
    """node.unique_name: a newcomer with ``refuse`` ends with one line and status 1; a newcomer
    with ``warn`` runs on, and both it and the node already running warn in the log, the
    first also in /diagnostics; the warning clears when the namesake leaves."""
    first = Harness(PAPER, ros['log_dir'], 'namesake', {'model.method': 'spring'})
    warning = 'another node named /cdpr_dynamics is running'

    def log(path) -> str:
        return path.read_text()

    def start(tag, parameters=None):
        with open(tmp_path / f'{tag}.log', 'w') as out:
            proc = start_node(PAPER, first.env, {'model.method': 'spring', **(parameters or {})},
                              stdout=out, stderr=subprocess.STDOUT)
        return proc, tmp_path / f'{tag}.log'

    def first_log() -> str:
        first._log.flush()
        return log(first.log_path)

    def balanced() -> bool:      # the first node's namesake warnings all cleared
        text = first_log()
        return text.count(warning) == text.count('no other node named')

    second = None
    try:
        refusing, refusing_log = start('refusing', {'node.unique_name': 'refuse'})
        try:
            assert refusing.wait(90) == 1
        finally:
            stop_process(refusing)
        lines = log(refusing_log).strip().splitlines()
        assert lines[-1] == (f'dynamics_node: error: {warning}: each input would be predicted '
                             'twice and set_parameters reach either (node.unique_name: refuse)')
        assert 'Traceback' not in log(refusing_log)
        wait_until(balanced, 30, 'the first node to see the refused one gone')
        since_diagnostics = len(first.diagnostics)
        since_log = len(first_log())
        second, second_log = start('second')
        wait_until(lambda: warning in log(second_log) or second.poll() is not None, 90,
                   'the newcomer to warn')
        wait_until(lambda: warning in first_log()[since_log:], 30, 'the first node to warn')
        assert second.poll() is None and first.alive()
        assert first.wait(lambda: any(
            warning in str(d.get('cdpr_dynamics: model', {}).get('values', {}).get('warnings'))
            for d in first.diagnostics[since_diagnostics:]))
        assert stop_process(second) == 0
        wait_until(lambda: 'no other node named' in first_log()[since_log:], 30,
                   'the first node to clear its warning')
    finally:
        if second is not None:
            stop_process(second)
        assert first.close() == 0


def test_a_namesake_is_counted_by_its_publishers_not_by_the_node_list(ros):
    """nodes_named: a node of the name counts once it publishes on /rosout or /parameter_events
    (one without /rosout too); another namespace does not count; and an entry in the node list
    without publishers (a node that has left, kept there by DDS) does not count."""
    with reserve_domain_id(1, 140) as reservation:
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=reservation.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        try:
            watcher = Node('watcher', context=context)
            nodes = [Node(NODE_NAME, context=context),
                     Node(NODE_NAME, namespace='/elsewhere', context=context)]
            wait_until(lambda: nodes_named(watcher, NODE_NAME, '/elsewhere') == 1, 10,
                       'the watcher to see its nodes')
            assert nodes_named(watcher, NODE_NAME, '/') == 1
            nodes.append(Node(NODE_NAME, context=context, enable_rosout=False))
            wait_until(lambda: nodes_named(watcher, NODE_NAME, '/') == 2, 10,
                       'the namesake without /rosout to count')
        finally:
            rclpy.try_shutdown(context=context)

    alive = SimpleNamespace(node_name=NODE_NAME, node_namespace='/')
    ghost = SimpleNamespace(get_node_names_and_namespaces=lambda: [(NODE_NAME, '/')] * 2,
                            get_publishers_info_by_topic=lambda topic: [alive])
    assert nodes_named(ghost, NODE_NAME, '/') == 1


def test_flood_of_wrenches(ros):
    """10 s of wrenches at 5 kHz from another process: alive, the newest wrenches win, bounded
    memory, still answering after; the rate is reported (and measured by cdpr_bench --dds)."""
    flood = Harness(PAPER, ros['log_dir'], 'flood')
    try:
        flood.wrench([0.0, 0.0, 100.0])
        before = flood.status('wrench input')
        rss = [rss_kib(flood.proc.pid)]
        count0 = flood.prediction_count
        sender = subprocess.Popen(
            [sys.executable, '-m', 'cdpr_dynamics.cli.bench_node', 'flood', '--rate', '5000',
             '--duration', '10', '--start-s', str(flood.t_ns * 1e-9 + 1.0)],
            env=flood.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        while sender.poll() is None:
            time.sleep(0.5)           # sampling period of the memory, not a synchronisation
            rss.append(rss_kib(flood.proc.pid))
        out, err = sender.communicate(timeout=30)
        assert sender.returncode == 0, err
        sent = json.loads(out.strip().splitlines()[-1])
        assert flood.alive(), flood.log_tail()
        flood.t_ns = int((sent['last_stamp_s'] + 1.5) * 1e9)
        after = flood.status('wrench input')
        accepted = int(after['values']['accepted']) - int(before['values']['accepted'])
        received = flood.prediction_count - count0
        growth_mib = (max(rss) - rss[0]) / 1024
        values = after['values']
        report = (f"flood: sent {sent['sent']} wrenches at {sent['rate_hz']:.0f} Hz for "
                  f"{sent['duration_s']:.1f} s; node processed {accepted} "
                  f"({accepted / sent['duration_s']:.0f}/s, "
                  f"{100 * accepted / sent['sent']:.1f}%), test received {received} "
                  f"predictions; node RSS {rss[0] / 1024:.1f} -> {max(rss) / 1024:.1f} MiB; "
                  f"compute p50/p99 {values.get('compute_ms_p50')}/"
                  f"{values.get('compute_ms_p99')} ms")
        print(report)
        (ros['log_dir'] / 'flood_report.txt').write_text(report + '\n')
        assert sent['sent'] >= 0.8 * 5000 * 10
        # behaviour, not speed (rates are cdpr_bench --dds's): wrenches were predicted, and the
        # newest win: the best-effort queue keeps the newest node.wrench_queue_depth (1000), so a
        # wrench sent after the flood is predicted once that short queue (and what the transport
        # still buffers) has drained, not after the ~40 000 older ones a first-in first-out
        # queue would hold. The node drains at the rate the host gives it (110-1 500/s beside
        # the stress lane's burners), and this process takes only some of its predictions (the
        # newest of a reliable queue of 1000: about 2 000 of 48 000 in a flood the node kept up
        # with), so what the node drained is its own count of accepted wrenches, and the wait
        # fails once neither that count nor the predictions received have moved for 20 s. Sent
        # again with a new stamp every 0.5 s: on a starved host the transport itself may drop a
        # message (the flood's own last stamps are no test for the same reason)
        assert accepted > 0, report
        fresh = []

        def accepted_now() -> int:    # the node's count in its newest wrench input status
            title = 'cdpr_dynamics: wrench input'
            return next(int(d[title]['values']['accepted']) for d in reversed(flood.diagnostics)
                        if title in d)

        def marks():   # now, what moves when the node works, the node's CPU, this process's
            return (time.monotonic(), (accepted_now(), flood.prediction_count),
                    cpu_seconds(flood.proc.pid), time.process_time(), len(flood.diagnostics))

        def stalled(since) -> str:   # what happened while nothing moved
            now = marks()
            return (f'meanwhile the node used {now[2] - since[2]:.1f} s of CPU, this process '
                    f'{now[3] - since[3]:.1f} s, and {now[4] - since[4]} of its diagnostics came; '
                    f'accepted, received: {now[1]}; wrenches of a new participant accepted: '
                    f'{newcomer_accepted()}')

        def newcomer_accepted() -> bool:   # does the node take wrenches from anyone?
            context = rclpy.Context()
            rclpy.init(context=context, domain_id=flood.reservation.domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
            try:
                publisher = Node('newcomer', context=context).create_publisher(
                    WrenchStamped, 'wrench', qos_profile_sensor_data)
                count = accepted_now()
                deadline = time.monotonic() + 10.0
                while accepted_now() == count and time.monotonic() < deadline:
                    publisher.publish(wrench_message([0.0, 0.0, 100.0], frame_id=flood.frame,
                                                     stamp=flood.next_stamp(0.005)))
                    time.sleep(0.5)        # a resend period, as answered()'s
                return accepted_now() != count
            finally:
                rclpy.try_shutdown(context=context)

        def answered():
            fresh.append(flood.next_stamp(0.005))
            flood.wrench_pub.publish(wrench_message([0.0, 0.0, 100.0], frame_id=flood.frame,
                                                    stamp=fresh[-1]))
            return flood.wait(lambda: any(stamp_to_ns(s) in flood.predictions for s in fresh),
                              0.5)

        since = start = marks()
        while not answered():
            now = marks()
            if now[1] != since[1]:
                since = now
            assert time.monotonic() - since[0] < 20.0, \
                f'the node did nothing for 20 s after the flood ({stalled(since)}); {report}'
            assert time.monotonic() - start[0] < 120.0, \
                f'no fresh wrench predicted in 120 s ({stalled(start)}); {report}'
        drained = (int(flood.fresh_status('wrench input')['values']['accepted'])
                   - int(after['values']['accepted']) - len(fresh))
        assert drained < 10_000, f'{drained} older wrenches predicted first; {report}'
        assert growth_mib < 50.0, report
        # still answers; the state carries on from the flood (the mirror never saw it), so
        # this prediction is checked for being there, not against the mirror
        stamp = next(s for s in fresh if stamp_to_ns(s) in flood.predictions)
        assert np.all(np.isfinite(flood.predictions[stamp_to_ns(stamp)]))
        assert flood.frf(['amplitude_z_m'])['amplitude_z_m'].size == 391
    finally:
        assert flood.close() == 0


def test_demo_writes_its_figure(tmp_path):
    """cdpr_demo end to end (2 s of controller): node, controller, service, PNG; exit 0."""
    demo = installed('cdpr_demo')
    png = tmp_path / 'demo.png'
    with reserve_domain_id(1, 140) as domain:
        env = isolated_env(domain.domain_id, tmp_path / 'log')
        run = subprocess.run([str(demo), '--duration', '2', '--output', str(png)], env=env,
                             capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert png.stat().st_size > 20000
    assert f'wrote {png.resolve()}' in run.stdout
    assert 'wrenches: 2000 published, ' in run.stdout and 'fem model, 363 DOFs' in run.stdout
    # all traffic recorded beside the PNG, and said where
    (recorded,) = tmp_path.glob('cdpr_demo_*.mcap')
    assert f'recorded to {recorded.resolve()}: ' in run.stdout
    info = recording_info(recorded)
    counts = {name.lstrip('/'): t.message_count for name, t in info.topics.items()}
    assert info.complete and all(counts.get(t, 0) > 0 for t in (
        'pose', 'wrench', 'predicted_displacement', 'cable_tensions', 'diagnostics',
        'frequency_response/_service_event')), counts


def test_demo_fails_with_one_line(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('cdpr_dynamics:\n  ros__parameters:\n    robot:\n      anchors: [1.0, 2.0]\n')
    run = subprocess.run([installed('cdpr_demo'), '--config', str(bad)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 1
    assert run.stderr.strip() == ('cdpr_demo: error: robot.anchors needs 3 values per cable, '
                                  'got 2 values')


INPUT_LOOP = r"""
import sys, threading, time
import rclpy
from geometry_msgs.msg import PoseStamped, WrenchStamped
from cdpr_dynamics.ros.rclpy_compat import InputLoop, LOOP_WAIT_S

rclpy.init()
node = rclpy.create_node('loop_test', start_parameter_services=False)
got = {'pose': [], 'wrench': []}
done = threading.Event()

def on(kind):
    def callback(msg):
        got[kind].append(msg.header.stamp.sec)
        if msg.header.stamp.sec == 999:
            raise ValueError('a callback failed')
        if len(got['pose']) == 50 and len(got['wrench']) == 50:
            done.set()
    return callback

subs = [node.create_subscription(PoseStamped, 'pose', on('pose'), 100),
        node.create_subscription(WrenchStamped, 'wrench', on('wrench'), 100)]
pubs = {'pose': node.create_publisher(PoseStamped, 'pose', 100),
        'wrench': node.create_publisher(WrenchStamped, 'wrench', 100)}
deadline = time.monotonic() + 20
while min(p.get_subscription_count() for p in pubs.values()) < 1:
    assert time.monotonic() < deadline, 'no discovery'
    time.sleep(0.01)
errors = []

def spin():
    try:
        InputLoop(node.context, subs).spin()
    except Exception as exc:
        errors.append(exc)

def publish_both():
    for i in range(50):
        for kind, cls in (('pose', PoseStamped), ('wrench', WrenchStamped)):
            msg = cls()
            msg.header.stamp.sec = i
            pubs[kind].publish(msg)

thread = threading.Thread(target=spin)
thread.start()
publish_both()
assert done.wait(20), got
assert got == {'pose': list(range(50)), 'wrench': list(range(50))}, got
msg = WrenchStamped()
msg.header.stamp.sec = 999
pubs['wrench'].publish(msg)            # its callback raises: the loop ends with the error
thread.join(20)
assert not thread.is_alive() and [str(e) for e in errors] == ['a callback failed'], errors

# a middleware that lost the wake-ups: its wait set reports nothing ready, and the loop takes
# each message all the same, on its turns that found nothing ready
class Deaf:
    def __init__(self, wait_set):
        self._wait_set = wait_set

    def __getattr__(self, name):
        return getattr(self._wait_set, name)

    def get_ready_entities(self, kind):
        return []

got = {'pose': [], 'wrench': []}
done.clear()
deaf = InputLoop(node.context, subs, stop=done.is_set)
deaf._wait_set = Deaf(deaf._wait_set)
thread = threading.Thread(target=deaf.spin, daemon=True)
thread.start()
publish_both()
assert done.wait(20), got
thread.join(20)
assert got == {'pose': list(range(50)), 'wrench': list(range(50))}, got
errors.clear()
thread = threading.Thread(target=spin)
thread.start()
rclpy.shutdown()                       # the loop sees the shutdown within LOOP_WAIT_S
start = time.monotonic()
thread.join(20)
assert not thread.is_alive() and not errors, errors
print('stopped after %.3f s (LOOP_WAIT_S %.1f)' % (time.monotonic() - start, LOOP_WAIT_S))

# a stop whose exception was lost (a signal inside a pybind11 call comes out as a RuntimeError
# the batch swallows): the loop asks stop() every turn and returns while messages keep coming
rclpy.init()
node = rclpy.create_node('loop_stop_test', start_parameter_services=False)
stopping = threading.Event()
handled = []

def on_wrench(msg):
    handled.append(msg.header.stamp.sec)
    if len(handled) == 20:
        stopping.set()                 # as the signal handler sets the stopper's flag

sub = node.create_subscription(WrenchStamped, 'wrench', on_wrench, 1000)
pub = node.create_publisher(WrenchStamped, 'wrench', 1000)
deadline = time.monotonic() + 20
while pub.get_subscription_count() < 1:
    assert time.monotonic() < deadline, 'no discovery'
    time.sleep(0.01)
flooding = threading.Event()
flooding.set()

def flood():
    k = 0
    while flooding.is_set():
        msg = WrenchStamped()
        msg.header.stamp.sec = k
        pub.publish(msg)
        k += 1
        time.sleep(0.0005)

flooder = threading.Thread(target=flood)
flooder.start()
InputLoop(node.context, [sub], stop=stopping.is_set).spin()   # returns: no join needed
flooding.clear()
flooder.join(20)
assert stopping.is_set() and 20 <= len(handled) < 1000, len(handled)
assert rclpy.ok()                      # it was stop(), not a shutdown, that ended the loop
rclpy.shutdown()
print('stop() ended the loop after %d wrenches' % len(handled))
"""


def test_input_loop_serves_its_subscriptions_in_order_and_stops(ros_env):
    """The node's own pose and wrench loop (InputLoop): every message of both subscriptions
    reaches its callback in order, an exception in a callback ends the loop with it, a wait set
    that reports nothing ready delays no message past a turn, a context shut down ends the
    loop, and so does its stop() under a stream of wrenches."""
    result = subprocess.run([sys.executable, '-c', INPUT_LOOP], env=ros_env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert 'stopped after' in result.stdout and 'stop() ended the loop' in result.stdout


def test_vibration_modes_of_a_moving_pose_carry_the_pose_they_belong_to(ros):
    """fem 16 (modes of 10-100 ms, in the worker): while the pose moves on faster than the
    modes come, each vibration_modes table carries the stamp of a pose sent and holds the
    modes of that pose's model (modes_job on the mirror's equilibrium there); once the pose
    stays, the last pose's table comes."""
    from std_msgs.msg import Float64MultiArray

    from cdpr_dynamics.ros.worker import modes_job
    from msg_adapters.arrays import read_table

    node = Harness(PAPER, ros['log_dir'], 'moving_modes', {'model.method': 'fem',
                                                           'model.elements_per_cable': 16})
    try:
        node.settings = node.settings.replace(method='fem', elements_per_cable=16)
        node.mirror = LivePredictor(node.settings)
        tables = []

        def keep(msg):
            with node.cond:
                tables.append(read_table(msg))
                node.cond.notify_all()
        node.node.create_subscription(Float64MultiArray, 'vibration_modes', keep, QoSProfile(
            depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert node.wait(lambda: tables)
        equilibria = {}
        centre = node.settings.initial_position_m
        deadline = time.monotonic() + 3.0
        k = 0
        while time.monotonic() < deadline:            # poses 30 ms apart for 3 s, each rebuilt
            angle = 0.1 * k
            node.pose(centre + 0.05 * np.array([np.cos(angle), np.sin(angle), 0.0]),
                      dt_s=0.03)
            equilibria[node.t_ns] = node.mirror.eq
            k += 1
            time.sleep(0.03)
        last = node.t_ns
        assert node.wait(lambda: any(keys['pose_stamp_ns'] == last for _, _, keys in tables),
                         30.0)
        stamped = [(keys['pose_stamp_ns'], rows) for rows, _, keys in tables
                   if keys['pose_stamp_ns'] in equilibria]
        # during the motion (a job the pose outlived answers) and at its end
        assert len({stamp for stamp, _ in stamped}) >= 2
        assert all(keys['pose_stamp_ns'] in equilibria or keys['pose_stamp_ns'] == 0
                   for _, _, keys in tables)
        point = {'point_m': (0.0, 0.0, 0.0), 'shaper': 'none', 'shaper_modes': 1,
                 'sample_rate_hz': 1000.0}
        for stamp, rows in stamped:
            expected = modes_job(node.settings, equilibria[stamp], 'fem', 16, 1000,
                                 point)['mode_table']
            np.testing.assert_allclose(rows, expected, rtol=1e-6, atol=1e-9)
    finally:
        assert node.close() == 0


def test_controller_topics_and_slack(ros):
    """vibration_modes, input_shaper, notch_filter and cable_length_offsets against the library
    (modes_job, the shapers, length_offsets), and the slack diagnostics under the paper's
    1500 N: the node predicts as a slack-aware mirror does."""
    from std_msgs.msg import Float64MultiArray

    from cdpr_dynamics.analysis.controller import length_offsets, mode_labels
    from cdpr_dynamics.dynamics import shapers
    from cdpr_dynamics.ros.worker import modes_job
    from msg_adapters.arrays import read_shaper, read_table

    overrides = {'model.method': 'spring', 'damping.modal_ratio': 0.02,
                 'damping.mass_factor': 0.0, 'damping.stiffness_factor': 0.0,
                 'node.shaper': 'zvd', 'node.shaper_modes': 2}
    node = Harness(PAPER, ros['log_dir'], 'controller', overrides)
    try:
        node.settings = node.settings.replace(method='spring', damping_modal_ratio=0.02,
                                              damping_mass_factor=0.0,
                                              damping_stiffness_factor=0.0)
        node.mirror = LivePredictor(node.settings)
        got = {}
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)

        def keep(name):
            def store(msg):
                with node.cond:
                    got.setdefault(name, []).append(msg)
                    node.cond.notify_all()
            return store
        for name in ('vibration_modes', 'input_shaper', 'notch_filter'):
            node.node.create_subscription(Float64MultiArray, name, keep(name), latched)
        node.node.create_subscription(JointState, 'cable_length_offsets',
                                      keep('cable_length_offsets'), latched)
        assert node.wait(lambda: len(got) == 4), sorted(got)
        eq = node.mirror.eq
        found = modes_job(node.settings, eq, 'spring', 1, 1000, {
            'point_m': (0.0, 0.0, 0.0), 'shaper': 'zvd', 'shaper_modes': 2,
            'sample_rate_hz': 1000.0})
        rows, labels, keys = read_table(got['vibration_modes'][-1])
        assert labels == mode_labels(3) and keys['pose_stamp_ns'] == 0
        np.testing.assert_allclose(rows, found['mode_table'], rtol=1e-9)
        times, amplitudes = read_shaper(got['input_shaper'][-1])
        assert amplitudes.sum() == pytest.approx(1.0)
        np.testing.assert_allclose(np.column_stack([times, amplitudes]).ravel(),
                                   found['shaper_pairs'], rtol=1e-12)
        notches, notch_labels, notch_keys = read_table(got['notch_filter'][-1])
        assert notch_labels == ('b0', 'b1', 'b2', 'a0', 'a1', 'a2') and notches.shape == (2, 6)
        assert notch_keys['sample_rate_hz'] == 1000.0
        gain = np.abs(shapers.biquad_response(notches[0], [0.0, rows[0, 0]], 1000.0))
        assert gain[0] == pytest.approx(1.0) and gain[1] < 1e-9
        offsets = got['cable_length_offsets'][-1]
        np.testing.assert_allclose(offsets.position, length_offsets(node.settings.robot, eq),
                                   rtol=1e-9)
        np.testing.assert_allclose(offsets.effort, eq.tensions.tension_n, rtol=1e-9)
        # a moved pose: new modes stamped with that pose
        stamp_before = len(got['vibration_modes'])
        node.pose([0.2, -0.1, 1.2])
        pose_ns = node.t_ns
        assert node.wait(lambda: any(read_table(m)[2]['pose_stamp_ns'] == pose_ns
                                     for m in got['vibration_modes'][stamp_before:]))
        # the paper's load slackens cables: the node steps the compression-free model
        for k in range(120):
            node.wrench([0.0, 0.0, 1500.0 * np.sin(2 * np.pi * 5.0 * (k + 1) * 0.002)],
                        dt_s=0.002)
        assert node.mirror.slack_time_s > 0
        status = node.fresh_status('model')
        assert float(status['values']['slack_time_s']) == pytest.approx(
            node.mirror.slack_time_s, abs=1e-9)
    finally:
        assert node.close() == 0
