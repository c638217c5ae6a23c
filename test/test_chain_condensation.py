"""Closed-form chain condensation (``fem``), real-arithmetic z cot z (``dsm``), the lean FRF.

References (test/oracles.py and below): the O(n) recursion, a dense Schur complement of the
chain's K - lam M, exact rational arithmetic (fractions) of the recursion, the dense global solve
of (K + i w C - w^2 M), and the complex cos/sin z cot z.

Tolerance 1e-10 relative, except near a pole or zero of the end stiffness: rounding d11 and
d12 perturbs a chain like a relative change of lam by ~n^2 eps (the chain's conditioning), and
S's relative sensitivity to lam is lam/|lam - lam_j| there, so every method (closed form,
recursion and dense solve alike, measured within 2x of each other) is only good to about
n^2 eps lam/|lam - lam_j|: the bound asserted there is 1e-10 + 4 n^2 eps lam/|lam - lam_j|
(measured 1.7e-6 at n = 256, 1e-6 from a pole, against a bound of 5.8e-5).
"""
import dataclasses
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from cdpr_dynamics import models
from cdpr_dynamics.analysis.pipeline import build_system, equilibrium
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import Damping, frequency_response, platform_system
from cdpr_dynamics.models.dsm import z_cot_z
from cdpr_dynamics.models.fem import chain_end_stiffness
from cdpr_dynamics.dynamics.modes import natural_frequencies
from oracles import chain_end_stiffness_recursive, fem_recursive, naive_frf, z_cot_z_complex

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'paper_cdpr.yaml'
NS = (1, 2, 3, 16, 64, 256)
EPS = np.finfo(float).eps
K_AXIAL, K_TRANSVERSE, MASS = 3.0e7, 1.0e4, 1.0e-3      # a fem 64 element of the paper robot


@pytest.fixture(scope='module')
def paper():
    settings = load_settings(CONFIG)
    return settings, equilibrium(settings)


def dense_end_stiffness(k, m, n, lam):
    """S = D_ee - D_ei D_ii^-1 D_ie of the assembled chain D = K - lam M (anchor fixed)."""
    kk = np.zeros((n + 1, n + 1))
    mm = np.zeros((n + 1, n + 1))
    for e in range(n):
        kk[e:e + 2, e:e + 2] += k * np.array([[1.0, -1.0], [-1.0, 1.0]])
        mm[e:e + 2, e:e + 2] += m / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])
    d = (kk[None] - np.atleast_1d(lam)[:, None, None] * mm[None])[:, 1:, 1:].astype(complex)
    if n == 1:
        return d[:, 0, 0]
    x = np.linalg.solve(d[:, :-1, :-1], d[:, :-1, -1:])[..., 0]
    return d[:, -1, -1] - np.einsum('li,li->l', d[:, -1, :-1], x)


def exact_end_stiffness(k, m, n, lam):
    """The recursion in exact rational arithmetic of the float inputs (no rounding at all)."""
    lr, li, k, m = (Fraction(float(v)) for v in (np.real(lam), np.imag(lam), k, m))
    d11, d12 = (k - lr * m / 3, -li * m / 3), (-k - lr * m / 6, -li * m / 6)

    def mul(a, b):
        return a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0]

    def div(a, b):
        norm = b[0] * b[0] + b[1] * b[1]
        return (a[0] * b[0] + a[1] * b[1]) / norm, (a[1] * b[0] - a[0] * b[1]) / norm

    s, square = d11, mul(d12, d12)
    for _ in range(n - 1):
        x = div(square, (s[0] + d11[0], s[1] + d11[1]))
        s = (d11[0] - x[0], d11[1] - x[1])
    return complex(float(s[0]), float(s[1]))


def lam_grid(k, m, damped):
    """lam from 0 through the pass band (lam < 12 k/m) deep into the stop band."""
    top = 12.0 * k / m
    lam = np.concatenate([[0.0], top * np.logspace(-14, 1.5, 60)])
    if damped:      # Rayleigh damping 0.05, 0.05 as in the paper, at w = sqrt(lam)
        w = np.sqrt(lam)
        lam = (lam - 0.05j * w) / (1.0 + 0.05j * w)
    return lam


def relative(a, b):
    return np.abs(a - b) / np.abs(b)


# --------------------------------------------------------------------------- the chain


@pytest.mark.parametrize('n', NS)
@pytest.mark.parametrize('damped', (False, True))
@pytest.mark.parametrize('k', (K_AXIAL, K_TRANSVERSE))
def test_closed_form_matches_recursion_and_dense_solve(n, damped, k):
    """Pass band and stop band, damped and undamped. Measured: 5e-12 at n = 256 (recursion
    and dense solve themselves differ by as much: the chain's own conditioning)."""
    lam = lam_grid(k, MASS, damped)
    closed = chain_end_stiffness(k, MASS, n, lam)
    assert closed.shape == lam.shape and np.iscomplexobj(closed) == damped
    recursive = chain_end_stiffness_recursive(k, MASS, n, lam)
    np.testing.assert_allclose(closed, recursive, rtol=1e-10, atol=0)
    dense = dense_end_stiffness(k, MASS, n, lam)
    np.testing.assert_allclose(closed, dense, rtol=1e-10, atol=0)


@pytest.mark.slow
@pytest.mark.parametrize('n', (1, 2, 3, 16, 64))
def test_closed_form_matches_exact_rational_arithmetic(n):
    """Against the recursion without any rounding (fractions): measured 6.7e-13 at n = 64."""
    for k in (K_AXIAL, K_TRANSVERSE):
        lam = np.concatenate([lam_grid(k, MASS, False)[::10], lam_grid(k, MASS, True)[::10]])
        exact = np.array([exact_end_stiffness(k, MASS, n, value) for value in lam])
        closed = chain_end_stiffness(k, MASS, n, lam)
        np.testing.assert_allclose(closed, exact, rtol=1e-10, atol=0)


def poles_and_zeros(k, m, n):
    """lam of the chain's poles (clamped interior modes, cos(j pi/n)) and zeros (S = 0, where
    cos(n theta) = 0): r = cos theta = (k - 2c)/(k + c) gives c = lam m/6 = k (1 - r)/(2 + r)."""
    poles = np.cos(np.arange(1, n) * np.pi / n)
    zeros = np.cos((np.arange(n) + 0.5) * np.pi / n)
    return [6.0 / m * k * (1.0 - r) / (2.0 + r) for r in (poles, zeros)]


def spread(values, count=12):
    """At most ``count`` of ``values``: the first, the last and evenly spaced between."""
    return values[np.unique(np.linspace(0, len(values) - 1, count).round().astype(int))]


@pytest.mark.parametrize('n', (2, 3, 16, 64, 256))
def test_near_poles_and_zeros_to_the_conditioning(n):
    """Within the bound of the module doc, 1e-9 to 1e-3 (relative) from every pole and zero,
    and huge (or inf) exactly at a pole (12 of each spread over the band)."""
    for k in (K_AXIAL, K_TRANSVERSE):
        poles, zeros = (spread(v) for v in poles_and_zeros(k, MASS, n))
        for offset in (1e-9, 1e-6, 1e-3):
            for base in (poles, zeros):
                for sign in (1.0, -1.0):
                    lam = base * (1.0 + sign * offset)
                    closed = chain_end_stiffness(k, MASS, n, lam)
                    bound = 1e-10 + 4.0 * n * n * EPS / offset
                    for reference in (chain_end_stiffness_recursive(k, MASS, n, lam),
                                      dense_end_stiffness(k, MASS, n, lam)):
                        assert relative(closed, reference).max() < bound, (k, offset, sign)
        at_pole = np.abs(chain_end_stiffness(k, MASS, n, poles))
        assert np.all(at_pole > 1e6 * k), at_pole.min() / k


def test_exact_pole_is_inf_like_the_recursion():
    """n = 2 with d11 = k - lam m/3 = 0 exactly (k = 1, m = 3, lam = 1): S_2 = d11 - d12^2/(2
    d11) has its pole; real and complex lam."""
    for lam in (np.array([1.0]), np.array([1.0 + 0j])):
        closed = chain_end_stiffness(1.0, 3.0, 2, lam)
        assert np.isinf(closed).all() and np.isinf(
            chain_end_stiffness_recursive(1.0, 3.0, 2, lam)).all()
        assert np.isfinite(chain_end_stiffness(1.0, 3.0, 2, lam * 1.001)).all()


@pytest.mark.parametrize('n', NS)
def test_zero_tension_transverse_chain(n):
    """k = 0 (T = 0): S = 0 at lam = 0 (0/0 in the formula), else the mass-only chain."""
    lam = np.array([0.0, 1.0, 1e4, 1e8])
    for values in (lam, lam.astype(complex), (lam - 0.3j * np.sqrt(lam)) / 1.1):
        closed = chain_end_stiffness(0.0, MASS, n, values)
        recursive = chain_end_stiffness_recursive(0.0, MASS, n, values)
        assert closed[0] == 0.0
        np.testing.assert_allclose(closed[1:], recursive[1:], rtol=1e-12)


def test_no_overflow_deep_in_the_stop_band():
    """|z|^n below the float range (n = 4096 far above the pass band): the semi-infinite chain
    -d12 sqrt(q), as the recursion converges to, no inf or nan; also the slack k < 0."""
    n = 4096
    for k in (K_TRANSVERSE, -K_TRANSVERSE):
        lam = np.array([1e3, 1e4, 1e6]) * 12.0 * abs(k) / MASS
        for values in (lam, (lam - 0.5j * np.sqrt(lam)) / (1 + 0.5j * np.sqrt(lam))):
            closed = chain_end_stiffness(k, MASS, n, values)
            assert np.isfinite(closed).all()
            np.testing.assert_allclose(closed, chain_end_stiffness_recursive(k, MASS, n, values),
                                       rtol=1e-10)


def test_broadcast_over_cables_and_real_equals_complex():
    """(nl, 2, n) for k (2, n) and m (n,): each entry is its own scalar chain; real lam gives
    the real part of the complex-lam result with zero imaginary input."""
    k = np.array([[3e7, 2e7, 1e7], [1e4, 0.0, 5e3]])
    m = np.array([1e-3, 2e-3, 5e-4])
    lam = np.array([0.0, 10.0, 1e6, 1e9, 1e11])
    out = chain_end_stiffness(k, m, 16, lam)
    assert out.shape == (5, 2, 3)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(out[:, i, j],
                                       chain_end_stiffness_recursive(k[i, j], m[j], 16, lam),
                                       rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(out, chain_end_stiffness(k, m, 16, lam + 0j).real, rtol=1e-15)


# --------------------------------------------------------------------------- dsm: z cot z


def test_z_cot_z_matches_the_complex_formula():
    """Real z^2 (undamped: z/tan z and y coth y) and complex z^2 (damped) on every branch:
    measured 3e-15 (the complex formula itself carries a few eps)."""
    rng = np.random.default_rng(7)
    real = np.concatenate([[0.0, 1e-9, -1e-9, 0.99e-6, 1.01e-6, -2.0, -900.0, -1e5, 1e5],
                           rng.uniform(-50.0, 400.0, 200)])
    z = rng.uniform(0.0, 12.0, 200) + 1j * rng.uniform(-40.0, 40.0, 200)
    complex_z2 = np.concatenate([(z * z), [1e-8j, 2e-7 + 1e-7j, (0.5 + 29.9j) ** 2,
                                           (0.5 + 30.1j) ** 2, (2.0 + 1e6j) ** 2]])
    for z2 in (real, complex_z2):
        got = z_cot_z(z2)
        assert np.iscomplexobj(got) == np.iscomplexobj(z2)
        np.testing.assert_allclose(got, z_cot_z_complex(z2), rtol=1e-12)
    assert abs(z_cot_z(np.array([np.pi ** 2]))[0]) > 1e14          # the pole at z = pi


def test_dsm_end_stiffness_real_for_undamped(paper):
    settings, eq = paper
    members = models.build('dsm', eq.cables).end_stiffness
    lam = (2 * np.pi * np.linspace(0.0, 400.0, 81)) ** 2
    np.testing.assert_allclose(members(lam), members(lam + 0j), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(members.axial(lam + 0j)[:, 0], (eq.cables.ea_n
                               / eq.cables.length_m[0]) * z_cot_z_complex(
        lam * eq.cables.mass_per_length_kg_m * eq.cables.length_m[0] ** 2 / eq.cables.ea_n),
        rtol=1e-12)


# --------------------------------------------------------------------------- the FRF


def generic(system):
    """The same system without the assembly's shortcuts: 3x3 blocks through the congruence."""
    assembly = dataclasses.replace(system.assembly, decoupled=None, constant_stiffness=None)
    return dataclasses.replace(system, assembly=assembly)


@pytest.mark.parametrize('method, n', (('spring', 1), ('fem', 4), ('fem', 64), ('dsm', 0),
                                       ('catenary', 1)))
def test_shortcuts_give_the_generic_dynamic_stiffness(paper, method, n):
    settings, eq = paper
    system = build_system(settings, eq, method, n)
    w = 2 * np.pi * np.linspace(0.0, 60.0, 61)
    for damping in (Damping(), Damping(0.05, 0.05)):
        fast, slow = system.dynamic_stiffness(w, damping), generic(system).dynamic_stiffness(
            w, damping)
        np.testing.assert_allclose(fast, slow, rtol=1e-12, atol=1e-12 * np.abs(slow).max())


@pytest.mark.parametrize('n', (1, 4, 16))
def test_fem_frf_matches_the_dense_global_solve(paper, n):
    """Damped (paper damping) and undamped FRF of the whole robot, 40 frequencies from 1 to
    60 Hz, against (K + i w C - w^2 M)^-1 F of the assembled matrices: measured 2e-13."""
    settings, eq = paper
    system = build_system(settings, eq, 'fem', n)
    f = np.linspace(1.0, 60.0, 40) + 0.0123
    for damping in (Damping(0.05, 0.05), Damping()):
        got = frequency_response(system, f, [30.0, -20.0, 1500.0], damping=damping)
        dense = naive_frf(system, f, [30.0, -20.0, 1500.0], damping)
        assert not got.singular.any()
        np.testing.assert_allclose(got.response[:, :3], dense, rtol=1e-10,
                                   atol=1e-10 * np.abs(dense).max())


def test_fem_frf_matches_the_recursion_path(paper):
    """The closed form with the shortcuts against the recursion through 3x3 blocks."""
    settings, eq = paper
    f = settings.frequencies_hz
    for n in (16, 256):
        fast = build_system(settings, eq, 'fem', n)
        slow = platform_system(settings.robot, eq.geometry,
                               fem_recursive(eq.cables, n))
        a = frequency_response(fast, f, settings.frf_force_n, damping=Damping(0.05, 0.05))
        b = frequency_response(slow, f, settings.frf_force_n, damping=Damping(0.05, 0.05))
        np.testing.assert_allclose(a.response, b.response, rtol=1e-10,
                                   atol=1e-10 * np.abs(b.response).max())


def svd_singular(system, f, damping=Damping()):
    """The former singular test: sigma_min <= 1e-12 max(sigma_max, stiffness + inertia scale)."""
    z = system.dynamic_stiffness(2 * np.pi * np.asarray(f), damping)
    sigma = np.linalg.svd(z, compute_uv=False)
    scale = np.maximum(sigma[:, 0], np.abs(system.static_stiffness()).max()
                       + (2 * np.pi * np.asarray(f)) ** 2 * np.abs(system.platform_mass).max())
    return ~(sigma[:, -1] > 1e-12 * scale)


@pytest.mark.parametrize('method, n', (('spring', 1), ('fem', 16), ('catenary', 1)))
def test_singular_at_an_exact_resonance_only(paper, method, n):
    """Undamped, exactly at a platform resonance (the eigensolver's frequency): singular, inf;
    1e-7 off it and elsewhere: finite, as the former SVD test says."""
    settings, eq = paper
    system = build_system(settings, eq, method, n)
    freqs = natural_frequencies(system, 30)
    platform = freqs[np.argmin(np.abs(freqs - 32.4))]
    f = np.array([platform, platform * (1 + 1e-7), platform * (1 - 1e-7), 5.0, 20.0])
    r = frequency_response(system, f, [0.0, 0.0, 1500.0])
    assert r.singular.tolist() == [True, False, False, False, False]
    assert np.isinf(r.amplitude_m[0]).all() and np.isfinite(r.amplitude_m[1:]).all()
    np.testing.assert_array_equal(r.singular, svd_singular(system, f))


def test_singular_when_z_vanishes_and_never_with_damping(paper):
    """Z = 0 (a repeated resonance: no norm of Z is a scale) is singular; damped never."""
    settings, eq = paper
    system = build_system(settings, eq, 'spring', 1)
    zero = dataclasses.replace(system, platform_stiffness=-system.static_stiffness(),
                               platform_mass=np.zeros((3, 3)) + 1e-30 * np.eye(3))
    assert frequency_response(zero, [0.0], [0.0, 0.0, 1.0]).singular.all()
    damped = frequency_response(system, settings.frequencies_hz, settings.frf_force_n,
                                damping=Damping(0.05, 0.05))
    assert not damped.singular.any() and np.isfinite(damped.response).all()


def test_static_stiffness_is_cached_and_not_shared(paper):
    settings, eq = paper
    system = build_system(settings, eq, 'fem', 8)
    first = system.static_stiffness()
    first[0, 0] = -1.0
    np.testing.assert_allclose(system.static_stiffness(),
                               system.dynamic_stiffness(np.zeros(1))[0].real, rtol=1e-14)


# --------------------------------------------------------------------------- fem_sag


@pytest.mark.parametrize('n', (1, 2, 16, 64))
def test_fem_sag_planar_split_matches_the_3x3_recursion(paper, n):
    """Each sagged chain lies in its vertical plane: the 2x2 + scalar split against the full
    3x3 flexibility recursion evaluated in long double (64-bit mantissa). Measured, damped:
    2e-12; undamped 1.7e-10 at n = 64 near a cable resonance (11 Hz), where the double 3x3
    recursion itself is off by 4.9e-9: the split is the more accurate."""
    from cdpr_dynamics.analysis.pipeline import equilibrium_for
    from cdpr_dynamics.models import fem_sag
    settings, eq = paper
    cables = equilibrium_for(settings, eq, 'fem_sag').cables
    elements = fem_sag.sag_chains(cables, n)[1]
    assert fem_sag.planar_chains(elements[0]) is not None
    extended = [np.asarray(e, dtype=np.longdouble) for e in elements]
    w = 2 * np.pi * settings.frequencies_hz
    for lam, tolerance in (((w * w - 0.05j * w) / (1 + 0.05j * w), 1e-10), (w * w, 1e-9)):
        split = fem_sag.series_end_stiffness(*elements, lam)
        reference = fem_sag._series_3d(*extended, lam)
        error = (np.abs(split - reference).max(axis=(1, 2, 3))
                 / np.abs(reference).max(axis=(1, 2, 3))).astype(float)
        assert error.max() < tolerance and np.median(error) < 1e-11, error.max()


def test_fem_sag_non_planar_chain_takes_the_3x3_recursion():
    """A chain twisted out of any plane is not split (planar_chains is None)."""
    from cdpr_dynamics.models import fem_sag
    e = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])[:, None, :]   # (n, 1, 3)
    ee = np.stack([e[..., i] * e[..., k] for i, k in fem_sag._UPPER])               # (6, 3, 1)
    assert fem_sag.planar_chains(ee) is None
    lam = np.array([0.0, 1e3, 1e5 + 10j])
    args = (ee, np.array([1e6]), np.full((3, 1), 1e3), np.array([1e-3]))
    np.testing.assert_array_equal(fem_sag.series_end_stiffness(*args, lam),
                                  fem_sag._series_3d(*args, lam))


@pytest.mark.parametrize('method, n', (('spring', 1), ('fem', 4), ('dsm', 0), ('fem_sag', 4)))
def test_empty_frequency_list(paper, method, n):
    settings, eq = paper
    system = build_system(settings, eq, method, n)
    for damping in (Damping(), Damping(0.05, 0.05)):
        r = frequency_response(system, [], [0.0, 0.0, 1.0], damping=damping)
        assert r.response.shape == (0, 3) and r.singular.shape == (0,)
