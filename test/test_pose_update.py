"""The pose update's shortcuts and fast paths, each against the general code it replaces.

* geometry with its tests on Python floats and |l_i| without np.linalg.norm's wrapper: the same
  arrays, bit for bit, as numpy's norm and cross product, and the same errors;
* the facet normals of a point-mass zonotope from one gather: the pairwise cross products;
* the warm active set of the tension QP with its fused KKT test: proxsuite's tensions where
  tensions sit on T_max as well as on T_min, silent (no RuntimeWarning) and correct for inf,
  NaN and huge inputs;
* LAPACK called directly (singular values, small inverses): numpy's numbers and errors;
* ChainNewmark with its couplings built from the cables' end blocks: the sparse LU's steps;
* ChainNewmark (the Newmark factorised through the cable chains: banded Cholesky, Schur
  complement on the platform DOFs) against Newmark on the assembled sparse (LU) and dense (LU)
  matrices, over 1000 steps;
* the tension QP's warm active set against proxsuite solving every pose cold;
* the sag statics' SQP warm-started pose to pose (its step QP kept) against a cold start;
* the design and wrench-set shortcuts (rank from singular values only, no second SVD for the
  chord structure matrix, the explicit cross product) against what they replace.
"""
import warnings
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.analysis.pipeline import (build_system, damping_for, equilibrium,
                                             new_tension_solver)
from cdpr_dynamics.dynamics.system import (ChainNewmark, Newmark, _chain_coupling,
                                           _end_coupling, _inverse)
from cdpr_dynamics.mechanics.feasibility import (WrenchSet, _facet_normals, _normals_of,
                                                 _subsets)
from cdpr_dynamics.mechanics.robot import (GeometryError, cross, geometry, quaternion_to_matrix,
                                           required_wrench, singular_values)
from cdpr_dynamics.mechanics.statics import sag_equilibrium
from cdpr_dynamics.mechanics.tensions import TensionSolver
from cdpr_dynamics.models.catenary import sag_parameter

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


def test_six_dof_normals_are_the_null_vectors_of_each_subset():
    """d = 6: the generalised cross products are, up to sign, the null vectors LAPACK's SVD
    gives each subset of 5 generators; a subset with two parallel generators is dropped."""
    rigid = load_settings(RIGID)
    rng = np.random.default_rng(3)
    for k in range(10):
        wt = geometry(rigid.robot, rigid.initial_position_m
                      + rng.normal(0.0, 0.1, 3)).structure_matrix
        if k == 1:
            wt[:, 6] = 2.0 * wt[:, 1]
        subsets = _subsets(8, 5)
        _, sing, vt = np.linalg.svd(wt.T[subsets])
        spanning = sing[:, -1] > 1e-9 * sing[:, 0]
        normals = _normals_of(wt, subsets)
        assert normals.shape[0] == spanning.sum() == (56 - 20 if k == 1 else 56)
        assert_allclose(np.abs(np.einsum('ki,ki->k', normals, vt[spanning, -1])), 1.0,
                        rtol=1e-12)
        assert np.abs(wt.T[subsets[spanning]] @ normals[..., None]).max() < 1e-12 * np.abs(
            wt).max()


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


@pytest.mark.slow
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


def _system(config, method, elements):
    settings = load_settings(config).replace(method=method, elements_per_cable=elements)
    system = build_system(settings, equilibrium(settings, method=method))
    return settings, system, damping_for(settings, system)


def _history(integrator, dofs, platform_dofs, steps=1000):
    """Platform DOFs (steps, ndof) under a 5 Hz force (and moment) on the platform."""
    load = np.zeros(dofs)
    direction = np.array([0.3, -0.2, 1.0, 0.1, 0.2, -0.1])[:platform_dofs]
    out = np.empty((steps, platform_dofs))
    for i in range(steps):
        load[:platform_dofs] = 1000.0 * np.sin(2 * np.pi * 5.0 * i * 1e-3) * direction
        out[i] = integrator.step(load)[:platform_dofs]
    return out


# ------------------------------------------------------------------------------ ChainNewmark

@pytest.mark.parametrize('config, method, elements, rtol', [
    (PAPER, 'spring', 1, 1e-13),          # point mass, massless cables: no interior
    (PAPER, 'catenary', 1, 1e-13),
    (PAPER, 'fem', 16, 1e-12),            # 363 DOFs
    (PAPER, 'fem_sag', 16, 1e-10),
    (RIGID, 'spring', 1, 1e-13),          # 6-DOF platform
    (RIGID, 'fem', 16, 1e-11),
    (RIGID, 'fem_sag', 16, 1e-10),
    (HEAVY, 'fem_sag', 16, 1e-8),         # heavy sag: A is the worst conditioned here
])
def test_chain_newmark_matches_the_sparse_and_dense_lu_over_1000_steps(
        config, method, elements, rtol):
    """Platform DOFs within ``rtol`` of the peak over 1000 steps, and never more than 20x
    further from a dense LU than the sparse LU is (both direct solves of the same steps: their
    difference is round-off amplified by the condition number of K + a0 M + a1 C)."""
    settings, system, damping = _system(config, method, elements)
    k, m = system.matrices()
    nd = system.platform_dofs
    chain = _history(ChainNewmark(system, damping, settings.dt_s), system.dofs, nd)
    sparse = _history(Newmark(k, m, damping, settings.dt_s), system.dofs, nd)
    dense = _history(Newmark(k.toarray(), m.toarray(), damping, settings.dt_s), system.dofs, nd)
    peak = np.abs(dense).max()
    assert peak > 0
    assert np.abs(chain - sparse).max() <= rtol * peak
    assert np.abs(chain - dense).max() <= 20 * np.abs(sparse - dense).max() + 1e-13 * peak


@pytest.mark.parametrize('config', [PAPER, RIGID])
def test_chain_bands_hold_the_assembled_matrices_exactly(config):
    """Band, coupling and platform block are the entries of K and M of matrices()."""
    _, system, damping = _system(config, 'fem', 4)
    chain = ChainNewmark(system, damping, 1e-3)
    nd, n = system.platform_dofs, system.dofs
    blocks, g = system.assembly.blocks, system.geometry.attachment_map()
    k_coupling, m_coupling = (_chain_coupling(_end_coupling(off, g), blocks.nodes - 1)
                              for off in (blocks.k_off, blocks.m_off))
    for band, coupling, platform, full in (
            (chain._k_band, k_coupling, chain._p_pair[:, nd:], chain.k.toarray()),
            (chain._m_band, m_coupling, chain._p_pair[:, :nd], chain.m.toarray())):
        rebuilt = np.zeros((n, n))
        ni = n - nd
        for offset in range(band.shape[0]):
            rows = np.arange(ni - offset)
            rebuilt[nd + rows + offset, nd + rows] = band[offset, :ni - offset]
            rebuilt[nd + rows, nd + rows + offset] = band[offset, :ni - offset]
        rebuilt[nd:, :nd] = coupling
        rebuilt[:nd, nd:] = coupling.T
        rebuilt[:nd, :nd] = platform
        assert np.array_equal(rebuilt, full)


def test_chain_newmark_assembles_its_matrices_only_when_asked(monkeypatch):
    """The live path never builds the global matrices; k, m, c are there for who asks."""
    settings, system, damping = _system(PAPER, 'fem', 16)
    calls = []
    original = type(system).matrices
    monkeypatch.setattr(type(system), 'matrices',
                        lambda self, dense=False: calls.append(dense) or original(self, dense))
    chain = ChainNewmark(system, damping, settings.dt_s)
    chain.step(np.ones(system.dofs))
    assert calls == []
    assert chain.k.shape == (system.dofs, system.dofs) and calls == [False]
    expected = damping.mass_factor * chain.m + damping.stiffness_factor * chain.k
    assert abs(chain.c - expected).max() == 0.0


def test_live_predictor_carries_its_state_into_and_out_of_the_chain_integrator():
    """spring -> fem -> spring: the platform state carries over (K_ii u_i = -K_ip u_p)."""
    settings = load_settings(PAPER)
    predictor = LivePredictor(settings.replace(method='spring'))
    for k in range(200):
        predictor.advance(k * 1_000_000, [30.0, -20.0, 100.0])
    before = predictor.integrator.u.copy()
    predictor.set_settings(settings.replace(method='fem', elements_per_cable=8))
    assert isinstance(predictor.integrator, ChainNewmark)
    u = predictor.integrator.u
    assert_allclose(u[:3], before)
    k = predictor.integrator.k
    assert np.abs((k @ u)[3:]).max() < 1e-9 * abs(k).max() * np.abs(u).max()
    predictor.set_settings(settings.replace(method='spring'))
    assert_allclose(predictor.integrator.u, u[:3])


# ------------------------------------------------------------------------------ tension QP

def _walk(settings, steps, seed=1, scale_m=0.01):
    """Poses of a random walk in the middle of the frame."""
    rng = np.random.default_rng(seed)
    lo, hi = settings.robot.frame_bounds_m
    p = np.asarray(settings.initial_position_m, dtype=float).copy()
    for _ in range(steps):
        p = np.clip(p + rng.normal(0.0, scale_m, 3), lo + 0.3 * (hi - lo), hi - 0.3 * (hi - lo))
        yield p


@pytest.mark.parametrize('config', [PAPER, RIGID, HEAVY])
def test_warm_active_set_gives_proxsuites_tensions(config):
    """Along 300 nearby poses the warm solver answers from the active set (0 proxsuite
    iterations) and matches proxsuite solving each pose cold to 1e-9 T_max."""
    settings = load_settings(config)
    robot = settings.robot
    wrench = required_wrench(robot, settings.external_force_n, settings.external_moment_nm)
    warm = new_tension_solver(settings)
    by_active_set = 0
    for p in _walk(settings, 300):
        wt = geometry(robot, p).structure_matrix
        a = warm.solve(wt, wrench)
        b = TensionSolver(robot.n_cables, robot.platform_dofs, settings.tension_min_n,
                          settings.tension_max_n, warm_start=False).solve(wt, wrench)
        assert a.feasible and b.feasible
        assert_allclose(a.tension_n, b.tension_n, rtol=0, atol=1e-9 * settings.tension_max_n)
        by_active_set += a.iterations == 0
    assert by_active_set >= 290


def test_active_set_jumps_and_failures_fall_back_to_proxsuite():
    """A jump across the workspace changes the active set; an infeasible wrench drops it; in
    both cases the answer is proxsuite's."""
    settings = load_settings(PAPER)
    robot = settings.robot
    wrench = required_wrench(robot)
    solver = new_tension_solver(settings)
    centre = geometry(robot, [0.0, 0.0, 1.25]).structure_matrix
    corner = geometry(robot, [0.8, -0.7, 0.6]).structure_matrix
    for wt, w in [(centre, wrench), (corner, wrench), (centre, [2000.0, 0.0, 294.3]),
                  (centre, wrench), (corner, wrench)]:
        got = solver.solve(wt, w)
        cold = TensionSolver(8, 3, settings.tension_min_n, settings.tension_max_n,
                             warm_start=False).solve(wt, w)
        assert (got.status, got.feasible) == (cold.status, cold.feasible)
        if cold.feasible:
            assert_allclose(got.tension_n, cold.tension_n, rtol=0, atol=1e-6)


def test_active_set_answer_meets_the_kkt_conditions():
    """Independently of any solver: stationarity with signed bound multipliers."""
    settings = load_settings(RIGID)
    robot = settings.robot
    wrench = required_wrench(robot, [20.0, -10.0, 0.0])
    solver = new_tension_solver(settings)
    for p in _walk(settings, 50, seed=3):
        wt = geometry(robot, p).structure_matrix
        result = solver.solve(wt, wrench)
        t = result.tension_n
        lo, hi = settings.tension_min_n, settings.tension_max_n
        at_lo, at_hi = t <= lo + 1e-9, t >= hi - 1e-9
        free = ~(at_lo | at_hi)
        lam = np.linalg.lstsq(wt[:, free].T, t[free], rcond=None)[0]    # C = I: T_F = W_F lam
        mu = t - wt.T @ lam
        assert np.abs(mu[free]).max(initial=0.0) < 1e-7
        assert mu[at_lo].min(initial=0.0) > -1e-7 and mu[at_hi].max(initial=0.0) < 1e-7
        assert np.abs(wt @ t - wrench).max() < 1e-6


# ------------------------------------------------------------------------------ sag statics

def test_sag_statics_warm_from_the_previous_pose_equals_a_cold_start():
    settings = load_settings(HEAVY)
    wrench = required_wrench(settings.robot, settings.external_force_n,
                             settings.external_moment_nm)
    previous = None
    for p in list(_walk(settings, 12, seed=5, scale_m=0.005)):
        chord = equilibrium(settings, p)
        args = (chord.cables, chord.geometry.lever_m, wrench, settings.tension_min_n,
                settings.tension_max_n)
        warm = sag_equilibrium(*args, start=previous)
        cold = sag_equilibrium(*args)
        if previous is not None and np.array_equal(previous.lower_bound_n, warm.lower_bound_n):
            assert warm.step_qp is previous.step_qp           # reused, not rebuilt
        assert_allclose(warm.tension_n, cold.tension_n, rtol=0,
                        atol=1e-7 * settings.tension_max_n)
        assert warm.warnings == cold.warnings
        previous = warm


# ------------------------------------------------------------------------------ shortcuts

def test_cross_is_numpys_bit_for_bit():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(28, 3)) * 1e3, rng.normal(size=(28, 3))
    assert np.array_equal(cross(a, b), np.cross(a, b))
    assert np.array_equal(cross(a[0], b[0]), np.cross(a[0], b[0]))


@pytest.mark.parametrize('config', [PAPER, RIGID])
def test_wrench_set_with_the_rank_known_is_the_same_set(config):
    settings = load_settings(config)
    wt = geometry(settings.robot, settings.initial_position_m + 0.05).structure_matrix
    need = required_wrench(settings.robot)
    a = WrenchSet(wt, settings.tension_min_n, settings.tension_max_n, need)
    b = WrenchSet(wt, settings.tension_min_n, settings.tension_max_n, need, full_rank=True)
    assert a.exact and b.exact
    assert np.array_equal(a.normals, b.normals) and np.array_equal(a.reach, b.reach)
    for force in ([0.0, 0.0, 100.0], [500.0, 0.0, 0.0], [0.0, 3000.0, 0.0]):
        assert a.reason(force) == b.reason(force)


def test_rank_deficient_design_still_refused_with_its_direction():
    """The rank test on singular values alone still names the unheld direction."""
    from cdpr_dynamics.analysis.pipeline import AnalysisError
    settings = load_settings(PAPER)
    anchors = settings.robot.anchors_m.copy()
    anchors[:, 2] = 2.5                                # every anchor on the ceiling plane
    flat = settings.replace(robot=type(settings.robot)(
        settings.robot.frame_id, anchors, settings.robot.attachments_m, settings.robot.mass_kg,
        settings.robot.inertia_kg_m2, settings.robot.gravity_m_s2))
    with pytest.raises(AnalysisError, match='rank'):
        equilibrium(flat, [0.0, 0.0, 2.5])
