"""Modes you can interpret: which natural modes move the platform, which are the cables'.

For a model with finite matrices (global K, M: platform DOFs first, then each cable's interior
nodes, :meth:`PlatformSystem.matrices`) the undamped modes solve K phi = w^2 M phi, mass
normalised (phi^T M phi = 1). For each mode:

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
  phi_c^T M_cc phi_c over cables c (None for a platform mode and for models without
  interior nodes).
* **effective modal mass** per platform DOF j: m_kj = (phi_k^T M e_j)^2 with e_j the unit
  vector of DOF j (mass-normalised phi_k). Because sum_k phi_k phi_k^T = M^-1,
  sum_k m_kj = e_j^T M M^-1 M e_j = M_jj: over all modes the effective masses add up to the
  platform diagonal of M (kg for translations, kg m^2 for rotations).

Massless models (``spring``, ``catenary``, ``catenary_exact``) have platform DOFs only: every
mode is a platform mode (e = 1), and the effective masses of a point mass are m per axis.
``dsm`` has no finite matrices: :func:`modes` refuses it (DynamicsError).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse.linalg as spla

from cdpr_dynamics.dynamics import DENSE_EIGEN_DOFS, DynamicsError, PlatformSystem

PLATFORM_SHARE = 0.5    # platform energy fraction at or above: kind 'platform'
CABLE_SHARE = 0.1       # platform energy fraction at or below: kind 'cable'
MIN_MODES = 12          # at least this many modes (SPEC section 6: "at least the 12 lowest")


@dataclass(frozen=True, eq=False)
class Modes:
    """The classified modes of one system, ascending in frequency.

    ``frequency_hz`` (k,); ``platform_fraction`` (k,) platform share of the kinetic energy;
    ``kind`` k strings; ``cable`` (k,) int, -1 where no cable (platform modes, massless
    models); ``effective_mass`` (k, ndof) kg / kg m^2; ``shapes`` (dofs, k) mass-normalised.
    """

    frequency_hz: np.ndarray
    platform_fraction: np.ndarray
    kind: tuple[str, ...]
    cable: np.ndarray
    effective_mass: np.ndarray
    shapes: np.ndarray

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
                 else 'mixed' for e in np.asarray(fraction, dtype=float))


def modes(system: PlatformSystem, f_max_hz: float | None = None,
          count: int = MIN_MODES, hint: int = 0) -> Modes:
    """Every mode up to ``f_max_hz`` and at least the ``count`` lowest, classified.

    ``f_max_hz=None``: the ``count`` lowest only; ``count`` at least the DOFs: all modes.
    Dense LAPACK for small models, shift-invert Lanczos (sigma = 0) otherwise, asked for
    ``max(count, hint + 2)`` modes first (``hint``: how many a neighbouring state had, e.g.
    the previous pose of a workspace chunk) and widened until the highest mode found lies
    above ``f_max_hz``; ``hint`` changes the cost, not the modes (beyond round-off).
    """
    if system.assembly.blocks is None:
        raise DynamicsError(f'method {system.assembly.method} has no finite matrices: its '
                            'modes cannot be classified (use fem or fem_sag)')
    k, m = system.matrices()
    values, shapes = _eigen(k, m, f_max_hz, count, hint)
    mass = m.toarray() if k.shape[0] <= DENSE_EIGEN_DOFS else m
    return _classified(system, values, shapes, mass)


def _eigen(k, m, f_max_hz, count, hint=0):
    """Lowest eigenpairs (w^2, mass-normalised phi) of K phi = w^2 M phi, ascending."""
    n = k.shape[0]
    limit = np.inf if f_max_hz is None else (2.0 * np.pi * f_max_hz) ** 2
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
