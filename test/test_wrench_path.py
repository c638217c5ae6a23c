"""The wrench path's shortcuts give the numbers of the general code they replace.

* ChainNewmark's right side [M K] [x; y] as one CSR product: the entries of the assembled K
  and M exactly; its state one (3, n) array whose rows are ``u``, ``v``, ``acc``;
* LivePredictor.advance's two reused load vectors: the zero-order hold of the previous wrench
  as a Newmark stepped with freshly built loads, on a 6-DOF platform with moments;
* LivePredictor.prediction's per-pose cache: p + R b + displacement and the quaternion of
  the current pose and point, however the point is given;
* WrenchSet.reason's one-product acceptance: the full slab test's answer for wrenches inside,
  outside and within the tolerance of the boundary.
"""
import numpy as np
import pytest
import scipy.sparse as sp
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.pipeline import damping_for, point_displacement
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import ChainNewmark, Newmark
from cdpr_dynamics.analysis.live import LivePredictor, rotated_quaternion
from cdpr_dynamics.mechanics.robot import matrix_to_quaternion
from test_pose_update import HEAVY, PAPER, RIGID, _system


@pytest.mark.parametrize('config, method, elements', [
    (PAPER, 'fem', 4), (PAPER, 'fem', 16), (RIGID, 'fem', 3), (HEAVY, 'fem_sag', 5)])
def test_chain_right_side_matrix_holds_m_and_k_exactly(config, method, elements):
    """The CSR [M K] (n, 2n) of the step is the assembled M and K side by side, entry for
    entry (the explicit zeros between chains aside)."""
    _, system, damping = _system(config, method, elements)
    chain = ChainNewmark(system, damping, 1e-3)
    k, m = system.matrices()
    assert sp.issparse(chain._pair_matrix)
    assert np.array_equal(chain._pair_matrix.toarray(), sp.hstack([m, k]).toarray())


def test_integrator_state_rows_are_u_v_acc():
    """u, v, acc are the rows of one array: a step overwrites them in place and returns u;
    assigning to them copies into the state; reset zeroes it."""
    settings, system, damping = _system(PAPER, 'fem', 4)
    chain = ChainNewmark(system, damping, settings.dt_s)
    lu = Newmark(*system.matrices(dense=True), damping, settings.dt_s)
    load = np.zeros(system.dofs)
    load[2] = 500.0
    for integrator in (chain, lu):
        u = integrator.u
        returned = integrator.step(load)
        assert returned is integrator.u or np.shares_memory(returned, integrator.u)
        assert np.shares_memory(u, integrator.u) and u[2] != 0.0
        before = integrator.v.copy()
        given = np.arange(system.dofs, dtype=float)
        integrator.acc = given
        assert integrator.acc is not given and np.array_equal(integrator.acc, given)
        assert np.array_equal(integrator.v, before)
        integrator.reset()
        assert not (integrator.u.any() or integrator.v.any() or integrator.acc.any())
        assert np.shares_memory(u, integrator.u)


def test_advance_holds_each_wrench_with_its_moment_until_the_next():
    """Zero-order hold on a 6-DOF platform (force and moment), intervals of 1-7 steps with
    remainders, a model change in between: advance's reused load vectors give what a Newmark
    stepped with loads built afresh for each interval gives (the linear model: with the
    cables' dampers inside their force, these steps of the wrench slacken cables)."""
    settings = load_settings(RIGID).replace(method='fem', elements_per_cable=3)
    predictor = LivePredictor(settings, slack='linear')
    system = predictor.system
    reference = ChainNewmark(system, damping_for(settings, system), settings.dt_s)
    rng = np.random.default_rng(3)
    stamp, remainder, held = 0, 0, None
    for k in range(60):
        force, moment = rng.normal(0, 50.0, 3), rng.normal(0, 5.0, 3)
        interval = int(rng.integers(1, 8)) * 1_000_000 + int(rng.integers(0, 3)) * 400_000
        stamp += interval
        got = predictor.advance(stamp, force, moment)
        if held is not None:
            steps, remainder = divmod(interval + remainder, 1_000_000)
            for _ in range(steps):
                reference.step(held.copy())
        held = np.zeros(system.dofs)
        held[:3], held[3:6] = force, moment
        assert_allclose(got, reference.u[:3], rtol=1e-12, atol=1e-15)
    assert np.abs(reference.u[:6]).max() > 0
    # a model change: the held wrench's platform part carries on, nothing else
    predictor.set_settings(settings.replace(method='spring'))
    spring = ChainNewmark(predictor.system, damping_for(settings, predictor.system),
                          settings.dt_s)
    spring.u, spring.v, spring.acc = predictor.integrator.u, predictor.integrator.v, \
        predictor.integrator.acc
    got = predictor.advance(stamp + 3_000_000, np.zeros(3), np.zeros(3))
    for _ in range(3):
        spring.step(held[:6].copy())
    assert_allclose(got, spring.u[:3], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize('config', [PAPER, RIGID])
def test_prediction_follows_the_pose_and_the_point(config):
    """p + R b + displacement and exp([theta]x) R's quaternion at the current pose, for points
    given as tuples, lists and arrays, across a pose update that rebuilds."""
    settings = load_settings(config)
    predictor = LivePredictor(settings)
    for k in range(30):
        predictor.advance(k * 1_000_000, [20.0, -10.0, 60.0], [1.0, -2.0, 0.5])
    for point in ((0.0, 0.0, 0.0), [0.05, -0.02, 0.01], np.array([0.05, -0.02, 0.01]),
                  (0.1, 0.0, 0.0)):
        for move in (False, True):
            if move:
                predictor.update_pose(predictor.position_m + [0.01, 0.0, -0.005],
                                      quaternion=[0.0, 0.02, 0.0, 0.9998])
                assert predictor.last_update.rebuilt
            nd = predictor.system.platform_dofs
            q = predictor.integrator.u[:nd]
            out = predictor.prediction(point)
            displacement = point_displacement(q, predictor.rotation, point)
            assert np.array_equal(out.displacement_m, displacement)
            assert np.array_equal(out.position_m, predictor.position_m + predictor.rotation
                                  @ np.asarray(point, dtype=float) + displacement)
            theta = q[3:6] if nd == 6 else np.zeros(3)
            assert np.array_equal(out.quaternion, rotated_quaternion(
                predictor.rotation, theta, matrix_to_quaternion(predictor.rotation)))


def _full_test(wrench_set, force, moment):
    """The slab test without the shortcut: accepted iff every slack >= -tolerance."""
    w = wrench_set._needed(force, moment)
    slack = wrench_set.reach - np.abs(wrench_set.normals @ w - wrench_set.offset)
    return bool(slack.min() >= -wrench_set.tolerance)


@pytest.mark.parametrize('config', [PAPER, RIGID])
def test_wrench_set_shortcut_gives_the_full_tests_answers(config):
    """Random directions scaled to inside, outside and within +-tolerance of the boundary
    (found by bisection): reason() accepts exactly what the full slab test accepts; a NaN is
    'not finite'."""
    predictor = LivePredictor(load_settings(config))
    wrench_set = predictor.wrench_set
    assert wrench_set.exact
    d = wrench_set.normals.shape[1]
    rng = np.random.default_rng(7)
    accepted = rejected = 0
    for _ in range(60):
        direction = rng.normal(size=d)
        direction /= np.linalg.norm(direction)
        low, high = 0.0, 1e6               # bisect the full test's boundary along direction
        for _ in range(200):
            mid = 0.5 * (low + high)
            low, high = (mid, high) if _full_test(wrench_set, *np.split(
                np.pad(mid * direction, (0, 6 - d)), 2)) else (low, mid)
        for scale in (0.0, 0.5 * low, low - 2 * wrench_set.tolerance, low, high,
                      low + 0.5 * wrench_set.tolerance, 1.5 * high):
            force, moment = np.split(np.pad(scale * direction, (0, 6 - d)), 2)
            expected = _full_test(wrench_set, force, moment)
            reason = wrench_set.reason(force, moment)
            assert (reason == '') == expected, (scale, low, reason)
            accepted += expected
            rejected += not expected
    assert accepted > 100 and rejected > 100
    assert wrench_set.reason([np.nan, 0.0, 0.0]) == 'wrench is not finite'
    assert wrench_set.reason([np.inf, 0.0, 0.0]) == 'wrench is not finite'
