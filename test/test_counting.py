"""Modes by Wittrick-Williams counting (cdpr_dynamics.dynamics.counting, .modes) against
independent answers.

The reference is scipy.linalg.eigh of the global K, M (PlatformSystem.matrices), classified
here by the definitions of the modes module's docstring: an independent path (no condensed
stiffness, no counting). Within a repeated frequency the dense basis is arbitrary, so both
sides are compared in the basis that diagonalises the platform energy M_pp in the eigenspace
(the one :func:`modes` reports); sums over a repeated frequency are compared as sums.

The fast paths of counting, modes and dsm:

* Newton on Z's eigenvalues (``Counter._roots``) against multisection of J (the same counter
  with Newton switched off) and against the dense eigensolver of the global K, M.
* ``fem``'s closed-form clamped-chain modes against inverse iteration of the banded chain
  (``_ChainInterior`` on the same matrices), compared basis-free.
* ``z_cot_z``'s series and root-sharing paths against extended precision, and the dsm FRF
  against the complex formula.
* the batched generalized eigensolver of the classification against scipy.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.pipeline import build_system, damping_for, equilibrium
from cdpr_dynamics.dynamics import counting
from cdpr_dynamics.dynamics.modes import (MIN_MODES, _generalized_eigh, classify, mode_count,
                                          modes, natural_frequencies)
from cdpr_dynamics.dynamics.system import Damping, frequency_response
from cdpr_dynamics.models import dsm
from oracles import z_cot_z_complex

REPO = Path(__file__).resolve().parents[1]
PAPER = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
RIGID = load_settings(REPO / 'test' / 'data' / 'rigid_cdpr.yaml')
HEAVY = load_settings(REPO / 'config' / 'heavy_sag_6dof.yaml')
SAGGING = load_settings(REPO / 'test' / 'data' / 'sagging_6dof.yaml')
COGIRO = load_settings(REPO / 'test' / 'data' / 'cogiro_heavy_sag.yaml')
OFF_CENTRE = np.array([0.35, -0.2, 1.0])        # unequal cable lengths and tensions
SAME = 1e-7                                      # dense eigenvalues this close: one frequency
TOL = 2 * np.pi * counting.TOL_HZ                # rad/s: the counter's bracket width


def dense_modes(system, size: int):
    """(frequency_hz, fraction, effective mass (k, nd), cable energy (k, ncab), groups) of
    the ``size`` lowest modes by a dense solve, in the canonical basis of repeated ones."""
    k, m = system.matrices(dense=True)
    values, vectors = scipy.linalg.eigh(k, m)          # M-orthonormal
    nd = system.platform_dofs
    groups = _runs(values, lambda a, b: abs(b - a) <= SAME * abs(b))
    basis = []
    for start, stop in groups:
        v = vectors[:, start:stop]
        share, w = np.linalg.eigh(v[:nd].T @ m[:nd, :nd] @ v[:nd])
        basis.append(v @ w[:, ::-1])                    # fractions descending
    phi = np.concatenate(basis, axis=1)[:, :size]
    fraction = np.einsum('ik,ij,jk->k', phi[:nd], m[:nd, :nd], phi[:nd])
    effective = ((m @ phi)[:nd].T) ** 2
    ncab = system.geometry.n_cables
    per = system.assembly.interior_dofs // ncab
    energy = np.stack([np.einsum('ik,ij,jk->k', phi[nd + c * per:nd + (c + 1) * per],
                                 m[nd + c * per:nd + (c + 1) * per,
                                   nd + c * per:nd + (c + 1) * per],
                                 phi[nd + c * per:nd + (c + 1) * per])
                       for c in range(ncab)], axis=1)
    frequency = np.sqrt(np.clip(values[:size], 0, None)) / (2 * np.pi)
    return frequency, fraction, effective, energy, [g for g in groups if g[0] < size]


def _runs(values, same):
    """(start, stop) of the runs of ``values`` whose neighbours are ``same``."""
    runs, start = [], 0
    for i in range(1, len(values) + 1):
        if i == len(values) or not same(values[i - 1], values[i]):
            runs.append((start, i))
            start = i
    return runs


CASES = [
    pytest.param(PAPER, None, 'fem', 8, id='paper-fem8'),
    pytest.param(PAPER, None, 'fem_sag', 8, id='paper-fem_sag8'),
    pytest.param(PAPER, OFF_CENTRE, 'fem', 8, id='unequal-fem8'),
    pytest.param(PAPER, OFF_CENTRE, 'fem_sag', 6, id='unequal-fem_sag6'),
    pytest.param(RIGID, None, 'fem', 6, id='rigid6dof-fem6'),
    pytest.param(RIGID, np.array([0.2, 0.1, 1.1]), 'fem', 6, id='rigid6dof-moved-fem6'),
    pytest.param(HEAVY, None, 'fem_sag', 8, id='heavy-sag-fem_sag8'),
    pytest.param(HEAVY, np.array([0.3, 0.4, 1.5]), 'fem_sag', 16, id='heavy-sag-moved-fem_sag16'),
    pytest.param(SAGGING, None, 'fem_sag', 12, id='sagging6dof-fem_sag12'),
    pytest.param(COGIRO, None, 'fem_sag', 10, id='cogiro-heavy-sag-fem_sag10'),
]


@pytest.mark.parametrize('settings, position, method, n', CASES)
def test_counted_modes_equal_the_dense_eigensolver(settings, position, method, n):
    eq = equilibrium(settings, position, method=method)
    system = build_system(settings, eq, method, n)
    assert_equal_dense(settings, system, modes(system, settings.f_max_hz))


@pytest.mark.slow
def test_chains_equal_up_to_round_off_are_one_repeated_frequency(monkeypatch):
    """fem_sag n = 64 at the chord statics (cdpr_bench's state): the pivots give the four
    upper cables' equal clamped eigenvalues up to 7e-10 Hz apart, in two brackets, one cable's
    where J does not rise. Taken as one frequency (modes.CLUSTER) they are classified by
    counting, without the eigensolver it fell back to before (slower than it), as dense."""
    from cdpr_dynamics.dynamics import modes as modes_module

    def no_eigensolver(*args, **kwargs):
        raise AssertionError('fell back to the eigensolver')
    system = build_system(PAPER, equilibrium(PAPER), 'fem_sag', 64)
    with monkeypatch.context() as patch:
        patch.setattr(modes_module, '_eigen', no_eigensolver)
        found = modes(system, PAPER.f_max_hz)
    assert_equal_dense(PAPER, system, found)
    assert found.frequency_hz.size == 27 and found.platform_hz.size == 3


def assert_equal_dense(settings, system, found):
    """``found`` (counted modes up to f_max) equals the dense solve: frequencies,
    multiplicities, fractions, kinds, effective masses per frequency, the cable of a mode."""
    size = found.frequency_hz.size
    assert size >= MIN_MODES and found.shapes is None
    f, fraction, effective, energy, groups = dense_modes(system, size)
    np.testing.assert_allclose(found.frequency_hz, f, rtol=1e-8)
    # every mode below f_max is there, and the first one above is not
    assert found.frequency_hz[-1] <= settings.f_max_hz or size == MIN_MODES
    k, m = system.matrices(dense=True)
    above = np.sqrt(scipy.linalg.eigh(k, m, eigvals_only=True)[size]) / (2 * np.pi)
    assert above > settings.f_max_hz or size == MIN_MODES
    # multiplicities: the counted repeated frequencies are bit-identical, as many as dense's
    counted = _runs(found.frequency_hz, lambda a, b: a == b)
    assert [b - a for a, b in counted] == [b - a for a, b in groups]
    np.testing.assert_allclose(found.platform_fraction, fraction, atol=1e-8)
    assert found.kind == classify(fraction)
    scale = np.diag(m)[:system.platform_dofs]
    for start, stop in groups:
        got = found.effective_mass[start:stop].sum(axis=0)
        np.testing.assert_allclose(got, effective[start:stop].sum(axis=0),
                                   atol=1e-8 * scale.max(), err_msg=f'modes {start}:{stop}')
        if stop - start == 1 and found.kind[start] != 'platform':
            top = np.sort(energy[start])[::-1]
            if top[0] > 1.01 * top[1]:             # one cable clearly carries it (no tie)
                assert found.cable[start] == np.argmax(energy[start]), start


@pytest.mark.parametrize('settings, position, method, n', [
    (PAPER, OFF_CENTRE, 'fem', 3), (PAPER, None, 'fem', 4), (PAPER, OFF_CENTRE, 'fem_sag', 3),
    (RIGID, None, 'fem', 2)])
def test_effective_masses_of_all_counted_modes_sum_to_the_platform_diagonal(
        settings, position, method, n):
    eq = equilibrium(settings, position, method=method)
    system = build_system(settings, eq, method, n)
    found = modes(system, count=system.dofs)
    assert found.frequency_hz.size == system.dofs
    _, mass = system.matrices(dense=True)
    np.testing.assert_allclose(found.effective_mass.sum(axis=0),
                               np.diag(mass)[:system.platform_dofs], rtol=1e-8)


def test_paper_robot_repeated_frequencies_are_exact():
    """Eight equal-length cables, four at each tension: at each string frequency 8 clamped
    modes, 3 of them couple with the platform (a triple just below) and 5 leave it at rest
    (exactly at the clamped-chain frequency, fraction 0); the platform triple at 32.4 Hz."""
    eq = equilibrium(PAPER)
    system = build_system(PAPER, eq, 'fem', 16)
    found = modes(system, PAPER.f_max_hz)
    sizes = [b - a for a, b in _runs(found.frequency_hz, lambda a, b: a == b)]
    assert sizes == [3, 5, 3, 5, 3, 5, 3]
    assert np.all(found.platform_fraction[3:8] == 0.0) and found.kind[3:8] == ('cable',) * 5
    # the 5-fold frequency is the clamped chain's closed form (6k/m)(1 - cos)/(2 + cos)
    cables = eq.cables
    low = int(np.argmin(cables.tension_n))
    k = cables.tension_n[low] / (cables.length_m[low] / 16)
    mass = cables.mass_per_length_kg_m * cables.length_m[low] / 16
    c = np.cos(np.pi / 16)
    chain = np.sqrt(6 * k / mass * (1 - c) / (2 + c)) / (2 * np.pi)
    np.testing.assert_allclose(found.frequency_hz[3:8], chain, rtol=1e-11)
    np.testing.assert_allclose(found.platform_hz, 32.40, atol=0.01)


@pytest.mark.parametrize('method, n', [('fem', 5), ('fem_sag', 5)])
def test_the_count_is_the_number_of_dense_eigenvalues_below(method, n):
    eq = equilibrium(PAPER, OFF_CENTRE, method=method)
    system = build_system(PAPER, eq, method, n)
    k, m = system.matrices(dense=True)
    values = scipy.linalg.eigh(k, m, eigvals_only=True)
    omega = np.sqrt(np.concatenate([np.linspace(1.0, 2e4, 60) ** 2,
                                    0.5 * (values[:-1] + values[1:])]))
    expected = np.searchsorted(values, omega ** 2)
    np.testing.assert_array_equal(mode_count(system, omega), expected)


def test_natural_frequencies_are_the_modes_frequencies():
    eq = equilibrium(PAPER, OFF_CENTRE)
    system = build_system(PAPER, eq, 'fem', 12)
    found = modes(system, 40.0)
    np.testing.assert_array_equal(natural_frequencies(system, 0, 40.0), found.frequency_hz)
    # another bracket (5 modes, no f_max), the same frequencies to the tolerance (1e-9 Hz)
    np.testing.assert_allclose(natural_frequencies(system, 5), found.frequency_hz[:5], atol=2e-9,
                               rtol=0)
    # the dense path (shapes) classifies alike
    dense = modes(system, 40.0, shapes=True)
    np.testing.assert_allclose(dense.frequency_hz, found.frequency_hz, rtol=1e-9)
    assert dense.kind == found.kind and dense.shapes.shape == (system.dofs, found.kind.__len__())


@pytest.fixture(scope='module')
def paper_dsm():
    eq = equilibrium(PAPER, OFF_CENTRE)
    return eq, modes(build_system(PAPER, eq, 'dsm'), PAPER.f_max_hz)


def test_dsm_modes_are_the_limit_of_fem(paper_dsm):
    """Unequal cables (off centre): fem's frequencies converge to dsm's as n^-2, and so do
    its platform fractions (measured: 0.155, 0.050, 0.013 at n = 16, 32, 64, largest on the
    platform mode at 31.4 Hz that a cable mode nearby mixes with); its effective masses as
    n^-1 (the end nodes' share mu l/3 per cable of the platform block)."""
    eq, exact = paper_dsm
    errors, shares = [], []
    for n in (16, 32, 64):
        fem = modes(build_system(PAPER, eq, 'fem', n), PAPER.f_max_hz)
        assert fem.frequency_hz.size == exact.frequency_hz.size
        errors.append(np.abs(fem.frequency_hz / exact.frequency_hz - 1).max())
        shares.append(np.abs(fem.platform_fraction - exact.platform_fraction).max())
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratios > 3.8) & (ratios < 4.2)), (errors, ratios)
    assert errors[-1] < 1e-3
    assert shares[-1] < 0.02 and shares[1] / shares[2] > 3.5, shares
    assert fem.kind == exact.kind
    np.testing.assert_allclose(fem.effective_mass.sum(axis=0), exact.effective_mass.sum(axis=0),
                               rtol=5e-4)


def test_dsm_platform_modes_carry_the_platform_mass(paper_dsm):
    eq, exact = paper_dsm
    platform = np.array([k == 'platform' for k in exact.kind])
    assert platform.sum() == 3 and np.all(exact.cable[platform] == -1)
    assert np.all(exact.cable[~platform] >= 0)
    # continuous cables: M_pp is the point mass alone, and the modes below 40 Hz hold nearly
    # all of it (the rest is in the infinitely many cable modes above)
    total = exact.effective_mass.sum(axis=0)
    assert np.all(exact.effective_mass >= 0)
    assert np.all((total > 0.99 * PAPER.robot.mass_kg) & (total < PAPER.robot.mass_kg))


# ----------------------------------------------------------------------------- fast paths

PATH_CASES = [
    pytest.param(PAPER, None, 'fem', 64, id='paper-fem64'),
    pytest.param(PAPER, OFF_CENTRE, 'fem', 16, id='unequal-fem16'),
    pytest.param(RIGID, np.array([0.2, 0.1, 1.1]), 'fem', 8, id='rigid6dof-moved-fem8'),
    pytest.param(PAPER, None, 'dsm', 1, id='paper-dsm'),
    pytest.param(RIGID, None, 'dsm', 1, id='rigid6dof-dsm'),
]


def _system(settings, position, method, n):
    return build_system(settings, equilibrium(settings, position, method=method), method, n)


@pytest.mark.parametrize('settings, position, method, n', PATH_CASES)
def test_newton_finds_what_multisection_finds(settings, position, method, n, monkeypatch):
    system = _system(settings, position, method, n)
    counter = counting.counter(system)
    taken = []
    real = counting.Counter._roots

    def spy(self, *args):
        found = real(self, *args)
        taken.append(found is not None)
        return found

    monkeypatch.setattr(counting.Counter, '_roots', spy)
    fast = counter.frequencies(settings.f_max_hz, 12, counting.TOL_HZ)
    assert taken == [True]                          # the Newton path, no fallback
    monkeypatch.setattr(counting.Counter, '_roots', lambda self, *args: None)
    slow = counter.frequencies(settings.f_max_hz, 12, counting.TOL_HZ)
    np.testing.assert_array_equal(fast[1], slow[1])                  # multiplicities
    assert fast[4] == slow[4]
    # two brackets of width <= tol around the same frequency
    np.testing.assert_allclose(fast[0], slow[0], rtol=0, atol=TOL)
    assert np.all(fast[3] - fast[2] <= TOL + 1e-12)


@pytest.mark.parametrize('settings, position, method, n', [
    pytest.param(PAPER, None, 'fem', 8, id='paper-fem8'), PATH_CASES[2]])
def test_counted_frequencies_equal_the_dense_eigensolver(settings, position, method, n):
    # (at n = 64 LAPACK's own error, ~eps lam_max with lam_max ~ 6 EA / (mu l^2), is 2e-9)
    system = _system(settings, position, method, n)
    found = modes(system, settings.f_max_hz)
    k, m = system.matrices(dense=True)
    values = scipy.linalg.eigh(k, m, eigvals_only=True,
                               subset_by_index=[0, found.frequency_hz.size - 1])
    dense_hz = np.sqrt(values) / (2 * np.pi)
    # Newton's zeros are exact to round-off: far inside the 1e-9 Hz brackets
    np.testing.assert_allclose(found.frequency_hz, dense_hz, rtol=1e-10)


@pytest.mark.parametrize('settings, position, n', [(HEAVY, None, 16), (HEAVY, None, 64),
                                                   (COGIRO, None, 24),
                                                   (PAPER, OFF_CENTRE, 12)])
def test_planar_chains_count_as_the_general_3d_ldl(settings, position, n):
    """fem_sag's chains split into their planes (2x2 and scalar pivots) count the clamped
    eigenvalues below each lam exactly as the block LDL^T of the whole 3x3 chains (away from
    the eigenvalues themselves), and condense to the same end stiffness (real and complex
    lam), which the flexibility series of the model gives independently."""
    eq = equilibrium(settings, position, method='fem_sag')
    system = build_system(settings, eq, 'fem_sag', n)
    planar = counting.counter(system).interior
    assert isinstance(planar, counting._PlanarChainInterior)
    general = counting._ChainInterior(system.assembly.blocks)
    lam = np.linspace(0.0, (2 * np.pi * settings.f_max_hz) ** 2, 301)[1:]
    count, ends = planar.sweep(lam)
    count_ref, ends_ref = general.sweep(lam)
    series = system.assembly.end_stiffness(lam).real
    exact = np.abs(planar.last_det) > 1e-6 * np.abs(planar.last_det).max()  # off the poles
    assert count[-1].sum() > 0 and np.array_equal(count[exact], count_ref[exact])
    # near a clamped eigenvalue both LDL^T forms lose digits to the pole (the series does
    # not): compared away from the poles, the planar split as close to the series as the
    # 3x3 LDL^T (both lose digits to the stiff axial terms)
    scale = np.abs(series).max(axis=(2, 3), keepdims=True)
    size = scale[..., 0, 0]
    far = exact & (size < 10.0 * np.median(size, axis=0))
    error, error_ref = (np.abs(a[far] - series[far]) / scale[far] for a in (ends, ends_ref))
    assert np.median(error) < 1e-10 and error.max() < max(10.0 * error_ref.max(), 1e-9)
    step = lam[:40] + 1e-20j * lam[:40]
    np.testing.assert_allclose(planar.sweep(step, count=False)[1],
                               general.sweep(step, count=False)[1],
                               rtol=0, atol=1e-8 * np.abs(ends_ref[:40]).max())


def test_chains_with_anchor_ends_take_the_general_ldl():
    """An anchor end in series makes the first element's block 3D: no plane basis."""
    settings = load_settings(REPO / 'config' / 'paper_pulleys.yaml')
    system = build_system(settings, equilibrium(settings, method='fem_sag'), 'fem_sag', 6)
    assert system.assembly.plane_basis is None
    assert type(counting.counter(system).interior) is counting._ChainInterior


def test_closed_form_clamped_ends_equal_inverse_iteration():
    eq = equilibrium(PAPER, OFF_CENTRE)
    system = build_system(PAPER, eq, 'fem', 12)
    uniform = counting.counter(system).interior
    general = counting._ChainInterior(system.assembly.blocks)
    poles = uniform.poles((2 * np.pi * 60.0) ** 2)
    assert poles.size > 4
    jumps_all = uniform.counts(poles * (1 + 1e-9)) - uniform.counts(poles * (1 - 1e-9))
    batched = uniform.clamped_ends(poles, jumps_all)           # every eigenvalue at once
    for k, lam in enumerate(poles):
        jumps = jumps_all[k:k + 1]
        force, mass, owner, group, scale = uniform.clamped_ends([lam], jumps)
        in_batch = batched[3] == k
        for one, many in zip((force, mass, owner), batched[:3]):
            np.testing.assert_array_equal(one, many[in_batch])
        assert np.all(group == 0) and scale[0] == batched[4][k]
        force_ref, mass_ref, owner_ref, _, scale_ref = counting._stacked_ends(
            general, [lam], jumps)
        scale, scale_ref = scale[0], scale_ref[0]
        np.testing.assert_array_equal(owner, owner_ref)
        for c in np.unique(owner):          # basis-free within a cable's repeated modes
            mine, theirs = owner == c, owner_ref == c
            for a, b in ((force, force), (force, mass), (mass, mass)):
                ref_a = force_ref if a is force else mass_ref
                ref_b = force_ref if b is force else mass_ref
                np.testing.assert_allclose(a[mine].T @ b[mine],
                                           ref_a[theirs].T @ ref_b[theirs],
                                           rtol=1e-7, atol=1e-9 * scale ** 2)
        assert scale == pytest.approx(scale_ref, rel=1e-7)


@pytest.mark.parametrize('position', [None, OFF_CENTRE], ids=['centre', 'unequal'])
def test_dsm_clamped_ends_are_the_residues_of_the_end_stiffness(position):
    # near a clamped eigenvalue lam_j, S_c(lam) ~ -sum f f^T / (lam_j - lam) over the clamped
    # modes there (f their end reactions): the residue checks the closed form independently
    # (the mean of (lam - lam_j) S_c at lam_j (1 -+ 1e-6) cancels the regular part's term)
    system = _system(PAPER, position, 'dsm', 1)
    interior = counting.counter(system).interior
    poles = interior.poles((2 * np.pi * 60.0) ** 2)
    jumps = interior.counts(poles * (1 + 1e-9)) - interior.counts(poles * (1 - 1e-9))
    force, mass, owner, group, scale = interior.clamped_ends(poles, jumps)
    assert np.all(mass == 0.0) and force.shape[0] == jumps.sum() > 8
    members = system.assembly.end_stiffness
    for k, lam in enumerate(poles):
        near = lam * (1 + np.array([-1e-6, 1e-6]))
        ends = members(near).real                                          # (2, ncab, 3, 3)
        for c in np.flatnonzero(jumps[k]):
            rows = (group == k) & (owner == c)
            assert rows.sum() == jumps[k, c]
            residue = np.einsum('k,kij->ij', near - lam, ends[:, c]) / 2
            np.testing.assert_allclose(residue, force[rows].T @ force[rows],
                                       rtol=0, atol=1e-8 * np.abs(residue).max())
        assert scale[k] == np.abs(force[group == k]).max()


def test_z_cot_z_agrees_with_extended_precision():
    rng = np.random.default_rng(3)
    size = 10.0 ** rng.uniform(-12, 1.6, 4000)
    z2 = size * np.exp(1j * rng.uniform(-np.pi, np.pi, size.size))
    z2 = np.concatenate([z2, [0.25, 0.25 * (1 - 1e-12), 0.25 * (1 + 1e-12), -0.25, 0.25j]])
    z = np.sqrt(z2.astype(np.clongdouble))
    reference = (z * np.cos(z) / np.sin(z)).astype(complex)
    clear = (np.abs(np.sin(z)) > 1e-2) & (np.abs(np.cos(z)) > 1e-2)   # off poles and zeros
    for given in (z2, z2.real, -np.abs(z2.real)):
        got = dsm.z_cot_z(given).astype(complex)
        zz = np.sqrt(given.astype(np.clongdouble))
        with np.errstate(invalid='ignore'):        # 0/0 at z = 0, left out below
            ref = (zz * np.cos(zz) / np.sin(zz)).astype(complex)
        ok = clear if given is z2 else (np.abs(np.sin(zz)) > 1e-2) & (np.abs(np.cos(zz)) > 1e-2)
        np.testing.assert_allclose(got[ok], ref[ok], rtol=1e-13)
    # the shared root (taut cables): z = sqrt(lam) sqrt(ratio) gives the same numbers
    lam = z2[:200]
    ratio = np.array([[1e-6, 0.5], [2.0, 1e-3]])
    np.testing.assert_allclose(dsm._taut_waves(lam, ratio),
                               dsm.z_cot_z(lam * ratio[..., None]), rtol=1e-13)
    assert np.all(np.isfinite(reference[clear]))


@pytest.mark.parametrize('position', [None, OFF_CENTRE], ids=['centre', 'unequal'])
def test_dsm_frf_equals_the_complex_formula(position):
    eq = equilibrium(PAPER, position)
    system = build_system(PAPER, eq, 'dsm', 1)
    members = dataclasses.replace(system.assembly.end_stiffness, wave=z_cot_z_complex)
    complex_ = dataclasses.replace(system, assembly=dataclasses.replace(
        system.assembly, end_stiffness=members,
        decoupled=system.assembly.decoupled._replace(stiffness=members.parts)))
    f = np.asarray(PAPER.frequencies_hz, dtype=float)
    for damping in (damping_for(PAPER, system), Damping(0.0, 0.0)):
        a = frequency_response(system, f, PAPER.frf_force_n, damping=damping)
        b = frequency_response(complex_, f, PAPER.frf_force_n, damping=damping)
        np.testing.assert_array_equal(a.singular, b.singular)
        fin = ~a.singular
        scale = np.abs(b.response[fin]).max(axis=1, keepdims=True)
        assert np.all(np.abs(a.response[fin] - b.response[fin]) <= 1e-10 * scale)


def test_batched_generalized_eigh_equals_scipy():
    rng = np.random.default_rng(5)
    a = rng.standard_normal((6, 4, 4))
    a = a + np.swapaxes(a, 1, 2)
    b = rng.standard_normal((6, 4, 4))
    b = b @ np.swapaxes(b, 1, 2) + 4 * np.eye(4)
    values, vectors = _generalized_eigh(a, b)
    for k in range(6):
        ref, ref_vectors = scipy.linalg.eigh(a[k], b[k])
        np.testing.assert_allclose(values[k], ref, rtol=1e-12)
        np.testing.assert_allclose(vectors[k].T @ b[k] @ vectors[k], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(np.abs(vectors[k]), np.abs(ref_vectors), rtol=1e-9,
                                   atol=1e-12)


def test_fem_sag_modes_of_a_symmetric_robot_are_classified_by_counting(monkeypatch):
    """The paper robot's mirror-image cables have equal clamped-chain frequencies to the last
    bit (the element stiffness is formed as EA/l ee + T/l (I - ee) for that): every pole's
    modes are found at rest on the platform, so fem_sag 64 never falls back to the
    eigensolver, and the repeated frequencies stay repeated."""
    from cdpr_dynamics.dynamics import modes as modes_module

    def no_eigensolver(*args, **kwargs):
        raise AssertionError('fell back to the eigensolver')
    monkeypatch.setattr(modes_module, '_eigen', no_eigensolver)
    found = modes(_system(PAPER, None, 'fem_sag', 64), PAPER.f_max_hz)
    assert found.frequency_hz.size == 27 and found.platform_hz.size == 3
    values, counts = np.unique(found.frequency_hz, return_counts=True)
    assert counts.max() >= 2                                 # mirror-image cables: exact pairs
