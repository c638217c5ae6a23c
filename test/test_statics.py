"""Sag-consistent statics and the validity rules against independent answers.

Convention (``cdpr_dynamics.models.catenary``): F is the force applied at the platform end B ON
the cable, sigma the unstrained arc length from B, gamma the weight per unstrained length, e the
unit up vector. The tension vector at sigma is F - gamma sigma e, and stepping from B towards
the anchor A the cable point moves by -(F - gamma sigma e)(1/T(sigma) + 1/EA) d sigma, so

    r(sigma) = r_B - integral_0^sigma (F - gamma s e)(1/|F - gamma s e| + 1/EA) ds,

which must reach the anchor at sigma = L0. The cable pulls the platform with f_i = -F_i; the
platform is in equilibrium when sum f_i + m g + f_e = 0 and sum r_i x f_i + tau_e = 0
(r_i = R b_i, moments about the centroid). Every check below recomputes these itself
(quadrature, a chain of elastic bars solved by scipy.optimize.root, finite differences with the
unstrained lengths held, a dense assembly) instead of reusing the library's closed forms.

The sag statics' fast path against its general one (the regression guard of both): the SQP of
``statics.sag_equilibrium`` takes each solve's tension sensitivity from the solve's own last
evaluation (``catenary.solve_with_sensitivity``) and starts its trial solves from the
first-order prediction alone (``warm_only``). The general path is ``catenary.solve`` (the
parabola start beside the warm start) followed by ``catenary.tension_sensitivity`` of the
lifted forces. Both must give the same tensions, end forces and unstrained lengths to rounding,
the same SQP iteration counts, warnings and refusals, along pose sequences that include the
lifted lower bounds (existence probes, step halving) of the low-tension robot.
"""
from __future__ import annotations

import functools
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from numpy.testing import assert_allclose
from scipy.integrate import quad_vec
from scipy.optimize import minimize, root
from scipy.spatial.transform import Rotation

from conftest import analyze, write_config
from cdpr_dynamics import models
from cdpr_dynamics.analysis.config import load_settings, read_params_file, settings_from_params
from cdpr_dynamics.analysis.pipeline import (AnalysisError, build_system, equilibrium,
                                             equilibrium_summary, model_warnings)
from cdpr_dynamics.cli.analyze import analyze_method
from cdpr_dynamics.dynamics.modes import natural_frequencies
from cdpr_dynamics.mechanics import statics
from cdpr_dynamics.mechanics.robot import geometry, required_wrench, skew
from cdpr_dynamics.models import catenary, fem_sag
from cdpr_dynamics.models.base import CableSet

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / 'config' / 'paper_cdpr.yaml'
LOW_TENSION = REPO / 'config' / 'low_tension_cdpr.yaml'
RIGID = REPO / 'test' / 'data' / 'rigid_cdpr.yaml'
HEAVY = REPO / 'config' / 'heavy_sag_6dof.yaml'
CONFIGS = {'paper': PAPER, 'low_tension': LOW_TENSION, 'rigid': RIGID, 'heavy': HEAVY}
#: the shipped robots, and the low-tension one with T_min below the least tension at which its
#: lower cables have a catenary (the statics lifts their lower bound)
CASES = {name: (name, {}) for name in CONFIGS}
CASES['low_tension_lifted'] = ('low_tension', {'tension__min_n': 0.5})


# ----------------------------------------------------------------------------- helpers

@functools.lru_cache(maxsize=None)
def settings_of(name: str, **changes):
    """Settings of a shipped config (complete parameter set), with flat ``changes``."""
    flat = read_params_file(CONFIGS[name])
    flat.update({k.replace('__', '.'): list(v) if isinstance(v, tuple) else v
                 for k, v in changes.items()})
    return settings_from_params(flat)


@functools.lru_cache(maxsize=None)
def sag_eq(name: str, **changes):
    return equilibrium(settings_of(name, **changes), method='fem_sag')


def up_gamma(settings):
    g = np.asarray(settings.robot.gravity_m_s2, dtype=float)
    return -g / np.linalg.norm(g), settings.cable.weight_per_length_n_per_m


def integrate_cable(force, l0, ea, gamma, up, sigma_end=None):
    """r_B - r(sigma_end) by adaptive quadrature of the catenary's tangent (module docstring)."""
    def rate(s):
        tension = force - gamma * s * up
        return tension * (1.0 / np.linalg.norm(tension) + 1.0 / ea)
    value, _ = quad_vec(rate, 0.0, l0 if sigma_end is None else sigma_end, epsabs=0.0,
                        epsrel=1e-13, limit=400)
    return value


def platform_wrench(settings, lever, force_on_platform):
    """Net wrench on the platform (N, then N m about the centroid): cables, gravity, load."""
    robot = settings.robot
    force = force_on_platform.sum(axis=0) + robot.mass_kg * robot.gravity_m_s2 \
        + settings.external_force_n
    if robot.platform_dofs == 3:
        return force
    moment = np.cross(lever, force_on_platform).sum(axis=0) + settings.external_moment_nm
    return np.concatenate([force, moment])


def relative_residual(settings, lever, residual):
    """max(|force| / weight, |moment| / (weight * largest lever arm))."""
    weight = np.linalg.norm(required_wrench(settings.robot, settings.external_force_n,
                                            settings.external_moment_nm)[:3])
    arm = np.linalg.norm(lever, axis=1).max()
    rel = np.linalg.norm(residual[:3]) / weight
    if residual.size > 3:
        rel = max(rel, np.linalg.norm(residual[3:]) / (weight * arm))
    return rel


def constraint_jacobian(eq):
    """A = [d_i; r_i x d_i] with d_i = -dF_i/dT_i (the end force on the platform per newton)."""
    d = -catenary.tension_sensitivity(eq.sag.state, eq.cables)[0]
    if eq.geometry.structure_matrix.shape[0] == 3:
        return d.T
    return np.concatenate([d.T, np.cross(eq.geometry.lever_m, d).T])


# ------------------------------------------------------------------- 1. tension sensitivity

@pytest.mark.parametrize('case', ['heavy', 'low_tension_lifted'])
def test_tension_sensitivity_equals_finite_differences_of_the_solve(case):
    """dF/dT and dL0/dT of every cable against central differences of solve(): the heavy
    robot's, and cables just above the least tension at which their catenary exists."""
    name, changes = CASES[case]
    eq = sag_eq(name, **changes)
    cables, state = eq.cables, eq.sag.state
    d_force, d_l0 = catenary.tension_sensitivity(state, cables)
    t = cables.tension_n
    h = 1e-5 * t
    plus = catenary.solve(cables.with_tension(t + h), start=state)
    minus = catenary.solve(cables.with_tension(t - h), start=state)
    assert plus.valid.all() and minus.valid.all()
    fd_force = (plus.force_n - minus.force_n) / (2 * h)[:, None]
    fd_l0 = (plus.unstrained_length_m - minus.unstrained_length_m) / (2 * h)
    for i in range(cables.n_cables):
        assert_allclose(d_force[i], fd_force[i], rtol=1e-6,
                        atol=1e-6 * np.abs(fd_force[i]).max(), err_msg=f'cable {i}')
    assert_allclose(d_l0, fd_l0, rtol=1e-6)
    # the platform-end tension moves by one newton per newton: F . dF/dT = |F|
    assert_allclose(np.einsum('ij,ij->i', state.force_n, d_force), t, rtol=1e-9)


# ------------------------------------------------------------------- 2. the equilibrium

@pytest.mark.parametrize('case', CASES)
def test_sag_equilibrium_holds_the_platform_by_quadrature(case):
    """Box, residual (reported and recomputed), and each cable integrated from its platform end
    with the solved force and L0 ends at its anchor; the end forces then hold the platform."""
    name, changes = CASES[case]
    settings = settings_of(name, **changes)
    eq = sag_eq(name, **changes)
    assert eq.statics == 'sag'
    t = eq.tensions.tension_n
    lower = np.maximum(settings.tension_min_n, eq.sag.lower_bound_n)
    assert np.all(t >= lower * (1 - 1e-12)) and np.all(t <= settings.tension_max_n * (1 + 1e-12))
    summary = equilibrium_summary(settings, eq)
    assert summary['statics'] == 'sag'
    assert summary['relative_residual'] < 1e-9
    up, gamma = up_gamma(settings)
    ea = settings.cable.ea_n
    geo = eq.geometry
    anchors = settings.robot.anchors_m
    attachments = geo.position_m + geo.lever_m
    force = np.asarray(eq.sag.state.force_n)
    l0 = np.asarray(eq.unstretched_length_m)
    assert_allclose(np.asarray(summary['unstretched_length_m']), l0, rtol=1e-15)
    assert_allclose(np.asarray(summary['end_force_n']), -force, rtol=1e-15)
    for i in range(eq.cables.n_cables):
        end = attachments[i] - integrate_cable(force[i], l0[i], ea, gamma, up)
        assert np.linalg.norm(end - anchors[i]) < 1e-8 * geo.length_m[i], f'cable {i}'
    assert_allclose(np.linalg.norm(force, axis=1), t, rtol=1e-12)    # T_i at the platform end
    residual = platform_wrench(settings, geo.lever_m, -force)
    assert relative_residual(settings, geo.lever_m, residual) < 1e-9
    assert_allclose(residual, eq.residual, atol=1e-9 * np.abs(eq.residual).max() + 1e-12
                    * settings.robot.mass_kg * 9.81)


# ------------------------------------------------------------------- 3. KKT of the objective

@pytest.mark.parametrize('case', CASES)
def test_sag_tensions_satisfy_the_kkt_conditions_of_the_least_norm_objective(case):
    """T = A^T lambda + mu_low - mu_up, mu >= 0 only on active bounds (A the exact Jacobian)."""
    name, changes = CASES[case]
    settings = settings_of(name, **changes)
    eq = sag_eq(name, **changes)
    t = eq.tensions.tension_n
    a_mat = constraint_jacobian(eq)
    assert np.all(np.isfinite(a_mat))
    lower = np.maximum(settings.tension_min_n, eq.sag.lower_bound_n)
    upper = np.full_like(t, settings.tension_max_n)
    gap = 1e-7 * settings.tension_max_n
    at_low, at_up = t <= lower + gap, t >= upper - gap
    free = ~(at_low | at_up)
    assert free.sum() >= 1
    lam = np.linalg.lstsq(a_mat[:, free].T, t[free], rcond=None)[0]
    stationarity = t[free] - a_mat[:, free].T @ lam
    # minus the step the undamped QP of the next SQP iteration would take (same active set):
    # the statics documents that it stops once that step is below OPTIMALITY_RTOL T_max, or
    # says that it did not settle (near a catenary's fold, where the end force turns sharply)
    unsettled = any('did not settle on the least-norm distribution' in w for w in eq.warnings)
    limit = (1e2 if unsettled else 1.0) * statics.OPTIMALITY_RTOL * settings.tension_max_n
    assert np.abs(stationarity).max() <= limit, stationarity
    assert unsettled == (case == 'low_tension_lifted')
    assert np.linalg.norm(stationarity) < (1e2 if unsettled else 1.0) * 1e-5 \
        * np.linalg.norm(t), stationarity
    multiplier = t - a_mat.T @ lam                  # mu_low - mu_up on the active cables
    scale = 1e-5 * np.linalg.norm(t)
    assert np.all(multiplier[at_low] >= -scale), multiplier[at_low]
    assert np.all(multiplier[at_up] <= scale), multiplier[at_up]


@pytest.mark.parametrize('case', ['heavy', 'rigid', 'low_tension_lifted'])
def test_sag_tensions_equal_a_general_nonlinear_solver(case):
    """The least-norm sag-consistent tensions found by scipy's SLSQP on the nonlinear problem
    (constraint Jacobian by its own finite differences, started from the chord tensions)."""
    name, changes = CASES[case]
    settings = settings_of(name, **changes)
    eq = sag_eq(name, **changes)
    chord = equilibrium(settings)
    lever = eq.geometry.lever_m
    weight = settings.robot.mass_kg * np.linalg.norm(settings.robot.gravity_m_s2)
    arm = np.linalg.norm(lever, axis=1).max() if settings.robot.platform_dofs == 6 else 1.0
    scale = np.r_[np.ones(3), np.full(3, 1.0 / arm)][:settings.robot.platform_dofs] / weight
    t_max = settings.tension_max_n

    def balance(t):
        state = catenary.solve(chord.cables.with_tension(t))
        return platform_wrench(settings, lever, -state.force_n) * scale

    lower = np.maximum(settings.tension_min_n, eq.sag.lower_bound_n)
    result = minimize(lambda t: 0.5 * t @ t / t_max ** 2, np.maximum(chord.tensions.tension_n,
                                                                     lower),
                      jac=lambda t: t / t_max ** 2, method='SLSQP',
                      bounds=list(zip(lower, np.full_like(lower, t_max))),
                      constraints=[{'type': 'eq', 'fun': balance}],
                      options={'ftol': 1e-14, 'maxiter': 200})
    assert result.success, result.message
    assert np.abs(balance(result.x)).max() < 1e-9
    assert_allclose(eq.tensions.tension_n, result.x, rtol=1e-7, atol=1e-7 * t_max)


# ------------------------------------------------------------------- 4. the finding

def test_chord_tensions_along_the_catenary_tangents_miss_the_weight_on_the_heavy_robot():
    settings = settings_of('heavy')
    chord = equilibrium(settings)
    assert chord.statics == 'chord'
    state = catenary.solve(chord.cables)
    assert state.valid.all()
    lever = chord.geometry.lever_m
    weight = settings.robot.mass_kg * np.linalg.norm(settings.robot.gravity_m_s2)
    missed = platform_wrench(settings, lever, -state.force_n)
    assert np.linalg.norm(missed[:3]) > 0.1 * weight, missed
    sag = sag_eq('heavy')
    assert relative_residual(settings, lever, platform_wrench(settings, lever,
                                                              sag.end_force_n)) < 1e-9
    # the chord statics itself balances along the chords
    assert relative_residual(settings, lever, platform_wrench(
        settings, lever, chord.tensions.tension_n[:, None] * chord.geometry.unit)) < 1e-9


@pytest.mark.parametrize('name', CONFIGS)
def test_weightless_cables_make_the_sag_statics_the_chord_statics(name):
    settings = settings_of(name, cable__weight_per_length_n_per_m=0.0)
    chord = equilibrium(settings)
    sag = sag_eq(name, cable__weight_per_length_n_per_m=0.0)
    assert sag.statics == 'sag'
    assert_allclose(sag.tensions.tension_n, chord.tensions.tension_n,
                    rtol=1e-9, atol=1e-9 * settings.tension_max_n)
    assert_allclose(sag.end_force_n, chord.tensions.tension_n[:, None] * chord.geometry.unit,
                    atol=1e-9 * settings.tension_max_n)


# ------------------------------------------------------------------- 5. chains of elastic bars

def chain_platform_force(anchor, attachment, l0, n, ea, gamma, up, start):
    """Force (N) on the platform of a cable as n elastic bars with lumped weights.

    Nodes x_0 = attachment (platform end) ... x_n = anchor, both fixed; bar k joins x_k and
    x_{k+1}, unstrained length l0/n, tension EA (l_k/(l0/n) - 1); each interior node carries the
    weight gamma l0/n (the end nodes half of it). Interior nodes from scipy.optimize.root
    started at ``start`` (n + 1, 3); the platform feels bar 0's pull plus its half weight.
    Returns (force, largest nodal force imbalance).
    """
    l0e = l0 / n
    weight = gamma * l0e * up

    def bars(x):
        nodes = np.vstack([attachment, x.reshape(n - 1, 3), anchor])
        d = np.diff(nodes, axis=0)
        length = np.linalg.norm(d, axis=1)
        return d / length[:, None], length, ea * (length / l0e - 1.0)

    def balance(x):
        e, length, tension = bars(x)
        pull = tension[:, None] * e                    # bar k pulls node k towards node k + 1
        out = (pull[1:] - pull[:-1] - weight).ravel()  # forces on the interior nodes
        ee = e[:, :, None] * e[:, None, :]
        k = ea / l0e * ee + (tension / length)[:, None, None] * (np.eye(3) - ee)
        jac = np.zeros((3 * (n - 1), 3 * (n - 1)))
        for j in range(n - 1):                         # node j + 1: bars j and j + 1
            jac[3 * j:3 * j + 3, 3 * j:3 * j + 3] = -k[j] - k[j + 1]
            if j + 1 < n - 1:
                jac[3 * j:3 * j + 3, 3 * j + 3:3 * j + 6] = k[j + 1]
            if j > 0:
                jac[3 * j:3 * j + 3, 3 * j - 3:3 * j] = k[j]
        return out, jac

    sol = root(balance, start[1:-1].ravel(), jac=True, method='hybr', options={'xtol': 1e-13})
    e, _, tension = bars(sol.x)
    return tension[0] * e[0] - 0.5 * weight, float(np.abs(balance(sol.x)[0]).max())


def test_chains_of_elastic_bars_converge_to_the_catenary_end_forces():
    """Heavy robot: the chains' platform forces tend to the catenaries' as n^-2, and so does
    the platform's residual wrench with the chain forces."""
    settings = settings_of('heavy')
    eq = sag_eq('heavy')
    up, gamma = up_gamma(settings)
    geo = eq.geometry
    attachments = geo.position_m + geo.lever_m
    exact = eq.end_force_n
    errors, residuals = [], []
    for n in (16, 32):
        start = fem_sag.node_positions(eq.sag.state, eq.cables, n)[:, ::-1] \
            + attachments[:, None, :]
        forces = []
        for i in range(geo.n_cables):
            force, imbalance = chain_platform_force(
                settings.robot.anchors_m[i], attachments[i], eq.unstretched_length_m[i], n,
                settings.cable.ea_n, gamma, up, start[i])
            assert imbalance < 1e-8 * eq.tensions.tension_n[i], (n, i, imbalance)
            forces.append(force)
        forces = np.array(forces)
        errors.append(np.linalg.norm(forces - exact, axis=1) / np.linalg.norm(exact, axis=1))
        residuals.append(relative_residual(settings, geo.lever_m,
                                           platform_wrench(settings, geo.lever_m, forces)))
    ratio = errors[0] / errors[1]
    assert np.all((ratio > 3.6) & (ratio < 4.4)), ratio
    assert errors[1].max() < 1e-3, errors[1]
    assert 3.6 < residuals[0] / residuals[1] < 4.4 and residuals[1] < 1e-3, residuals


# ------------------------------------------------------------------- 6. fem_sag -> catenary_exact

def test_fem_sag_static_stiffness_converges_to_catenary_exact_as_n_squared():
    settings = settings_of('heavy')
    eq = sag_eq('heavy')
    exact = build_system(settings, eq, 'catenary_exact').static_stiffness()
    errors = [np.linalg.norm(build_system(settings, eq, 'fem_sag', n).static_stiffness() - exact)
              / np.linalg.norm(exact) for n in (8, 16, 32)]
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratios > 3.8) & (ratios < 4.2)), (errors, ratios)
    assert errors[-1] < 1e-3


# ------------------------------------------------------------------- 7. stiffness by differences

def end_forces_at_fixed_lengths(settings, eq, q):
    """Cable forces on the platform displaced by q (translation, small rotation vector), each
    cable's unstrained length held: Newton on end_position(F, L0) = attachment - anchor."""
    up, gamma = up_gamma(settings)
    ea = settings.cable.ea_n
    rotation = Rotation.from_rotvec(q[3:]).as_matrix() @ eq.geometry.rotation
    geo = geometry(settings.robot, eq.geometry.position_m + q[:3], rotation)
    force = np.array(eq.sag.state.force_n)
    l0 = np.asarray(eq.unstretched_length_m)
    for _ in range(30):
        miss = catenary.end_position(force, l0, ea, gamma, up) + geo.chord_m
        if np.abs(miss).max() < 1e-14 * geo.length_m.max():
            break
        flex = catenary.flexibility(force, l0, ea, gamma, up)
        force = force - np.linalg.solve(flex, miss[..., None])[..., 0]
    else:
        raise AssertionError(f'fixed-length Newton did not converge at q = {q}')
    return geo, -force


@pytest.mark.parametrize('name', ['heavy', 'rigid'])
def test_catenary_exact_stiffness_equals_differences_of_the_wrench_at_fixed_lengths(name):
    settings = settings_of(name)
    eq = sag_eq(name)

    def wrench(q):
        geo, force = end_forces_at_fixed_lengths(settings, eq, q)
        return np.concatenate([force.sum(0), np.cross(geo.lever_m, force).sum(0)])

    assert_allclose(wrench(np.zeros(6)), np.r_[eq.end_force_n.sum(0),
                                               np.cross(eq.geometry.lever_m,
                                                        eq.end_force_n).sum(0)],
                    atol=1e-9 * settings.tension_max_n)
    h = 1e-6
    fd = np.array([-(wrench(h * e) - wrench(-h * e)) / (2 * h) for e in np.eye(6)]).T
    k = build_system(settings, eq, 'catenary_exact').static_stiffness()
    assert_allclose(k, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


# ------------------------------------------------------------------- 8. modes, dense assembly

def dense_fem_sag(settings, eq, n):
    """Global K, M (platform DOFs, then every cable's interior nodes) of fem_sag, dense.

    Nodes at sigma = k L0/n on each cable by quadrature; bar k from node k (platform side) to
    k + 1 with K_e = EA/l0 e e^T + T_e/l_e (I - e e^T), T_e = |F - gamma sigma_mid e| and
    M_e = mu l0/6 [2I I; I 2I]; node 0 moves with the platform, x_0 = u + theta x r_i, the
    anchor node not at all. Platform: diag(m I, R I_P R^T) and, as the forces f_i on it stay
    put while r_i turns, d(r_i x f_i) = (theta x r_i) x f_i = [f_i]x [r_i]x theta: stiffness
    -sum [f_i]x [r_i]x (its antisymmetric part, [sum f_i x r_i]x, vanishes at equilibrium
    without an external moment), symmetrised.
    """
    robot = settings.robot
    up, gamma = up_gamma(settings)
    ea = settings.cable.ea_n
    mu = gamma / np.linalg.norm(robot.gravity_m_s2)
    geo = eq.geometry
    ncab = geo.n_cables
    size = 6 + 3 * (n - 1) * ncab
    eye = np.eye(3)
    k_glob, m_glob = np.zeros((size, size)), np.zeros((size, size))
    for i in range(ncab):
        force, l0 = eq.sag.state.force_n[i], eq.unstretched_length_m[i]
        l0e = l0 / n
        start = geo.position_m + geo.lever_m[i]
        x = np.array([start] + [start - integrate_cable(force, l0, ea, gamma, up, k * l0e)
                                for k in range(1, n + 1)])
        to_global = np.zeros((3 * (n + 1), size))
        to_global[0:3, 0:3] = eye
        to_global[0:3, 3:6] = -skew(geo.lever_m[i])          # theta x r = -[r]x theta
        for k in range(1, n):
            col = 6 + 3 * ((n - 1) * i + k - 1)
            to_global[3 * k:3 * k + 3, col:col + 3] = eye
        k_cable = np.zeros((3 * (n + 1),) * 2)
        m_cable = np.zeros_like(k_cable)
        for k in range(n):
            d = x[k + 1] - x[k]
            length = np.linalg.norm(d)
            ee = np.outer(d, d) / length ** 2
            t_mid = np.linalg.norm(force - gamma * (k + 0.5) * l0e * up)
            ke = ea / l0e * ee + t_mid / length * (eye - ee)
            rows = slice(3 * k, 3 * k + 6)
            k_cable[rows, rows] += np.block([[ke, -ke], [-ke, ke]])
            m_cable[rows, rows] += mu * l0e / 6.0 * np.block([[2 * eye, eye], [eye, 2 * eye]])
        k_glob += to_global.T @ k_cable @ to_global
        m_glob += to_global.T @ m_cable @ to_global
    f = -eq.sag.state.force_n
    k_rot = -sum(skew(f[i]) @ skew(geo.lever_m[i]) for i in range(ncab))
    k_glob[3:6, 3:6] += 0.5 * (k_rot + k_rot.T)
    m_glob[:3, :3] += robot.mass_kg * eye
    m_glob[3:6, 3:6] += geo.rotation @ robot.inertia_kg_m2 @ geo.rotation.T
    return k_glob, m_glob


def test_fem_sag_modes_equal_a_dense_assembly_of_our_own():
    settings = settings_of('heavy')
    eq = sag_eq('heavy')
    n = 6
    k, m = dense_fem_sag(settings, eq, n)
    system = build_system(settings, eq, 'fem_sag', n)
    assert system.dofs == k.shape[0]
    mine = np.sqrt(scipy.linalg.eigh(k, m, eigvals_only=True, subset_by_index=[0, 11])) \
        / (2 * np.pi)
    assert_allclose(natural_frequencies(system, 12), mine, rtol=1e-8)


# ------------------------------------------------------------------- 9. validity

def test_paper_catenary_is_invalid_where_no_catenary_exists_and_exact_lifts_the_bound():
    settings = settings_of('low_tension', tension__min_n=0.5)
    chord = equilibrium(settings)
    with pytest.raises(AnalysisError, match='no taut elastic catenary') as info:
        analyze_method(settings.replace(method='catenary'), chord, [], 1.0)
    assert '\n' not in str(info.value)
    doc = analyze_method(settings.replace(method='catenary_exact'), chord, [], 1.0)
    lifted = [w for w in doc['warnings'] if 'its lower bound is' in w]
    assert lifted and all('tension.min_n = 0.5 N' in w for w in lifted), doc['warnings']
    assert doc['equilibrium']['statics'] == 'sag'
    assert doc['equilibrium']['relative_residual'] < 1e-9
    # the catenaries it reports exist: each closes on its chord (quadrature)
    sag = sag_eq('low_tension', tension__min_n=0.5)
    assert_allclose(doc['tensions_n'], sag.tensions.tension_n, rtol=1e-12)
    assert np.all(sag.tensions.tension_n >= sag.sag.lower_bound_n)
    assert np.any(sag.sag.lower_bound_n > settings.tension_min_n)


def paper_miss_by_quadrature(settings, eq, i):
    """|l(F = -T u, L0 = L) - (attachment - anchor)| for cable i, by quadrature."""
    up, gamma = up_gamma(settings)
    force = -eq.tensions.tension_n[i] * eq.geometry.unit[i]
    end = integrate_cable(force, eq.geometry.length_m[i], settings.cable.ea_n, gamma, up)
    return np.linalg.norm(end + eq.geometry.chord_m[i])


@pytest.mark.parametrize('name', ['heavy', 'low_tension'])
def test_paper_misclosure_equals_quadrature_and_is_warned(name):
    settings = settings_of(name)
    eq = equilibrium(settings)
    miss = catenary.paper_misclosure(eq.cables)
    mine = np.array([paper_miss_by_quadrature(settings, eq, i) for i in range(eq.cables.n_cables)])
    assert_allclose(miss, mine, rtol=1e-8)
    assembly = models.build('catenary', eq.cables)
    warnings = [w for w in model_warnings(settings, eq, assembly) if w.startswith('catenary:')]
    worst = int(np.argmax(mine / eq.geometry.length_m))
    if mine[worst] / eq.geometry.length_m[worst] > settings.tolerance:
        assert len(warnings) == 1, warnings
        match = re.search(r'cable (\d+) .* misses its anchor by ([0-9.e+-]+) m', warnings[0])
        assert match and int(match.group(1)) == worst, warnings[0]
        assert_allclose(float(match.group(2)), mine[worst], rtol=5e-3)
    else:
        assert not warnings
    if name == 'heavy':
        assert mine.max() > 1.0            # metres: the paper's assumed catenary is far off


def test_fem_sag_sag_resolution_warning():
    settings = settings_of('heavy')
    eq = sag_eq('heavy')

    def sag_warnings(n):
        return [w for w in model_warnings(settings, eq, models.build('fem_sag', eq.cables, n))
                if w.startswith('sag:') and 'fem_sag' in w]

    coarse, fine = sag_warnings(1), sag_warnings(64)
    assert len(coarse) == 1 and 'with 1 element' in coarse[0], coarse
    if fine:
        def percent(text):
            return float(re.search(r'~([0-9.e+-]+) %', text).group(1))
        assert percent(fine[0]) < percent(coarse[0])


def box_in_box(tmp_path):
    """8 cables from the corners of a 2.5 x 2.5 x 3 m frame to the facing corners of a 0.4 m
    cube at its centre: every cable's horizontal part points along its lever's, so no cable has
    a moment about z (the frame is not a scaled cube, so the x and y moments remain)."""
    flat = read_params_file(RIGID)
    anchors = np.array(flat['robot.anchors']).reshape(-1, 3)
    anchors[anchors[:, 2] > 0, 2] = 3.0
    centre = np.array([0.0, 0.0, 1.5])
    attachments = 0.2 * np.sign(anchors - centre)
    return write_config(tmp_path, RIGID, **{'robot.anchors': anchors.ravel().tolist(),
                                            'robot.attachments': attachments.ravel().tolist(),
                                            'robot.initial_position': centre.tolist()})


@pytest.mark.slow
def test_rank_deficient_box_in_box_design_is_refused(tmp_path):
    path = box_in_box(tmp_path)
    settings = settings_from_params(read_params_file(path))
    # our own structure matrix: rank 5, the wrench it cannot make is a pure moment about z
    lever = settings.robot.attachments_m
    chord = settings.robot.anchors_m - settings.initial_position_m - lever
    unit = chord / np.linalg.norm(chord, axis=1)[:, None]
    wt = np.vstack([unit.T, np.cross(lever, unit).T])
    assert np.linalg.matrix_rank(wt) == 5
    missing = scipy.linalg.null_space(wt.T)[:, 0]
    assert_allclose(np.abs(missing), [0, 0, 0, 0, 0, 1], atol=1e-12)
    with pytest.raises(AnalysisError) as info:
        equilibrium(settings)
    text = str(info.value)
    assert 'rank 5 < 6' in text and 'moment z' in text and '\n' not in text
    result = analyze('--config', path)
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and 'rank 5 < 6' in lines[0] and 'moment z' in lines[0], \
        result.stderr
    assert 'Traceback' not in result.stderr + result.stdout


def segment_gap(p0, p1, q0, q1):
    """Least distance (m) between segments p0-p1 and q0-q1: bounded least squares on (s, t)."""
    d1, d2 = p1 - p0, q1 - q0
    best = np.inf
    for s0, t0 in ((0.5, 0.5), (0.0, 0.0), (1.0, 1.0), (0.0, 1.0), (1.0, 0.0)):
        fit = minimize(lambda st: np.sum((p0 + st[0] * d1 - q0 - st[1] * d2) ** 2), [s0, t0],
                       bounds=[(0, 1), (0, 1)], method='L-BFGS-B',
                       options={'ftol': 1e-20, 'gtol': 1e-14})
        best = min(best, float(np.sqrt(fit.fun)))
    return best


@pytest.mark.slow
def test_crossing_cables_are_refused_by_cdpr_analyze(tmp_path):
    """rigid_cdpr.yaml turned 45 degrees about z (the pose the node refuses in test_node_dds):
    one line naming two cables, which do come within the cable diameter of each other."""
    turn = Rotation.from_euler('z', 45, degrees=True).as_quat().tolist()
    path = write_config(tmp_path, RIGID, **{'robot.initial_orientation': turn})
    result = analyze('--config', path)
    assert result.returncode == 1, result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    match = re.search(r'cables (\d+) and (\d+) cross', lines[0])
    assert match, lines[0]
    i, j = int(match.group(1)), int(match.group(2))
    settings = settings_from_params(read_params_file(path))
    rotation = Rotation.from_quat(turn).as_matrix()
    ends = settings.initial_position_m + settings.robot.attachments_m @ rotation.T
    anchors = settings.robot.anchors_m
    diameter = 2.0 * np.sqrt(settings.cable.area_m2 / np.pi)
    assert segment_gap(ends[i], anchors[i], ends[j], anchors[j]) < diameter
    # the unturned robot's cables keep clear of each other (so the turn is what is refused)
    plain = settings_of('rigid')
    ends0 = plain.initial_position_m + plain.robot.attachments_m
    along = np.linspace(0.0, 1.0, 101)[:, None, None]
    points = ends0 + along * (anchors - ends0)                     # (101, 8, 3), ~3 cm apart
    gaps = np.linalg.norm(points[:, None, :, None] - points[None, :, None, :], axis=-1)
    gaps = gaps.min(axis=(0, 1))[np.triu_indices(8, 1)]
    assert gaps.min() > 10 * diameter


# ---------------------------------------------------------------------- the SQP's fast path

#: the robots, and the lifted lower bounds of the low-tension and heavy ones
SQP_CASES = {'paper': ('paper', None), 'heavy': ('heavy', None), 'rigid': ('rigid', None),
             'low_tension': ('low_tension', None), 'low_tension_lifted': ('low_tension', 0.5),
             'heavy_lifted': ('heavy', 0.5)}


def general_solve_with_sensitivity(cables, start=None, warm_only=False):
    """The general path: solve (both starts), then the sensitivity of the lifted forces."""
    state = catenary.solve(cables, start=start)
    return (state, *catenary.tension_sensitivity(state, cables))


def pose_sequence(settings, n=24, seed=5):
    """A 5 cm circle of 12 poses, then a random walk of 3 cm steps with small rotations."""
    rng = np.random.default_rng(seed)
    start = np.asarray(settings.initial_position_m, dtype=float)
    poses = [(start + 0.05 * np.array([np.cos(a), np.sin(a), 0.0]), np.eye(3))
             for a in np.linspace(0.0, 2 * np.pi, n // 2, endpoint=False)]
    position = start
    for _ in range(n - n // 2):
        position = position + rng.normal(0.0, 0.03, 3)
        poses.append((position, Rotation.from_rotvec(rng.normal(0.0, 0.02, 3)).as_matrix()))
    return poses


def sag_sequence(settings, poses):
    """(tensions, end forces, L0, iterations, warnings) or the refusal's text, per pose, each
    pose warm-started from the previous answer (as the live predictor does)."""
    out, previous = [], None
    for position, rot in poses:
        try:
            eq = equilibrium(settings, position, rot, method='catenary_exact', start=previous)
        except AnalysisError as exc:
            out.append(str(exc))
            previous = None
            continue
        out.append((eq.tensions.tension_n, eq.end_force_n, eq.unstretched_length_m,
                    eq.iterations, eq.warnings))
        previous = eq
    return out


@pytest.mark.slow
@pytest.mark.parametrize('case', sorted(SQP_CASES))
def test_fast_sag_statics_equal_the_general_path(case, monkeypatch):
    name, t_min = SQP_CASES[case]
    settings = load_settings(str(CONFIGS[name])).replace(method='catenary_exact')
    if t_min is not None:
        settings = settings.replace(tension_min_n=t_min)
    poses = pose_sequence(settings)
    fast = sag_sequence(settings, poses)
    monkeypatch.setattr(catenary, 'solve_with_sensitivity', general_solve_with_sensitivity)
    general = sag_sequence(settings, poses)
    t_max = settings.tension_max_n
    solved = 0
    for mine, ref in zip(fast, general):
        assert type(mine) is type(ref)
        if isinstance(ref, str):
            assert mine == ref                      # the same refusal, word for word
            continue
        solved += 1
        tension, force, l0, iterations, warnings = mine
        assert iterations == ref[3] and warnings == ref[4]
        assert_allclose(tension, ref[0], rtol=0, atol=1e-9 * t_max)
        assert_allclose(tension, ref[0], rtol=1e-11)
        assert_allclose(force, ref[1], rtol=0, atol=1e-11 * np.abs(ref[1]).max())
        assert_allclose(l0, ref[2], rtol=1e-11)
    assert solved >= len(poses) // 2


@pytest.mark.slow
def test_lifted_sequences_exercise_the_probes_and_the_halvings(monkeypatch):
    """The lifted cases above go through lowest_tension's probes and halved SQP steps."""
    calls = {'lowest': 0, 'halved': 0}
    lowest, solve = statics.lowest_tension, catenary.solve_with_sensitivity

    def count_lowest(*args, **kwargs):
        calls['lowest'] += 1
        return lowest(*args, **kwargs)

    def count_trials(cables, start=None, warm_only=False):
        calls['halved'] += warm_only
        return solve(cables, start=start, warm_only=warm_only)

    monkeypatch.setattr(statics, 'lowest_tension', count_lowest)
    monkeypatch.setattr(catenary, 'solve_with_sensitivity', count_trials)
    settings = load_settings(str(CONFIGS['heavy']))
    settings = settings.replace(method='catenary_exact', tension_min_n=0.5)
    iterations = 0
    for item in sag_sequence(settings, pose_sequence(settings, n=6)):
        iterations += 0 if isinstance(item, str) else item[3] - 1
    assert calls['lowest'] > 0
    assert calls['halved'] > iterations           # more trial solves than accepted steps


@pytest.mark.slow
@pytest.mark.parametrize('seed', range(4))
def test_solve_with_sensitivity_equals_solve_then_tension_sensitivity(seed):
    rng = np.random.default_rng(seed)
    for _ in range(25):
        n = int(rng.integers(1, 9))
        chord = rng.normal(size=(n, 3)) * rng.uniform(0.1, 5.0, (n, 1))
        gamma = float(rng.choice([0.0, 0.5, 5.0]))
        tension = (gamma + 1.0) * np.linalg.norm(chord, axis=1) * rng.uniform(-0.2, 4.0, n)
        cables = CableSet(chord, tension, float(rng.choice([1e4, 1e6])), gamma, (0, 0, -9.81))
        start = catenary.solve(cables)
        moved = cables.with_tension(tension * (1.0 + rng.normal(0.0, 0.01, n)))
        for warm_only in (False, True):
            state, d_force, d_length = catenary.solve_with_sensitivity(moved, start, warm_only)
            ref = catenary.solve(moved, start=start)
            ref_force, ref_length = catenary.tension_sensitivity(ref, moved)
            assert np.array_equal(state.valid, ref.valid) and state.reasons == ref.reasons
            ok = ref.valid
            assert_allclose(state.force_n[ok], ref.force_n[ok], rtol=1e-12,
                            atol=1e-12 * np.abs(moved.tension_n).max())
            assert_allclose(state.unstrained_length_m, ref.unstrained_length_m, rtol=1e-12)
            assert np.array_equal(np.isnan(d_length), np.isnan(ref_length))
            fin = ~np.isnan(ref_length)     # rounding of the lift and back, where d.w cancels
            assert_allclose(d_length[fin], ref_length[fin], rtol=1e-8,
                            atol=1e-8 * np.abs(ref_length[fin]).max(initial=0.0))
            assert_allclose(d_force[fin], ref_force[fin], rtol=1e-8,
                            atol=1e-8 * np.abs(ref_force[fin]).max(initial=0.0))
            if not warm_only:       # the same solve: the very same catenaries
                assert np.array_equal(state.force_n, ref.force_n)
