"""The pose update's fast paths give the numbers of the general code they replace.

* ChainNewmark (the Newmark factorised through the cable chains: banded Cholesky, Schur
  complement on the platform DOFs) against Newmark on the assembled sparse (LU) and dense (LU)
  matrices, over 1000 steps;
* the tension QP's warm active set against proxsuite solving every pose cold;
* the sag statics' SQP warm-started pose to pose (its step QP kept) against a cold start;
* the design and wrench-set shortcuts (rank from singular values only, no second SVD for the
  chord structure matrix, the explicit cross product) against what they replace.
"""
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.pipeline import (build_system, damping_for, equilibrium,
                                             new_tension_solver)
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import ChainNewmark, Newmark, _chain_coupling, _end_coupling
from cdpr_dynamics.mechanics.feasibility import WrenchSet
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.mechanics.robot import cross, geometry, required_wrench
from cdpr_dynamics.mechanics.statics import sag_equilibrium
from cdpr_dynamics.mechanics.tensions import TensionSolver

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / 'config' / 'paper_cdpr.yaml'
RIGID = ROOT / 'test' / 'data' / 'rigid_cdpr.yaml'
HEAVY = ROOT / 'config' / 'heavy_sag_6dof.yaml'


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
