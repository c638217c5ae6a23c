"""cdpr_demo as a user's first experience, with its in-process recording: the start waits for
the match, the counts it prints are what happened and what its MCAP file holds, the load comes
from the config, and its messages offer only its own flags."""
from __future__ import annotations

import ast
import json
import re
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.cli import demo, demo_figure, demo_plan, demo_results
from cdpr_dynamics.analysis.config import load_settings
from conftest import installed

DEMO_SOURCES = [Path(m.__file__) for m in (demo, demo_figure, demo_plan, demo_results)]
FLAGS = {s for a in demo._parser()._actions for s in a.option_strings}
#: flags the demo's messages may name that belong to the node it starts
NODE_FLAGS = {'--ros-args', '--params-file'}


def flags_in(text: str) -> set:
    return set(re.findall(r'(?<![\w-])(--[a-z][\w-]*)', text))


# ------------------------------------------------------------------ messages and flags


def test_every_flag_the_source_mentions_exists():
    """Each ``--flag`` in a string of the demo's modules (messages, help, usage) is one of its
    own, or the node's command line (``--force`` was suggested and missing)."""
    strings = [n.value for path in DEMO_SOURCES for n in ast.walk(ast.parse(path.read_text()))
               if isinstance(n, ast.Constant) and isinstance(n.value, str)
               and n.value != demo.RECORDER_ADVICE]
    mentioned = set().union(*map(flags_in, strings))
    assert '--record' in mentioned and '--amplitude-n' in mentioned      # it does look
    assert mentioned - FLAGS - NODE_FLAGS == set()


@pytest.mark.parametrize('argv,hint', [
    (['--force'], None),
    (['--amplitud-n', '3'], '--amplitude-n'),
    (['--no-recrd'], '--no-record'),
])
def test_a_bad_flag_is_one_line_naming_existing_flags(capsys, argv, hint):
    with pytest.raises(SystemExit) as exit_:
        demo.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('cdpr_demo: error: unrecognized arguments'), err
    offered = flags_in(err[0]) - {argv[0]}
    assert '--help' in offered and offered <= FLAGS, err
    if hint:
        assert f'did you mean {hint}?' in err[0]


@pytest.mark.parametrize('argv,message', [
    (['--amplitude-n', '-1'], '--amplitude-n must be a number >= 0, got -1'),
    (['--amplitude-n', 'nan'], '--amplitude-n must be a number >= 0, got nan'),
    (['--duration', '0'], '--duration must be a positive number, got 0'),
    (['--wrench-rate', '-5'], '--wrench-rate must be a positive number, got -5'),
])
def test_bad_numbers_are_refused_with_one_line(capsys, argv, message):
    assert demo.main(argv) == 1
    assert capsys.readouterr().err.strip().splitlines() == [f'cdpr_demo: error: {message}']


def test_an_existing_recording_is_refused_naming_the_demos_flags(capsys, tmp_path):
    existing = tmp_path / 'run.mcap'
    existing.write_bytes(b'not mine')
    assert demo.main(['--record', str(existing), '--output', str(tmp_path / 'a.png')]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f'cdpr_demo: error: {existing} exists; not overwriting it (give another '
                   '--record path, or --no-record)'], err
    assert existing.read_bytes() == b'not mine'
    assert flags_in(err[0]) <= FLAGS
    # the recorder's own wording (cdpr_record has --force) is turned into the demo's
    assert '--force' not in demo._own_flags('x exists; not overwriting it (use --force to '
                                            'replace it)')


def test_a_bad_config_is_one_line_naming_no_missing_flag(capsys, tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('cdpr_dynamics:\n  ros__parameters:\n    robot:\n      mass_kgg: 3.0\n')
    assert demo.main(['--config', str(bad), '--no-record']) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('cdpr_demo: error: '), err
    assert 'robot.mass_kgg' in err[0] and flags_in(err[0]) <= FLAGS | NODE_FLAGS


# ------------------------------------------------------------------------------ the load


def test_the_load_is_the_configs_and_amplitude_keeps_its_direction():
    settings = load_settings()
    assert np.array_equal(demo_plan.demo_load(settings, None, 5.0).force_n, settings.frf_force_n)
    rigid = SimpleNamespace(frf_force_n=np.array([3.0, 0.0, 4.0]),
                            frf_moment_nm=np.array([0.0, 2.0, 0.0]),
                            robot=SimpleNamespace(point_mass=False))
    load = demo_plan.demo_load(rigid, 10.0, 2.0)
    assert np.allclose(load.force_n, [6.0, 0.0, 8.0]) and load.amplitude_n == pytest.approx(10)
    assert np.allclose(load.moment_nm, [0.0, 4.0, 0.0])        # scaled with the force
    force, moment = load.at([0.125])                           # sin(2 pi 2 0.125) = 1
    assert np.allclose(force, [[6.0, 0.0, 8.0]]) and np.allclose(moment, [[0.0, 4.0, 0.0]])
    off = demo_plan.demo_load(rigid, 0.0, 2.0)        # no load, the direction kept (the FRF's)
    assert off.amplitude_n == 0 and np.allclose(off.direction, [0.6, 0.0, 0.8])
    point = SimpleNamespace(**{**vars(rigid), 'robot': SimpleNamespace(point_mass=True)})
    assert not np.any(demo_plan.demo_load(point, None, 2.0).moment_nm)   # no moment on a point
    zero = SimpleNamespace(**{**vars(rigid), 'frf_force_n': np.zeros(3)})
    with pytest.raises(demo_plan.DemoError, match='frf.force_n'):
        demo_plan.demo_load(zero, 10.0, 2.0)


def test_stamps_are_integer_nanoseconds_at_the_rate():
    stamps = demo_plan.stamps_ns(1_700_000_000_123_456_789, 4, 1000.0)
    assert stamps.dtype == np.int64
    assert np.array_equal(np.diff(stamps), [1_000_000] * 3)
    assert stamps[0] == 1_700_000_000_123_456_789


def test_sparse_predictions_get_markers_and_gaps_break_lines():
    t = np.array([0.0, 0.001, 0.002, 0.05, 0.2, 0.201, 0.5])
    lonely = [False, False, False, True, False, False, True]
    assert demo_figure._lonely(t, 0.001).tolist() == lonely
    x = demo_figure._broken(t, 0.001)
    assert np.isnan(x).tolist() == [False, False, False, True, True, False, True]
    mask = np.array([True, True, False, True, True, True, True])
    spans = [(-0.001, 0.002), (0.049, 0.051), (0.199, 0.202), (0.499, 0.501)]
    assert np.allclose(demo_figure._spans(t, mask, 0.002), spans)


def test_the_frf_along_the_load_is_the_projection_of_the_complex_response():
    frf = {'amplitude_x_m': np.array([3.0]), 'amplitude_y_m': np.array([0.0]),
           'amplitude_z_m': np.array([4.0]), 'phase_x_rad': np.array([0.0]),
           'phase_y_rad': np.array([0.0]), 'phase_z_rad': np.array([np.pi / 2])}
    d = np.array([0.6, 0.0, 0.8])
    assert demo_results.along(frf, d) == pytest.approx(abs(0.6 * 3 + 0.8 * 4j))


@pytest.mark.slow
def test_slack_comparison_and_the_taut_amplitude():
    """The demo's own run of the node's predictor: the paper's 1500 N at 5 Hz on the circle
    slackens cables (the slack-aware peak above the linear one); at the amplitude it advises no
    cable slackens in either prediction, at every pose of the circle."""
    from cdpr_dynamics.analysis.config import node_options
    settings = load_settings().replace(method='spring')
    options = node_options({})

    def comparison(amplitude):
        args = SimpleNamespace(amplitude_n=amplitude, excitation_hz=5.0, duration=1.0,
                               radius=0.05, wrench_rate=1000.0, pose_rate=50.0)
        plan = demo_plan.Trajectory(settings, args)
        return demo_results.slack_comparison(settings, options, plan, 10**18, 1000, 50), plan
    loud, plan = comparison(1500.0)
    assert loud.slack.any() and loud.force_linear.min() < 0 <= loud.force_aware.min()
    assert np.abs(loud.u_aware).max() > np.abs(loud.u_linear).max()
    assert 'slack' in loud.sentence()
    taut = loud.taut_amplitude_n(1500.0)
    assert 0 < taut < 1500.0
    quiet, _ = comparison(0.98 * taut)
    assert not quiet.slack.any() and quiet.force_linear.min() > 0
    assert_allclose(quiet.u_aware, quiet.u_linear, rtol=0, atol=1e-15)
    assert 'no cable slackens' in quiet.sentence()
    over, _ = comparison(1.02 * taut)
    assert over.force_linear.min() < 0


def test_the_tension_sentence_says_slack_and_below_minimum():
    t = np.array([0.0, 0.5, 1.0])
    static = np.full((3, 2), 100.0)
    slack = demo_results.TensionEstimate(t, static, static + [[0, 0], [-150, 10], [0, -20]], 100.0)
    assert slack.lowest == (-50.0, 0, 0.5)
    assert slack.sentence().startswith('the load slackens cable(s) 0: lowest tension -50.0 N '
                                       '(cable 0 at 0.50 s), a cable slack 33% of the time')
    low = demo_results.TensionEstimate(t, static, static - [[0, 0], [30, 0], [0, 0]], 100.0)
    assert low.sentence() == ('no cable slackens, but cable 0 dips to 70.0 N at 0.50 s, below '
                              'tension.min_n 100 N')


def test_rejected_poses_are_counted_by_kind(monkeypatch):
    monkeypatch.setattr(demo_results.os, 'getloadavg', lambda: (3.25, 0.0, 0.0))
    monkeypatch.setattr(demo_results.os, 'cpu_count', lambda: 2)
    status = {'values': {'accepted': '140', 'rejected': '8', 'rejected_frame': '5',
                         'rejected_order': '3', 'last_rejection': 'pose in frame map'}}
    assert demo_results.input_sentence('poses', 150, status) == (
        'poses: 150 published, 140 accepted by the node, 8 rejected (frame 5, order 3; last: '
        'pose in frame map), 2 not taken by the node (dropped from its queue while it was '
        'busy; load average 3.2 on 2 CPUs)')
    status = {'values': {'accepted': '75', 'rejected': '0', 'late': '2',
                         'late_max_ms': '0.731'}}
    assert demo_results.input_sentence('poses', 75, status) == (
        'poses: 75 published, 75 accepted by the node, 0 rejected, 2 taken after a wrench '
        'stamped at or after it (up to 0.731 ms; that wrench had the previous pose)')
    assert demo_results.input_sentence('poses', 3, None) == (
        'poses: 3 published; the node reported no counts')


# ------------------------------------------------------------------------ end to end


def recorded(path: Path) -> dict:
    """{topic: [header stamp ns (None without a header), ...]} of an MCAP file."""
    from cdpr_dynamics.recording.reader import read_messages
    out: dict = {}
    for m in read_messages(path):
        header = getattr(m.message, 'header', None)
        out.setdefault(m.topic.lstrip('/'), []).append(
            None if header is None else header.stamp.sec * 10**9 + header.stamp.nanosec)
    return out


def test_the_demo_starts_after_the_match_and_reports_what_its_recording_holds(
        ros_env, tmp_path):
    png, mcap, summary = tmp_path / 'demo.png', tmp_path / 'demo.mcap', tmp_path / 'demo.json'
    run = subprocess.run([installed('cdpr_demo'), '--duration', '1.5',   # no suffix: .png
                          '--output', str(png.with_suffix('')),
                          '--record', str(mcap), '--json', str(summary)], env=ros_env,
                         capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(summary.read_text())
    # the controller started only once its publishers saw the node and the recorder
    for counts in (result['subscribers_matched_at_start'], result['subscribers_at_first_wrench']):
        assert counts['pose'] >= 2 and counts['wrench'] >= 2, result
    assert result['wrenches_published'] == 1500 and result['poses_published'] == 75
    published = set(demo_plan.stamps_ns(result['t0_ns'], 1500, 1000.0).tolist())
    holds = recorded(mcap)
    # the report's recorded counts are what the file holds, topic by topic
    assert result['recorded'] == {t: len(holds.get(t, [])) for t in result['recorded']}
    assert set(holds) >= {'pose', 'wrench', 'predicted_displacement', 'predicted_pose',
                          'cable_tensions', 'diagnostics', 'frequency_response/_service_event'}
    # no wrench before t0 (nor any other): every recorded one is a published one
    assert set(holds['wrench']) <= published and min(holds['wrench']) >= result['t0_ns']
    # predictions carry the stamp of a published wrench, here and in the file
    assert result['predictions_not_of_a_published_wrench'] == 0
    assert set(holds['predicted_displacement']) <= published
    assert 0 < result['wrenches_predicted'] <= result['wrenches_published']
    assert result['prediction_ratio'] == result['wrenches_predicted'] / 1500
    assert result['node_wrenches_accepted'] >= result['wrenches_predicted']
    # latency ends at the DDS arrival on the wall clock of the stamps: after the stamp, and not
    # seconds or 1e9 off (a clock or unit slip); how short it is is the benchmark's business
    assert 0 < result['latency_ms_p50'] <= result['latency_ms_p99'] < 10_000
    # what it printed is what it counted
    out = run.stdout
    assert (f'wrenches: 1500 published, {result["wrenches_predicted"]} predicted (received '
            f'here, matched by stamp)') in out
    assert (f'poses: 75 published, {result["node_poses_accepted"]} accepted by the node, '
            f'{result["node_poses_rejected"]} rejected') in out
    assert re.search(r'tensions: (the load slackens|no cable slackens)', out), out
    assert 'prediction: node.slack = aware (the compression-free model while a cable is slack)' \
        in out and result['slack_mode'] == 'aware'
    # the node's predictions are the demo's own run of the same predictor on what it sent,
    # also when the node ran behind (it takes the waiting inputs in stamp order); within the
    # tension QP's round-off, as the replay tests (1e-6 of the peak). Where the node took every
    # input in time: a busy host drops some from its queues, and delivers a pose after a wrench
    # stamped after it or the other way round (the topics are delivered apart), which the node
    # then counts as late
    for what in ('poses', 'wrenches'):
        late = result[f'node_{what}_late']
        assert late is not None and (not late or f', {late} taken after a ' in out)
    if (result['node_wrenches_accepted'] == 1500 and result['node_poses_accepted'] == 75
            and result['node_poses_late'] == result['node_wrenches_late'] == 0):
        assert result['node_vs_local_max_m'] <= 1e-6 * result['peak_aware_m']
    assert f'recorded to {mcap.resolve()}: ' in out
    assert f'wrench {len(holds["wrench"])} of 1500' in out
    assert png.stat().st_size > 20000 and f'wrote {png.resolve()}' in out


RIGID = Path(__file__).parent / 'data' / 'rigid_cdpr.yaml'


def test_an_infeasible_load_is_answered_with_an_amplitude_the_node_then_accepts(
        ros_env, tmp_path):
    """The rigid 6-DOF robot's frf.force_n (1500 N along z) exceeds what its cables hold
    (about 300 N): the demo says how much they hold and suggests --amplitude-n; a run with
    it has no infeasible wrench."""
    def run(*extra):
        done = subprocess.run([installed('cdpr_demo'), '--config', str(RIGID), '--duration',
                               '1', '--no-record', '--output', str(tmp_path / 'rigid.png'),
                               '--json', str(tmp_path / 'rigid.json'), *extra], env=ros_env,
                              capture_output=True, text=True, timeout=180)
        assert done.returncode == 0, done.stderr[-3000:]
        return done.stdout, json.loads((tmp_path / 'rigid.json').read_text())
    out, result = run()
    assert result['node_wrenches_rejected'] > 0
    hint = re.search(r'the cables hold up to ([\d.]+) N along this load .* e\.g\. '
                     r'--amplitude-n ([\d.]+)', out)
    assert hint, out
    assert float(hint[1]) == pytest.approx(result['amplitude_limit_n'], rel=1e-3)
    assert 0.9 * float(hint[1]) <= float(hint[2]) < float(hint[1]) < 1500.0
    out, result = run('--amplitude-n', hint[2])
    assert result['node_wrenches_rejected'] == 0 and 'amplitude_limit_n' not in result, out
    assert 'the cables hold up to' not in out


def test_arrival_is_the_rmw_receive_time_and_now_without_one(monkeypatch):
    """The Listener polls every POLL_S: a prediction's latency ends when DDS received it
    (take_message's received_timestamp, ns), not when the poll took it."""
    monkeypatch.setattr(demo.time, 'time', lambda: 1234.5)
    assert demo.arrival_s({'received_timestamp': 1_796_229_917_302_763_405}) == \
        pytest.approx(1_796_229_917.302763405, abs=1e-6)
    assert demo.arrival_s({'received_timestamp': 0}) == 1234.5      # an RMW that gives none
    assert demo.arrival_s({}) == 1234.5


def test_a_node_that_does_not_come_up_is_named_with_what_is_missing(tmp_path):
    """The start waits on conditions, and its timeout says which did not appear."""
    import threading
    graph = SimpleNamespace(count_subscribers=lambda name: 1 if name == 'pose' else 0)
    listener = SimpleNamespace(unmatched=lambda: ['predicted_pose'], tensions=[[0.0, 1.0]],
                               diagnostics=[], cond=threading.Condition())
    listener.wait = lambda predicate, timeout_s: demo.Listener.wait(listener, predicate,
                                                                    timeout_s)
    running = SimpleNamespace(poll=lambda: None, returncode=None)
    log = tmp_path / 'node.log'
    with open(log, 'w') as stream, pytest.raises(demo_plan.DemoError) as error:
        demo._wait_until_up(graph, listener, running, stream, log, 0.3)
    assert str(error.value) == (
        'dynamics_node did not come up within 0.3 s: missing its wrench subscription, its '
        f'predicted_pose publisher, a /diagnostics message (log: {log})')


def test_a_polled_recorder_takes_everything_in_bounded_batches(tmp_path, ros_context):
    """Recorder.poll (the demo's recorder on a node no executor spins): discovery, then each
    call takes at most one batch per topic, and polling until the queue is empty records every
    message of a reliable burst, as the file then holds."""
    import rclpy
    from geometry_msgs.msg import WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from cdpr_dynamics.ros.process import wait_until
    from cdpr_dynamics.recording.reader import recording_info
    from cdpr_dynamics.recording.recorder import _TAKE_BATCH, Recorder
    from msg_adapters.validation import ns_to_stamp
    from msg_adapters.wrench import wrench_message

    burst = 3 * _TAKE_BATCH + 17
    talker = rclpy.create_node('talker', context=ros_context)
    quiet = rclpy.create_node('quiet', context=ros_context)      # never spun
    pub = talker.create_publisher(WrenchStamped, 'wrench', QoSProfile(
        depth=burst, reliability=ReliabilityPolicy.RELIABLE))
    recorder = Recorder(quiet, tmp_path / 'w.mcap', ['wrench'], qos_depth=burst)
    assert wait_until(lambda: pub.get_subscription_count() == 1, 10.0, recorder.poll)
    for k in range(burst):
        pub.publish(wrench_message([0.0, 0.0, k], stamp=ns_to_stamp(k + 1)))
    assert pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10.0))
    recorder.poll()
    assert recorder.topic_counts['/wrench'] == _TAKE_BATCH     # one batch per call
    assert wait_until(lambda: recorder.topic_counts['/wrench'] == burst, 10.0,
                      recorder.poll)
    summary = recorder.close()
    assert summary.topics == {'/wrench': burst}
    assert recording_info(tmp_path / 'w.mcap').topics['/wrench'].message_count == burst
