"""Checks of a state the live node is asked to use: cable interference and wrench feasibility.

ROS-free. Both checks return a one-line reason, or ``''`` when the state is fine, so the node and
``cdpr_replay`` reject the same inputs with the same words.

Wrench-feasible set. With the structure matrix W^T (d, n) at a pose, the wrenches the cables can
supply with tensions in the box [T_min, T_max] form the zonotope

    Z = { W^T T : T_min <= T_i <= T_max } = c + sum_i [-h, h] g_i,
    c = (T_min + T_max)/2 W^T 1,   h = (T_max - T_min)/2,   g_i = column i of W^T.

A full-dimensional zonotope in R^d is the intersection of the slabs whose normals are
orthogonal to d - 1 of its generators, |nu . (w - c)| <= h sum_i |nu . g_i|, so once those
normals are known (once per pose) a wrench is tested exactly with one small matrix product:
microseconds, against the ~0.1 ms of a QP. The normals come from the pairs of generators
(cross products) for d = 3 and from the 5-subsets (null vectors) for d = 6; where there would
be too many, or W^T is rank deficient, :class:`WrenchSet` falls back to the tension QP.
"""
from __future__ import annotations

from functools import lru_cache
from itertools import combinations
from math import comb

import numpy as np

#: more facet normals than this: test wrenches with the QP instead (rare: many cables, 6 DOF).
MAX_NORMALS = 4000


def _segment_distance(p0, p1, q0, q1):
    """Closest distance between segments p0-p1 and q0-q1, stacked over the first axis."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum('ij,ij->i', d1, d1)
    e = np.einsum('ij,ij->i', d2, d2)
    f = np.einsum('ij,ij->i', d2, r)
    c = np.einsum('ij,ij->i', d1, r)
    b = np.einsum('ij,ij->i', d1, d2)
    denom = a * e - b * b
    with np.errstate(divide='ignore', invalid='ignore'):
        s = np.where(denom > 1e-12 * a * e, np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
        t = (b * s + f) / e
    # clamp t, then recompute s for the clamped t (Ericson, Real-Time Collision Detection 5.1.9)
    t_clamped = np.clip(t, 0.0, 1.0)
    s = np.where(t != t_clamped, np.clip((b * t_clamped - c) / a, 0.0, 1.0), s)
    t = t_clamped
    gap = (p0 + s[:, None] * d1) - (q0 + t[:, None] * d2)
    return np.linalg.norm(gap, axis=1), s, t


def cable_crossing(anchors_m, attachments_world_m, clearance_m: float) -> str:
    """Reason why two straight cables would touch or cross, or ``''``.

    ``anchors_m`` (n, 3) and ``attachments_world_m`` (n, 3) are the cable ends in the frame;
    cables closer than ``clearance_m`` (e.g. the cable diameter) anywhere along their length
    interfere. Pairs that share an end (all cables of a point-mass end-effector, or two cables
    on one anchor) are not compared.
    """
    a = np.asarray(anchors_m, dtype=float)
    b = np.asarray(attachments_world_m, dtype=float)
    n = a.shape[0]
    if n < 2:
        return ''
    i, j = np.triu_indices(n, 1)
    shared = ((np.linalg.norm(a[i] - a[j], axis=1) <= clearance_m)
              | (np.linalg.norm(b[i] - b[j], axis=1) <= clearance_m))
    i, j = i[~shared], j[~shared]
    if i.size == 0:
        return ''
    dist, s, _ = _segment_distance(b[i], a[i], b[j], a[j])
    hit = np.flatnonzero(dist < clearance_m)
    if hit.size == 0:
        return ''
    k = hit[np.argmin(dist[hit])]
    where = b[i[k]] + s[k] * (a[i[k]] - b[i[k]])
    return (f'cables {i[k]} and {j[k]} cross: {dist[k] * 1e3:.1f} mm apart at '
            f'{np.round(where, 3).tolist()} m (clearance {clearance_m * 1e3:.1f} mm)')


@lru_cache(maxsize=16)
def _subsets(n: int, k: int) -> np.ndarray:
    return np.array(list(combinations(range(n), k)))


def _facet_normals(wt: np.ndarray) -> np.ndarray | None:
    """Unit normals of the zonotope's facets, (k, d); None when not available."""
    d, n = wt.shape
    if n < d or comb(n, d - 1) > MAX_NORMALS:
        return None
    sing = np.linalg.svd(wt, compute_uv=False)
    if sing[-1] <= 1e-9 * sing[0]:
        return None                             # rank deficient: a flat set
    if d == 3:
        i, j = np.triu_indices(n, 1)
        normals = np.cross(wt.T[i], wt.T[j])
    else:
        gens = wt.T[_subsets(n, d - 1)]         # (k, d-1, d)
        _, sing, vt = np.linalg.svd(gens)       # null vector: last right singular vector
        normals = vt[:, -1, :]
        normals = normals[sing[:, -1] > 1e-9 * sing[:, 0]]
    norm = np.linalg.norm(normals, axis=1)
    keep = norm > 1e-9
    return normals[keep] / norm[keep, None]


class WrenchSet:
    """The wrench-feasible set at one pose; :meth:`reason` tests the external wrench.

    ``required`` (d,) is what the cables supply at rest (gravity and static load, Eq. 9); an
    external wrench f (force then moment) is feasible when ``required - f`` lies in Z. ``solver``
    (a :class:`cdpr_dynamics.tensions.TensionSolver`) is used only where the normals are not.
    """

    def __init__(self, structure_matrix, t_min_n: float, t_max_n: float, required,
                 solver=None, tolerance_n: float = 1e-6):
        self.wt = np.asarray(structure_matrix, dtype=float)
        self.required = np.asarray(required, dtype=float)
        self.t_min_n, self.t_max_n = float(t_min_n), float(t_max_n)
        self.centre = self.wt @ np.full(self.wt.shape[1], 0.5 * (t_min_n + t_max_n))
        self.half = 0.5 * (t_max_n - t_min_n)
        self.solver = solver
        self.normals = _facet_normals(self.wt)
        if self.normals is not None:
            self.offset = self.normals @ self.centre
            self.reach = self.half * np.abs(self.normals @ self.wt).sum(axis=1)
        scale = max(1.0, float(np.abs(self.required).max(initial=0.0)), t_max_n)
        self.tolerance = tolerance_n * scale

    def margin(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> float:
        """Smallest slack of the facet inequalities (N or N m per unit normal); < 0: outside."""
        w = self._needed(force_n, moment_nm)
        if self.normals is None:
            return 0.0 if self._qp_feasible(w) else -np.inf
        return float(np.min(self.reach - np.abs(self.normals @ w - self.offset)))

    def reason(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> str:
        """Why the external wrench cannot be held by the cables within the box, or ``''``."""
        w = self._needed(force_n, moment_nm)
        if not np.all(np.isfinite(w)):
            return 'wrench is not finite'
        if self.normals is not None:
            slack = self.reach - np.abs(self.normals @ w - self.offset)
            k = int(np.argmin(slack))
            if slack[k] >= -self.tolerance:
                return ''
            return (f'wrench outside the feasible set: the cables would need '
                    f'{_fmt(w)} with tensions in [{self.t_min_n:g}, {self.t_max_n:g}] N; '
                    f'exceeds the reachable set by {-slack[k]:.4g} along '
                    f'{_fmt(self.normals[k])}')
        if self._qp_feasible(w):
            return ''
        return (f'wrench outside the feasible set: the cables would need {_fmt(w)} with '
                f'tensions in [{self.t_min_n:g}, {self.t_max_n:g}] N')

    def _needed(self, force_n, moment_nm) -> np.ndarray:
        ext = np.concatenate([np.asarray(force_n, dtype=float).reshape(3),
                              np.asarray(moment_nm, dtype=float).reshape(3)])
        return self.required - ext[:self.required.size]

    def _qp_feasible(self, w) -> bool:
        if self.solver is None:
            from cdpr_dynamics.tensions import TensionSolver
            self.solver = TensionSolver(self.wt.shape[1], self.wt.shape[0], self.t_min_n,
                                        self.t_max_n)
        return bool(self.solver.solve(self.wt, w).feasible)


def _fmt(v) -> str:
    return '[' + ', '.join(f'{x:.4g}' for x in np.asarray(v).ravel()) + ']'
