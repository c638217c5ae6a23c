"""cdpr_markers (msg_adapters.markers): geometry equals the model's, colours, stable ids; the
message through the MCAP recorder (project reader, rosbags, Foxglove's own decoder)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from visualization_msgs.msg import Marker

from cdpr_dynamics.analysis.pipeline import equilibrium, geometry_summary
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.recording.cdr import serialize
from cdpr_dynamics.recording.reader import read_messages
from cdpr_dynamics.recording.writer import RecordingWriter
from cdpr_dynamics.mechanics.robot import quaternion_to_matrix
from msg_adapters.joint_state import tensions_message
from msg_adapters.displacement import displacement_message
from msg_adapters.markers import (equilibrium_markers, markers_message, plot_markers,
                                  robot_shape, tension_colours, update_arrow)
from msg_adapters.validation import ns_to_stamp

REPO = Path(__file__).resolve().parents[1]
HEAVY = REPO / 'config' / 'heavy_sag_6dof.yaml'
PAPER = REPO / 'config' / 'paper_cdpr.yaml'
NPM_PACKAGES = ['@mcap/core', '@foxglove/rosmsg', '@foxglove/rosmsg2-serialization']


@pytest.fixture(scope='module')
def heavy():
    settings = load_settings(HEAVY)
    assert settings.method == 'fem_sag'
    return settings, equilibrium(settings, method='fem_sag')


def points(marker) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in marker.points]).reshape(-1, 3)


def by_ns(array, ns: str) -> list:
    return [m for m in array.markers if m.ns == ns]


@pytest.mark.parametrize('config', [HEAVY, PAPER], ids=['heavy_sag_fem_sag', 'paper_fem'])
def test_cable_lines_end_at_attachment_and_anchor(config):
    settings = load_settings(config)
    eq = equilibrium(settings, method=settings.method)
    cables = by_ns(equilibrium_markers(settings, eq), 'cables')
    assert [m.id for m in cables] == list(range(settings.robot.n_cables))
    # independent: p + R b_i from the config's attachments, the anchors as configured
    p, rot = settings.initial_position_m, settings.initial_rotation
    attachment = p + settings.robot.attachments_m @ rot.T
    for i, m in enumerate(cables):
        line = points(m)
        assert m.type == Marker.LINE_STRIP and len(line) > 2
        np.testing.assert_allclose(line[0], attachment[i], atol=1e-9)
        np.testing.assert_allclose(line[-1], settings.robot.anchors_m[i], atol=1e-6)
    if eq.statics != 'sag':       # straight: every point on the chord
        for i, m in enumerate(cables):
            line, a, b = points(m), attachment[i], settings.robot.anchors_m[i]
            off = np.cross(line - a, b - a) / np.linalg.norm(b - a)
            assert np.abs(off).max() < 1e-9


def test_sagged_cable_at_the_catenary_sag(heavy):
    settings, eq = heavy
    assert eq.statics == 'sag'
    samples = 65
    shape = robot_shape(eq, samples)
    array = markers_message(shape, settings.tension_min_n, settings.tension_max_n)
    expected = np.array(geometry_summary(eq, samples)['max_sag_m'])
    assert expected.max() > 0.5                 # heavy sag: a metre on the slackest cable
    attachment = eq.geometry.position_m + eq.geometry.lever_m
    for i, m in enumerate(by_ns(array, 'cables')):
        line, a, b = points(m), attachment[i], settings.robot.anchors_m[i]
        chord = b - a
        along = np.clip((line - a) @ chord / (chord @ chord), 0.0, 1.0)
        sag = np.linalg.norm(line - a - along[:, None] * chord, axis=1).max()
        np.testing.assert_allclose(sag, expected[i], rtol=1e-9, atol=1e-12)
        # sag hangs down: the line's midpoint lies below the chord's midpoint
        assert line[samples // 2, 2] < (a[2] + b[2]) / 2 - 0.5 * expected[i]


def test_colours_monotone_in_tension(heavy):
    settings, eq = heavy
    t = np.linspace(settings.tension_min_n - 50, settings.tension_max_n + 50, 101)
    rgba = tension_colours(t, settings.tension_min_n, settings.tension_max_n)
    assert np.all(np.diff(rgba[:, 0]) >= 0) and np.all(np.diff(rgba[:, 2]) <= 0)
    np.testing.assert_allclose(rgba[0], [0, 0, 1, 1])
    np.testing.assert_allclose(rgba[-1], [1, 0, 0, 1])
    cables = by_ns(equilibrium_markers(settings, eq), 'cables')
    order = np.argsort(eq.tensions.tension_n)
    reds = np.array([cables[i].color.r for i in order])
    assert np.all(np.diff(reds) >= 0) and reds[-1] > reds[0]
    span = settings.tension_max_n - settings.tension_min_n
    s = (eq.tensions.tension_n - settings.tension_min_n) / span
    np.testing.assert_allclose([m.color.r for m in cables], s, rtol=1e-6)


def test_ids_namespaces_and_platform_are_stable(heavy):
    settings, eq = heavy
    moved = equilibrium(settings, settings.initial_position_m + [0.2, -0.1, 0.1],
                        method='fem_sag')
    first = equilibrium_markers(settings, eq)
    second = equilibrium_markers(settings, moved, [1e-3, 0, 0], 50.0, ns_to_stamp(5))
    keys = [[(m.ns, m.id, m.type) for m in a.markers] for a in (first, second)]
    assert keys[0] == keys[1] and len(set(keys[0])) == len(keys[0])
    for m in first.markers + second.markers:
        assert m.frame_locked and m.header.frame_id == settings.robot.frame_id
        assert (m.lifetime.sec, m.lifetime.nanosec) == (0, 0) and m.action == Marker.ADD
    box, = by_ns(first, 'platform')
    assert box.type == Marker.CUBE               # rigid platform: a box over its attachments
    b = settings.robot.attachments_m
    np.testing.assert_allclose([box.scale.x, box.scale.y, box.scale.z],
                               np.maximum(b.max(0) - b.min(0), 0.02), rtol=1e-12)
    o = box.pose.orientation
    np.testing.assert_allclose(quaternion_to_matrix((o.x, o.y, o.z, o.w)),
                               settings.initial_rotation, atol=1e-12)
    arrow, = by_ns(second, 'displacement')
    tail, tip = points(arrow)
    np.testing.assert_allclose(tail, moved.geometry.position_m)
    np.testing.assert_allclose(tip - tail, [0.05, 0, 0], atol=1e-15)
    # the node's arrow refresh: only the arrow moves, the rest equals a fresh build
    stamp = ns_to_stamp(7)
    assert serialize(update_arrow(first, [0, 2e-3, 0], 50.0, stamp)) == serialize(
        equilibrium_markers(settings, eq, [0, 2e-3, 0], 50.0, stamp))


def test_point_mass_is_a_sphere():
    settings = load_settings(PAPER)
    eq = equilibrium(settings)
    assert eq.geometry.structure_matrix.shape[0] == 3
    platform, = by_ns(equilibrium_markers(settings, eq), 'platform')
    assert platform.type == Marker.SPHERE
    np.testing.assert_allclose([platform.pose.position.x, platform.pose.position.y,
                                platform.pose.position.z], settings.initial_position_m)


def demo_recording(path: Path, settings, wrenches: int = 20) -> list:
    """A small demo: a step force on the platform, its predicted displacement, the tensions,
    and the markers at start and every 5 wrenches (as the node would at its diagnostics rate).
    Returns the MarkerArrays written."""
    predictor = LivePredictor(settings)
    predictor.update_pose(settings.initial_position_m, rotation=settings.initial_rotation)
    eq, frame = predictor.eq, settings.robot.frame_id
    written = [equilibrium_markers(settings, eq, stamp=ns_to_stamp(0))]
    with RecordingWriter(path, force=True) as writer:
        writer.add_topic('/cdpr_markers', 'visualization_msgs/msg/MarkerArray')
        writer.add_topic('/predicted_displacement', 'geometry_msgs/msg/Vector3Stamped')
        writer.add_topic('/cable_tensions', 'sensor_msgs/msg/JointState')
        writer.write('/cdpr_markers', written[0], 0)
        writer.write('/cable_tensions', tensions_message(eq.geometry.length_m,
                                                         eq.tensions.tension_n,
                                                         ns_to_stamp(0), frame), 0)
        for k in range(1, wrenches + 1):
            t_ns = k * 5_000_000
            u = predictor.advance(t_ns, [0.0, 0.0, -200.0])
            writer.write('/predicted_displacement',
                         displacement_message(u, frame, ns_to_stamp(t_ns)), t_ns)
            if k % 5 == 0:
                written.append(equilibrium_markers(settings, eq, u, 100.0, ns_to_stamp(t_ns)))
                writer.write('/cdpr_markers', written[-1], t_ns)
    return written


@pytest.fixture(scope='module')
def recording(tmp_path_factory, heavy):
    path = tmp_path_factory.mktemp('markers') / 'demo_markers.mcap'
    return path, demo_recording(path, heavy[0])


def test_markers_round_trip_through_the_recorder(recording):
    recording, written = recording
    ours = [r for r in read_messages(recording, ['/cdpr_markers'])]
    assert len(ours) == len(written) == 5
    for mine, sent in zip(ours, written):
        # every field, after the float32 colours' rounding: the same CDR bytes (padding zeroed)
        assert serialize(mine.message) == serialize(sent)
    with AnyReader([recording]) as reader:
        conns = [c for c in reader.connections if c.topic == '/cdpr_markers']
        assert conns[0].msgtype == 'visualization_msgs/msg/MarkerArray'
        decoded = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    assert len(decoded) == len(ours)
    for theirs, mine in zip(decoded, ours):
        assert len(theirs.markers) == len(mine.message.markers)
        for a, b in zip(theirs.markers, mine.message.markers):
            assert (a.ns, a.id, a.type, a.frame_locked) == (b.ns, b.id, b.type, True)
            np.testing.assert_array_equal(points(a), points(b))
            assert (a.color.r, a.color.b) == (np.float32(b.color.r), np.float32(b.color.b))


def _npm_install(target: Path) -> str:
    """'' when the Foxglove packages are installed in ``target``, else why they are not."""
    if shutil.which('node') is None or shutil.which('npm') is None:
        return 'node or npm is not installed'
    run = subprocess.run(['npm', 'install', '--prefix', str(target), '--no-audit', '--no-fund',
                          '--loglevel=error', *NPM_PACKAGES],
                         capture_output=True, text=True, timeout=300)
    if run.returncode != 0:
        text = run.stderr + run.stdout
        if any(w in text for w in ('ENOTFOUND', 'EAI_AGAIN', 'ECONNREFUSED', 'ETIMEDOUT',
                                   'E403', 'E401', 'network')):
            return f'the npm registry refused: {text.strip().splitlines()[-1]}'
        raise AssertionError(f'npm install failed: {text[-2000:]}')
    return ''


@pytest.mark.slow
def test_recording_decodes_in_foxglove(recording, tmp_path_factory):
    recording, _ = recording
    modules = tmp_path_factory.mktemp('foxglove_npm')
    why = _npm_install(modules)
    if why:
        pytest.skip(why)
    run = subprocess.run(['node', str(REPO / 'test' / 'foxglove_decode.mjs'), str(recording)],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, 'FOXGLOVE_MODULES': str(modules)})
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout)
    python_counts = {}
    ours = []
    for r in read_messages(recording):
        python_counts[r.topic] = python_counts.get(r.topic, 0) + 1
        if r.topic == '/cdpr_markers':
            ours.append(r.message)
    print('foxglove decoder counts:', out['counts'], 'python:', python_counts)
    assert out['counts'] == python_counts
    assert python_counts == {'/cdpr_markers': 5, '/predicted_displacement': 20,
                             '/cable_tensions': 1}
    for theirs, mine in zip(out['markers'], ours, strict=True):
        assert [m[:4] for m in theirs] == [[m.ns, m.id, m.type, True] for m in mine.markers]
        for t, m in zip(theirs, mine.markers):
            np.testing.assert_array_equal(np.array(t[4]).reshape(-1, 3), points(m))


def test_picture_from_a_recorded_array(recording, tmp_path, heavy):
    recording, _ = recording
    *_, last = read_messages(recording, ['/cdpr_markers'])
    out = tmp_path / 'markers.png'
    settings = heavy[0]
    plot_markers(last.message, out, 'test', (settings.tension_min_n, settings.tension_max_n))
    assert out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and out.stat().st_size > 20000
