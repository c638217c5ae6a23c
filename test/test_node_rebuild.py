"""``node.rebuild: worker`` through DDS: the statics of moved poses in a worker process.

The node under test integrates fem_sag (8 elements per cable) on the paper's robot, whose
sag-consistent statics cost milliseconds per pose. Checked against a mirror
:class:`LivePredictor` fed the same inputs inline (as ``cdpr_replay`` does): once a pose's model
is swapped in (its ``cable_tensions`` arrive), tensions and predictions agree with the inline
path; a pose the statics refuse is rejected with the reason and the old model keeps predicting;
poses faster than their statics never stall the wrench path and the node ends at the last one.
"""
from __future__ import annotations

import numpy as np
import pytest

from cdpr_dynamics.analysis.live import LivePredictor
from msg_adapters.diagnostics import OK
from msg_adapters.joint_state import read_tensions
from msg_adapters.pose import pose_message
from msg_adapters.wrench import wrench_message
from test_node_dds import PAPER, Harness, ros  # noqa: F401 - ros: the module's ROS fixture

pytestmark = pytest.mark.ros   # nodes, DDS, worker processes, signals

PARAMETERS = {'node.rebuild': 'worker', 'model.method': 'fem_sag',
              'model.elements_per_cable': 8}


@pytest.fixture(scope='module')
def background(ros):  # noqa: F811 - the fixture imported above
    harness = Harness(PAPER, ros['log_dir'], 'background', PARAMETERS)
    harness.settings = harness.settings.replace(method='fem_sag', elements_per_cable=8)
    harness.mirror = LivePredictor(harness.settings)
    yield harness
    status = harness.close()
    assert status == 0, f'dynamics_node exited with {status}: {harness.log_tail()}'


def test_swapped_model_equals_the_inline_one(background):
    """After each swap the node's tensions and predictions are the mirror's (inline)."""
    h = background
    for position in ([0.1, 0.05, 1.2], [-0.2, 0.1, 1.0], [-0.2, 0.1, 1.0 + 5e-5]):
        h.pose(position)                   # waits for its tensions, compared to 1e-9
        for _ in range(20):
            h.wrench([10.0, -5.0, 300.0])  # predictions compared to 1e-9
    values = h.status('model')['values']
    assert values['rebuild'] == 'worker'
    assert values['method'] == 'fem_sag'
    assert int(values['rebuilds']) >= 2
    assert float(values['swap_ms_p50']) > 0.0


def test_refused_pose_keeps_the_old_model(background):
    """The worker's AnalysisError reaches /diagnostics as the pose's rejection."""
    h = background
    h.pose([0.0, 0.1, 1.1])
    h.bad_pose([0.0, 0.0, 2.4], words='infeasible tension distribution', model=True)
    h.wrench([0.0, 0.0, 500.0])            # still the last good pose's model
    h.pose([0.05, 0.1, 1.15])
    h.wrench([0.0, 0.0, 500.0])
    h.expect_status('pose input', OK, 'accepted')


def test_poses_faster_than_their_statics(background):
    """A burst of poses, each moved, with a wrench after each: every wrench is predicted
    while the statics run, the latest pose wins and the node ends at the last pose. (Runs
    last: the predictions during the burst depend on when each swap landed, so the mirror
    cannot follow them.)"""
    h = background
    before = h.prediction_count
    accepted = int(h.fresh_status('pose input')['values']['accepted'])
    before_model = h.fresh_status('model')['values']
    rebuilds, superseded = int(before_model['rebuilds']), int(before_model['poses_superseded'])
    stamps = []
    for k in range(40):
        position = [0.1 - 0.005 * k, 0.05, 1.1 + 0.002 * k]
        stamp = h.next_stamp(0.001)
        h.pose_pub.publish(pose_message(position, (0.0, 0.0, 0.0, 1.0), h.frame, stamp))
        h.wrench_pub.publish(wrench_message([0.0, 0.0, 300.0], (0.0, 0.0, 0.0), h.frame,
                                            h.next_stamp(0.001)))
        stamps.append(stamp)
    assert h.wait(lambda: h.prediction_count - before == 40), \
        f'{h.prediction_count - before} of 40 wrenches predicted'
    assert h.wait(lambda: any(m.header.stamp == stamps[-1] for m in h.tensions)), \
        'no cable_tensions for the last pose'
    h.mirror.update_pose(position)
    msg = next(m for m in reversed(h.tensions) if m.header.stamp == stamps[-1])
    lengths, tensions = read_tensions(msg)
    np.testing.assert_allclose(tensions, h.mirror.eq.tensions.tension_n, rtol=1e-6)
    np.testing.assert_allclose(lengths, h.mirror.eq.geometry.length_m, rtol=1e-12)
    # every pose the node took (DDS drops some of a burst: best effort, depth 5), each 5 mm
    # from the one before, was either solved and swapped in (a rebuild) or replaced by a newer
    # one; counted by the node (cable_tensions, latched with depth 1, may skip one of two
    # published back to back)
    accepted = int(h.fresh_status('pose input')['values']['accepted']) - accepted
    model = h.fresh_status('model')['values']
    swapped = int(model['rebuilds']) - rebuilds
    superseded = int(model['poses_superseded']) - superseded
    assert swapped + superseded == accepted, (model, accepted)
    assert 1 <= swapped <= accepted
    assert h.alive()
