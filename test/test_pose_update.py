"""The light pose update: each shortcut against what it replaces.

* geometry with its tests on Python floats and |l_i| without np.linalg.norm's wrapper: the same
  arrays, bit for bit, as numpy's norm and cross product, and the same errors;
* the facet normals of a point-mass zonotope from one gather: the pairwise cross products;
* the warm active set of the tension QP with its fused KKT test: proxsuite's tensions where
  tensions sit on T_max as well as on T_min, silent (no RuntimeWarning) and correct for inf,
  NaN and huge inputs;
* LAPACK called directly (singular values, small inverses): numpy's numbers and errors;
* ChainNewmark with its couplings built from the cables' end blocks: the sparse LU's steps.
"""
import warnings
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.pipeline import (build_system, damping_for, equilibrium,
                                             new_tension_solver)
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import ChainNewmark, Newmark, _inverse
from cdpr_dynamics.mechanics.feasibility import _facet_normals, _normals_of, _subsets
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.mechanics.robot import (GeometryError, geometry, quaternion_to_matrix,
                                           required_wrench, singular_values)
from cdpr_dynamics.mechanics.tensions import TensionSolver

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / 'config' / 'paper_cdpr.yaml'
RIGID = ROOT / 'test' / 'data' / 'rigid_cdpr.yaml'
HEAVY = ROOT / 'config' / 'heavy_sag_6dof.yaml'


def _reference_geometry(robot, p, rot):
    """Eqs. 1-6 written out with numpy's own norm and cross product."""
    lever = robot.attachments_m @ rot.T
    chord = robot.anchors_m - (p + lever)
    length = np.linalg.norm(chord, axis=1)
    unit = chord / length[:, None]
    wt = unit.T if robot.point_mass else np.vstack([unit.T, np.cross(lever, unit).T])
    return lever, chord, length, unit, wt


@pytest.mark.parametrize('config', [PAPER, RIGID, HEAVY])
def test_geometry_is_the_reference_bit_for_bit(config):
    settings = load_settings(config)
    robot = settings.robot
    rng = np.random.default_rng(4)
    for k in range(100):
        p = settings.initial_position_m + rng.normal(0.0, 0.1, 3)
        rot = quaternion_to_matrix(np.r_[rng.normal(0.0, 0.1, 3), 1.0]) if k % 2 else None
        geo = geometry(robot, p, rot)
        lever, chord, length, unit, wt = _reference_geometry(robot, p, np.eye(3) if rot is None
                                                             else rot)
        for got, want in ((geo.lever_m, lever), (geo.chord_m, chord), (geo.length_m, length),
                          (geo.unit, unit), (geo.structure_matrix, wt)):
            assert got.shape == want.shape
            assert np.array_equal(got, want)
        assert geo.structure_matrix.flags['C_CONTIGUOUS']


def test_geometry_refuses_what_it_refused():
    robot = load_settings(PAPER).robot
    for position, message in (([np.nan, 0.0, 1.0], 'pose is not finite'),
                              ([0.0, 0.0, np.inf], 'pose is not finite'),
                              (robot.anchors_m[3], 'cable 3 has zero length')):
        with pytest.raises(GeometryError, match=message):
            geometry(robot, position)
    with pytest.raises(GeometryError, match='pose is not finite'):
        geometry(robot, [0.0, 0.0, 1.0], np.full((3, 3), np.nan))
    for beyond in ([0.0, 0.0, 2.6], [-1.3, 0.0, 1.0], [0.0, 0.0, -3.0]):   # suspended or beside
        assert geometry(robot, beyond).length_m.min() > 0


def test_required_wrench_of_a_point_mass_and_of_a_rigid_platform():
    point, rigid = load_settings(PAPER).robot, load_settings(RIGID).robot
    assert_allclose(required_wrench(point, [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]),
                    [-1.0, -2.0, 30 * 9.81 - 3.0], rtol=1e-15)
    assert_allclose(required_wrench(rigid, [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]),
                    [-1.0, -2.0, 30 * 9.81 - 3.0, -4.0, -5.0, -6.0], rtol=1e-15)


@pytest.mark.parametrize('config', [PAPER, HEAVY])
def test_pair_normals_are_the_pairwise_cross_products(config):
    """d = 3 (point mass): the gathered products are the generic path's numbers exactly,
    degenerate pairs dropped, for C- and Fortran-ordered W^T; d = 6 keeps the generic path."""
    settings = load_settings(PAPER)
    rng = np.random.default_rng(6)
    for k in range(30):
        wt = geometry(settings.robot, settings.initial_position_m
                      + rng.normal(0.0, 0.2, 3)).structure_matrix
        if k == 1:
            wt[:, 5] = wt[:, 2]                 # one pair spans no plane
        if k == 2:
            wt = np.asfortranarray(wt)
        fast = _facet_normals(wt, full_rank=True)
        generic = _normals_of(wt, _subsets(wt.shape[1], 2))
        assert np.array_equal(fast, generic)
        assert fast.shape[0] == (27 if k == 1 else 28)
        assert_allclose(np.linalg.norm(fast, axis=1), 1.0, rtol=1e-15)
    rigid = load_settings(config if config != PAPER else RIGID)
    wt = geometry(rigid.robot, rigid.initial_position_m).structure_matrix
    assert np.array_equal(_facet_normals(wt, full_rank=True), _normals_of(wt, _subsets(8, 5)))


def _walk_wrenches(settings, n, seed, force_n):
    """Nearby poses, the external force ``force_n`` switched off, on and raised by 40 % every
    25 poses: tensions on T_min, on T_max (the paper robot) and out of reach."""
    rng = np.random.default_rng(seed)
    p = np.asarray(settings.initial_position_m, dtype=float).copy()
    for k in range(n):
        p = p + rng.normal(0.0, 0.004, 3)
        level = (0.0, 1.0, 1.4)[k // 25 % 3]
        yield (geometry(settings.robot, p).structure_matrix,
               required_wrench(settings.robot, level * np.asarray(force_n)))


@pytest.mark.parametrize('config, force_n, upper', [
    (PAPER, [-800.0, -300.0, -600.0], 20), (RIGID, [-1000.0, 0.0, -500.0], 0)])
def test_warm_active_set_at_both_bounds_is_proxsuites_answer(config, force_n, upper):
    """Warm solves along 200 poses with tensions on T_min and on T_max and wrenches out of
    reach: the same status, reason and tensions (1e-9 T_max) as proxsuite solving each pose
    cold, the feasible ones mostly answered by the active set."""
    settings = load_settings(config)
    robot = settings.robot
    warm = new_tension_solver(settings)
    counts = {'upper': 0, 'lower': 0, 'by_active_set': 0, 'infeasible': 0}
    for wt, w in _walk_wrenches(settings, 200, 2, force_n):
        a = warm.solve(wt, w)
        b = TensionSolver(robot.n_cables, robot.platform_dofs, settings.tension_min_n,
                          settings.tension_max_n, warm_start=False).solve(wt, w)
        assert (a.status, a.feasible, a.reason) == (b.status, b.feasible, b.reason)
        assert_allclose(a.tension_n, b.tension_n, rtol=0, atol=1e-9 * settings.tension_max_n)
        counts['infeasible'] += not a.feasible
        if a.feasible:
            counts['upper'] += bool(np.any(a.tension_n >= settings.tension_max_n - 1e-9))
            counts['lower'] += bool(np.any(a.tension_n <= settings.tension_min_n + 1e-9))
            counts['by_active_set'] += a.iterations == 0
            assert abs(a.residual_n - np.abs(wt @ a.tension_n - w).max()) < 1e-9
    assert counts['upper'] >= upper and counts['lower'] >= 20 and counts['infeasible'] >= 10
    assert counts['by_active_set'] >= 0.8 * (200 - counts['infeasible'])


@pytest.mark.parametrize('bad', ['inf wt', '-inf wt', 'nan wt', 'inf w', 'nan w', 'huge w',
                                 'huge wt'])
def test_warm_active_set_is_silent_and_right_on_non_finite_input(bad):
    """After a warm solve, non-finite or huge inputs raise no RuntimeWarning (the warm path
    runs under errstate) and get the cold path's answer."""
    settings = load_settings(PAPER)
    solver = new_tension_solver(settings)
    wt0 = geometry(settings.robot, settings.initial_position_m).structure_matrix
    w0 = required_wrench(settings.robot)
    assert solver.solve(wt0, w0).feasible
    wt, w = wt0.copy(), w0.copy()
    if bad.endswith('wt'):
        if bad == 'huge wt':
            wt *= 1e100          # W^T W ~ 1e200: no overflow in the cold path's norms either
        else:
            wt[1, 2] = {'inf wt': np.inf, '-inf wt': -np.inf, 'nan wt': np.nan}[bad]
    else:
        w[1] = {'inf w': np.inf, 'nan w': np.nan, 'huge w': 1e300}[bad]
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        got = solver.solve(wt, w)
    assert not got.feasible
    assert got.status == ('not_finite' if 'f' in bad or 'nan' in bad else 'infeasible')
    assert solver.solve(wt0, w0).feasible           # and recovers


def test_singular_values_and_inverse_are_numpys():
    rng = np.random.default_rng(8)
    for shape in ((3, 8), (6, 8), (6, 4), (3, 3)):
        a = rng.normal(size=shape)
        assert_allclose(singular_values(a), np.linalg.svd(a, compute_uv=False), rtol=1e-14)
    for n in (3, 6):
        a = rng.normal(size=(n, n)) + n * np.eye(n)
        assert_allclose(_inverse(a), np.linalg.inv(a), rtol=1e-14)
        assert _inverse(a).flags['C_CONTIGUOUS']
    with pytest.raises(np.linalg.LinAlgError):
        _inverse(np.zeros((3, 3)))


@pytest.mark.parametrize('config, method, elements', [
    (PAPER, 'spring', 1), (PAPER, 'fem', 16), (RIGID, 'fem', 4), (HEAVY, 'fem', 8)])
def test_chain_newmark_steps_are_the_sparse_lus(config, method, elements):
    """The integrator built from the end blocks steps as Newmark on the assembled matrices
    (an independent direct solve) does, over 300 steps of a 5 Hz load."""
    settings = load_settings(config).replace(method=method, elements_per_cable=elements)
    system = build_system(settings, equilibrium(settings, method=method))
    damping = damping_for(settings, system)
    k, m = system.matrices()
    chain = ChainNewmark(system, damping, settings.dt_s)
    lu = Newmark(k, m, damping, settings.dt_s)
    nd = system.platform_dofs
    load = np.zeros(system.dofs)
    worst = peak = 0.0
    for i in range(300):
        load[:3] = 800.0 * np.sin(2 * np.pi * 5.0 * i * 1e-3) * np.array([0.3, -0.2, 1.0])
        a, b = chain.step(load)[:nd], lu.step(load)[:nd]
        worst, peak = max(worst, np.abs(a - b).max()), max(peak, np.abs(b).max())
    assert peak > 0 and worst <= 1e-10 * peak


def test_sag_parameter_of_taut_and_slack_cables():
    """Irvine's lambda^2 (closed form for a level cable) and inf for a cable without tension,
    with and without the errstate-free path for taut cables."""
    settings = load_settings(PAPER)
    eq = equilibrium(settings)
    cables = eq.cables
    lam2 = sag_parameter(cables.with_tension(cables.tension_n))
    up = -settings.robot.gravity_m_s2 / np.linalg.norm(settings.robot.gravity_m_s2)
    chord = np.asarray(cables.chord_m)
    length = np.linalg.norm(chord, axis=1)
    cos = np.linalg.norm(chord - np.outer(chord @ up, up), axis=1) / length
    ratio = settings.cable.weight_per_length_n_per_m * length * cos / cables.tension_n
    want = ratio ** 2 * settings.cable.ea_n / (cables.tension_n * (1 + ratio ** 2 / 8))
    assert_allclose(lam2, want, rtol=1e-14)
    slack = cables.tension_n.copy()
    slack[2] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        out = sag_parameter(cables.with_tension(slack))
    assert np.isinf(out[2]) and np.all(np.isfinite(np.delete(out, 2)))
