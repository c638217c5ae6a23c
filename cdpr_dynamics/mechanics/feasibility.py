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
microseconds. The normals come from the pairs of generators (cross products) for d = 3 and from
the (d-1)-subsets (null vectors) for d = 6.

The slab inequality holds on Z for any unit nu (its right side is the support function of
Z - c), so a wrench outside one slab is infeasible whatever nu is: a rejection by a slab is
always right, even with a rounded or partial set of normals. Where all normals would be too many
(``MAX_NORMALS``: many cables on a 6-DOF platform) or W^T is rank deficient, :class:`WrenchSet`
keeps ``MAX_NORMALS`` facet normals of random subsets (an outer bound: rejects exactly) and
accepts a wrench inside it when the least-norm tensions T = T_mid + (W^T)^+ (w - c) lie in the
box and meet W^T T = w (an inner test); only a wrench between the two (near the boundary) is
decided by a linear program (HiGHS, ``scipy.optimize.linprog``: find T in the box with
W^T T = w; a few ms for 1000 cables, against 100-130 ms for the tension QP it replaces).
"""
from __future__ import annotations

from functools import cached_property, lru_cache
from itertools import combinations
from math import comb, inf

import numpy as np

from cdpr_dynamics.mechanics.robot import cross, row_norm, singular_values

#: more facet normals than this: keep this many (random subsets) as an outer bound, decide the
#: rest with the inner test and an LP (many cables on a 6-DOF platform).
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
    """(C(n, k), k) index subsets of n generators (for k = 2 the pairs i < j of triu_indices)."""
    if k == 2:
        return np.column_stack(np.triu_indices(n, 1))
    return np.array(list(combinations(range(n), k)))


def _rank_full(wt: np.ndarray) -> bool:
    sing = singular_values(wt)
    return wt.shape[1] >= wt.shape[0] and sing[-1] > 1e-9 * sing[0]


def _normals_of(wt: np.ndarray, subsets: np.ndarray) -> np.ndarray:
    """Unit normals (k, d) of the hyperplanes spanned by the generator ``subsets`` (k, d-1).

    d > 3: the generalised cross product of the d - 1 generators g (rows of A), component i
    (-1)^i det(A without column i), orthogonal to every g; its length is the volume they
    span, and subsets whose volume is at most 1e-9 of the product of their lengths (nearly
    dependent generators) span no hyperplane."""
    d = wt.shape[0]
    if d == 3:
        return _unit_rows(cross(wt.T[subsets[:, 0]], wt.T[subsets[:, 1]]))
    a = wt.T[subsets]                                                     # (k, d - 1, d)
    cols, sign = _minor_columns(d)
    normals = np.linalg.det(a[:, :, cols].transpose(0, 2, 1, 3)) * sign   # (k, d)
    volume = row_norm(normals)
    keep = volume > 1e-9 * np.prod(row_norm(a), axis=1)
    return normals[keep] / volume[keep, None]


@lru_cache(maxsize=4)
def _minor_columns(d: int) -> tuple[np.ndarray, np.ndarray]:
    """((d, d - 1) the columns left in each minor of a (d - 1, d) matrix, (d,) its sign),
    read-only (kept)."""
    cols = np.array([[j for j in range(d) if j != i] for i in range(d)])
    sign = (-1.0) ** np.arange(d)
    cols.flags.writeable = sign.flags.writeable = False
    return cols, sign


@lru_cache(maxsize=16)
def _pair_cross_index(n: int) -> np.ndarray:
    """(4, 3, C(n, 2)) flat indices into a C-ordered (3, n) W^T of the factors of the cross
    products g_i x g_j of all pairs i < j (the order of :func:`_subsets`): component c is
    a_{c+1} b_{c+2} - a_{c+2} b_{c+1} (indices mod 3) with a = g_i, b = g_j, as
    :func:`~cdpr_dynamics.mechanics.robot.cross` computes it."""
    i, j = np.triu_indices(n, 1)
    r1, r2 = np.array([[1], [2], [0]]), np.array([[2], [0], [1]])
    return np.stack([r1 * n + i, r2 * n + j, r2 * n + i, r1 * n + j])


def _unit_rows(normals: np.ndarray) -> np.ndarray:
    """The rows of ``normals`` (k, d) scaled to unit length; rows of length below 1e-9 of the
    longest (and of 1) dropped: degenerate subsets span no hyperplane."""
    norm = row_norm(normals)
    keep = norm > 1e-9 * max(1.0, float(norm.max(initial=0.0)))
    if keep.all():
        return normals / norm[:, None]
    return normals[keep] / norm[keep, None]


def _facet_normals(wt: np.ndarray, full_rank: bool = False) -> np.ndarray | None:
    """Unit normals of all the zonotope's facets, (k, d); None when too many or rank deficient
    (``full_rank``: the caller has checked the rank already). For d = 3 the cross products of
    all pairs come from one gather of W^T's entries (:func:`_pair_cross_index`)."""
    d, n = wt.shape
    if n < d or comb(n, d - 1) > MAX_NORMALS or not (full_rank or _rank_full(wt)):
        return None
    if d == 3:     # C-ordered normals: the products with them below sum as before
        f = np.ascontiguousarray(wt).ravel().take(_pair_cross_index(n))
        return _unit_rows((f[0] * f[1] - f[2] * f[3]).T.copy())
    return _normals_of(wt, _subsets(n, d - 1))


def _sampled_normals(wt: np.ndarray, count: int = MAX_NORMALS) -> np.ndarray:
    """Unit normals of ``count`` facets from random (d-1)-subsets (fixed seed), with the axes."""
    d, n = wt.shape
    rng = np.random.default_rng(0)
    subsets = np.argsort(rng.random((count, n)), axis=1)[:, :d - 1] if n >= d - 1 else \
        np.zeros((0, d - 1), dtype=int)
    return np.vstack([np.eye(d), _normals_of(wt, subsets)]) if subsets.size else np.eye(d)


class WrenchSet:
    """The wrench-feasible set at one pose; :meth:`reason` tests the external wrench.

    ``required`` (d,) is what the cables supply at rest (gravity and static load, Eq. 9); an
    external wrench f (force then moment) is feasible when ``required - f`` lies in Z.
    ``exact``: all facet normals are known (the test is one matrix product); otherwise the
    outer bound, the inner test and, between them, an LP decide (module docstring).
    ``full_rank``: W^T is known to have rank d (checked with singular values above 1e-9 of
    the largest, as here): its SVD is skipped.
    """

    def __init__(self, structure_matrix, t_min_n: float, t_max_n: float, required,
                 tolerance_n: float = 1e-6, full_rank: bool = False):
        self.wt = np.asarray(structure_matrix, dtype=float)
        self.required = np.asarray(required, dtype=float)
        self.t_min_n, self.t_max_n = float(t_min_n), float(t_max_n)
        self.mid = 0.5 * (t_min_n + t_max_n)
        self.centre = self.wt @ np.full(self.wt.shape[1], self.mid)
        self.half = 0.5 * (t_max_n - t_min_n)
        self.normals = _facet_normals(self.wt, full_rank)
        self.exact = self.normals is not None
        if not self.exact:
            self.normals = _sampled_normals(self.wt)
            self._pinv = np.linalg.pinv(self.wt)
        self.offset = self.normals @ self.centre
        self.reach = self.half * np.abs(self.normals @ self.wt).sum(axis=1)
        scale = max(1.0, max(map(abs, self.required.tolist()), default=0.0), t_max_n)
        self.tolerance = tolerance_n * scale
        self.lp_calls = 0

    def margin(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> float:
        """Smallest slack of the facet inequalities (N or N m per unit normal); < 0: outside.
        Without all normals: that slack where it is negative, else 0.0 (inside) or -inf."""
        w = self._needed(force_n, moment_nm)
        slack = float(np.min(self.reach - np.abs(self.normals @ w - self.offset)))
        if self.exact or slack < -self.tolerance:
            return slack
        return 0.0 if self._inside(w) else -np.inf

    def reason(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> str:
        """Why the external wrench cannot be held by the cables within the box, or ``''``.

        A wrench well inside (every facet's slack >= 0, not only >= -tolerance) is accepted
        by :attr:`_inside_test` alone, one product; any other goes through the full test."""
        if self.exact:
            test, external = self._inside_test
            external[:3] = force_n
            if external.size == 7:
                external[3:6] = moment_nm
            if test.dot(external).max() <= 0.0:         # NaN: not <= 0, the full test says
                return ''
        w = self._needed(force_n, moment_nm)
        slack = self.reach - np.abs(self.normals.dot(w) - self.offset)
        k = int(slack.argmin())
        if not slack[k] >= -self.tolerance:          # outside, or NaN/inf (one test per wrench)
            if not np.isfinite(w).all():
                return 'wrench is not finite'
            return (f'wrench outside the feasible set: the cables would need '
                    f'{_fmt(w)} with tensions in [{self.t_min_n:g}, {self.t_max_n:g}] N; '
                    f'exceeds the reachable set by {-slack[k]:.4g} along '
                    f'{_fmt(self.normals[k])}')
        if self.exact or self._inside(w):
            return ''
        return (f'wrench outside the feasible set: the cables would need {_fmt(w)} with '
                f'tensions in [{self.t_min_n:g}, {self.t_max_n:g}] N (linear program)')

    def inside_many(self, force_n: np.ndarray, moment_nm: np.ndarray) -> np.ndarray:
        """(k,) True for the external wrenches (rows of ``force_n`` (k, 3), ``moment_nm``
        (k, 3)) that :meth:`reason` accepts by its first test alone, one product for all; the
        others (False) are for :meth:`reason` itself to decide. All False without every facet
        normal."""
        force_n = np.asarray(force_n, dtype=float)
        if not self.exact:
            return np.zeros(len(force_n), dtype=bool)
        test, _ = self._inside_test
        d = test.shape[1] - 1
        external = np.ones((len(force_n), d + 1))
        external[:, :3] = force_n
        if d == 6:
            external[:, 3:6] = moment_nm
        with np.errstate(invalid='ignore'):        # NaN: not inside, reason says why
            return (external @ test.T).max(axis=1, initial=-np.inf) <= 0.0

    def symmetric_limit(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> float:
        """The largest s >= 0 with both +s f and -s f feasible (f = (force, moment), the
        amplitude of a harmonic load as a multiple of f); 0 where even f = 0 is not, inf where
        no facet bounds f. With all facet normals, closed form: facet k holds +-s f while
        |c_k| + s |n_k . f| <= reach_k, c_k = n_k . required - offset_k, so s is the least
        (reach_k - |c_k|) / |n_k . f|. Otherwise that bound over the sampled normals (an outer
        one) and bisection of :meth:`reason` below it, to 1e-9 of it."""
        f = self.required - self._needed(force_n, moment_nm)      # the external wrench
        c = self.normals @ self.required - self.offset
        a = np.abs(self.normals @ f)
        room = self.reach - np.abs(c)
        if room.min() < 0.0:
            return 0.0
        bounded = a > 1e-12 * max(float(np.abs(f).max(initial=0.0)), 1.0) * \
            np.abs(self.normals).sum(axis=1)
        if not np.any(bounded):
            return inf
        upper = float(np.min(room[bounded] / a[bounded]))
        if self.exact:
            return upper
        force, moment = np.asarray(force_n, float), np.asarray(moment_nm, float)

        def holds(scale):
            return all(self.reason(sign * scale * force, sign * scale * moment) == ''
                       for sign in (1.0, -1.0))
        lo, hi = 0.0, upper
        if holds(hi):
            return hi
        while hi - lo > 1e-9 * upper:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if holds(mid) else (lo, mid)
        return lo

    @cached_property
    def _inside_test(self) -> tuple[np.ndarray, np.ndarray]:
        """(T (2k, d+1), buffer (d+1,) ending in 1) with T [f; 1] <= 0 iff every facet's
        slack is >= 0 for the external wrench f: with c = n . required - offset per normal n,
        the slack reach - |c - n . f| >= 0 reads n . f - (c + reach) <= 0 and
        -n . f + (c - reach) <= 0. Its rounding (~1e-16 of the wrench scale) is far inside
        the tolerance the full test allows, so the answers are the full test's."""
        c = self.normals @ self.required - self.offset
        test = np.block([[self.normals, -(c + self.reach)[:, None]],
                         [-self.normals, (c - self.reach)[:, None]]])
        external = np.zeros(self.normals.shape[1] + 1)
        external[-1] = 1.0
        return test, external

    def _needed(self, force_n, moment_nm) -> np.ndarray:
        """w = the required wrench minus the external one (3 or 6,)."""
        w = self.required.copy()
        w[:3] -= force_n
        if w.size == 6:
            w[3:] -= moment_nm
        return w

    def _inside(self, w) -> bool:
        """Inner test (least-norm tensions in the box), else the LP: is w in Z?"""
        t = self.mid + self._pinv @ (w - self.centre)
        if (t.min() >= self.t_min_n - self.tolerance and t.max() <= self.t_max_n + self.tolerance
                and np.abs(self.wt @ t - w).max() <= self.tolerance):
            return True
        return self._lp_feasible(w)

    def _lp_feasible(self, w) -> bool:
        from scipy.optimize import linprog
        self.lp_calls += 1
        n = self.wt.shape[1]
        result = linprog(np.zeros(n), A_eq=self.wt, b_eq=w,
                         bounds=[(self.t_min_n, self.t_max_n)] * n, method='highs')
        if result.status != 0:
            return False
        return bool(np.abs(self.wt @ result.x - w).max() <= self.tolerance)


def _fmt(v) -> str:
    return '[' + ', '.join(f'{x:.4g}' for x in np.asarray(v).ravel()) + ']'
