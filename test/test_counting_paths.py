"""The fast paths of counting, modes and dsm against independent answers.

* Newton on Z's eigenvalues (``Counter._roots``) against multisection of J (the same counter
  with Newton switched off) and against the dense eigensolver of the global K, M.
* ``fem``'s closed-form clamped-chain modes against inverse iteration of the banded chain
  (``_ChainInterior`` on the same matrices), compared basis-free.
* ``z_cot_z``'s series and root-sharing paths against extended precision, and the dsm FRF
  against the former complex formula.
* the batched generalized eigensolver of the classification against scipy.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from cdpr_dynamics.dynamics import counting
from cdpr_dynamics.analysis.pipeline import build_system, damping_for, equilibrium
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import Damping, frequency_response
from cdpr_dynamics.models import dsm
from cdpr_dynamics.dynamics.modes import _generalized_eigh, modes

REPO = Path(__file__).resolve().parents[1]
PAPER = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
RIGID = load_settings(REPO / 'test' / 'data' / 'rigid_cdpr.yaml')
OFF_CENTRE = np.array([0.35, -0.2, 1.0])
TOL = 2 * np.pi * counting.TOL_HZ          # rad/s

CASES = [
    pytest.param(PAPER, None, 'fem', 64, id='paper-fem64'),
    pytest.param(PAPER, OFF_CENTRE, 'fem', 16, id='unequal-fem16'),
    pytest.param(RIGID, np.array([0.2, 0.1, 1.1]), 'fem', 8, id='rigid6dof-moved-fem8'),
    pytest.param(PAPER, None, 'dsm', 1, id='paper-dsm'),
    pytest.param(RIGID, None, 'dsm', 1, id='rigid6dof-dsm'),
]


def _system(settings, position, method, n):
    return build_system(settings, equilibrium(settings, position, method=method), method, n)


@pytest.mark.parametrize('settings, position, method, n', CASES)
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
    pytest.param(PAPER, None, 'fem', 8, id='paper-fem8'), CASES[2]])
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
def test_dsm_frf_equals_the_former_complex_formula(position):
    eq = equilibrium(PAPER, position)
    system = build_system(PAPER, eq, 'dsm', 1)
    members = dataclasses.replace(system.assembly.end_stiffness, wave=dsm.z_cot_z_reference)
    former = dataclasses.replace(system, assembly=dataclasses.replace(
        system.assembly, end_stiffness=members,
        decoupled=system.assembly.decoupled._replace(stiffness=members.parts)))
    f = np.asarray(PAPER.frequencies_hz, dtype=float)
    for damping in (damping_for(PAPER, system), Damping(0.0, 0.0)):
        a = frequency_response(system, f, PAPER.frf_force_n, damping=damping)
        b = frequency_response(former, f, PAPER.frf_force_n, damping=damping)
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
