"""Modes you can interpret: which natural modes move the platform, which are the cables'.

The undamped modes solve K phi = w^2 M phi of the global matrices (platform DOFs first, then
each cable's interior nodes, :meth:`PlatformSystem.matrices`), mass normalised
(phi^T M phi = 1). For each mode:

* **platform energy fraction** e = phi_p^T M_pp phi_p / phi^T M phi: the share of the mode's
  kinetic energy (at its velocity peak, T = w^2 phi^T M phi / 2) carried by the platform DOFs
  phi_p, M_pp the platform block of M (the platform's mass and inertia plus the cables'
  end-node share of the consistent mass). Coupling terms phi_p^T M_pc phi_c belong to neither
  side, so the platform and cable shares need not add up to exactly 1.
* **kind**: ``platform`` where e >= :data:`PLATFORM_SHARE` (the platform carries at least
  half of the energy: the mode the platform mass on the cable springs would have), ``cable``
  where e <= :data:`CABLE_SHARE` (the platform carries at most 10 %: a cable vibrating with
  the platform nearly at rest), ``mixed`` in between (a platform mode and a cable mode near
  the same frequency exchanging energy).
* **cable**: the index of the cable whose interior nodes carry the most kinetic energy,
  phi_c^T M_cc phi_c over cables c (-1 for a platform mode and for models without
  interior nodes).
* **effective modal mass** per platform DOF j: m_kj = (phi_k^T M e_j)^2 with e_j the unit
  vector of DOF j (mass-normalised phi_k). Because sum_k phi_k phi_k^T = M^-1,
  sum_k m_kj = e_j^T M M^-1 M e_j = M_jj: over all modes the effective masses add up to the
  platform diagonal of M (kg for translations, kg m^2 for rotations).
* **repeated frequencies** (symmetric robots have exact 3- and 5-fold ones): any basis of the
  eigenspace is a set of modes; the one reported makes the platform energy stationary (the
  modes diagonalise M_pp within the eigenspace, fractions descending), so the fractions of a
  repeated frequency do not depend on the solver. Sums over a repeated frequency (effective
  masses, fractions) are basis-free; a degenerate cable mode's ``cable`` is not.

How they are found (the default, ``shapes=False``): by Wittrick-Williams counting
(:mod:`cdpr_dynamics.dynamics.counting`), each mode's platform shape, mass, cable shares and
effective masses then following from the condensed dynamic stiffness Z alone (the derivation:
doc/theory.md, section "Classifying the modes from Z").

A state where this bookkeeping does not add up (negative stiffness, a platform mode exactly at
a clamped-chain frequency) falls back to the dense path. ``shapes=True`` (mode shapes of every
DOF, for plots) uses the dense path: LAPACK for small models, shift-invert Lanczos otherwise.

Massless models (``spring``, ``catenary``, ``catenary_exact``) have platform DOFs only: every
mode is a platform mode (e = 1), and the effective masses of a point mass are m per axis.
``dsm`` (continuous cables, no finite matrices) is classified by counting too: M_pp is the
platform's own mass, the cables carry the rest; its list is the modes below f_max of an
infinite spectrum, so its effective masses add up to less than M_pp. It has no shapes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse.linalg as spla

from cdpr_dynamics.dynamics.counting import STEP as _STEP, TOL_HZ, counter as _counter
from cdpr_dynamics.dynamics.system import DENSE_EIGEN_DOFS, DynamicsError, PlatformSystem

PLATFORM_SHARE = 0.5    # platform energy fraction at or above: kind 'platform'
CABLE_SHARE = 0.1       # platform energy fraction at or below: kind 'cable'
MIN_MODES = 12          # at least this many modes ("at least the 12 lowest")
#: relative width (of omega) within which counted frequencies and clamped-chain eigenvalues
#: are one repeated frequency: the pivots' round-off splits equal chains' eigenvalues by
#: 2-3e-11 at fem_sag n = 64 (four symmetric cables), so 30x that
CLUSTER = 1e-9


@dataclass(frozen=True, eq=False)
class Modes:
    """The classified modes of one system, ascending in frequency.

    ``frequency_hz`` (k,); ``platform_fraction`` (k,) platform share of the kinetic energy;
    ``kind`` k strings; ``cable`` (k,) int, -1 where no cable (platform modes, massless
    models); ``effective_mass`` (k, ndof) kg / kg m^2; ``shapes`` (dofs, k) mass-normalised
    (``modes(..., shapes=True)`` only, else None).
    """

    frequency_hz: np.ndarray
    platform_fraction: np.ndarray
    kind: tuple[str, ...]
    cable: np.ndarray
    effective_mass: np.ndarray
    shapes: np.ndarray | None = None

    @property
    def platform_hz(self) -> np.ndarray:
        """Frequencies (Hz) of the modes of kind ``platform``."""
        return self.frequency_hz[np.array([k == 'platform' for k in self.kind], dtype=bool)]

    @property
    def cable_hz(self) -> np.ndarray:
        """Frequencies (Hz) of the modes of kind ``cable``."""
        return self.frequency_hz[np.array([k == 'cable' for k in self.kind], dtype=bool)]


def classify(fraction) -> tuple[str, ...]:
    """Kinds of modes with platform energy fractions ``fraction`` (module doc)."""
    return tuple('platform' if e >= PLATFORM_SHARE else 'cable' if e <= CABLE_SHARE
                 else 'mixed' for e in np.asarray(fraction, dtype=float).tolist())


def modes(system: PlatformSystem, f_max_hz: float | None = None, count: int = MIN_MODES,
          hint: int = 0, shapes: bool = False, tol_hz: float = TOL_HZ) -> Modes:
    """Every mode up to ``f_max_hz`` and at least the ``count`` lowest, classified.

    ``f_max_hz=None``: the ``count`` lowest only; ``count`` at least the DOFs: all modes.
    By counting (module doc) unless ``shapes`` (mode shapes wanted) or the model has no cable
    DOFs: then dense LAPACK for small models, shift-invert Lanczos (sigma = 0) otherwise,
    asked for ``max(count, hint + 2)`` modes first (``hint``: how many a neighbouring state
    had) and widened until the highest mode found lies above ``f_max_hz``; ``hint`` changes
    the cost, not the modes (beyond round-off).
    """
    counter = _counter(system)
    if counter is not None and not shapes:
        found = _Classifier(counter).modes(f_max_hz, count, tol_hz)
        if found is not None:
            return found
        if system.assembly.blocks is None:
            raise DynamicsError('dsm modes cannot be classified at this state (negative '
                                'stiffness, or a platform mode at a clamped-cable frequency)')
    if system.assembly.blocks is None:
        raise DynamicsError(f'method {system.assembly.method} has no finite matrices: no '
                            'mode shapes (use fem or fem_sag)')
    k, m = system.matrices()
    values, vectors = _eigen(k, m, f_max_hz, count, hint)
    mass = m.toarray() if k.shape[0] <= DENSE_EIGEN_DOFS else m
    return _classified(system, values, vectors, mass)


def natural_frequencies(system: PlatformSystem, count: int = MIN_MODES,
                        f_max_hz: float | None = None, tol_hz: float = TOL_HZ) -> np.ndarray:
    """Undamped natural frequencies (Hz, ascending): every one up to ``f_max_hz`` and at least
    the ``count`` lowest (fewer where the DOFs lack).

    Wittrick-Williams counting to ``tol_hz`` (module doc) for models with cable DOFs and for
    ``dsm``; repeated frequencies appear with their multiplicity, unstable modes (negative
    stiffness) as 0 Hz. Massless models: the eigenvalues of their platform DOFs. Raises
    :class:`DynamicsError` where the count is not defined (a ``dsm`` cable with T <= 0).
    """
    counter = _counter(system)
    if counter is not None:
        omega, multiplicity, _, _, take, _ = counter.frequencies(f_max_hz, count, tol_hz)
        return np.repeat(omega, multiplicity)[:take] / (2.0 * math.pi)
    k, m = system.matrices()
    values, _ = _eigen(k, m, f_max_hz, count, vectors=False)
    return np.sqrt(np.clip(values, 0.0, None)) / (2.0 * np.pi)


def mode_count(system: PlatformSystem, omega_rad_s) -> np.ndarray:
    """Wittrick-Williams J(omega): how many natural frequencies lie below each omega (rad/s)."""
    counter = _counter(system)
    if counter is None:
        raise DynamicsError(f'method {system.assembly.method} has no cable DOFs to count')
    omega = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    return counter.count(omega * omega)[0]


# --------------------------------------------------------------------------- classification

class _Classifier:
    """The modes of a counted system (module doc): Z's null vectors, the chains' shares."""

    def __init__(self, counter):
        self.counter = counter
        self.system = system = counter.system
        self.interior = counter.interior
        self.blocks = blocks = counter.blocks
        self.nd = counter.nd
        self.mass_pp = system.platform_mass + (
            0.0 if blocks is None else system.cables_on_platform(blocks.m_diag[:, -1][None])[0])
        self.z = counter.z
        self.g_map = system.geometry.attachment_map()                    # (ncab, 3, nd)

    def modes(self, f_max_hz, count, tol_hz) -> Modes | None:
        """Classified modes by counting (module doc); None where the bookkeeping fails."""
        omega, mult, lo, hi, take, jumps = self.counter.frequencies(f_max_hz, count, tol_hz)
        if omega.size and omega[0] == 0.0 and lo[0] == hi[0]:
            return None                                 # negative stiffness: dense
        omega, mult, jumps = _merged(omega, mult, lo, hi, jumps,
                                     np.maximum(2.0 * math.pi * tol_hz, CLUSTER * omega))
        poles = np.any(jumps > 0, axis=1)
        if np.any(poles):       # every chain with an eigenvalue within CLUSTER, J rising or not
            lam = omega[poles] ** 2
            jumps[poles] = self.interior.counts(lam * (1.0 + 2.0 * CLUSTER)) \
                - self.interior.counts(lam * (1.0 - 2.0 * CLUSTER))
        lam = omega * omega
        nd = self.nd
        parts = []
        regular = ~np.any(jumps > 0, axis=1)
        if np.any(regular):
            parts.append(self._coupled(lam[regular], mult[regular], np.flatnonzero(regular)))
        if not np.all(regular):
            poles = np.flatnonzero(~regular)
            found = self._at_poles(lam[poles], mult[poles], jumps[poles], poles)
            if found is None:
                return None
            parts += found
        if not parts:
            empty = np.zeros(0)
            return Modes(empty, empty, (), np.zeros(0, int), np.zeros((0, nd)))
        order = np.concatenate([p[0] for p in parts])
        sort = np.argsort(order, kind='stable')[:take]
        fraction = np.concatenate([p[1] for p in parts])[sort]
        effective = np.concatenate([p[2] for p in parts])[sort]
        energy = np.concatenate([p[3] for p in parts])[sort]
        frequency = np.repeat(omega, mult)[:take] / (2.0 * math.pi)
        kinds = classify(fraction)
        cable = np.where(np.array([k != 'platform' for k in kinds], dtype=bool),
                         np.argmax(energy, axis=1), -1)
        return Modes(frequency, fraction, kinds, cable, effective)

    def _coupled(self, lam, mult, groups):
        """Modes that move the platform at frequencies where no clamped chain resonates."""
        s = self.system
        step = _STEP * np.maximum(lam, 1.0)
        _, ends_c = self.interior.sweep(lam + 1j * step, count=False)
        ends = ends_c.real
        d_ends = ends_c.imag / step[:, None, None, None]                 # S_c'(lam)
        z = self.z(lam, ends)
        dz = s.cables_on_platform(d_ends) - s.platform_mass[None]        # Z'(lam)
        coupling = self._coupling_mass(lam, ends)                        # (g, ncab, 3, 3)
        total_map = self.mass_pp[None] + (np.zeros((lam.size, 1, 1)) if coupling is None
                                          else s.cables_on_platform(coupling))
        g_map = self.g_map
        values, vectors = np.linalg.eigh(z)
        out = [[], [], [], []]
        for m in np.unique(mult):              # groups of one multiplicity at once
            i = np.flatnonzero(mult == m)
            nearest = np.sort(np.argsort(np.abs(values[i]), axis=1, kind='stable')[:, :m],
                              axis=1)
            basis = np.take_along_axis(vectors[i], nearest[:, None, :], axis=2)  # (k, nd, m)
            basis_t = np.swapaxes(basis, 1, 2)
            modal = -basis_t @ dz[i] @ basis                               # phi^T M phi
            platform = basis_t @ self.mass_pp @ basis
            share, w = _generalized_eigh(platform, modal)                  # w^T modal w = I
            share, w = share[:, ::-1], w[:, :, ::-1]
            phi = basis @ w                                                # (k, nd, m)
            d = np.einsum('cia,gak->gcik', g_map, phi)                     # (k, ncab, 3, m)
            cables = -np.einsum('gcik,gcij,gcjk->gkc', d, d_ends[i], d)
            if self.blocks is not None:
                end = np.einsum('gcik,cij,gcjk->gkc', d, self.blocks.m_diag[:, -1], d)
                cables = cables - end - 2.0 * np.einsum('gcik,gcij,gcjk->gkc', d,
                                                        coupling[i], d)
            out[0].append(np.repeat(groups[i], m))
            out[1].append(share.ravel())
            out[2].append((np.swapaxes(total_map[i] @ phi, 1, 2) ** 2).reshape(-1, self.nd))
            out[3].append(cables.reshape(-1, cables.shape[-1]))
        return [np.concatenate(o) for o in out]

    def _coupling_mass(self, lam, ends):
        """(g, ncab, 3, 3) M_e,last X_c: the end node's mass coupling to the last interior
        node, X_c = O_c^-T (S_c - D_ee) that node's motion per unit end motion; None (dsm)."""
        if self.blocks is None:
            return None
        kd, ko, md, mo = self.blocks
        lam4 = lam[:, None, None, None]
        own = kd[None, :, -1] - lam4 * md[None, :, -1]
        off = ko[None, :, -1] - lam4 * mo[None, :, -1]
        x = np.linalg.solve(np.swapaxes(off, -1, -2), ends - own)
        return np.swapaxes(mo[None, :, -1], -1, -2) @ x

    def _at_poles(self, lam, mult, jumps, groups):
        """Modes with the platform at rest at clamped-chain eigenvalues ``lam`` (g,): at each,
        the combinations of the chains' clamped modes whose end forces cancel on the
        platform. None where they are not all ``mult`` modes of a frequency (dense fallback)."""
        force, mass, owner, at, scale = self.interior.clamped_ends(lam, jumps)
        g_map = self.g_map[owner]                                          # (r, 3, nd)
        forces = np.einsum('rin,ri->rn', g_map, force)                     # (r, nd)
        masses = np.einsum('rin,ri->rn', g_map, mass)
        n_cables = self.system.geometry.n_cables
        size = np.bincount(at, minlength=len(groups))          # clamped modes per eigenvalue
        start = np.cumsum(size) - size                         # (``at`` ascends)
        if np.any(size < mult):
            return None                    # fewer clamped modes than the count says
        found = {}
        for r in np.unique(size):          # one batched SVD per number of clamped modes
            ks = np.flatnonzero(size == r)
            take = (start[ks, None] + np.arange(r)).ravel()
            stacked = np.swapaxes(forces[take].reshape(ks.size, r, -1), 1, 2)  # (k, nd, r)
            _, sing, vt = np.linalg.svd(stacked)
            found.update((k, (sing[i].tolist(), vt[i])) for i, k in enumerate(ks.tolist()))
        parts = []
        for k, group in enumerate(groups):
            rows = slice(start[k], start[k] + size[k])
            sing, vt = found[k]
            # the count says how many combinations leave the platform at rest (mult); the
            # end forces (accurate to ~eps (EA/T)^2 of their size) must agree: a clear gap
            rank = int(size[k] - mult[k])
            sing = sing + [0.0] * max(int(size[k]) - len(sing), 0)
            if (rank > 0 and sing[rank - 1] < 1e-3 * sing[0]) \
                    or (rank < len(sing) and sing[rank] > 1e-6 * scale[k]):
                return None
            null = vt[rank:].T                                             # (r_k, mult)
            energy = (null ** 2).T @ (owner[rows][:, None] == np.arange(n_cables))  # per cable
            effective = (masses[rows].T @ null).T ** 2
            parts.append((np.full(mult[k], group), np.zeros(mult[k]), effective, energy))
        return parts


def _merged(omega, mult, lo, hi, jumps, tol):
    """Counted frequencies whose brackets lie within ``tol`` (rad/s, per frequency) of the
    previous one's as one repeated frequency: (omega (g,), multiplicity, jumps (g, ncab)),
    omega the multiplicity-weighted mean. Round-off in the pivots' signs can split an exactly
    repeated frequency (four symmetric cables' equal clamped eigenvalues at fem_sag n = 64,
    4e-10 Hz apart) into neighbouring brackets; its modes are the eigenspace of the whole
    group (a part of it alone has no platform-at-rest combination, or shares a null vector)."""
    if omega.size < 2:
        return omega, mult, jumps
    group = np.cumsum(np.concatenate([[True], lo[1:] - hi[:-1] > tol[1:]])) - 1
    size = np.bincount(group, weights=mult)
    summed = np.zeros((group[-1] + 1, jumps.shape[1]), dtype=jumps.dtype)
    np.add.at(summed, group, jumps)
    return np.bincount(group, weights=mult * omega) / size, size.astype(int), summed


def _generalized_eigh(a: np.ndarray, b: np.ndarray):
    """Stacked symmetric-definite eigenproblems a w = s b w (b positive definite): (s
    ascending (k, m), w (k, m, m) with w^T b w = I), by the Cholesky reduction b = L L^T,
    L^-1 a L^-T y = s y, w = L^-T y (what LAPACK's sygv does, batched)."""
    lower_inv = np.linalg.inv(np.linalg.cholesky(b))
    values, y = np.linalg.eigh(lower_inv @ a @ np.swapaxes(lower_inv, 1, 2))
    return values, np.swapaxes(lower_inv, 1, 2) @ y


# --------------------------------------------------------------------------- dense path

def _eigen(k, m, f_max_hz, count, hint=0, vectors=True):
    """Lowest eigenpairs (w^2, mass-normalised phi) of K phi = w^2 M phi, ascending."""
    n = k.shape[0]
    limit = np.inf if f_max_hz is None else (2.0 * np.pi * f_max_hz) ** 2
    count = int(count or 0)
    want = min(max(count, hint + 2, 1), n)
    while True:
        if n <= DENSE_EIGEN_DOFS or want >= n - 1:
            values, shapes = scipy.linalg.eigh(k.toarray(), m.toarray())
            take = max(min(count, n), int(np.searchsorted(values, limit, side='right')))
            return values[:take], shapes[:, :take]
        start = np.random.default_rng(0).standard_normal(n)     # reproducible Lanczos
        values, shapes = spla.eigsh(k, k=want, M=m, sigma=0.0, which='LM', v0=start)
        order = np.argsort(values)
        values, shapes = values[order], shapes[:, order]
        if values[-1] > limit or want >= n - 2:
            keep = max(min(want, count), int(np.searchsorted(values, limit, side='right')))
            shapes = shapes / np.sqrt(np.einsum('ik,ik->k', shapes, m @ shapes))
            return values[:keep], shapes[:, :keep]
        want = min(n - 2, 2 * want)


def _classified(system: PlatformSystem, values, shapes, mass) -> Modes:
    nd = system.platform_dofs
    m_phi = mass @ shapes                                   # (dofs, k)
    total = np.einsum('ik,ik->k', shapes, m_phi)
    platform = np.einsum('ik,ik->k', shapes[:nd], (mass[:nd, :nd] @ shapes[:nd]))
    fraction = platform / total
    kinds = classify(fraction)
    interior = system.assembly.interior_dofs
    cable = np.full(values.size, -1)
    if interior:
        n_cables = system.geometry.n_cables
        per = interior // n_cables
        energy = np.empty((n_cables, values.size))
        for c in range(n_cables):
            rows = slice(nd + c * per, nd + (c + 1) * per)
            energy[c] = np.einsum('ik,ik->k', shapes[rows], mass[rows, rows] @ shapes[rows])
        cable = np.where(np.array([k != 'platform' for k in kinds], dtype=bool),
                         np.argmax(energy, axis=0), -1)
    effective = (m_phi[:nd].T ** 2) / total[:, None]        # (k, ndof)
    frequency = np.sqrt(np.clip(values, 0.0, None)) / (2.0 * np.pi)
    return Modes(frequency, fraction, kinds, cable, effective, shapes)
