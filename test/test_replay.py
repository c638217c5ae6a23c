"""cdpr_replay and the golden recordings of test/data.

The golden recordings (``test/data/golden_<scenario>.mcap``) hold the inputs of a scripted
scenario (``cdpr_dynamics/recording/scenarios.py``) and the predictions ``cdpr_replay`` made from
them
with the paper config, ``fem`` with 4 elements per cable. A fresh replay - offline through
``cdpr_replay``, and live through ``dynamics_node`` - must give the same predictions.

Tolerance: every quantity within RTOL = 1e-6 of its peak over the scenario (|u| for the
displacement, the longest cable, the largest tension). What legitimately differs between
machines is rounding: the tension QP stops within ~1e-7 of the tension scale (proxsuite's
eps_abs = 1e-12 scale, complementarity within ~100 eps), and BLAS/LAPACK kernels and the
Newmark recursion differ in the last bits (~1e-14 of the peak, seen between runs here). A
model change of a few per cent moves the displacement by ~1e-2 of its peak, 10^4 times the
tolerance: a +5 % Young's modulus or stiffness-damping factor must fail the comparison (tested).

Regenerate the golden files after an intended change of the numbers (then review the diff of
the predictions, e.g. with compare_outputs):

    python -m cdpr_dynamics.recording.scenarios --golden test/data --force

ROS processes get a domain id of their own (fixture ``ros_env``); their recordings and logs
land in ``test_output/test_replay/<test>/``, kept when a test fails.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from std_msgs.msg import String

from cdpr_dynamics.recording import scenarios
from cdpr_dynamics.analysis.config import read_params_file
from cdpr_dynamics.recording.base import message_class, RecordingError
from cdpr_dynamics.recording.cdr import serialize
from cdpr_dynamics.recording.reader import read_messages, recording_info
from cdpr_dynamics.recording.writer import partial_files, RecordingWriter
from cdpr_dynamics.analysis.config import ConfigError
from cdpr_dynamics.recording.replay import (NodeOptions, ReplayError, compare_outputs,
                                            load_replay_config, read_predictions, replay_offline)
from msg_adapters import mcap_schema
from msg_adapters.pose import pose_message
from msg_adapters.validation import stamp_to_ns
from msg_adapters.wrench import wrench_message
from conftest import installed, wait_until
from processes import counts_so_far, finish, Processes

PYTHON = sys.executable
REPO = Path(__file__).resolve().parents[1]
DATA = REPO / 'test' / 'data'
CONFIG = REPO / 'config' / 'paper_cdpr.yaml'
RTOL = 1e-6
GOLDEN_ARGS = ['--config', str(CONFIG), '--method', scenarios.GOLDEN['method'],
               '--elements', str(scenarios.GOLDEN['elements_per_cable'])]
POSE, WRENCH = 'geometry_msgs/msg/PoseStamped', 'geometry_msgs/msg/WrenchStamped'


def golden(name: str) -> Path:
    return DATA / scenarios.golden_name(name)


def replay_cli(*args, env=None, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, '-m', 'cdpr_dynamics.cli.replay', *map(str, args)],
                          env=env, capture_output=True, text=True, timeout=timeout)


def golden_settings(**changes):
    settings, options, _ = load_replay_config(CONFIG)
    settings = settings.replace(method=scenarios.GOLDEN['method'],
                                elements_per_cable=scenarios.GOLDEN['elements_per_cable'])
    return (settings.replace(**changes) if changes else settings), options


def leftovers(folder: Path) -> list:
    """Temporary files a writer would leave behind."""
    return sorted(p.name for p in folder.iterdir() if '.partial-' in p.name)


# ----------------------------------------------------------------------------- golden files


@pytest.mark.parametrize('name', list(scenarios.SCENARIOS))
def test_golden_file_is_small_and_made_as_documented(name):
    path = golden(name)
    assert path.stat().st_size < 1_000_000
    info = recording_info(path)
    assert info.complete and info.profile == 'ros2'
    meta = info.metadata['cdpr_replay']
    assert meta['method'] == scenarios.GOLDEN['method']
    assert int(meta['elements_per_cable']) == scenarios.GOLDEN['elements_per_cable']
    used = json.loads(meta['parameters'])
    now = read_params_file(CONFIG)
    changed = sorted(k for k in now if k not in ('model.method', 'model.elements_per_cable')
                     and str(now[k]) != str(used.get(k)))
    assert not changed, (f'config/paper_cdpr.yaml changed since {path.name} was made '
                         f'({", ".join(changed)}): regenerate the golden files')


def _values(msg) -> list:
    if hasattr(msg, 'pose'):
        p, q = msg.pose.position, msg.pose.orientation
        return [p.x, p.y, p.z, q.x, q.y, q.z, q.w]
    f, m = msg.wrench.force, msg.wrench.torque
    return [f.x, f.y, f.z, m.x, m.y, m.z]


@pytest.mark.parametrize('name', list(scenarios.SCENARIOS))
def test_scenario_tool_writes_the_golden_inputs(name):
    """The golden file's inputs are what the scenario tool writes today: same topics, times,
    stamps and frames; the same values up to the last bits of libm's sin and cos (byte for
    byte here, where the files were made)."""
    want = scenarios.scenario_messages(name)
    have = list(read_messages(golden(name), {'pose': POSE, 'wrench': WRENCH}, raw=True))
    assert [(m.topic, m.log_time_ns, stamp_to_ns(m.message.header.stamp),
             m.message.header.frame_id) for m in have] == \
        [(topic, t, stamp_to_ns(msg.header.stamp), msg.header.frame_id)
         for topic, t, msg in want]
    np.testing.assert_allclose(np.concatenate([_values(m.message) for m in have]),
                               np.concatenate([_values(msg) for _, _, msg in want]),
                               rtol=1e-13, atol=1e-13)
    if all(m.data == serialize(msg) for m, (_, _, msg) in zip(have, want)):
        return
    print(f'\n{name}: the inputs differ from the golden file in the last bits only')


@pytest.mark.parametrize('name', list(scenarios.SCENARIOS))
def test_fresh_replay_matches_golden(name, tmp_path, ros_env):
    out = tmp_path / 'replay.mcap'
    result = replay_cli(golden(name), '--output', out, *GOLDEN_ARGS, '--no-progress',
                        env=ros_env)
    assert result.returncode == 0, result.stderr
    assert 'Traceback' not in result.stderr
    assert f'to {out.resolve()}' in result.stdout
    comparison = compare_outputs(read_predictions(golden(name)), read_predictions(out), RTOL)
    assert comparison.ok, str(comparison)
    # the inputs are copied unchanged, with their log and publish times
    topics = {'pose': POSE, 'wrench': WRENCH}
    fresh = [(m.topic, m.log_time_ns, m.publish_time_ns, m.data)
             for m in read_messages(out, topics, raw=True)]
    assert fresh == [(m.topic, m.log_time_ns, m.publish_time_ns, m.data)
                     for m in read_messages(golden(name), topics, raw=True)]


@pytest.mark.parametrize('change', [
    {'cable': 1.05},                           # Young's modulus +5 %
    {'damping_stiffness_factor': 1.05},        # Rayleigh stiffness damping +5 %
], ids=['youngs_modulus+5%', 'stiffness_damping+5%'])
def test_a_model_change_fails_the_comparison(change, tmp_path):
    base, options = golden_settings()
    if 'cable' in change:
        cable = base.cable
        settings = base.replace(cable=type(cable)(cable.area_m2,
                                                  cable.youngs_modulus_pa * change['cable'],
                                                  cable.weight_per_length_n_per_m, cable.g_m_s2))
    else:
        settings = base.replace(damping_stiffness_factor=base.damping_stiffness_factor * 1.05)
    reference = read_predictions(golden('step_wrench'))
    out = tmp_path / 'changed.mcap'
    replay_offline(golden('step_wrench'), out, settings, options=options)
    comparison = compare_outputs(reference, read_predictions(out), RTOL)
    assert not comparison.ok
    assert comparison.problems[0].startswith('displacement differs')
    assert comparison.worst['displacement'] > 1e3 * RTOL   # far outside, not at the edge
    # and the unchanged model passes (same process: the comparison itself is not too strict)
    same = tmp_path / 'same.mcap'
    replay_offline(golden('step_wrench'), same, base, options=options)
    assert compare_outputs(reference, read_predictions(same), RTOL).ok


def test_comparator_reports_missing_and_changed_rejections():
    reference = read_predictions(golden('invalid_inputs'))
    candidate = read_predictions(golden('invalid_inputs'))
    dropped = sorted(candidate.displacement)[10]
    del candidate.displacement[dropped]
    candidate.rejected.pop(next(iter(candidate.rejected)))
    comparison = compare_outputs(reference, candidate, RTOL)
    assert not comparison.ok
    text = str(comparison)
    assert 'displacement: 1 of 195 stamps missing' in text
    assert 'rejected inputs differ' in text


# ----------------------------------------------------------------------------- rejections


def test_infeasible_poses_are_diagnosed_and_predictions_go_on(tmp_path):
    path = golden('infeasible_crossing')
    poses = {stamp_to_ns(m.message.header.stamp): m.message.pose.position.x
             for m in read_messages(path, {'pose': POSE})}
    pred = read_predictions(path)
    rejected = {stamp: kind for (what, stamp), (kind, _) in pred.rejected.items()}
    assert set(what for what, _ in pred.rejected) == {'pose'}
    assert set(rejected.values()) == {'state'}
    # the poses beyond the workspace edge (~1.07 m), and only those, are rejected
    assert 15 <= len(rejected) <= 30
    edge_in = max(x for s, x in poses.items() if s not in rejected)
    edge_out = min(x for s, x in poses.items() if s in rejected)
    assert 1.0 < edge_in < edge_out < 1.15
    for (_, stamp), (_, reason) in pred.rejected.items():
        assert reason.startswith('pose rejected: infeasible tension distribution')
    for item in read_messages(path, ['/diagnostics']):
        (status,) = item.message.status
        assert status.level == b'\x02' and status.name == 'cdpr_dynamics: pose input'
        assert stamp_to_ns(item.message.header.stamp) in rejected
    # tensions for every accepted pose, none for the rejected ones
    assert set(pred.tension) == set(poses) - set(rejected)
    # a prediction for every wrench, finite, and the same as if the rejected poses had never
    # been sent: the node went on from its last good state
    assert len(pred.displacement) == 600
    assert all(np.isfinite(u).all() for u in pred.displacement.values())
    filtered = tmp_path / 'without_rejected.mcap'
    with RecordingWriter(filtered) as writer:
        writer.add_topic('/pose', POSE)
        writer.add_topic('/wrench', WRENCH)
        for m in read_messages(path, {'pose': POSE, 'wrench': WRENCH}, raw=True):
            if not (m.topic == '/pose' and stamp_to_ns(m.message.header.stamp) in rejected):
                writer.write(m.topic, m.data, m.log_time_ns)
    settings, options = golden_settings()
    out = tmp_path / 'out.mcap'
    summary = replay_offline(filtered, out, settings, options=options)
    assert summary.poses == len(poses) - len(rejected) and not summary.rejected
    # (not bit for bit: after a failed solve the tension QP starts cold, not warm, which moves
    # the answer within its tolerance, ~1e-10 of the peak here)
    comparison = compare_outputs(pred, read_predictions(out), RTOL, diagnostics=False)
    assert comparison.ok, str(comparison)


def test_each_bad_input_gets_its_diagnostic():
    pred = read_predictions(golden('invalid_inputs'))
    pose_stamps = [stamp_to_ns(m.message.header.stamp)
                   for m in read_messages(golden('invalid_inputs'), {'pose': POSE})]
    t0 = scenarios.T0_NS
    pose_index = {s: round((s - t0 - scenarios.POSE_OFFSET_NS) / scenarios.POSE_PERIOD_NS)
                  for s in pose_stamps}
    got = {}
    for (what, stamp), (kind, reason) in pred.rejected.items():
        index = (pose_index[stamp] if what == 'pose'
                 else round((stamp - t0) / scenarios.WRENCH_PERIOD_NS))
        got[(what, index)] = kind
        assert reason and '\n' not in reason
    assert got == {('pose', 5): 'frame', ('pose', 8): 'quaternion', ('pose', 11): 'not_finite',
                   ('pose', 13): 'stamp', ('wrench', 40): 'frame', ('wrench', 60): 'not_finite',
                   ('wrench', 80): 'stamp', ('wrench', 100): 'infeasible',
                   ('wrench', 120): 'not_finite'}
    assert len(pred.displacement) == 200 - 5 and len(pred.tension) == 20 - 4


def test_node_options_are_validated_like_the_nodes_parameters():
    assert NodeOptions() == NodeOptions.from_params({})
    assert NodeOptions.from_params({'node.quaternion_tolerance': 0.01}).quaternion_tolerance \
        == 0.01
    with pytest.raises(ConfigError, match='node.quaternion_tolerance = 2.0 is outside'):
        NodeOptions.from_params({'node.quaternion_tolerance': 2.0})


# ----------------------------------------------------------------------------- the output file


def test_replay_output_reads_with_independent_readers(tmp_path):
    settings, options = golden_settings()
    out = tmp_path / 'replay.mcap'
    summary = replay_offline(golden('invalid_inputs'), out, settings, options=options)
    want = {'/pose': (POSE, 20), '/wrench': (WRENCH, 200),
            '/predicted_displacement': ('geometry_msgs/msg/Vector3Stamped', 195),
            '/predicted_pose': (POSE, 195),
            '/cable_tensions': ('sensor_msgs/msg/JointState', 16),
            '/diagnostics': ('diagnostic_msgs/msg/DiagnosticArray', 9)}
    assert summary.messages_written == sum(n for _, n in want.values())

    # mcap + mcap-ros2-support: summary, schemas, channel metadata, every message decoded
    decoded = {}
    with open(out, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        s = reader.get_summary()
        assert reader.get_header().profile == 'ros2' and s.chunk_indexes
        for schema in s.schemas.values():
            assert schema.encoding == 'ros2msg'
            assert schema.data.decode() == mcap_schema.message_definition(schema.name)
        for channel in s.channels.values():
            assert channel.message_encoding == 'cdr'
            assert set(channel.metadata) == {'offered_qos_profiles', 'topic_type_hash'}
            assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        bag = yaml.safe_load(meta['rosbag2']['serialized_metadata'])
        assert {t['topic_metadata']['name']: t['message_count']
                for t in bag['topics_with_message_count']} == {k: n for k, (_, n) in
                                                               want.items()}
        for schema, channel, message, ros in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(ros)
    assert {t: len(v) for t, v in decoded.items()} == {k: n for k, (_, n) in want.items()}

    # rosbags: types, counts, every message decoded (exact CDR sizes: no trailing bytes)
    seen = {}
    with AnyReader([out]) as reader:
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == want
        for conn, _, raw in reader.messages():
            seen.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))

    # the three readers agree on the predictions and their stamps
    mine = read_predictions(out)
    wrench_stamps = [stamp_to_ns(m.header.stamp) for m in decoded['/wrench']]
    for a, b in zip(decoded['/predicted_displacement'], seen['/predicted_displacement']):
        stamp = a.header.stamp.sec * 10**9 + a.header.stamp.nanosec
        assert stamp == b.header.stamp.sec * 10**9 + b.header.stamp.nanosec
        assert stamp in wrench_stamps and a.header.frame_id == 'world'
        for v in (a.vector, b.vector):
            np.testing.assert_array_equal([v.x, v.y, v.z], mine.displacement[stamp])
    for a, b in zip(decoded['/cable_tensions'], seen['/cable_tensions']):
        assert list(a.name) == list(b.name) == [f'cable_{i}' for i in range(8)]
        np.testing.assert_array_equal(a.effort, b.effort)
        assert min(a.effort) >= 100.0 - 1e-6 and min(a.position) > 0
    reasons = [d.status[0].message for d in decoded['/diagnostics']]
    assert reasons == [d.status[0].message for d in seen['/diagnostics']]


def test_namespaced_bag_and_topic_overrides(tmp_path):
    """A ros2-bag-like file: namespaced topics, something else recorded beside them."""
    source = tmp_path / 'bag.mcap'
    with RecordingWriter(source) as writer:
        for ns in ('/left', '/right'):
            writer.add_topic(f'{ns}/pose', POSE)
            writer.add_topic(f'{ns}/wrench', WRENCH)
        writer.add_topic('/rosout_like', 'std_msgs/msg/String')
        for k in range(20):
            t = scenarios.T0_NS + k * 5_000_000
            stamp = stamp_msg(t)
            for ns, z in (('/left', 1.25), ('/right', 1.3)):
                if k % 10 == 0:
                    writer.write(f'{ns}/pose', pose_message([0, 0, z], stamp=stamp), t)
                writer.write(f'{ns}/wrench', wrench_message([0, 0, 10.0 * k], stamp=stamp), t + 1)
            writer.write('/rosout_like', String(data='x'), t)
    settings, options = golden_settings()
    with pytest.raises(ReplayError, match='several pose topics .*--pose-topic'):
        replay_offline(source, tmp_path / 'a.mcap', settings, options=options)
    out = tmp_path / 'right.mcap'
    summary = replay_offline(source, out, settings, options=options, pose_topic='right/pose',
                             wrench_topic='/right/wrench')
    assert (summary.poses, summary.wrenches, dict(summary.rejected)) == (2, 20, {})
    info = recording_info(out)
    assert set(info.topics) == {'/right/pose', '/right/wrench', '/right/predicted_displacement',
                                '/right/predicted_pose', '/right/cable_tensions', '/diagnostics'}
    assert leftovers(tmp_path) == []


def test_bag_written_by_rosbags_replays(tmp_path):
    """A rosbag2 bag directory from an independent writer (rosbags, storage mcap, namespaced
    topics, rosbag2's own QoS metadata), given as the directory: the same predictions."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_typestore, Stores

    store = get_typestore(Stores.ROS2_JAZZY)
    bag = tmp_path / 'bag'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {t: writer.add_connection(f'/robot{t}', typ, typestore=store)
                       for t, typ in (('/pose', POSE), ('/wrench', WRENCH))}
        for m in read_messages(golden('step_wrench'), {'pose': POSE, 'wrench': WRENCH},
                               raw=True):
            writer.write(connections[m.topic], m.log_time_ns, m.data)
    settings, options = golden_settings()
    out = tmp_path / 'out.mcap'
    summary = replay_offline(bag, out, settings, options=options)
    assert (summary.pose_topic, summary.wrench_topic) == ('/robot/pose', '/robot/wrench')
    assert set(recording_info(out).topics) >= {'/robot/predicted_displacement',
                                               '/robot/cable_tensions'}
    comparison = compare_outputs(read_predictions(golden('step_wrench')),
                                 read_predictions(out), RTOL)
    assert comparison.ok, str(comparison)


def stamp_msg(t_ns: int):
    from builtin_interfaces.msg import Time
    return Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)


def test_header_stamp_order(tmp_path):
    """--order stamp sorts by header stamp: the late out-of-order messages are accepted."""
    settings, options = golden_settings()
    out = tmp_path / 'by_stamp.mcap'
    summary = replay_offline(golden('invalid_inputs'), out, settings, options=options,
                             order='stamp')
    assert 'pose:stamp' not in summary.rejected and 'wrench:stamp' not in summary.rejected
    assert summary.rejected['pose:frame'] == 1 and summary.rejected['wrench:infeasible'] == 1


def test_interrupted_replay_leaves_no_file(tmp_path):
    settings, options = golden_settings()
    out = tmp_path / 'never.mcap'

    def progress(done, total):
        if done >= 100:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        replay_offline(golden('step_wrench'), out, settings, progress=progress,
                       options=options)
    assert not out.exists() and leftovers(tmp_path) == []


# ----------------------------------------------------------------------------- bad files


def write_inputs(path: Path, topics: dict, n: int = 5) -> None:
    """A small file with the given topic -> type, each with ``n`` default messages."""
    with RecordingWriter(path) as writer:
        for topic, type_name in topics.items():
            writer.add_topic(topic, type_name)
        for k in range(n):
            for topic, type_name in topics.items():
                msg = message_class(type_name)()
                if hasattr(msg, 'header'):
                    msg.header.frame_id = 'world'
                    msg.header.stamp = stamp_msg(scenarios.T0_NS + k * 10**7)
                writer.write(topic, msg, scenarios.T0_NS + k * 10**7)


def test_bad_files_give_one_line_errors_and_no_output(tmp_path, ros_env):
    data = golden('step_wrench').read_bytes()
    files = {}
    chunked = tmp_path / 'chunked.mcap'   # small chunks: a cut file keeps the first ones
    with RecordingWriter(chunked, chunk_size=16384) as writer:
        writer.add_topic('/pose', POSE)
        writer.add_topic('/wrench', WRENCH)
        for m in read_messages(golden('step_wrench'), {'pose': POSE, 'wrench': WRENCH},
                               raw=True):
            writer.write(m.topic, m.data, m.log_time_ns)
    files['truncated'] = tmp_path / 'truncated.mcap'
    cut = chunked.read_bytes()
    files['truncated'].write_bytes(cut[:len(cut) // 2])
    chunked.unlink()
    files['garbage'] = tmp_path / 'garbage.mcap'
    files['garbage'].write_bytes(os.urandom(5000))
    files['empty'] = tmp_path / 'empty.mcap'
    files['empty'].write_bytes(b'')
    corrupt = bytearray(data)
    corrupt[len(data) // 3] ^= 0xFF   # inside a chunk: its CRC no longer matches
    files['corrupt'] = tmp_path / 'corrupt.mcap'
    files['corrupt'].write_bytes(bytes(corrupt))
    files['no_wrench'] = tmp_path / 'no_wrench.mcap'
    write_inputs(files['no_wrench'], {'/pose': POSE})
    files['wrong_type'] = tmp_path / 'wrong_type.mcap'
    write_inputs(files['wrong_type'], {'/pose': POSE, '/wrench': POSE})
    files['missing'] = tmp_path / 'missing.mcap'
    expect = {'truncated': 'incomplete MCAP file', 'garbage': 'not an MCAP file',
              'empty': 'empty', 'corrupt': 'corrupt', 'no_wrench': 'no wrench topic',
              'wrong_type': 'topic /wrench has type geometry_msgs/msg/PoseStamped, expected '
                            'geometry_msgs/msg/WrenchStamped',
              'missing': 'no such file'}
    outputs = tmp_path / 'out'
    outputs.mkdir()
    for label, path in files.items():
        out = outputs / f'{label}.mcap'
        result = replay_cli(path, '--output', out, '--no-progress', env=ros_env)
        err = result.stderr.strip()
        assert result.returncode == 1, (label, result.stdout, err)
        assert err.count('\n') == 0 and 'Traceback' not in err, (label, err)
        assert err.startswith('cdpr_replay: error: ') and expect[label] in err, (label, err)
        assert not out.exists(), label
    assert leftovers(outputs) == []
    # what survives of the truncated file can still be replayed, on request
    out = outputs / 'survivors.mcap'
    result = replay_cli(files['truncated'], '--output', out, '--allow-incomplete',
                        '--no-progress', *GOLDEN_ARGS, env=ros_env)
    assert result.returncode == 0, result.stderr
    assert 0 < recording_info(out).topics['/wrench'].message_count < 400


def test_existing_output_is_kept_unless_force(tmp_path, ros_env):
    target = tmp_path / 'precious.mcap'
    target.write_bytes(b'what the user had')
    result = replay_cli(golden('invalid_inputs'), '--output', target, '--no-progress',
                        env=ros_env)
    assert result.returncode == 1 and 'exists' in result.stderr
    assert result.stderr.strip().count('\n') == 0
    assert target.read_bytes() == b'what the user had'
    same = replay_cli(target, '--output', target, '--force', '--no-progress', env=ros_env)
    assert same.returncode == 1 and 'is the input file' in same.stderr
    result = replay_cli(golden('invalid_inputs'), '--output', target, '--force',
                        '--no-progress', '--method', 'spring', env=ros_env)
    assert result.returncode == 0, result.stderr
    assert recording_info(target).complete and leftovers(tmp_path) == []
    with pytest.raises(RecordingError, match='exists'):
        RecordingWriter(target)


# ----------------------------------------------------------------------------- bad messages


def with_bad_message(path: Path, bad_index: int) -> tuple[list, str]:
    """The golden step_wrench inputs with message ``bad_index`` (in reading order) replaced by
    bytes that do not decode; the inputs as read and the topic of the bad one."""
    inputs = list(read_messages(golden('step_wrench'), {'pose': POSE, 'wrench': WRENCH},
                                raw=True))
    with RecordingWriter(path) as writer:
        writer.add_topic('/pose', POSE)
        writer.add_topic('/wrench', WRENCH)
        for i, m in enumerate(inputs):
            data = b'\x00\x01\x00\x00' + b'\xff' * 8 if i == bad_index else m.data
            writer.write(m.topic, data, m.log_time_ns, m.publish_time_ns)
    return inputs, inputs[bad_index].topic


def test_skip_bad_replays_past_an_undecodable_message(tmp_path, ros_env):
    source = tmp_path / 'one_bad.mcap'
    bad = 123
    inputs, topic = with_bad_message(source, bad)
    assert topic == '/wrench'
    # without --skip-bad: one line naming the message and its topic, no output
    out = tmp_path / 'stopped.mcap'
    result = replay_cli(source, '--output', out, '--no-progress', *GOLDEN_ARGS, env=ros_env)
    err = result.stderr.strip()
    assert result.returncode == 1 and err.count('\n') == 0 and 'Traceback' not in err, err
    assert f'cannot decode message {bad} (a {WRENCH} on /wrench' in err, err
    assert not out.exists() and leftovers(tmp_path) == []
    # with it: every other input replayed, the skip counted and named
    out = tmp_path / 'skipped.mcap'
    result = replay_cli(source, '--output', out, '--no-progress', '--skip-bad', *GOLDEN_ARGS,
                        env=ros_env)
    assert result.returncode == 0, result.stderr
    assert f'skipped 1 undecodable input message(s); the first: {source}: cannot decode ' \
           f'message {bad}' in result.stdout, result.stdout
    wrenches = sum(1 for m in inputs if m.topic == '/wrench')
    assert f'{wrenches - 1} wrenches' in result.stdout
    kept = [m.data for m in read_messages(out, {'pose': POSE, 'wrench': WRENCH}, raw=True)]
    assert kept == [m.data for i, m in enumerate(inputs) if i != bad]
    assert recording_info(out).topics['/predicted_displacement'].message_count == wrenches - 1
    # the library call counts the same
    settings, options = golden_settings()
    summary = replay_offline(source, tmp_path / 'api.mcap', settings, options=options,
                             skip_bad=True)
    assert summary.skipped == 1 and summary.wrenches == wrenches - 1


def file_messages(path: Path) -> list:
    """(topic, log time, publish time, bytes) of every message, in file order, read with the
    mcap library's own reader."""
    with open(path, 'rb') as stream:
        reader = make_reader(stream, validate_crcs=True)
        return [(channel.topic, m.log_time, m.publish_time, m.data)
                for _, channel, m in reader.iter_messages(log_time_order=False)]


@pytest.fixture(scope='module')
def minute_log(tmp_path_factory) -> tuple[Path, list]:
    """60 s of 1 kHz wrenches and 50 Hz poses (63 000 inputs: a replay of seconds), and the
    messages of its uninterrupted replay with the golden settings, by the tool as the replays
    compared with it (the BLAS thread count changes fem's runs in the modes in the last bits:
    the tool takes one thread, this process may have more)."""
    folder = tmp_path_factory.mktemp('minute')
    source = folder / 'minute.mcap'
    scenarios.write_long_log(source, 60.0)
    reference = folder / 'reference.mcap'
    done = replay_cli(source, '--output', reference, '--no-progress', *GOLDEN_ARGS,
                      timeout=300)
    assert done.returncode == 0, done.stderr
    return source, file_messages(reference)


def start_replay(source: Path, out: Path, env: dict, *extra) -> subprocess.Popen:
    """``cdpr_replay`` (the console script a user runs) of ``source`` into ``out``."""
    return subprocess.Popen([installed('cdpr_replay'), str(source), '--output',
                             str(out), '--no-progress', *GOLDEN_ARGS, *extra], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def partial_size(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.iterdir() if '.partial-' in p.name)


def signal_mid_replay(source: Path, out: Path, env: dict, sig, written: int) -> tuple:
    """A CLI replay of ``source`` sent ``sig`` once its partial output holds ``written``
    bytes: (process, stdout, stderr) once it has ended."""
    proc = start_replay(source, out, env)
    try:
        wait_until(lambda: partial_size(out.parent) > written or proc.poll() is not None, 120,
                   'the replay to write its first chunks')
        assert proc.poll() is None, 'the replay ended before the signal'
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc, stdout, stderr


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM, signal.SIGKILL],
                         ids=['SIGINT', 'SIGTERM', 'SIGKILL'])
def test_interrupted_replay_resumes_to_the_uninterrupted_output(sig, minute_log, tmp_path,
                                                                ros_env):
    """A signal mid-replay leaves no output but its partial file; --resume continues it to
    the output an uninterrupted replay writes, message for message."""
    source, reference = minute_log
    out = tmp_path / 'never.mcap'
    proc, stdout, stderr = signal_mid_replay(source, out, ros_env, sig, 1_500_000)
    kept = leftovers(tmp_path)
    assert len(kept) == 1, (proc.returncode, kept, stderr[-3000:])
    partial = kept[0]
    assert not out.exists()
    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL
    else:
        assert proc.returncode == 130, (stdout, stderr)
        err = stderr.strip()
        assert err.count('\n') == 0, err
        assert err.startswith('cdpr_replay: error: interrupted after '), err
        assert f'{partial} is kept: --resume continues it; no output written' in err, err
    result = replay_cli(source, '--output', out, '--no-progress', '--resume', *GOLDEN_ARGS,
                        env=ros_env, timeout=300)
    assert result.returncode == 0, result.stderr
    assert f'resumed {tmp_path / partial}: kept its output of ' in result.stdout, result.stdout
    # Ctrl-C and SIGTERM leave a checkpoint: the written inputs are not predicted again
    how = 'predicted again' if sig == signal.SIGKILL else 'continued from its checkpoint'
    assert how in result.stdout, result.stdout
    assert leftovers(tmp_path) == []
    resumed = file_messages(out)
    assert len(resumed) == len(reference)
    if sig == signal.SIGKILL:
        # the written inputs predicted again one at a time, where the uninterrupted replay
        # stepped fem's runs in the model's modes (a different order of the same arithmetic):
        # its state, and the predictions after it, equal to round-off
        assert predictions_off_by(resumed, reference) <= 1e-9
    else:
        assert sorted(resumed) == sorted(reference)


def test_a_killed_replays_partial_output_is_named_and_removed(minute_log, tmp_path, ros_env):
    source, reference = minute_log
    out = tmp_path / 'out.mcap'
    signal_mid_replay(source, out, ros_env, signal.SIGKILL, 500_000)
    [partial] = leftovers(tmp_path)
    size = (tmp_path / partial).stat().st_size
    # the file a running writer holds is not a leftover
    running = RecordingWriter(out)
    assert partial_files(out) == [tmp_path / partial]
    running.abort()
    result = replay_cli(source, '--output', out, '--no-progress', *GOLDEN_ARGS, env=ros_env,
                        timeout=300)
    assert result.returncode == 0, result.stderr
    assert (f'cdpr_replay: removed {tmp_path / partial} ({size} bytes), the partial output of '
            'an interrupted replay') in result.stdout, result.stdout
    assert sorted(file_messages(out)) == sorted(reference) and leftovers(tmp_path) == []
    nothing = replay_cli(source, '--output', tmp_path / 'fresh.mcap', '--resume',
                         '--no-progress', env=ros_env)
    assert nothing.returncode == 1 and 'nothing to resume' in nothing.stderr


# ----------------------------------------------------------------------------- long logs

BOUNDED = """
import os, resource, sys
from cdpr_dynamics.recording.replay import load_replay_config, replay_offline
source, warm_up, output, config, order, incomplete, headroom = sys.argv[1:8]
settings, options, _ = load_replay_config(config)
# a short replay first: imports, BLAS buffers and the model's arrays are there before the limit
replay_offline(warm_up, output, settings, 'spring', options=options, force=True,
               order='log' if order == 'hold' else order)
with open('/proc/self/status') as status:
    size = next(int(line.split()[1]) * 1024 for line in status if line.startswith('VmSize:'))
limit = size + int(headroom)
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
if order == 'hold':      # the control: what holding the input in memory needs
    with open(source, 'rb') as stream:
        data = stream.read()
    sys.exit(0)
summary = replay_offline(source, output, settings, 'spring', options=options, order=order,
                         allow_incomplete=incomplete == '1', force=True)
print(summary.poses_accepted, summary.wrenches_accepted, summary.salvage.lines())
"""
HEADROOM = 64 * 2**20


@pytest.mark.parametrize('order, incomplete', [('log', False), ('stamp', False),
                                               ('log', True)],
                         ids=['log', 'stamp', 'allow-incomplete'])
def test_a_log_larger_than_the_memory_allowed_replays(order, incomplete, tmp_path,
                                                      big_log, ros_env):
    """A child limits its address space to what it has after a short replay plus 64 MiB, and
    replays a 230 MB log (207 MB cut) in each mode: every input predicted. Holding the log's
    bytes alone fails under the same limit."""
    source, warm_up, config, poses, wrenches = big_log
    if incomplete:   # a recorder killed at 90 %: no summary, the last chunk cut
        cut = tmp_path / 'cut.mcap'
        with open(source, 'rb') as full, open(cut, 'wb') as out:
            out.write(full.read(int(source.stat().st_size * 0.9)))
        expected = None
        source = cut
    else:
        expected = f'{poses} {wrenches} []'

    def child(mode: str, output: Path) -> subprocess.CompletedProcess:
        return subprocess.run(
            [PYTHON, '-c', BOUNDED, str(source), str(warm_up), str(output), str(config), mode,
             '1' if incomplete else '0', str(HEADROOM)],
            env={**ros_env, 'OPENBLAS_NUM_THREADS': '1', 'MALLOC_ARENA_MAX': '1'},
            capture_output=True, text=True, timeout=600)

    assert source.stat().st_size > 3 * HEADROOM
    control = child('hold', tmp_path / 'out.mcap')
    assert control.returncode != 0 and 'MemoryError' in control.stderr, control
    result = child(order, tmp_path / 'out.mcap')
    assert result.returncode == 0, result.stderr[-2000:]
    if expected is not None:
        assert result.stdout.strip() == expected
    else:
        accepted = [int(v) for v in result.stdout.split()[:2]]
        info = recording_info(source)
        assert accepted == [info.topics['/pose'].message_count,
                            info.topics['/wrench'].message_count]
        assert 0.8 * wrenches < accepted[1] < wrenches
    out = recording_info(tmp_path / 'out.mcap')
    assert out.topics['/predicted_displacement'].message_count == \
        out.topics['/wrench'].message_count


@pytest.fixture(scope='module')
def big_log(tmp_path_factory):
    """A 230 MB log (135 s of 1 kHz wrenches and 50 Hz poses, every message carrying a
    1500-character frame id), 1 s of the same for a warm-up, the config naming that frame, its
    pose and wrench counts."""
    folder = tmp_path_factory.mktemp('big')
    frame = 'cdpr_frame_' + 'x' * 1489
    params = yaml.safe_load(CONFIG.read_text())
    params['/**']['ros__parameters']['robot']['frame_id'] = frame
    config = folder / 'long_frame.yaml'
    config.write_text(yaml.safe_dump(params))
    source = folder / 'big.mcap'
    written = scenarios.write_long_log(source, 135.0, frame_id=frame)
    warm_up = folder / 'warm_up.mcap'
    scenarios.write_long_log(warm_up, 1.0, frame_id=frame)
    return source, warm_up, config, written.topics['/pose'], written.topics['/wrench']


# ----------------------------------------------------------------------------- garbage


def test_bytes_of_another_type_are_refused_or_skipped(tmp_path, ros_env):
    """A wrench channel carrying PoseStamped bytes: refused with one line naming the message,
    or every one skipped and counted with --skip-bad; none is predicted."""
    source = tmp_path / 'poses_as_wrenches.mcap'
    with RecordingWriter(source) as writer:
        writer.add_topic('/pose', POSE)
        writer.add_topic('/wrench', WRENCH)
        for k in range(2000):
            t = scenarios.T0_NS + k * 10**6
            if k % 20 == 0:
                writer.write('/pose', pose_message((0.05, 0.0, 1.25), stamp=stamp_msg(t),
                                                   frame_id='world'), t)
            writer.write('/wrench', pose_message((1.0, 2.0, 3.0), stamp=stamp_msg(t + 1),
                                                 frame_id='world'), t + 1)
    out = tmp_path / 'out.mcap'
    result = replay_cli(source, '--output', out, '--no-progress', env=ros_env)
    err = result.stderr.strip()
    assert result.returncode == 1 and err.count('\n') == 0 and 'Traceback' not in err, err
    assert (f'cannot decode message 1 (a {WRENCH} on /wrench at log time '
            f'{scenarios.T0_NS + 1}): 80 bytes of data, a {WRENCH} with this frame_id ends '
            'after 72 (the bytes are of another type)') in err, err
    assert not out.exists()
    result = replay_cli(source, '--output', out, '--no-progress', '--skip-bad', env=ros_env)
    assert result.returncode == 0, result.stderr
    assert 'skipped 2000 undecodable input message(s)' in result.stdout
    assert '0 wrenches (0 predictions)' in result.stdout
    info = recording_info(out)
    assert info.topics['/wrench'].message_count == 0
    assert info.topics['/predicted_displacement'].message_count == 0
    with pytest.raises(RecordingError, match='the bytes are of another type'):
        list(read_messages(source, ['wrench']))


# ----------------------------------------------------------------------------- live


@pytest.fixture
def procs(ros_env, output_dir):
    """Processes on a domain id reserved through node_process's lock files, which cdpr_demo
    and the benchmark use too: their traffic must not land in these recordings."""
    from cdpr_dynamics.ros.process import reserve_domain_id
    with reserve_domain_id() as domain:
        env = dict(ros_env, ROS_DOMAIN_ID=str(domain.domain_id))
        p = Processes(env, output_dir)
        yield p
        p.stop_all()


def test_live_replay_keeps_the_recorded_timing(procs, output_dir):
    """cdpr_replay --live to a subscriber in another process (cdpr_record): every message,
    unchanged, with the recorded spacing divided by --rate."""
    rate = 2.0
    source = golden('step_wrench')
    path = output_dir / 'live.mcap'
    recorder = procs.start('cdpr_record', [PYTHON, '-m', 'cdpr_dynamics.cli.record',
                                           '--output', path, '--topics', 'pose', 'wrench'])
    replay = procs.start('cdpr_replay', [PYTHON, '-m', 'cdpr_dynamics.cli.replay', source,
                                         '--live', '--rate', rate, '--no-progress'])
    replay.wait(timeout=90)
    out = finish(replay)
    assert 'published 440 of 440 messages' in out, out
    wait_until(lambda: counts_so_far(path) == {'/pose': 40, '/wrench': 400}, 20,
               f'the recording to hold everything (has {counts_so_far(path)})')
    finish(recorder)

    topics = {'pose': POSE, 'wrench': WRENCH}
    sent = list(read_messages(source, topics, raw=True))
    got = list(read_messages(path, topics, raw=True))
    for topic in ('/pose', '/wrench'):   # in order on each topic (not across topics: the
        assert [m.data for m in got if m.topic == topic] == \
            [m.data for m in sent if m.topic == topic]   # recorder takes them as it likes)
    recorded = np.array([m.log_time_ns for m in sent]) * 1e-9
    arrived = np.array([m.log_time_ns for m in got]) * 1e-9
    span_want = (recorded[-1] - recorded[0]) / rate
    span = arrived[-1] - arrived[0]
    gaps = np.diff(arrived)
    wrench_gaps = np.diff(arrived[[m.topic == '/wrench' for m in got]])
    print(f'\nlive replay at rate {rate:g}: {len(got)} messages over {span:.3f} s '
          f'(recorded {span_want:.3f} s at this rate); wrench inter-arrival median '
          f'{np.median(wrench_gaps) * 1e3:.2f} ms (recorded {5 / rate:.2f} ms), '
          f'p99 {np.percentile(wrench_gaps, 99) * 1e3:.2f} ms')
    assert span == pytest.approx(span_want, rel=0.25)
    assert np.median(wrench_gaps) == pytest.approx(0.005 / rate, rel=0.4)
    assert gaps.min() >= 0


def node_order(recording: Path, source: Path) -> tuple[list, int, int]:
    """The inputs of ``source`` in the order the node processed them, how many it took before
    one that arrived earlier, and how many it never processed (dropped on the way).

    The node publishes an output right after processing each accepted input (cable_tensions:
    pose, predicted_displacement: wrench), and the recorder keeps each message's DDS source
    timestamp as its publish time: sorting the outputs by it gives the node's order. An input
    the offline replay accepted (``source`` has an output for it) without an output from the
    node never reached it. The inputs the replay rejected (no output: they leave the state
    alone) keep their place in the arrival order, moved only as far as needed to stay between
    their neighbours on their own topic, which each subscription delivers in order: that is
    all their rejection depends on (an out-of-order stamp).
    """
    inputs = [(m.topic, stamp_to_ns(m.message.header.stamp))
              for m in read_messages(source, {'pose': POSE, 'wrench': WRENCH})]
    kind = {'/cable_tensions': '/pose', '/predicted_displacement': '/wrench'}
    outputs = {(kind[m.topic], stamp_to_ns(m.message.header.stamp)): m.publish_time_ns
               for m in read_messages(source, list(kind), raw=True)}
    done = sorted((m.publish_time_ns, (kind[m.topic], stamp_to_ns(m.message.header.stamp)))
                  for m in read_messages(recording, list(kind), raw=True))
    wanted = set(inputs)
    processed = [key for _, key in done if key in wanted]
    position = {key: i for i, key in enumerate(inputs)}
    flips = sum(1 for a, b in zip(processed, processed[1:]) if position[b] < position[a])
    seen = set(processed)
    dropped = {key for key in inputs if key in outputs and key not in seen}
    kept = [key for key in inputs if key not in dropped]
    rest = iter(processed)       # the processed inputs fill the slots of processed inputs
    order = [next(rest) if key in seen else key for key in kept]
    for topic in ('/pose', '/wrench'):
        same = [key for key in kept if key[0] == topic]       # delivery order on the topic
        for i, key in enumerate(same):
            if key in seen:
                continue
            at = order.index(key)
            before = [order.index(k) for k in same[:i]]
            after = [order.index(k) for k in same[i + 1:]]
            if before and max(before) > at:
                order.remove(key)
                order.insert(max(before), key)   # right after the last one before it
            elif after and min(after) < at:
                order.remove(key)
                order.insert(min(after), key)    # right before the first one after it
    return order, flips, len(dropped)


def write_in_order(source: Path, order: list, path: Path) -> None:
    """``source``'s pose and wrench messages in the given order (log times 1 us apart)."""
    raw = {(m.topic, stamp_to_ns(m.message.header.stamp)): m
           for m in read_messages(source, {'pose': POSE, 'wrench': WRENCH}, raw=True)}
    with RecordingWriter(path) as writer:
        writer.add_topic('/pose', POSE)
        writer.add_topic('/wrench', WRENCH)
        for i, key in enumerate(order):
            writer.write(key[0], raw[key].data, scenarios.T0_NS + 1000 * i)


def node_settled(path: Path, since_ns: int) -> bool:
    """True once the recording holds a /diagnostics message the node sent after ``since_ns``
    and as many predictions as the wrenches it says it accepted (it publishes them at least
    once a second): the node has answered everything that reached it."""
    try:
        accepted, predictions = None, 0
        for m in read_messages(path, ['/diagnostics', 'predicted_displacement'],
                               allow_incomplete=True, raw=True):
            if m.topic != '/diagnostics':
                predictions += 1
            elif m.publish_time_ns >= since_ns:
                for status in m.message.status:
                    if status.name.endswith('wrench input'):
                        accepted = int({kv.key: kv.value for kv in status.values}['accepted'])
    except (RecordingError, KeyError, ValueError):
        return False
    return accepted is not None and predictions >= accepted


def node_ready(path: Path) -> bool:
    counts = counts_so_far(path)
    return counts.get('/cable_tensions', 0) >= 1 and counts.get('/diagnostics', 0) >= 1


def dynamics_node_available() -> str:
    try:
        from cdpr_dynamics.ros import process as node_process
    except ImportError as exc:
        return f'cdpr_dynamics.ros.process: {exc}'
    command = node_process.node_command()
    if command[0] == sys.executable:
        return '' if (REPO / 'cdpr_dynamics' / 'node.py').exists() else 'no node.py'
    return ''


@pytest.mark.parametrize('name', ['trajectory_harmonic', 'invalid_inputs'])
def test_replay_through_the_node_matches_golden(name, procs, output_dir):
    """dynamics_node fed by cdpr_replay --live, everything recorded by cdpr_record: the node's
    predictions match the golden ones (the node is the same code as the offline replay)."""
    missing = dynamics_node_available()
    if missing:
        pytest.skip(f'dynamics_node not available: {missing}')
    from cdpr_dynamics.ros import process as node_process
    path = output_dir / 'node.mcap'
    node = procs.start('dynamics_node', node_process.node_command() + [
        '--ros-args', '--params-file', CONFIG,
        '-p', f'model.method:={scenarios.GOLDEN["method"]}',
        '-p', f'model.elements_per_cable:={scenarios.GOLDEN["elements_per_cable"]}'])
    recorder = procs.start('cdpr_record', [PYTHON, '-m', 'cdpr_dynamics.cli.record',
                                           '--output', path])
    wait_until(lambda: node_ready(path) or node.poll() is not None, 60,
               'the recorder to hear the node (its latched cable_tensions)')
    assert node.poll() is None, node.logs[1].read_text()
    reference = read_predictions(golden(name))
    replay = procs.start('cdpr_replay', [PYTHON, '-m', 'cdpr_dynamics.cli.replay',
                                         golden(name), '--live', '--subscribers', 2,
                                         '--no-progress'])
    replay.wait(timeout=120)
    finish(replay)
    replay_done_ns = time.time_ns()
    wait_until(lambda: node_settled(path, replay_done_ns), 30,
               f'every prediction of the node recorded (recording has {counts_so_far(path)})')
    finish(recorder)
    finish(node)
    fresh = read_predictions(path, diagnostics_source=None)
    order, flips, dropped = node_order(path, golden(name))
    if flips or dropped:
        # Under load the node's executor may take a pose before a wrench that arrived first
        # (both ready: no order across subscriptions), and a stalled node loses best-effort
        # inputs. Then the golden sequence is not what the node computed: replay offline what
        # the node saw, in its order, and hold the node to that with the same RTOL.
        reordered = output_dir / 'in_node_order.mcap'
        write_in_order(golden(name), order, reordered)
        settings, options = golden_settings()
        expected = output_dir / 'expected_in_node_order.mcap'
        replay_offline(reordered, expected, settings, options=options)
        reference = read_predictions(expected)
    comparison = compare_outputs(reference, fresh, RTOL, diagnostics=False, extra_ok=True)
    assert comparison.ok, (f'{comparison} ({flips} inputs taken out of arrival order, '
                           f'{dropped} never processed)')
    assert flips + dropped <= 0.2 * len(order), 'the node lost or reordered too many inputs'
    info = recording_info(path)
    print(f'\n{name} through dynamics_node: {comparison}; {flips} inputs taken out of '
          f'arrival order, {dropped} never processed; recorded '
          + ', '.join(f'{t} {i.message_count}' for t, i in sorted(info.topics.items())))
    if reference.rejected:   # the node's diagnostics count each kind of rejection it saw
        counts = {}
        for item in read_messages(path, ['/diagnostics']):
            for status in item.message.status:
                for what in ('pose', 'wrench'):
                    if status.name.endswith(f'{what} input'):
                        counts.update({(what, kv.key[len('rejected_'):]): int(kv.value)
                                       for kv in status.values
                                       if kv.key.startswith('rejected_')})
        for what, kind in {(w, k) for (w, _), (k, _) in reference.rejected.items()}:
            assert counts.get((what, kind), 0) >= 1, (what, kind, counts)


# ----------------------------------------------------------------------------- slack


@pytest.mark.slow
def test_slack_aware_replay_gives_the_analyze_numbers(tmp_path):
    """The paper's 1500 N at 5 Hz as a 1 kHz wrench stream (the wrench stamped t_k carries the
    load at t_k + dt, as cdpr_analyze's history steps): cdpr_replay's predictions are
    harmonic_history's (the function behind cdpr_analyze --slack-aware) to round-off."""
    import math

    from builtin_interfaces.msg import Time

    from cdpr_dynamics.analysis.live import harmonic_history

    settings, _ = golden_settings(method='spring')
    dt_ns = 1_000_000
    steps = 400
    source = tmp_path / 'paper_5hz.mcap'
    with RecordingWriter(source) as writer:
        writer.add_topic('/pose', POSE, scenarios.QOS)
        writer.add_topic('/wrench', WRENCH, scenarios.QOS)
        before = scenarios.T0_NS - dt_ns                   # the initial pose: no rebuild
        writer.write('/pose', pose_message(settings.initial_position_m, (0.0, 0.0, 0.0, 1.0),
                                           'world', Time(sec=before // 10**9,
                                                         nanosec=before % 10**9)), before)
        for k in range(steps + 1):
            stamp = scenarios.T0_NS + k * dt_ns
            load = 1500.0 * math.sin(2 * math.pi * 5.0 * (k + 1) * dt_ns * 1e-9)
            writer.write('/wrench', wrench_message(
                (0.0, 0.0, load), (0.0, 0.0, 0.0), 'world',
                Time(sec=stamp // 10**9, nanosec=stamp % 10**9)), stamp)
    out = replay_cli(source, '--output', tmp_path / 'aware.mcap', '--config', CONFIG,
                     '--method', 'spring')
    assert out.returncode == 0, out.stderr
    got = read_predictions(tmp_path / 'aware.mcap')
    replayed = np.array([got.displacement[scenarios.T0_NS + k * dt_ns]
                         for k in range(steps + 1)])
    expected = harmonic_history(settings, 5.0, steps * dt_ns * 1e-9)
    assert expected.slack.any()
    peak = np.abs(expected.u).max()
    # two orders of the same arithmetic (the replay's runs, the history's steps) through slack
    # switches: their round-off depends on the CPU's vector kernels (4.5e-12 of the peak on
    # an AMD EPYC)
    assert np.abs(replayed - expected.u[:, :3]).max() <= 1e-10 * peak
    linear = harmonic_history(settings, 5.0, steps * dt_ns * 1e-9, slack='linear')
    assert np.abs(replayed - linear.u[:, :3]).max() > 0.1 * peak


@pytest.mark.slow
def test_a_replay_that_lacks_the_pose_before_a_wrench_says_so(tmp_path):
    """A recording that missed the pose the live node had (published before the recorder
    subscribed) replays at robot.initial_position: the replay warns, naming the pose topic,
    with how many predictions it concerns; a file with a pose first has no warning."""
    settings, options = golden_settings()

    def replay(poses_from: int | None, name: str):
        path = tmp_path / f'{name}.mcap'
        with RecordingWriter(path) as writer:
            writer.add_topic('/pose', POSE)
            writer.add_topic('/wrench', WRENCH)
            for k in range(5):
                t = scenarios.T0_NS + k * 10**7
                if poses_from is not None and k >= poses_from:
                    writer.write('/pose', pose_message([0.0, 0.0, 1.25], [0.0, 0.0, 0.0, 1.0],
                                                       'world', stamp_msg(t)), t)
                writer.write('/wrench', wrench_message([0.0, 0.0, 5.0], stamp=stamp_msg(t + 1)),
                             t + 1)
        return replay_offline(path, tmp_path / f'{name}_out.mcap', settings, options=options)

    assert replay(0, 'pose_first').warnings == []
    late, = replay(3, 'pose_late').warnings
    assert late.startswith('3 of 5 wrench(es) came before the first pose on /pose: ')
    missing, = replay(None, 'no_pose').warnings
    assert missing.startswith('no pose on /pose: ') and 'robot.initial_position' in missing
    done = replay_cli(tmp_path / 'pose_late.mcap', '--output', tmp_path / 'cli.mcap',
                      *GOLDEN_ARGS, '--no-progress')
    assert done.returncode == 0, done.stderr
    assert f'cdpr_replay: warning: {late}' in done.stderr.splitlines()


# ----------------------------------------------------------------------------- runs


def predictions_off_by(messages: list, reference: list) -> float:
    """The largest difference of the predictions (predicted_displacement, and the
    predicted_pose's position and quaternion) in ``messages`` from those in ``reference``
    (:func:`file_messages` of two files) over the reference's peak |displacement|, once every
    message is checked to be the reference's (topic, log and publish time) and every other
    message's bytes equal."""
    from geometry_msgs.msg import PoseStamped, Vector3Stamped
    from rclpy.serialization import deserialize_message

    def key(message):
        return message[:3]
    mine, theirs = sorted(messages, key=key), sorted(reference, key=key)
    assert [key(m) for m in mine] == [key(m) for m in theirs]
    differ = {m[0] for m, t in zip(mine, theirs) if m[3] != t[3]}
    assert differ <= {'/predicted_displacement', '/predicted_pose'}, differ

    def numbers(data: bytes, topic: str) -> np.ndarray:
        if topic == '/predicted_displacement':
            v = deserialize_message(data, Vector3Stamped).vector
            return np.array([v.x, v.y, v.z])
        pose = deserialize_message(data, PoseStamped).pose
        p, q = pose.position, pose.orientation
        return np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
    peak = max(np.abs(numbers(t[3], t[0])).max() for t in theirs
               if t[0] == '/predicted_displacement')
    largest = max((np.abs(numbers(m[3], m[0]) - numbers(t[3], t[0])).max()
                   for m, t in zip(mine, theirs) if m[3] != t[3]), default=0.0)
    return largest / peak


def mixed_log(path: Path, position) -> None:
    """600 wrenches at 1 kHz (200 N at 5 Hz, a 40-wrench 1500 N push that slackens cables)
    with refused ones among them (not finite, out of order, another frame, unstamped,
    infeasible), and a pose every 20 wrenches: the same pose, one that moves, one refused, and
    back."""
    from builtin_interfaces.msg import Time

    def stamp(ns: int) -> Time:
        return Time(sec=ns // 10**9, nanosec=ns % 10**9)

    t0 = scenarios.T0_NS
    moved = np.asarray(position) + (0.01, 0.0, 0.0)
    with RecordingWriter(path) as writer:
        writer.add_topic('/pose', POSE, scenarios.QOS)
        writer.add_topic('/wrench', WRENCH, scenarios.QOS)
        writer.write('/pose', pose_message(position, (0.0, 0.0, 0.0, 1.0), 'world',
                                           stamp(t0 - 1000)), t0 - 1000)
        for k in range(600):
            ns = t0 + k * 1_000_000
            load = 1500.0 if 300 <= k < 340 else 200.0 * np.sin(2 * np.pi * 5.0 * k * 1e-3)
            frame, at = 'world', ns
            load, at, frame = {50: (float('nan'), at, frame), 60: (load, ns - 3_000_000, frame),
                               70: (load, at, 'other'), 80: (load, 0, frame),
                               90: (1e7, at, frame)}.get(k, (load, at, frame))
            writer.write('/wrench', wrench_message((0.0, 0.0, load), (0.0, 0.0, 0.0), frame,
                                                   stamp(at)), ns)
            if k % 20 == 10:
                where, quaternion = {210: (moved, (0.0, 0.0, 0.0, 1.0)),
                                     230: (moved, (0.0, 0.0, 0.0, 2.0))}.get(
                    k, (moved if 210 < k < 400 else position, (0.0, 0.0, 0.0, 1.0)))
                writer.write('/pose', pose_message(where, quaternion, 'world', stamp(ns)), ns)


@pytest.mark.parametrize('source, method', [('mixed', 'spring'), ('mixed', 'fem'),
                                            ('mixed', 'heavy_sag_6dof'),
                                            *((name, 'fem') for name in scenarios.SCENARIOS)])
def test_runs_write_what_one_input_at_a_time_writes(source, method, tmp_path, monkeypatch):
    """Runs of inputs replayed at once (the default) write the file that replaying one input
    message at a time writes, byte for byte: every golden scenario's inputs and a log with
    refused wrenches and poses amid the runs, a pose that moves the model and a push that
    slackens cables (slack-aware steps in the middle of a run), on the paper robot and on a
    6-DOF platform (fem_sag, predictions at a point off the centroid). Where runs step in the
    model's modes (fem: HeldLoadSteps.run), a different order of the same arithmetic, the
    predictions are equal to round-off (1e-9 of the peak |u|) and every other byte equal."""
    from cdpr_dynamics.analysis.live import LivePredictor
    from cdpr_dynamics.dynamics.held_load import HeldLoadSteps
    from cdpr_dynamics.recording import replay

    if method == 'heavy_sag_6dof':
        settings, _, _ = load_replay_config(REPO / 'config' / f'{method}.yaml')
        options = NodeOptions(output_point_m=(0.05, -0.02, 0.1))
    else:
        settings, options = golden_settings(method=method)
    if source == 'mixed':
        path = tmp_path / 'mixed.mcap'
        mixed_log(path, settings.initial_position_m)
    else:
        path = golden(source)
    counts = {'run': 0, 'slack': 0, 'modes': 0}
    wrench_run, enter_slack = replay.InputHandler.wrench_run, LivePredictor._enter_slack
    modal_run = HeldLoadSteps.run

    def counted_modes(self, *args):
        counts['modes'] += 1
        return modal_run(self, *args)

    def counted_run(self, *args):
        done, q = wrench_run(self, *args)
        counts['run'] += done
        return done, q

    def counted_slack(self, *args, **kwargs):
        counts['slack'] += 1
        return enter_slack(self, *args, **kwargs)
    monkeypatch.setattr(replay.InputHandler, 'wrench_run', counted_run)
    monkeypatch.setattr(LivePredictor, '_enter_slack', counted_slack)
    monkeypatch.setattr(HeldLoadSteps, 'run', counted_modes)
    (tmp_path / 'runs').mkdir()
    (tmp_path / 'single').mkdir()
    runs = replay_offline(path, tmp_path / 'runs' / 'out.mcap', settings, options=options)
    assert counts['run'] > runs.wrenches_accepted / 3     # most went in runs
    if source == 'mixed':
        assert counts['slack'] and runs.rebuilds == 2 and runs.poses_accepted < runs.poses
        assert runs.wrenches - runs.wrenches_accepted >= 5
    monkeypatch.setattr(replay, 'RUN_INPUTS', 1)
    counts['run'] = 0
    single = replay_offline(path, tmp_path / 'single' / 'out.mcap', settings, options=options)
    assert counts['run'] == 0
    assert (runs.rejected, runs.wrenches_accepted) == (single.rejected, single.wrenches_accepted)
    files = tmp_path / 'runs' / 'out.mcap', tmp_path / 'single' / 'out.mcap'
    if method != 'fem':
        assert counts['modes'] == 0
    if method == 'fem':       # runs in the modes: the steps' numbers to round-off
        assert counts['modes']
        off_by = predictions_off_by(*map(file_messages, files))
        print(f'\n{source} {method}: predictions off by {off_by:.2g} x peak |u|')
        assert off_by <= 1e-9
    else:
        assert files[0].read_bytes() == files[1].read_bytes()


def test_an_underactuated_robot_replays_as_the_live_predictor_runs(tmp_path):
    """suspended_3cable (three cables over pulleys, a 6-DOF platform hanging below them): poses
    that are not equilibria and a push, replayed, give what LivePredictor gives on the same
    inputs (the node's core), at the equilibria of the poses' cable lengths."""
    from builtin_interfaces.msg import Time

    from cdpr_dynamics.analysis.config import load_settings
    from cdpr_dynamics.analysis.live import LivePredictor

    config = REPO / 'config' / 'suspended_3cable.yaml'
    settings = load_settings(config)
    predictor = LivePredictor(settings)
    t0 = scenarios.T0_NS
    source = tmp_path / 'hanging.mcap'
    expected = {}
    with RecordingWriter(source) as writer:
        writer.add_topic('/pose', POSE, scenarios.QOS)
        writer.add_topic('/wrench', WRENCH, scenarios.QOS)
        for k in range(300):
            ns = t0 + k * 1_000_000
            stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            if k % 100 == 0:
                where = np.add(settings.initial_position_m, (0.02 * k / 100, -0.01, 0.0))
                writer.write('/pose', pose_message(where, (0.0, 0.0, 0.0, 1.0), 'world', stamp),
                             ns)
                predictor.update_pose(where)
                assert predictor.eq.balance is not None
            force = (3.0 if k < 150 else 0.0, 0.0, 0.0)
            writer.write('/wrench', wrench_message(force, (0.0, 0.0, 0.0), 'world', stamp), ns)
            expected[ns] = predictor.advance(ns, force, (0.0, 0.0, 0.0))
    assert predictor.eq.balance.far          # the last pose settled away from where it was sent
    out = replay_cli(source, '--output', tmp_path / 'out.mcap', '--config', config)
    assert out.returncode == 0, out.stderr
    got = read_predictions(tmp_path / 'out.mcap')
    assert set(got.displacement) == set(expected)
    peak = max(np.abs(u).max() for u in expected.values())
    assert peak > 1e-4
    for ns, u in expected.items():
        np.testing.assert_allclose(got.displacement[ns], u[:3], rtol=0, atol=1e-9 * peak)
