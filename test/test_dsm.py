"""``dsm``: exact continuous taut cables, Wittrick-Williams natural frequencies, FEM convergence.

Reference case: the paper's robot (8 equal cables, L = 2.165 m, mu = 0.02559 kg/m,
EA = 1.01e6 N, T = 100 N below and 227.4 N above). Tolerances are the measured values with a
margin; the measurements are in the comments.
"""
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from cdpr_dynamics import models
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import (Damping, DynamicsError, frequency_response,
                                           platform_system, rayleigh_from_modal_ratio)
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.models.dsm import ContinuousCables, z_cot_z
from cdpr_dynamics.models.fem import chain_end_stiffness
from cdpr_dynamics.dynamics.modes import mode_count, natural_frequencies
from cdpr_dynamics.mechanics.robot import Robot, geometry

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'paper_cdpr.yaml'
BAND_HZ = 40.0
NS = (4, 8, 16, 32, 64)


@pytest.fixture(scope='module')
def paper():
    s = load_settings(CONFIG)
    g = geometry(s.robot, s.initial_position_m, s.initial_rotation)
    tension = np.where(g.unit[:, 2] > 0, 100 + 30 * 9.81 * np.sqrt(3) / 4, 100.0)
    cables = CableSet(g.chord_m, tension, s.cable.ea_n, s.cable.weight_per_length_n_per_m,
                      s.robot.gravity_m_s2)
    return s.robot, g, cables


def system(robot, g, cables, method, n=16):
    return platform_system(robot, g, models.build(method, cables, n))


@pytest.fixture(scope='module')
def dsm_band(paper):
    """Every dsm natural frequency of the paper robot below 40 Hz."""
    return natural_frequencies(system(*paper, 'dsm'), 0, BAND_HZ)


@pytest.fixture(scope='module')
def fem_band(paper, dsm_band):
    """The same number of lowest fem natural frequencies for n = 4 ... 64."""
    return {n: natural_frequencies(system(*paper, 'fem', n), dsm_band.size) for n in NS}


def string_hz(cables, j=1, axial=False):
    """Closed form j/(2L) sqrt(T/mu) (transverse) or j/(2L) sqrt(EA/mu) (axial)."""
    stiffness = cables.ea_n if axial else cables.tension_n
    return j / (2 * cables.length_m) * np.sqrt(stiffness / cables.mass_per_length_kg_m)


# --------------------------------------------------------------------------- the member

def test_z_cot_z_matches_cos_over_sin_on_every_branch():
    z = np.array([1e-6, 9.99e-4, 1.001e-3, 1e-3 * (1 + 1j), 2e-4j, 0.7, 2.0 + 0.3j,
                  -1.0 + 5.0j, 0.5 + 29.9j, 0.5 + 30.1j, 3.0 - 200.0j, 10.0j])
    reference = z * np.cos(z) / np.sin(z)
    np.testing.assert_allclose(z_cot_z(z * z), reference, rtol=1e-14)
    assert z_cot_z(np.array([0.0]))[0] == 1.0
    far = z_cot_z(np.array([(2.0 + 1e6j) ** 2]))[0]       # cos, sin would overflow here
    np.testing.assert_allclose(far, (2.0 + 1e6j) * -1j, rtol=1e-14)
    assert abs(z_cot_z(np.array([math.pi ** 2]))[0]) > 1e14          # pole at z = pi


def test_static_limit_is_the_spring(paper):
    robot, g, cables = paper
    dsm = models.build('dsm', cables)
    spring = models.build('spring', cables)
    np.testing.assert_allclose(dsm.static_end_stiffness(), spring.static_end_stiffness(),
                               rtol=1e-15, atol=1e-9)
    np.testing.assert_allclose(system(*paper, 'dsm').static_stiffness(),
                               system(*paper, 'spring').static_stiffness(), rtol=1e-14, atol=1e-9)
    # stable as lam -> 0: z cot z = 1 - z^2/3 + O(z^4)
    members = dsm.end_stiffness
    lam = np.array([1e-9, 1e-9 * (1 - 1j)])
    mu, length = cables.mass_per_length_kg_m, cables.length_m
    expected = cables.tension_n / length * (1 - lam[:, None] * mu * length ** 2
                                            / cables.tension_n / 3)
    np.testing.assert_allclose(members.transverse(lam), expected, rtol=1e-15)


@pytest.mark.parametrize('damping', [Damping(), Damping(0.05, 0.05), Damping(2.0, 1e-4)])
def test_end_stiffness_is_t_k_cot_kl(paper, damping):
    """S_t = T k cot(kL), S_a = EA k cot(kL) with complex k = sqrt(lam mu / (T or EA))."""
    _, _, cables = paper
    members = models.build('dsm', cables).end_stiffness
    w = 2 * np.pi * np.array([3.0, 17.0, 250.0, 1700.0])
    lam = (w * w - 1j * w * damping.mass_factor) / (1 + 1j * w * damping.stiffness_factor)
    mu, length = cables.mass_per_length_kg_m, cables.length_m[0]
    for stiffness, got in ((cables.tension_n[0], members.transverse(lam)[:, 0]),
                           (cables.ea_n, members.axial(lam)[:, 0])):
        k = np.sqrt(lam * mu / stiffness)
        np.testing.assert_allclose(got, stiffness * k / np.tan(k * length), rtol=1e-12)
    # the 3x3 tensor: axial along u, transverse across
    full = members(lam)
    u = cables.unit
    np.testing.assert_allclose(np.einsum('ci,lcij,cj->lc', u, full, u), members.axial(lam),
                               rtol=1e-13)


@pytest.mark.parametrize('kind, frequencies_hz', [
    ('transverse', (3.0, 11.0, 18.0, 25.0, 33.0)),   # poles 14.4, 28.9, zeros 7.2, 21.7, 36.1
    ('axial', (300.0, 1100.0, 1800.0, 2550.0)),      # poles 1451, 2902, zeros 726, 2177 Hz
])
def test_fem_end_stiffness_converges_to_dsm_as_n_minus_2(paper, kind, frequencies_hz):
    """fem's chain (EA/l or T/l, l = L/n, consistent mass) -> (EA/L or T/L) z cot z.

    Measured order log2(e_n / e_2n), n = 4 ... 64: 1.98-2.00 on the first branch (kL < pi);
    on the second (kL up to 2.3 pi, one wavelength over 4 elements at n = 4) 1.50-3.14 from
    4 to 8, 1.83-2.11 from 8 to 16, 1.95-2.02 from 16 to 32, 1.99-2.005 from 32 to 64.
    Relative error at n = 64: 1.5e-6 (3 Hz, 300 Hz) to 7.2e-3 (33 Hz transverse, near the zero
    of S_t at 36.1 Hz, where a relative error is large). Asserted: order in [1.8, 2.2] from
    n = 8, [1.9, 2.1] from n = 16, error at n = 64 below 1e-2.
    """
    _, _, cables = paper
    members = models.build('dsm', cables).end_stiffness
    length, mu = cables.length_m[0], cables.mass_per_length_kg_m
    stiffness = cables.tension_n[0] if kind == 'transverse' else cables.ea_n
    lam = (2 * np.pi * np.asarray(frequencies_hz)) ** 2 + 0j
    exact = getattr(members, kind)(lam)[:, 0]
    errors = []
    for n in NS:
        fem = chain_end_stiffness(stiffness * n / length, mu * length / n, n, lam)
        errors.append(np.abs(fem / exact - 1))
    order = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((order[1] > 1.8) & (order[1] < 2.2)), order
    assert np.all((order[2:] > 1.9) & (order[2:] < 2.1)), order
    assert np.all(errors[-1] < 1e-2), errors[-1]


# --------------------------------------------------------------------------- Wittrick-Williams

def test_registry_and_interface(paper):
    robot, g, cables = paper
    assembly = models.build('dsm', cables, 99)
    assert 'dsm' in models.REGISTRY
    assert assembly.method == 'dsm' and assembly.blocks is None and assembly.valid
    assert assembly.interior_dofs == 0 and assembly.elements_per_cable == 0
    np.testing.assert_allclose(assembly.end_force_n, cables.tension_n[:, None] * cables.unit)
    with pytest.raises(DynamicsError):
        platform_system(robot, g, assembly).matrices()


def test_natural_frequencies_are_where_the_count_rises(paper):
    sysm = system(*paper, 'dsm')
    f = natural_frequencies(sysm, 12)
    assert f.size == 12 and np.all(np.diff(f) >= 0)
    # J(w) counts the frequencies below w: each f_k has J < k just below and J >= k above
    k = np.arange(1, 13)
    assert np.all(mode_count(sysm, 2 * np.pi * f * (1 - 1e-9)) < k)
    assert np.all(mode_count(sysm, 2 * np.pi * f * (1 + 1e-9)) >= k)
    # count and band give the same modes; the tolerance is honoured
    band = natural_frequencies(sysm, 0, 25.0)
    np.testing.assert_allclose(band, natural_frequencies(sysm, band.size), atol=2e-9)
    np.testing.assert_allclose(natural_frequencies(sysm, 12, tol_hz=1e-4), f, atol=1e-4)


def test_fixed_end_mode_count():
    members = ContinuousCables(np.eye(3)[:2], np.array([2.0, 1.0]), np.array([100.0, 400.0]),
                               1e6, 0.025)
    fa, ft = members.fixed_end_fundamentals_rad_s()
    np.testing.assert_allclose(ft, np.pi * np.sqrt([100 / 0.025, 400 / 0.025]) / [2.0, 1.0])
    np.testing.assert_allclose(fa, np.pi * np.sqrt(1e6 / 0.025) / [2.0, 1.0])
    # ft[1] = 4 ft[0] and fa[0] = 100 ft[0]: at 1.001 fa[0], 1 axial + 2 (100 + 25) transverse
    w = np.array([0.0, 0.999 * ft[0], 1.001 * ft[0], 2.5 * ft[0], 1.001 * fa[0]])
    np.testing.assert_array_equal(members.fixed_end_mode_count(w), [0, 0, 2, 4, 251])


def test_cable_modes_are_the_taut_string_closed_form(paper, dsm_band):
    """Equal cables: 8 member modes at each closed form, 3 of them couple with the platform and
    move; the other 5 do not move the platform and stay exactly at j/(2L) sqrt(T/mu)."""
    robot, g, cables = paper
    sysm = system(*paper, 'dsm')
    for f in (string_hz(cables)[0], string_hz(cables)[4], string_hz(cables, 2)[0]):
        assert np.sum(np.abs(dsm_band / f - 1) < 1e-10) == 5
        jump = mode_count(sysm, 2 * np.pi * f * np.array([1 - 1e-9, 1 + 1e-9]))
        assert jump[1] - jump[0] == 5
    axial = string_hz(cables, axial=True)[0]          # 1451.2 Hz
    jump = mode_count(sysm, 2 * np.pi * axial * np.array([1 - 1e-9, 1 + 1e-9]))
    assert jump[1] - jump[0] == 5


def test_single_cable_on_a_heavy_platform_gives_the_string_and_rod_modes():
    """One cable, platform 1e9 kg (nearly fixed): modes j/(2L) sqrt(T/mu) (twice each, two
    directions) and 1/(2L) sqrt(EA/mu), to the bisection tolerance."""
    robot = Robot('world', np.array([[0.0, 0.0, 3.0]]), np.zeros((1, 3)), 1e9,
                  np.zeros((3, 3)), np.array([0.0, 0.0, -9.81]))
    g = geometry(robot, [0.4, -0.3, 0.5])
    cables = CableSet(g.chord_m, np.array([150.0]), 1.0e6, 0.25, robot.gravity_m_s2)
    sysm = platform_system(robot, g, models.build('dsm', cables))
    f_t, f_a = string_hz(cables)[0], string_hz(cables, axial=True)[0]
    found = natural_frequencies(sysm, 0, 5.5 * f_t)
    cable = found[3:]                                  # 3 platform modes near 0 Hz first
    assert np.all(found[:3] < 1e-2)
    np.testing.assert_allclose(cable, np.repeat(np.arange(1, 6), 2) * f_t, rtol=1e-10)
    rod = natural_frequencies(sysm, 0, 1.0001 * f_a)
    np.testing.assert_allclose(rod[-1], f_a, rtol=1e-10)


def test_slack_cable_is_flagged_and_refused(paper):
    robot, g, cables = paper
    tension = cables.tension_n.copy()
    tension[0], tension[1] = 0.0, -20.0
    assembly = models.build('dsm', cables.with_tension(tension))
    assert not assembly.valid and len(assembly.warnings) == 2
    lam = np.array([0.0, 1e4, 1e4 - 50j])
    values = assembly.end_stiffness(lam)
    assert np.all(np.isfinite(values))
    np.testing.assert_allclose(assembly.end_stiffness.transverse(lam)[:, 0], 0.0)
    assert np.all(assembly.end_stiffness.transverse(lam[:2])[:, 1].real < 0)   # T < 0: unstable
    with pytest.raises(DynamicsError, match='taut'):
        natural_frequencies(platform_system(robot, g, assembly), 6)


# --------------------------------------------------------------------------- FEM -> dsm

def test_wittrick_williams_misses_no_mode_and_adds_none(paper, dsm_band, fem_band):
    """Below 40 Hz: 27 modes by both; fem n = 64 above dsm by its discretisation error only.

    Consistent-mass FEM bounds from above; its relative error on the j-th cable mode is about
    (j pi / n)^2 / 24 (measured at n = 64: 1.00e-4 for j = 1, 4.02e-4 for j = 2).
    """
    fem64 = natural_frequencies(system(*paper, 'fem', 64), dsm_band.size + 3)
    assert dsm_band.size == 27 == np.sum(fem64 < BAND_HZ)
    error = fem64[:dsm_band.size] / dsm_band - 1
    assert np.all(error > 0) and np.all(error < 4.5e-4), error


def test_fem_natural_frequencies_converge_at_rate_two(dsm_band, fem_band):
    """Observed order log2(e_n / e_2n), n = 4 ... 64, on the first cable modes (14.4, 21.8 Hz),
    the second (28.9 Hz) and the platform modes (32.4 Hz).

    Measured: cable modes 1.96-2.006 (n = 4 -> 8) and 2.000-2.005 beyond; platform modes 3.59
    (4 -> 8: at n = 4 fem's second cable mode, 31.8 Hz, sits next to the platform mode and
    inflates its error), then 2.14, 2.03, 2.006. Asserted: [1.9, 2.1] for cable modes at every
    n, [1.8, 2.2] for the platform modes from n = 8.
    """
    errors = np.array([fem_band[n] / dsm_band - 1 for n in NS])      # (5, 27)
    order = np.log2(errors[:-1] / errors[1:])
    cable = order[:, :24]
    platform = order[1:, 24:]
    assert np.all((cable > 1.9) & (cable < 2.1)), cable
    assert np.all((platform > 1.8) & (platform < 2.2)), platform


def test_fem_error_on_uncoupled_cable_modes_is_the_chain_dispersion(dsm_band, fem_band):
    """The 5-fold cable modes that leave the platform still are exactly fixed-fixed chain modes:
    fem / dsm = sqrt(6 (1 - cos t) / (2 + cos t)) / t, t = j pi / n (~ 1 + t^2 / 24)."""
    exact = dsm_band[[3, 11, 19]]                       # j = 1 (100 N), j = 1 (227 N), j = 2
    for n in NS:
        t = np.array([1, 1, 2]) * np.pi / n
        ratio = np.sqrt(6 * (1 - np.cos(t)) / (2 + np.cos(t))) / t
        np.testing.assert_allclose(fem_band[n][[3, 11, 19]], exact * ratio, rtol=1e-9)


def test_fem_frf_matches_dsm(paper):
    """Damped FRF over 1-40 Hz, F = (0, 0, 1500) N: |A_fem - A_dsm| / |A_dsm| at every frequency.

    Paper damping (0.05, 0.05) overdamps every cable mode: measured 2.84e-8 at n = 64 (4.5e-7
    at n = 16, 1.0e-4 at n = 1). Light damping (2 % at 10 and 40 Hz) shows the cable
    resonances: 6.5e-4 at n = 64 (1.0e-2 at n = 16), worst at the 28.9 Hz cable mode.
    """
    f = np.linspace(1.0, 40.0, 391)
    cases = ((Damping(0.05, 0.05), 1e-7), (rayleigh_from_modal_ratio(0.02, 10.0, 40.0), 1.5e-3))
    for damping, tolerance in cases:
        exact = frequency_response(system(*paper, 'dsm'), f, [0, 0, 1500], damping=damping)
        fem = frequency_response(system(*paper, 'fem', 64), f, [0, 0, 1500], damping=damping)
        assert not exact.singular.any()
        error = np.linalg.norm(fem.response - exact.response, axis=1) / \
            np.linalg.norm(exact.response, axis=1)
        assert error.max() < tolerance, (damping, error.max())


def test_general_robot_six_dofs_matches_fem(paper):
    """Unequal cables and tensions, rigid 6-DOF platform: 24 modes below 40 Hz by both."""
    base, _, cables = paper
    corners = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                        [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]]) * [0.1, 0.12, 0.08]
    robot = dataclasses.replace(base, attachments_m=corners,
                                inertia_kg_m2=np.diag([0.4, 0.5, 0.6]))
    g = geometry(robot, [0.3, -0.2, 1.0])
    skewed = CableSet(g.chord_m, np.linspace(120.0, 400.0, 8), cables.ea_n,
                      cables.weight_per_length_n_per_m, cables.gravity_m_s2)
    exact = natural_frequencies(platform_system(robot, g, models.build('dsm', skewed)),
                                0, BAND_HZ)
    fem = natural_frequencies(platform_system(robot, g, models.build('fem', skewed, 64)),
                              exact.size + 2)
    assert exact.size == 24 == np.sum(fem < BAND_HZ)
    error = fem[:exact.size] / exact - 1
    assert np.all(error > -1e-9) and np.all(error < 4.5e-4), error
