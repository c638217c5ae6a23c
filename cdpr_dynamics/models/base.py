"""The one interface every cable model implements.

A cable runs from its anchor (fixed) to its platform attachment. A model turns the cables'
state (:class:`CableSet`) into a :class:`CableAssembly`: what the platform feels of each cable.

* ``end_stiffness(lam)``: the cable's dynamic stiffness condensed onto its platform end,
  ``S_i(lam) = K_ee - lam M_ee - (K_ei - lam M_ei)(K_ii - lam M_ii)^-1 (K_ie - lam M_ie)``,
  shape (len(lam), n, 3, 3), for complex ``lam``. With Rayleigh damping C = dM M + dK K the
  damped dynamic stiffness is ``(1 + i w dK) S(lam)`` with ``lam = (w^2 - i w dM)/(1 + i w dK)``,
  so one function serves damped and undamped, static (lam = 0) and dynamic analyses.
* ``blocks``: the cable's finite matrices as block-tridiagonal 3x3 blocks over its free nodes
  (interior nodes from the anchor side, the platform end node last), for eigenvalues and time
  history; ``None`` for a model without finite matrices (``dsm``).

Models are registered by name in :mod:`cdpr_dynamics.models`.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np


def row_norm(x: np.ndarray) -> np.ndarray:
    """|x| along the last axis: ``np.linalg.norm(x, axis=-1)``'s arithmetic (the same
    numbers) without its argument handling, half the cost on a few rows."""
    return np.sqrt(np.add.reduce(x * x, axis=-1))


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


class AnchorEnd(NamedTuple):
    """What lies between each cable's free span and its fixed end, stacked over cables.

    ``series_length_m`` (n,): cable in series with the free span (wrapped on a pulley and
    between drum and anchor): axial compliance series_length / EA. ``plane_normal`` (n, 3):
    the unit normal of a swivelling pulley's plane (zero rows: no pulley); ``pivot_m`` (n,):
    the distance c = r tan(beta/2) from the exit point back along the cable to the swivel
    axis, about which the span turns out of the pulley plane: compliance c / T along the
    normal. In the pulley plane, across the cable, the exit point does not move.
    """

    series_length_m: np.ndarray
    plane_normal: np.ndarray
    pivot_m: np.ndarray

    @property
    def has_pulleys(self) -> bool:
        return bool(np.any(self.pivot_m))

    def compliance(self, ea_n: float, tension_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(axial, out-of-plane) compliance of each anchor end (m/N), (n,) each."""
        tension_n = np.asarray(tension_n)
        if tension_n.min() > 0.0:
            normal = self.pivot_m / tension_n
        else:                           # slack cables: no swivel compliance (invalid anyway)
            with np.errstate(divide='ignore', invalid='ignore'):
                normal = np.where(self.pivot_m > 0, self.pivot_m / tension_n, 0.0)
        return self.series_length_m / ea_n, normal


@dataclass(frozen=True, eq=False)
class CableSet:
    """The cables at one state, stacked over cables (first axis n); SI units.

    ``chord_m`` points from the platform attachment to the anchor (world frame);
    ``tension_n`` is the tension at the platform end from the tension distribution;
    ``sag_state`` the elastic catenaries at these tensions where the statics already solved
    them (a :class:`cdpr_dynamics.models.catenary.CatenaryState`, reused by the sag-aware
    models), else None; ``anchor_end`` the pulleys and winch-side cable in series at the
    anchor ends (:class:`AnchorEnd`), None for fixed anchors.
    """

    chord_m: np.ndarray
    tension_n: np.ndarray
    ea_n: float
    weight_per_length_n_per_m: float
    gravity_m_s2: np.ndarray
    sag_state: object = None
    anchor_end: AnchorEnd | None = None

    @property
    def n_cables(self) -> int:
        return self.chord_m.shape[0]

    @functools.cached_property
    def length_m(self) -> np.ndarray:
        return np.linalg.norm(self.chord_m, axis=1)

    @functools.cached_property
    def unit(self) -> np.ndarray:
        return self.chord_m / self.length_m[:, None]

    @functools.cached_property
    def mass_per_length_kg_m(self) -> float:
        g = np.asarray(self.gravity_m_s2, dtype=float).ravel()
        g = math.sqrt(g.dot(g))                   # np.linalg.norm's arithmetic, no wrapper
        return self.weight_per_length_n_per_m / g if g > 0 else 0.0

    def with_tension(self, tension_n) -> 'CableSet':
        return CableSet(self.chord_m, np.asarray(tension_n, dtype=float), self.ea_n,
                        self.weight_per_length_n_per_m, self.gravity_m_s2,
                        anchor_end=self.anchor_end)

    def reversed(self) -> 'CableSet':
        """Each cable seen from its other end (anchor <-> attachment), same tension, both
        ends fixed (no anchor end)."""
        return CableSet(-self.chord_m, self.tension_n, self.ea_n,
                        self.weight_per_length_n_per_m, self.gravity_m_s2)


class ChainBlocks(NamedTuple):
    """Block-tridiagonal cable matrices over the free nodes of each cable.

    ``k_diag``, ``m_diag``: (n, nodes, 3, 3); ``k_off``, ``m_off``: (n, nodes - 1, 3, 3), block
    (k, k+1). Node ``nodes - 1`` is the platform end; the anchor node is fixed and left out.
    """

    k_diag: np.ndarray
    k_off: np.ndarray
    m_diag: np.ndarray
    m_off: np.ndarray

    @property
    def nodes(self) -> int:
        return self.k_diag.shape[1]


@dataclass(frozen=True, eq=False)
class CableAssembly:
    """What one model gives for one state (see the module docstring)."""

    method: str
    elements_per_cable: int
    end_stiffness: Callable[[np.ndarray], np.ndarray]
    end_force_n: np.ndarray            # (n, 3) force of each cable on the platform
    blocks: ChainBlocks | None
    valid: bool = True
    warnings: tuple[str, ...] = field(default=())
    # optional shortcuts of end_stiffness (the same numbers, cheaper for the platform sums):
    decoupled: 'AxialTransverse | None' = None     # S_i = a_i u u^T + t_i (I - u u^T)
    constant_stiffness: np.ndarray | None = None   # (n, 3, 3) real: S_i(lam) for every lam
    # (n, 3, 3) rows: two in-plane axes and the normal of the plane each chain lies in (its
    # blocks split into in-plane 2x2 and normal 1x1 parts), None where they do not
    plane_basis: np.ndarray | None = None

    @property
    def interior_dofs(self) -> int:
        """Cable DOFs besides the platform's (all cables together)."""
        if self.blocks is None:
            return 0
        n, nodes = self.blocks.k_diag.shape[:2]
        return 3 * n * (nodes - 1)

    def static_end_stiffness(self) -> np.ndarray:
        """(n, 3, 3) real stiffness of each cable at its platform end (N/m); computed once per
        assembly (a pose update asks for it several times), returned as a copy."""
        return self._static_end.copy()

    @functools.cached_property
    def _static_end(self) -> np.ndarray:
        return self.end_stiffness(np.zeros(1))[0].real


class AxialTransverse(NamedTuple):
    """End stiffness of straight cables whose axial and transverse motions decouple:
    S_i(lam) = a_i(lam) u_i u_i^T + t_i(lam) (I - u_i u_i^T), and with pulleys
    + (o_i(lam) - t_i(lam)) m_i m_i^T (o: across the cable, normal to the pulley plane m_i).

    ``unit`` (n, 3); ``stiffness(lam)`` for ``lam`` (nl,) gives (2, n, nl): a (row 0) and t
    (row 1) in N/m, frequency last, real for real lam and complex for complex lam; with
    ``normal`` (n, 3) it gives (3, n, nl), o in row 2.
    """

    unit: np.ndarray
    stiffness: Callable[[np.ndarray], np.ndarray]
    normal: np.ndarray | None = None

    def end_stiffness(self, lam) -> np.ndarray:
        """(nl, n, 3, 3) complex: the :class:`CableAssembly` ``end_stiffness`` of these."""
        parts = self.stiffness(np.ravel(lam))
        return axial_transverse(self.unit, parts[0].T, parts[1].T, self.normal,
                                None if self.normal is None else parts[2].T
                                ).astype(complex, copy=False)


def axial_transverse(unit: np.ndarray, axial: np.ndarray, transverse: np.ndarray,
                     normal: np.ndarray | None = None, out_of_plane=None) -> np.ndarray:
    """3x3 tensors ``a u u^T + t (I - u u^T)`` for stacked unit vectors, and with ``normal``
    (n, 3) unit vectors normal to u (or zero) ``+ (o - t) m m^T`` (o: ``out_of_plane``).

    ``unit`` (n, 3); ``axial``, ``transverse`` broadcastable to (..., n): result (..., n, 3, 3).
    """
    uu = unit[:, :, None] * unit[:, None, :]
    axial = np.asarray(axial)[..., None, None]
    transverse = np.asarray(transverse)[..., None, None]
    out = axial * uu + transverse * (_EYE3 - uu)
    if normal is not None:
        mm = normal[:, :, None] * normal[:, None, :]
        out = out + (np.asarray(out_of_plane)[..., None, None] - transverse) * mm
    return out


def anchor_series(stiffness: np.ndarray, cables: CableSet, lam=None) -> np.ndarray:
    """End stiffness (..., n, 3, 3) of cables with their :class:`AnchorEnd` in series.

    Massless cables (``lam`` None): (S^-1 + F)^-1 with F = f_a u u^T + f_m m m^T
    (:meth:`AnchorEnd.compliance`, u the chord), as S - S V E (I + V^T S V E)^-1 V^T S with
    V = [u m], E = diag(f_a, f_m) (no inverse of S, exact where F = 0). Cables with mass at
    ``lam`` (nl,), the leading axis of ``stiffness``: the anchor end moves the cable's far
    end, whose transfer t^2 = s^2 + k mu lam (k = EA along u, T along m) a straight
    continuous cable has, so each direction also loses k mu lam f / (1 + s f) (exact for
    straight cables: (s - k mu lam f)/(1 + s f), ``dsm``'s). ``stiffness`` unchanged without
    an anchor end."""
    end = cables.anchor_end
    if end is None:
        return stiffness
    f_axial, f_normal = end.compliance(cables.ea_n, cables.tension_n)
    v = np.stack([cables.unit, end.plane_normal], axis=-1)            # (n, 3, 2)
    sv = stiffness @ v                                                # (..., n, 3, 2)
    vsv = np.swapaxes(v, -1, -2) @ sv                                 # (..., n, 2, 2)
    e = np.stack([f_axial, f_normal], axis=-1)                        # (n, 2)
    a = np.eye(2) + vsv * e[..., None, :]                             # I + V^T S V E
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    inverse = np.stack([np.stack([a[..., 1, 1], -a[..., 0, 1]], -1),
                        np.stack([-a[..., 1, 0], a[..., 0, 0]], -1)], -2) / det[..., None, None]
    out = stiffness - (sv * e[..., None, :]) @ inverse @ np.swapaxes(sv, -1, -2)
    if lam is None:
        return out
    k = np.stack([np.full(cables.n_cables, cables.ea_n), cables.tension_n], axis=-1)    # (n, 2)
    lam = np.asarray(lam).reshape((-1,) + (1,) * (stiffness.ndim - 2))
    s = np.diagonal(vsv, axis1=-2, axis2=-1)                          # (..., n, 2)
    loss = k * cables.mass_per_length_kg_m * lam * e / (1.0 + s * e)
    return out - np.einsum('cia,...ca,cja->...cij', v, loss, v)


def massless_assembly(method: str, stiffness: np.ndarray, end_force_n: np.ndarray, valid: bool,
                      warnings) -> CableAssembly:
    """A model without cable DOFs: one node per cable with its (n, 3, 3) static ``stiffness``
    at the platform end and no mass; its end stiffness is the same at every frequency."""
    zeros = np.zeros((stiffness.shape[0], 0, 3, 3))
    blocks = ChainBlocks(stiffness[:, None], zeros, np.zeros_like(stiffness)[:, None], zeros)

    def end_stiffness(lam):
        return np.broadcast_to(stiffness, (np.size(lam),) + stiffness.shape).astype(complex)

    return CableAssembly(method, 1, end_stiffness, end_force_n, blocks, valid=valid,
                         warnings=tuple(warnings), constant_stiffness=stiffness)


def slack_warnings(tension_n: np.ndarray) -> tuple[str, ...]:
    """Warnings for cables that carry no tension (T <= 0): straight models are invalid there."""
    if np.asarray(tension_n).min(initial=np.inf) > 0.0:     # the usual case: no loop over
        return ()                                            # numpy scalars
    return tuple(f'cable {i} is slack (T = {t:.3g} N <= 0): its geometric stiffness is not '
                 'positive' for i, t in enumerate(tension_n) if not t > 0.0)
