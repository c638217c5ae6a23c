"""``fem_sag``: convergence to the elastic catenary, the weightless limit, Irvine's modes.

Irvine (Cable Structures, 1981, Ch. 3) for a level cable of span L, horizontal tension H and
mass mu per length, w = omega L / sqrt(H/mu): out-of-plane modes w = n pi, antisymmetric
in-plane w = 2 pi n, first symmetric in-plane tan(w/2) = w/2 - (4/lambda^2)(w/2)^3 with
lambda^2 = (mu g L/H)^2 L/(H L_e/EA), L_e = L (1 + 8 (d/L)^2).
"""
import math

import numpy as np
import pytest
import scipy.linalg
from numpy.testing import assert_allclose
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from cdpr_dynamics import models
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import platform_system
from cdpr_dynamics.dynamics.modes import natural_frequencies
from cdpr_dynamics.models import catenary
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.mechanics.robot import geometry

EA = 2.01e10 * 5.0265e-5
G = np.array([0.0, 0.0, -9.81])


def paper_cables():
    s = load_settings()
    g = geometry(s.robot, s.initial_position_m, s.initial_rotation)
    tension = np.where(g.unit[:, 2] > 0, 100 + 30 * 9.81 * math.sqrt(3) / 4, 100.0)
    return s, g, CableSet(g.chord_m, tension, s.cable.ea_n, s.cable.weight_per_length_n_per_m,
                          s.robot.gravity_m_s2)


# sagging cables of several shapes: (chord, tension, gamma)
SAGGING = CableSet(np.array([[3.0, 0.0, 0.5], [-2.0, 1.0, -3.0], [0.5, 0.0, 3.0],
                             [1.0, -2.5, 0.0]]), np.array([20.0, 15.0, 5.0, 12.0]), EA, 2.0, G)


def chain_matrices(blocks, cable):
    """Dense K, M of one cable's free nodes (anchor fixed, platform end node last)."""
    n = blocks.nodes
    k, m = np.zeros((3 * n, 3 * n)), np.zeros((3 * n, 3 * n))
    for j in range(n):
        k[3 * j:3 * j + 3, 3 * j:3 * j + 3] = blocks.k_diag[cable, j]
        m[3 * j:3 * j + 3, 3 * j:3 * j + 3] = blocks.m_diag[cable, j]
    for j in range(n - 1):
        for mat, off in ((k, blocks.k_off), (m, blocks.m_off)):
            mat[3 * j:3 * j + 3, 3 * j + 3:3 * j + 6] = off[cable, j]
            mat[3 * j + 3:3 * j + 6, 3 * j:3 * j + 3] = off[cable, j].T
    return k, m


def fixed_fixed_omegas(blocks, cable=0, directions=(0, 1, 2), count=4):
    """Lowest circular frequencies of a cable with both ends fixed (platform node removed),
    restricted to the given displacement directions of the interior nodes."""
    k, m = chain_matrices(blocks, cable)
    interior = blocks.nodes - 1
    idx = np.array([3 * j + d for j in range(interior) for d in directions])
    values = scipy.linalg.eigh(k[np.ix_(idx, idx)], m[np.ix_(idx, idx)], eigvals_only=True,
                               subset_by_index=[0, count - 1])
    return np.sqrt(values)


# ------------------------------------------------------------------------ statics

@pytest.mark.parametrize('which', ['paper', 'sagging'])
def test_static_condensation_converges_to_catenary_exact(which):
    """sum of element flexibilities = midpoint rule of the catenary's: error ~ n^-2."""
    cables = paper_cables()[2] if which == 'paper' else SAGGING
    exact = models.build('catenary_exact', cables).static_end_stiffness()
    scale = np.linalg.norm(exact, axis=(1, 2))
    errors = []
    for n in [8, 16, 32, 64]:
        k = models.build('fem_sag', cables, n).static_end_stiffness()
        errors.append(np.max(np.linalg.norm(k - exact, axis=(1, 2)) / scale))
    rates = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all((rates > 1.9) & (rates < 2.1)), rates
    assert errors[-1] < (5e-6 if which == 'paper' else 1e-3)


def test_end_stiffness_matches_the_blocks():
    """The series recursion of end_stiffness is the Schur complement of ``blocks``."""
    assembly = models.build('fem_sag', SAGGING, 8)
    lams = np.array([0.0, 3e3, 2e4 + 500j, 1e5 - 2e3j])
    ends = assembly.end_stiffness(lams)
    for cable in range(SAGGING.n_cables):
        k, m = chain_matrices(assembly.blocks, cable)
        for lam, end in zip(lams, ends[:, cable]):
            z = k - lam * m
            schur = z[-3:, -3:] - z[-3:, :-3] @ np.linalg.solve(z[:-3, :-3], z[:-3, -3:])
            assert_allclose(end, schur, rtol=1e-7, atol=1e-8 * np.abs(schur).max())


def test_stiffness_rotates_with_the_scene():
    rot = Rotation.from_euler('zyx', [0.7, 0.3, -1.3]).as_matrix()
    turned = CableSet(SAGGING.chord_m @ rot.T, SAGGING.tension_n, EA, 2.0, rot @ G)
    lam = np.array([5e3 + 10j])
    z = models.build('fem_sag', SAGGING, 12).end_stiffness(lam)
    assert_allclose(models.build('fem_sag', turned, 12).end_stiffness(lam), rot @ z @ rot.T,
                    rtol=1e-8, atol=1e-10 * np.abs(z).max())


# ------------------------------------------------------------------------ weightless limit

def weightless(cables, eps=1e-9, ea=None, mass_scale=1.0):
    """Same mass per length, weight (gamma and g) scaled by eps: sag -> 0."""
    return CableSet(cables.chord_m, cables.tension_n, cables.ea_n if ea is None else ea,
                    cables.weight_per_length_n_per_m * eps * mass_scale, cables.gravity_m_s2 * eps)


@pytest.mark.parametrize('n', [1, 4, 16])
def test_weightless_fem_sag_is_fem(n):
    """No weight: straight elements at uniform T. fem_sag's axial term is EA/l0 = (EA + T)/l
    and its mass mu L0 = mu L/(1 + T/EA); the paper's fem has EA/l and mu L. So (a) the two
    agree to T/EA (< 3e-4 here: tolerance 1e-3 on stiffness and frequencies), and (b) fem with
    EA + T (one cable) and the unstrained mass is fem_sag to rounding."""
    s, g, cables = paper_cables()
    light = weightless(cables)
    lams = np.array([0.0, (2 * np.pi * 5.0) ** 2, (2 * np.pi * 30.0) ** 2 * (1 + 0.01j)])
    sag = models.build('fem_sag', light, n)
    straight = models.build('fem', light, n)
    assert sag.valid
    z_sag, z_fem = sag.end_stiffness(lams), straight.end_stiffness(lams)
    assert_allclose(z_sag, z_fem, rtol=1e-3, atol=1e-3 * np.abs(z_fem).max())
    f_sag = natural_frequencies(platform_system(s.robot, g, sag), 12)
    f_fem = natural_frequencies(platform_system(s.robot, g, straight), 12)
    assert_allclose(f_sag, f_fem, rtol=1e-3)
    for i in [0, 4]:                                   # one lower, one upper cable
        t = cables.tension_n[i]
        one = CableSet(cables.chord_m[i:i + 1], cables.tension_n[i:i + 1], EA, 0.251,
                       cables.gravity_m_s2)
        sag_one = models.build('fem_sag', weightless(one), n)
        fem_one = models.build('fem', weightless(one, ea=EA + t, mass_scale=1 / (1 + t / EA)),
                               n)
        z1, z2 = sag_one.end_stiffness(lams), fem_one.end_stiffness(lams)
        assert_allclose(z1, z2, rtol=1e-7, atol=1e-9 * np.abs(z2).max())


# ------------------------------------------------------------------------ Irvine's modes

def irvine_symmetric(lam2):
    """First symmetric in-plane root of tan(w/2) = w/2 - (4/lambda^2)(w/2)^3, in (pi, 3pi)."""
    return 2 * brentq(lambda x: math.tan(x) - x + 4 / lam2 * x ** 3, math.pi / 2 + 1e-9,
                      1.5 * math.pi - 1e-9)


@pytest.mark.parametrize('lam2,sag_ratio', [(1.0, 0.002), (4 * math.pi ** 2, 0.005),
                                            (100.0, 0.01)])
def test_level_cable_reproduces_irvine(lam2, sag_ratio):
    """Span 10 m, H about 1000 N, EA chosen for lambda^2; 100 elements. Irvine's linear theory
    itself is good to O((d/L)^2, H/EA), the mesh to O(n^-2): agreement within 1e-3."""
    span, h = 10.0, 1000.0
    gamma = 8 * sag_ratio * h / span
    ea = lam2 * h / (gamma * span / h) ** 2 * (1 + 8 * sag_ratio ** 2)
    cables = CableSet(np.array([[-span, 0.0, 0.0]]), np.array([math.hypot(h, gamma * span / 2)]),
                      ea, gamma, G)
    assembly = models.build('fem_sag', cables, 100)
    assert assembly.valid
    force = catenary.solve(cables).force_n[0]
    h = math.hypot(force[0], force[1])                  # the solved horizontal tension
    mu = cables.mass_per_length_kg_m
    d = gamma * span ** 2 / (8 * h)
    lam2 = (gamma * span / h) ** 2 * span / (h * span * (1 + 8 * (d / span) ** 2) / ea)
    scale = math.sqrt(h / mu) / span                    # omega = w sqrt(H/mu)/L
    in_plane = fixed_fixed_omegas(assembly.blocks, directions=(0, 2), count=2) / scale
    out_of_plane = fixed_fixed_omegas(assembly.blocks, directions=(1,), count=2) / scale
    expected = sorted([irvine_symmetric(lam2), 2 * math.pi])
    assert_allclose(in_plane, expected, rtol=1e-3)
    assert_allclose(out_of_plane, [math.pi, 2 * math.pi], rtol=1e-3)
    # and the two planes are really uncoupled: all modes = in-plane + out-of-plane (to the
    # ~eps EA/T accuracy of the eigenvalues)
    both = fixed_fixed_omegas(assembly.blocks, count=4) / scale
    assert_allclose(both, np.sort(np.concatenate([in_plane, out_of_plane])), rtol=1e-7)


@pytest.mark.parametrize('cable', range(4))
def test_reversing_the_ends_changes_nothing(cable):
    """Solved from the anchor with the anchor's tension: same nodes, same element tensions,
    so the same fixed-fixed modes and the same static end stiffness."""
    one = CableSet(SAGGING.chord_m[cable:cable + 1], SAGGING.tension_n[cable:cable + 1], EA,
                   2.0, G)
    state = catenary.solve(one)
    flipped = CableSet(-one.chord_m, state.anchor_tension_n, EA, 2.0, G)
    a, b = models.build('fem_sag', one, 24), models.build('fem_sag', flipped, 24)
    assert_allclose(fixed_fixed_omegas(b.blocks, count=6),
                    fixed_fixed_omegas(a.blocks, count=6), rtol=1e-7)   # eigh: ~eps EA/T
    k = a.static_end_stiffness()
    assert_allclose(b.static_end_stiffness(), k, rtol=1e-8, atol=1e-9 * np.abs(k).max())


# ------------------------------------------------------------------------ the paper's robot

def test_paper_robot_modes():
    """fem_sag on the paper's robot: a few tenths of a percent from the straight fem (the
    paper's cables are taut, lambda^2 <= 0.2), converging with n; build in ms."""
    s, g, cables = paper_cables()
    f16 = natural_frequencies(platform_system(s.robot, g, models.build('fem_sag', cables, 16)))
    f64 = natural_frequencies(platform_system(s.robot, g, models.build('fem_sag', cables, 64)))
    fem = natural_frequencies(platform_system(s.robot, g, models.build('fem', cables, 16)))
    assert_allclose(f16, fem, rtol=1e-2)
    assert_allclose(f64, f16, rtol=3e-3)
    assert_allclose(f64[[0, 2, 4, 5, 7, 8]], [14.4257, 14.4285, 14.4481, 14.4852, 14.5463,
                                              21.7627], rtol=1e-4)


# ------------------------------------------------------------------------ validity

@pytest.mark.parametrize('chord,tension,valid', [
    ((0.0, 0.0, 2.0), 5.0, True),           # hanging vertically below the anchor: H = 0
    ((0.0, 0.0, -2.0), 2.5, True),          # standing below the platform, just held
    ((0.0, 0.0, -2.0), 1.5, False),         # ... too light to hold its own 2 N
    ((2.0, 0.0, 0.0), 1.0, False),          # no catenary spans the level chord (T < 1.51 N)
    ((2.0, 0.0, 0.0), 1.52, True),          # just above: very deep sag
    ((2.0, 0.0, 0.0), 0.0, False),          # slack
    ((1.0, 1.0, 1.0), -3.0, False)])
def test_validity_near_slack(chord, tension, valid):
    cables = CableSet(np.array([chord, (0.0, 1.0, 1.0)], dtype=float),
                      np.array([tension, 50.0]), 1e5, 1.0, G)
    assembly = models.build('fem_sag', cables, 16)
    assert assembly.valid == valid
    if not valid:
        assert assembly.warnings[0].startswith('cable 0')
        assert 'not valid' in assembly.warnings[-1]
    z = assembly.end_stiffness(np.array([0.0, 400.0, 1e4 + 100j]))
    assert np.all(np.isfinite(z))
    for block in assembly.blocks:
        assert np.all(np.isfinite(block))
    assert np.all(np.isfinite(assembly.end_force_n))
    k = assembly.static_end_stiffness()
    assert np.all(np.linalg.eigvalsh(k) > 0)
