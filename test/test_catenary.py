"""The elastic catenary (``catenary``, ``catenary_exact``) against independent answers.

Flexibility against finite differences and the position against quadrature of the catenary
integral; the paper's Eqs. 25 and 29 as corrected; limits (weightless: spring; vertical:
closed form; H -> 0: continuous); the end-swap symmetry; closure of the Newton solve; validity.
"""
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.integrate import quad
from scipy.spatial.transform import Rotation

from cdpr_dynamics import models
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import platform_system
from cdpr_dynamics.dynamics.modes import natural_frequencies
from cdpr_dynamics.models import catenary
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.mechanics.robot import geometry

EA = 2.01e10 * 5.0265e-5
GAMMA = 0.251
G = np.array([0.0, 0.0, -9.81])
UP = np.array([0.0, 0.0, 1.0])

# (force at B on the cable N, unstrained length m, gamma N/m, up): heavy cables (gamma L0 a
# sizeable part of T) so that every term of the closed forms matters
TILTED_UP = np.array([0.3, -0.4, math.sqrt(0.75)])
CASES = {
    'rising': (np.array([80.0, 30.0, 60.0]), 3.0, 7.5, UP),
    'falling': (np.array([80.0, -30.0, -60.0]), 3.0, 7.5, UP),
    'low point inside': (np.array([30.0, 10.0, 5.0]), 3.0, 7.5, UP),
    'nearly vertical, B on top': (np.array([1e-3, 0.0, 100.0]), 3.0, 7.5, UP),
    'nearly vertical, B below': (np.array([0.0, 1e-3, -100.0]), 3.0, 7.5, UP),
    'paper lower cable': (np.array([57.7, 57.7, 57.7]), 2.165, GAMMA, UP),
    'tilted gravity': (np.array([40.0, 70.0, -20.0]), 3.0, 7.5, TILTED_UP),
}
CASE_IDS = list(CASES)


def ea_for(case):
    return 1e5 if case == 'low point inside' else EA


def one_cable(chord, tension, gamma=GAMMA, ea=EA, gravity=G):
    return CableSet(np.array([chord], dtype=float), np.array([float(tension)]), ea, gamma,
                    np.asarray(gravity, dtype=float))


def paper_cables():
    s = load_settings()
    g = geometry(s.robot, s.initial_position_m, s.initial_rotation)
    tension = np.where(g.unit[:, 2] > 0, 100 + 30 * 9.81 * math.sqrt(3) / 4, 100.0)
    cables = CableSet(g.chord_m, tension, s.cable.ea_n, s.cable.weight_per_length_n_per_m,
                      s.robot.gravity_m_s2)
    return s, g, cables


# ------------------------------------------------------------------------ the closed forms

@pytest.mark.parametrize('case', CASE_IDS)
def test_flexibility_is_the_derivative_of_the_end_position(case):
    """Analytic dl/dF against central differences of the end position (Eq. 25 corrected)."""
    force, length, gamma, up = CASES[case]
    ea = ea_for(case)
    flex = catenary.flexibility(force, length, ea, gamma, up)
    h = 1e-5 * np.linalg.norm(force)
    numeric = np.empty((3, 3))
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        numeric[:, j] = (catenary.end_position(force + d, length, ea, gamma, up)
                         - catenary.end_position(force - d, length, ea, gamma, up)) / (2 * h)
    # truncation (h/|F|)^2 ~ 1e-10 and rounding eps |l| / h ~ 1e-12 of the largest entry
    assert_allclose(flex, numeric, rtol=1e-6, atol=1e-8 * np.abs(flex).max())
    assert_allclose(flex, flex.T, rtol=0, atol=1e-14 * np.abs(flex).max())
    assert np.all(np.linalg.eigvalsh(flex) > 0)          # K = C^-1 positive definite


@pytest.mark.parametrize('case', CASE_IDS)
def test_end_position_matches_quadrature_of_the_catenary(case):
    """l = F L0/EA - gamma L0^2/(2 EA) e + int_0^L0 (F - gamma s e)/|F - gamma s e| ds."""
    force, length, gamma, up = CASES[case]
    ea = ea_for(case)

    def integrand(sigma, i):
        v = force - gamma * sigma * up
        return v[i] / np.linalg.norm(v)

    integral = np.array([quad(integrand, 0.0, length, args=(i,), epsabs=1e-13, epsrel=1e-13,
                              limit=200)[0] for i in range(3)])
    expected = force * length / ea - gamma * length ** 2 / (2 * ea) * up + integral
    assert_allclose(catenary.end_position(force, length, ea, gamma, up), expected,
                    rtol=1e-11, atol=1e-12)
    t_b, t_a, _ = catenary.tensions(force, length, gamma, up)
    assert_allclose([t_b, t_a], [np.linalg.norm(force),
                                 np.linalg.norm(force - gamma * length * up)], rtol=1e-14)


def paper_eq25_corrected(fp, length, ea, gamma):
    """The paper's Eq. 25 with its misprints corrected, in the paper's own variables.

    ``fp`` is the force at node I ON the cable (I at the origin, z up), the result J - I.
    """
    f1, f2, f3 = fp
    ti = math.sqrt(f1 * f1 + f2 * f2 + f3 * f3)
    f6 = gamma * length - f3
    tj = math.sqrt(f1 * f1 + f2 * f2 + f6 * f6)
    log = math.log((tj + f6) / (ti - f3))
    return np.array([-f1 * length / ea - f1 / gamma * log,
                     -f2 * length / ea - f2 / gamma * log,
                     -f3 * length / ea + gamma * length ** 2 / (2 * ea) + (tj - ti) / gamma])


def paper_eq29(fp, length, ea, gamma, printed=False):
    """The paper's Eq. 29 (flexibility dl/dF_I), corrected or as printed."""
    f1, f2, f3 = fp
    ti = math.sqrt(f1 * f1 + f2 * f2 + f3 * f3)
    f6 = gamma * length - f3
    tj = math.sqrt(f1 * f1 + f2 * f2 + f6 * f6)
    diag = -(length / ea + math.log((tj + f6) / (ti - f3)) / gamma)
    bracket = (1 / (ti * (ti - f3)) - 1 / (tj * (tj + f6))) / gamma
    f13 = f1 / gamma * (1 / tj - 1 / ti)
    f23 = f2 / gamma * ((1 / ti - 1 / tj) if printed else (1 / tj - 1 / ti))
    f33 = -length / ea - (f6 / ti + f3 / ti if printed else f6 / tj + f3 / ti) / gamma
    return np.array([[diag + f1 * f1 * bracket, f1 * f2 * bracket, f13],
                     [f1 * f2 * bracket, diag + f2 * f2 * bracket, f23],
                     [f13, f23, f33]])


@pytest.mark.parametrize('case', ['rising', 'falling', 'low point inside', 'paper lower cable'])
def test_corrected_paper_equations_agree(case):
    """Eq. 25/29 in the paper's variables: F_I = gamma L0 e - F, same l, dl/dF_I = -C.

    The printed f23 (sign) and f33 (F6/T_i for F6/T_j) are wrong: they disagree.
    """
    force, length, gamma, up = CASES[case]
    ea = ea_for(case)
    fp = gamma * length * up - force
    assert_allclose(paper_eq25_corrected(fp, length, ea, gamma),
                    catenary.end_position(force, length, ea, gamma, up), rtol=1e-10, atol=1e-13)
    flex = catenary.flexibility(force, length, ea, gamma, up)
    assert_allclose(paper_eq29(fp, length, ea, gamma), -flex, rtol=1e-9,
                    atol=1e-12 * np.abs(flex).max())
    printed = paper_eq29(fp, length, ea, gamma, printed=True)
    assert not np.allclose(printed, -flex, rtol=1e-3, atol=0)


def test_paper_form_fails_for_a_vertical_cable_hanging_from_node_i():
    """T_i - F3 = 0 when node I is the top of a vertical cable: Eq. 29 is 0/0, ours finite."""
    fp = np.array([0.0, 0.0, 100.0])          # force at the top end I, pointing up
    with np.errstate(all='ignore'):
        assert not np.all(np.isfinite(paper_eq29(fp, 3.0, EA, 7.5)))
    flex = catenary.flexibility(7.5 * 3.0 * UP - fp, 3.0, EA, 7.5, UP)
    assert np.all(np.isfinite(flex))


# ------------------------------------------------------------------------ limits

@pytest.mark.parametrize('gamma', [0.0, 1e-9])
@pytest.mark.parametrize('chord', [(1.2, -0.9, 1.6), (2.0, 0.0, 0.0), (0.0, 0.0, -1.5)])
def test_catenary_tends_to_spring_without_weight(gamma, chord):
    """gamma -> 0: K = EA/L u u^T + T/L EA/(EA + T) (I - u u^T) for ``catenary`` (L0 = chord:
    transverse flexibility L/EA + L/T), (EA + T)/L u u^T + T/L (I - u u^T) for
    ``catenary_exact`` (L0 = L/(1 + T/EA)); ``spring`` has EA/L and T/L."""
    tension = 250.0
    cables = one_cable(chord, tension, gamma=gamma)
    length, u = cables.length_m[0], cables.unit[0]
    uu, ea = np.outer(u, u), EA
    k_cat = models.build('catenary', cables).static_end_stiffness()[0]
    k_exact = models.build('catenary_exact', cables).static_end_stiffness()[0]
    k_spring = models.build('spring', cables).static_end_stiffness()[0]
    expected = ea / length * uu + tension / length * ea / (ea + tension) * (np.eye(3) - uu)
    assert_allclose(k_cat, expected, rtol=1e-9, atol=1e-11 * ea / length)   # sag: O(gamma)
    expected = (ea + tension) / length * uu + tension / length * (np.eye(3) - uu)
    assert_allclose(k_exact, expected, rtol=1e-9, atol=1e-11 * ea / length)
    # relative to the spring: axial identical, transverse smaller by T/(EA + T)
    assert_allclose(u @ k_cat @ u, u @ k_spring @ u, rtol=1e-9)
    assert_allclose(np.trace(k_cat) - u @ k_cat @ u,
                    (np.trace(k_spring) - u @ k_spring @ u) * ea / (ea + tension), rtol=1e-9)


@pytest.mark.parametrize('platform_below', [True, False])
def test_vertical_cable_closed_form(platform_below):
    """H = 0: axial flexibility L0/EA, lateral L0/EA + ln(T_top/T_bottom)/gamma (the integral
    of d sigma/T along the hanging cable); finite, and the limit of H -> 0."""
    gamma, length, tension = 7.5, 2.0, 100.0
    chord = (0.0, 0.0, length) if platform_below else (0.0, 0.0, -length)
    cables = one_cable(chord, tension, gamma=gamma)
    k = models.build('catenary', cables).static_end_stiffness()[0]
    top, bottom = (tension + gamma * length, tension) if platform_below else \
        (tension, tension - gamma * length)
    lateral = length / EA + math.log(top / bottom) / gamma
    assert_allclose(k, np.diag([1 / lateral, 1 / lateral, EA / length]), rtol=1e-12)
    # continuity as the cable tilts: C(H) - C(0) = O(H/T)
    force = -tension * cables.unit[0]
    flex0 = catenary.flexibility(force, length, EA, gamma, UP)
    for h in [1e-3, 1e-6, 1e-9]:
        flex = catenary.flexibility(force + [h * tension, 0.0, 0.0], length, EA, gamma, UP)
        assert_allclose(flex, flex0, rtol=0, atol=10 * h * np.abs(flex0).max())


def test_exact_solution_of_a_vertical_cable_stays_vertical():
    cables = one_cable((0.0, 0.0, 2.0), 100.0, gamma=7.5)
    state = catenary.solve(cables)
    assert state.valid[0]
    assert_allclose(state.force_n[0], [0.0, 0.0, -100.0], atol=1e-12)
    # stretched length of the hanging cable: int (1 + T/EA) = L0 + (T L0 + gamma L0^2/2)/EA
    l0 = state.unstrained_length_m[0]
    assert_allclose(l0 + (100.0 * l0 + 7.5 * l0 ** 2 / 2) / EA, 2.0, rtol=1e-14)
    assert np.all(np.isfinite(models.build('catenary_exact', cables).static_end_stiffness()))


# ------------------------------------------------------------------------ symmetry

@pytest.mark.parametrize('case', CASE_IDS)
def test_swapping_the_ends_leaves_the_flexibility(case):
    """Seen from the other end: l -> -l, F -> gamma L0 e - F, same flexibility."""
    force, length, gamma, up = CASES[case]
    ea = ea_for(case)
    other = gamma * length * up - force
    assert_allclose(catenary.end_position(other, length, ea, gamma, up),
                    -catenary.end_position(force, length, ea, gamma, up), rtol=1e-11,
                    atol=1e-13)
    flex = catenary.flexibility(force, length, ea, gamma, up)
    assert_allclose(catenary.flexibility(other, length, ea, gamma, up), flex, rtol=1e-10,
                    atol=1e-13 * np.abs(flex).max())


@pytest.mark.parametrize('chord,tension,gamma', [((1.25, 1.25, -1.25), 100.0, GAMMA),
                                                 ((1.25, -1.25, 1.25), 227.0, GAMMA),
                                                 ((3.0, 0.0, 0.5), 20.0, 2.0),
                                                 ((-2.0, 1.0, -3.0), 15.0, 2.0)])
def test_exact_catenary_reversed_gives_the_same_stiffness(chord, tension, gamma):
    """MoorPy-style swap: solve from the anchor end with the anchor's tension: same L0,
    end force gamma L0 e - F, same 3x3 stiffness."""
    cables = one_cable(chord, tension, gamma=gamma)
    state = catenary.solve(cables)
    flipped = CableSet(-cables.chord_m, state.anchor_tension_n, EA, gamma, G)
    other = catenary.solve(flipped)
    assert state.valid[0] and other.valid[0]
    assert_allclose(other.unstrained_length_m, state.unstrained_length_m, rtol=1e-12)
    assert_allclose(other.force_n[0], gamma * state.unstrained_length_m[0] * UP
                    - state.force_n[0], rtol=1e-9, atol=1e-9 * tension)
    k = models.build('catenary_exact', cables).static_end_stiffness()
    assert_allclose(models.build('catenary_exact', flipped).static_end_stiffness(), k,
                    rtol=1e-8, atol=1e-8 * np.abs(k).max())


@pytest.mark.parametrize('method', ['catenary', 'catenary_exact'])
def test_stiffness_rotates_with_the_scene(method):
    """Any gravity direction: rotating chords and gravity by R gives R K R^T."""
    rot = Rotation.from_euler('xyz', [0.4, -1.1, 2.0]).as_matrix()
    cables = CableSet(np.array([[1.0, 0.5, -1.2], [-0.7, 0.2, 1.4]]), np.array([30.0, 45.0]),
                      EA, 3.0, G)
    turned = CableSet(cables.chord_m @ rot.T, cables.tension_n, EA, 3.0, rot @ G)
    k = models.build(method, cables).static_end_stiffness()
    assert_allclose(models.build(method, turned).static_end_stiffness(),
                    rot @ k @ rot.T, rtol=1e-9, atol=1e-9 * np.abs(k).max())


# ------------------------------------------------------------------------ the exact solve

@pytest.mark.parametrize('chord,tension,gamma', [((1.25, 1.25, -1.25), 100.0, GAMMA),
                                                 ((1.25, -1.25, 1.25), 227.0, GAMMA),
                                                 ((4.0, 0.0, 0.0), 10.0, 2.0),
                                                 ((3.0, 1.0, -2.0), 8.0, 2.0),
                                                 ((0.5, 0.0, 3.0), 5.0, 1.0)])
def test_exact_catenary_closes_with_the_qp_tension(chord, tension, gamma):
    cables = one_cable(chord, tension, gamma=gamma)
    state = catenary.solve(cables)
    assert state.valid[0] and not state.reasons
    up, _ = catenary.up_and_weight(cables)
    end = catenary.end_position(state.force_n, state.unstrained_length_m, EA, gamma, up)
    assert np.linalg.norm(end[0] + cables.chord_m[0]) < 1e-9
    assert_allclose(np.linalg.norm(state.force_n[0]), tension, rtol=1e-12)
    assembly = models.build('catenary_exact', cables)
    assert assembly.valid
    assert_allclose(assembly.end_force_n, -state.force_n, rtol=1e-15)
    k = assembly.static_end_stiffness()[0]
    assert np.all(np.linalg.eigvalsh(k) > 0)


def test_paper_robot_catenary_models_agree():
    """Taut, light cables: the modified method is close to the exact one (and both close to
    the spring); the Newton solve needs a few iterations."""
    s, g, cables = paper_cables()
    state = catenary.solve(cables)
    assert np.all(state.valid) and state.iterations <= 6
    assert np.all(state.residual_m < 1e-12)
    freqs = {}
    for method in ['catenary', 'catenary_exact', 'spring']:
        assembly = models.build(method, cables)
        assert assembly.valid
        freqs[method] = natural_frequencies(platform_system(s.robot, g, assembly), 3)
    assert_allclose(freqs['catenary'], freqs['catenary_exact'], rtol=2e-3)
    assert_allclose(freqs['catenary_exact'], freqs['spring'], rtol=1e-2)
    # pinned: the exact elastic catenary of the paper's robot (Irvine's effective-modulus drop)
    assert_allclose(freqs['catenary_exact'], [32.2779, 32.2780, 32.2780], rtol=2e-5)


# ------------------------------------------------------------------------ validity

@pytest.mark.parametrize('chord,tension', [((2.0, 0.0, 0.0), 0.0),       # no tension
                                           ((2.0, 0.0, 0.0), -5.0),
                                           ((0.0, 0.0, -2.0), 1.5),       # can't hold itself
                                           ((2.0, 0.0, 0.0), 1.0),        # no catenary spans
                                           ((1.0, 1.0, -1.0), 1.2)])
def test_slack_cables_are_invalid_and_finite(chord, tension):
    """gamma = 1 N/m: a level 2 m chord needs T > 1.51 N (H cosh(gamma L/2H) minimised), a
    cable hanging 2 m below the platform T > 2 N."""
    cables = CableSet(np.array([chord, (0.0, 1.0, 1.0)], dtype=float),
                      np.array([tension, 50.0]), EA, 1.0, G)
    assembly = models.build('catenary_exact', cables)
    assert not assembly.valid
    assert len(assembly.warnings) == 1 and assembly.warnings[0].startswith('cable 0')
    for method in ['catenary', 'catenary_exact']:
        assembly = models.build(method, cables)
        assert np.all(np.isfinite(assembly.end_stiffness(np.array([0.0, 1e4 + 1e2j]))))
        assert np.all(np.isfinite(assembly.end_force_n))
    if tension <= 0 or chord == (0.0, 0.0, -2.0):
        assembly = models.build('catenary', cables)
        assert not assembly.valid and 'cable 0' in assembly.warnings[0]


def test_nearly_slack_level_cable_still_solves():
    """Just above the least end tension of a level chord (1.509 N): a deep but valid sag."""
    cables = one_cable((2.0, 0.0, 0.0), 1.6, gamma=1.0, ea=1e5)
    state = catenary.solve(cables)
    assert state.valid[0]
    assert state.unstrained_length_m[0] > 2.2
    assert 0 < state.min_tension_n[0] < 1.6


# ------------------------------------------------------------------------ sag parameter

def test_sag_parameter():
    """Irvine's lambda^2 = (gamma L cos(theta)/H)^2 L/(H L_e/EA), L_e = L(1 + 8 (d/L)^2)."""
    cables = CableSet(np.array([[10.0, 0.0, 0.0], [0.0, 0.0, 3.0], [3.0, 0.0, 4.0],
                                [1.0, 0.0, 0.0]]), np.array([1000.0, 100.0, 100.0, 0.0]),
                      1.5e7, 8.0, G)
    lam2 = catenary.sag_parameter(cables)
    d_over_l = 8.0 * 10.0 / (8 * 1000.0)
    level = (8.0 * 10.0 / 1000.0) ** 2 * 1.5e7 / (1000.0 * (1 + 8 * d_over_l ** 2))
    ratio = 8.0 * 5.0 * 0.6 / 100.0
    inclined = ratio ** 2 * 1.5e7 / (100.0 * (1 + ratio ** 2 / 8))
    assert_allclose(lam2, [level, 0.0, inclined, np.inf], rtol=1e-12)
    _, _, paper = paper_cables()
    assert_allclose(catenary.sag_parameter(paper), [0.19891] * 4 + [0.016908] * 4, rtol=1e-4)
