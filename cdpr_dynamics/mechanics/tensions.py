"""Cable tension distribution (paper Eqs. 10-12): a small QP, solved with proxsuite.

The tensions T (n,) in N are the solution of

    minimise    1/2 T^T C T + c^T T                    (Eq. 10)
    subject to  T_min <= T_i <= T_max,  i = 1..n        (Eq. 11)
                W^T T = w                                (Eq. 12)

with the structure matrix W^T (ndof, n) of :func:`cdpr_dynamics.mechanics.robot.geometry` (wrench
per unit
tension: N/N in the force rows, N m/N in the moment rows), the wrench w (ndof,) the cables must
supply (:func:`cdpr_dynamics.mechanics.robot.required_wrench`: N, then N m), ndof = 3 for a
point-mass
platform and 6 for a rigid one. The default weights C = I, c = 0 give the tensions of least
2-norm. The optimality (KKT) conditions are

    C T + c - W lambda - mu_low + mu_up = 0,   mu_low, mu_up >= 0,
    mu_low_i (T_i - T_min) = 0,   mu_up_i (T_max - T_i) = 0.

:class:`TensionSolver` keeps one ``proxsuite.proxqp.dense.QP`` with native box constraints for
(11): it is set up once, then only W^T and w are updated (``qp.update``) and each solve is
warm-started from the previous solution, so a live node pays a few tens of microseconds per pose.

Between nearby poses the QP is answered from the previous pose's active set (one
ndof x ndof linear solve, KKT-checked: exact where it holds; proxsuite decides otherwise). A
proxsuite answer is polished the same way on its own active set: its last bits differ from one
QP object to another, the polished tensions are a function of W^T and w alone (node, replay and
tools give the same bits). Infeasibility is never taken on the solver's word alone: a
per-component reachability test, a check of the returned T against (11) and (12) within
``tolerance_n``, and the box tensions closest to w (:func:`closest_tensions`) when the QP
fails. The derivations: doc/theory.md, section "Cable tensions".
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import proxsuite
from scipy.linalg.lapack import dposv as _posv

from cdpr_dynamics.mechanics.robot import WRENCH_AXES

_proxqp = proxsuite.proxqp

#: primal-dual active-set rounds of the warm path before proxsuite decides (module docstring)
ACTIVE_SET_ROUNDS = 3

#: proxsuite outcomes as TensionResult.status strings.
_STATUS = {
    _proxqp.PROXQP_SOLVED: 'solved',
    _proxqp.PROXQP_PRIMAL_INFEASIBLE: 'infeasible',
    _proxqp.PROXQP_SOLVED_CLOSEST_PRIMAL_FEASIBLE: 'infeasible',
    _proxqp.PROXQP_MAX_ITER_REACHED: 'max_iter',
    _proxqp.PROXQP_DUAL_INFEASIBLE: 'dual_infeasible',
    _proxqp.PROXQP_NOT_RUN: 'not_run',
}


@dataclass(frozen=True, eq=False)
class TensionResult:
    """Outcome of one tension distribution.

    ``tension_n`` (n,) N: the optimal tensions when ``feasible``; after a failed solve the box
    tensions closest to the wrench (best effort, never outside [T_min, T_max]), or NaN for
    inputs that are not finite. ``status``: ``'solved'``, ``'infeasible'``, ``'max_iter'``,
    ``'not_finite'`` (or a rarer proxsuite outcome: ``'dual_infeasible'``, ``'not_run'``).
    ``feasible``: status ``'solved'`` and bounds and ``W^T T = w`` hold within ``tolerance_n``.
    ``residual_n``: max |W^T T - w| (N, N m). ``iterations``: proxsuite iterations of the main QP
    (0 when it was not run, e.g. answered by the warm active set). ``reason``: one readable line
    when not feasible, else ''.
    ``solve_time_s``: wall time of :meth:`TensionSolver.solve`. ``tolerance_n``: the tolerance
    (N, N m) that ``feasible`` was judged with.
    """

    tension_n: np.ndarray
    status: str
    feasible: bool
    residual_n: float
    iterations: int
    reason: str = ''
    solve_time_s: float = 0.0
    tolerance_n: float = 0.0

    @classmethod
    def solved(cls, tension_n: np.ndarray, residual_n: float, solve_time_s: float,
               tolerance_n: float) -> 'TensionResult':
        """The answer of the warm active set (feasible, no proxsuite iterations), its fields
        set at once: the generated ``__init__`` of a frozen dataclass sets each through
        ``object.__setattr__``, ~2 us of a ~20 us warm solve."""
        out = object.__new__(cls)
        out.__dict__.update(tension_n=tension_n, status='solved', feasible=True,
                            residual_n=residual_n, iterations=0, reason='',
                            solve_time_s=solve_time_s, tolerance_n=tolerance_n)
        return out


def _fmt(v) -> str:
    """A short vector for messages: ``[0, 0, 294.3]``."""
    return '[' + ', '.join(f'{x:.4g}' for x in np.asarray(v, dtype=float).tolist()) + ']'


def below_text(value: float, bound: float, digits: int = 1) -> str:
    """``value`` (< ``bound``) with at least ``digits`` decimals and as many more as it takes
    to print below ``bound`` ('9.98' for 9.98 under 10, never '10.0')."""
    for d in range(digits, 16):
        text = f'{value:.{d}f}'
        if float(text) < bound:
            return text
    return repr(float(value))


def _box(n_cables: int, t_min_n: float, t_max_n: float) -> tuple[float, float]:
    """The tension bounds (N) as floats, checked: finite and T_min <= T_max."""
    if n_cables < 1:
        raise ValueError(f'need at least one cable, got n_cables = {n_cables}')
    lo, hi = float(t_min_n), float(t_max_n)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f'tension bounds must be finite, got [{lo}, {hi}] N')
    if lo > hi:
        raise ValueError(f'minimum tension {lo:g} N exceeds maximum tension {hi:g} N')
    return lo, hi


def _objective(n: int, weights, linear) -> tuple[np.ndarray, np.ndarray]:
    """Objective terms C (n, n) and c (n,) of Eq. 10, checked.

    ``weights``: None (C = I), an (n,) diagonal or an (n, n) symmetric positive semi-definite
    matrix; ``linear``: None (c = 0) or (n,) in N.
    """
    if weights is None:
        c_mat = np.eye(n)
    else:
        c_mat = np.asarray(weights, dtype=float)
        if c_mat.shape == (n,):
            c_mat = np.diag(c_mat)
        if c_mat.shape != (n, n):
            raise ValueError(f'weights must have shape ({n},) or ({n}, {n}), got '
                             f'{np.shape(weights)}')
    c_vec = np.zeros(n) if linear is None else np.asarray(linear, dtype=float).reshape(-1)
    if c_vec.shape != (n,):
        raise ValueError(f'linear must have shape ({n},), got {np.shape(linear)}')
    if not (np.all(np.isfinite(c_mat)) and np.all(np.isfinite(c_vec))):
        raise ValueError('weights and linear must be finite')
    if not np.allclose(c_mat, c_mat.T, rtol=1e-12, atol=1e-12 * np.abs(c_mat).max()):
        raise ValueError('weights C must be symmetric')
    c_mat = 0.5 * (c_mat + c_mat.T)
    if np.linalg.eigvalsh(c_mat).min() < -1e-10 * max(1.0, np.abs(c_mat).max()):
        raise ValueError('weights C must be positive semi-definite')
    return c_mat, c_vec


class TensionSolver:
    """Warm-started tension distribution for one robot (fixed n, ndof, bounds and weights).

    ``TensionSolver(n_cables, ndof, t_min_n, t_max_n, weights=None, linear=None)`` sets up the
    QP of Eqs. 10-12 (module docstring); :meth:`solve` takes W^T (ndof, n) and w (ndof,) at each
    pose. ``weights``: C as an (n,) diagonal or an (n, n) symmetric PSD matrix (default I);
    ``linear``: c (n,) in N (default 0). ``tolerance_n``: allowed violation of the bounds and of
    W^T T = w for a feasible answer (default 1e-7 max(1, |T_min|, |T_max|) N, i.e. 0.1 mN for
    T_max = 1000 N); proxsuite itself runs to eps_abs = 1e-12 max(1, |T_min|, |T_max|) N.
    ``max_iter``: cap on proxsuite's outer and inner iterations per attempt, which bounds the
    time spent on an infeasible wrench (proxsuite does not always certify a mildly infeasible QP
    and would otherwise iterate for seconds). ``warm_start=False`` solves every pose cold.

    Attempts per :meth:`solve`: warm (when the previous solve succeeded), then cold; on failure
    :func:`closest_tensions` decides between 'infeasible' and one last cold attempt with
    4 x ``max_iter``.

    Raises ValueError for invalid settings (T_min > T_max, non-finite bounds, bad weights);
    :meth:`solve` raises only for wrong array shapes and reports every other problem in its
    :class:`TensionResult`.
    """

    def __init__(self, n_cables: int, ndof: int, t_min_n: float, t_max_n: float,
                 weights=None, linear=None, *, tolerance_n: float | None = None,
                 warm_start: bool = True, max_iter: int = 25):
        if ndof not in (3, 6):
            raise ValueError(f'ndof must be 3 (point mass) or 6 (rigid platform), got {ndof}')
        self.n_cables, self.ndof = int(n_cables), int(ndof)
        self.t_min_n, self.t_max_n = _box(self.n_cables, t_min_n, t_max_n)
        self.hessian, self.linear = _objective(self.n_cables, weights, linear)
        scale = max(1.0, abs(self.t_min_n), abs(self.t_max_n))
        self.tolerance_n = 1e-7 * scale if tolerance_n is None else float(tolerance_n)
        if not self.tolerance_n > 0.0:
            raise ValueError(f'tolerance_n must be positive, got {tolerance_n}')
        # proxsuite's stopping test ignores complementarity: a box-active tension may stop
        # ~100 eps from its bound. 1e-12 scale keeps the answer within ~1e-7 scale of the optimum.
        self._eps = min(1e-12 * scale, 1e-2 * self.tolerance_n)
        self.warm_start = bool(warm_start)
        self.max_iter = int(max_iter)
        self._lower = np.full(self.n_cables, self.t_min_n)
        self._upper = np.full(self.n_cables, self.t_max_n)
        self._mid = np.full(self.n_cables, 0.5 * (self.t_min_n + self.t_max_n))
        self._half = np.full(self.n_cables, 0.5 * (self.t_max_n - self.t_min_n))
        self._qp = None  # set up on the first solve, dropped after a failure
        off = self.hessian - np.diag(np.diag(self.hessian))
        self._h = np.diag(self.hessian).copy() if not off.any() and np.all(
            np.diag(self.hessian) > 0) else None     # the warm active set needs C = diag(h > 0)
        self._kkt_tol = 1e-9 * scale                   # KKT sign and box slack of round-off
        self._unit = self._h is not None and bool(np.all(self._h == 1.0) and not self.linear.any())
        self._active = None   # int8 (n,): -1 at T_min, +1 at T_max, 0 free; None: no answer
        self._terms = {}      # per active set: what _active_set needs of it

    def reset(self) -> None:
        """Forget the previous solution: the next solve starts cold."""
        self._qp = None
        self._active = None

    def _active_of(self, tension: np.ndarray) -> np.ndarray:
        """The active set of an answer: the tensions within ``tolerance_n`` of a bound."""
        return (np.where(tension >= self.t_max_n - self.tolerance_n, 1, 0)
                - (tension <= self.t_min_n + self.tolerance_n)).astype(np.int8)

    @np.errstate(invalid='ignore', over='ignore')   # inf or huge input fails the checks below
    def _active_set(self, wt: np.ndarray, w: np.ndarray, start: float,
                    active: np.ndarray) -> TensionResult | None:
        """The active-set answer from ``active`` (module docstring), or None where it does not
        settle; with warm starts on, the set it settles on is kept for the next solve.

        Per round: the gram G = W^T_F diag(1/h_F) W_F and the right side r = w - W^T base
        (G = W^T W, r = w when every tension is free and C = I, c = 0), lambda = G^-1 r by one
        Cholesky (LAPACK posv), the pull p = W lambda (n,), then one (3, n) array
        q = gain * p + offset (:meth:`_set_terms`) whose first two rows are the KKT tests
        (max <= tol: free tensions in the box, fixed multipliers signed) and whose last row is
        T. Tiny arrays: each numpy call costs ~1 us, so the calls are few and the maxima are
        taken over Python lists; NaN still fails: NaN in p makes T NaN and so every entry of
        W^T T - w, whose maximum is then NaN."""
        tol = self._kkt_tol
        for _ in range(ACTIVE_SET_ROUNDS):
            inv_free, base, gain, offset, plain = self._set_terms(active)
            if plain:
                gram, rhs = wt.dot(wt.T), w
            else:
                gram, rhs = (wt * inv_free).dot(wt.T), w - wt.dot(base)
            _, lam, info = _posv(gram, rhs)     # Cholesky: SPD when W^T_F has full rank,
            if info != 0:                       # else proxsuite decides
                return None
            pull = lam.dot(wt)                                       # W lambda (n,)
            q = gain * pull
            q += offset
            tension = q[2]
            worst = max(q[:2].ravel().tolist())
            if worst <= tol:
                if worst > 0.0:        # within round-off of a bound: onto it
                    tension = np.minimum(np.maximum(tension, self.t_min_n), self.t_max_n)
                miss = wt.dot(tension)
                miss -= w
                residual = max(map(abs, miss.tolist()))     # NaN where T has a NaN
                if not residual <= self.tolerance_n:
                    return None
                if self.warm_start:
                    self._active = active
                return TensionResult.solved(tension, residual, time.perf_counter() - start,
                                            self.tolerance_n)
            # bound multipliers mu = h T + c - W lambda (0 where free): the next set
            trial = tension - ((tension if self._unit else self._h * tension + self.linear)
                               - pull)
            active = (np.where(trial > self.t_max_n, 1, 0)
                      - (trial < self.t_min_n)).astype(np.int8)
        return None

    def _set_terms(self, active: np.ndarray):
        """What :meth:`_active_set` needs of an active set, cached per set: (1/h on the free
        tensions and 0 on the fixed; base: -c/h on the free and T_A on the fixed; gain and
        offset (3, n) of q = gain * (W lambda) + offset; plain: every tension free and C = I,
        c = 0).

        Rows of q, free i (T_i = (W lambda)_i / h_i - c_i / h_i): T_i - T_max, T_min - T_i,
        T_i; fixed i (sign s_i = -1 at T_min, +1 at T_max): s_i mu_i = s_i (h_i T_Ai + c_i)
        - s_i (W lambda)_i twice, then T_Ai."""
        key = active.tobytes()
        terms = self._terms.get(key)
        if terms is None:
            free = active == 0
            sign = active.astype(float)
            h, c = self._h, self.linear
            inv_free = np.where(free, 1.0 / h, 0.0)
            bound = np.where(active > 0, self.t_max_n, self.t_min_n)
            base = np.where(free, -c / h, bound)
            gain = np.vstack([np.where(free, np.array([[1.0], [-1.0]]) / h, -sign), inv_free])
            offset = np.vstack([np.where(free, [-c / h - self.t_max_n, c / h + self.t_min_n],
                                         sign * (h * bound + c)), base])
            if len(self._terms) > 64:
                self._terms.clear()
            terms = self._terms[key] = (inv_free, base, gain, offset,
                                        bool(free.all() and self._unit))
        return terms

    def _new_qp(self, structure_matrix: np.ndarray, wrench: np.ndarray, max_iter: int):
        qp = _proxqp.dense.QP(self.n_cables, self.ndof, 0, True)
        settings = qp.settings
        settings.eps_abs = self._eps
        settings.eps_rel = 0.0
        settings.max_iter = max_iter
        settings.max_iter_in = max_iter
        settings.verbose = False
        settings.initial_guess = _proxqp.EQUALITY_CONSTRAINED_INITIAL_GUESS
        qp.init(self.hessian, self.linear, structure_matrix, wrench, None, None, None,
                self._lower, self._upper)
        return qp

    def solve(self, structure_matrix, wrench) -> TensionResult:
        """Tensions (N) for structure matrix W^T (ndof, n) and wrench w (ndof,) in N and N m."""
        start = time.perf_counter()
        wt = np.asarray(structure_matrix, dtype=float)
        w = np.asarray(wrench, dtype=float).reshape(-1)
        if wt.shape != (self.ndof, self.n_cables) or w.shape != (self.ndof,):
            raise ValueError(f'expected structure matrix ({self.ndof}, {self.n_cables}) and '
                             f'wrench ({self.ndof},), got {wt.shape} and {w.shape}')
        if self._active is not None:   # warm: the previous answer's active set (a KKT point is
            result = self._active_set(wt, w, start, self._active)   # feasible: no test needed
            if result is not None:                         # before it; NaN fails its checks)
                return result
        # Necessary condition, per wrench component: reachable range of W^T T over the box.
        # NaN or inf anywhere in W^T or w makes the test fail too, so it is the finite check.
        with np.errstate(invalid='ignore'):
            excess = np.abs(w - wt @ self._mid) - np.abs(wt) @ self._half
        if not excess.max() <= self.tolerance_n:
            self.reset()
            if not (np.isfinite(wt).all() and np.isfinite(w).all()):
                what = 'structure matrix' if not np.isfinite(wt).all() else 'wrench'
                return TensionResult(np.full(self.n_cables, np.nan), 'not_finite', False,
                                     np.nan, 0, f'{what} is not finite',
                                     time.perf_counter() - start, self.tolerance_n)
            tension = closest_tensions(wt, w, self.t_min_n, self.t_max_n, self.tolerance_n)
            return TensionResult(tension, 'infeasible', False,
                                 float(np.abs(wt @ tension - w).max()), 0,
                                 self._row_reason(wt, w, excess), time.perf_counter() - start,
                                 self.tolerance_n)

        qp = self._qp
        if qp is not None:  # warm: update W^T and w, start from the previous solution
            qp.update(A=wt, b=w)
            result = self._run(qp, wt, w, start, 0)
            if result.feasible:
                return result
            # a warm start far from the answer (a jump in pose) can stall: go cold once
            result = self._run(self._new_qp(wt, w, self.max_iter), wt, w, start,
                               result.iterations)
        else:
            result = self._run(self._new_qp(wt, w, self.max_iter), wt, w, start, 0)
        if result.feasible:
            return result
        # Failure: never trust the solver alone. The closest tensions in the box decide whether
        # the wrench is out of reach or proxsuite just stopped early (then retry, cold, longer).
        tension = closest_tensions(wt, w, self.t_min_n, self.t_max_n, self.tolerance_n)
        residual = float(np.abs(wt @ tension - w).max())
        if residual > self.tolerance_n:
            return TensionResult(tension, 'infeasible', False, residual, result.iterations,
                                 self._residual_reason(wt, w, residual),
                                 time.perf_counter() - start, self.tolerance_n)
        first = result
        result = self._run(self._new_qp(wt, w, 4 * self.max_iter), wt, w, start,
                           first.iterations)
        if result.feasible:
            return result
        return TensionResult(tension, result.status if result.status != 'infeasible'
                             else 'max_iter', False, residual, result.iterations,
                             f'tension QP stopped ({first.status}, then {result.status}) after '
                             f'{result.iterations} iterations although the wrench {_fmt(w)} is '
                             f'reachable; returned tensions meet the constraints but are not '
                             f'optimal', time.perf_counter() - start, self.tolerance_n)

    def _run(self, qp, wt, w, start, previous_iterations) -> TensionResult:
        """Solve ``qp`` and check its answer against Eqs. 11-12; keep it for warm starts."""
        qp.solve()
        info = qp.results.info
        iterations = previous_iterations + int(info.iter)
        status = _STATUS.get(info.status, str(info.status))
        x = qp.results.x
        if status == 'solved':
            bound_violation = np.abs(x - self._mid).max() - self._half[0]
            tension = np.clip(x, self.t_min_n, self.t_max_n) if bound_violation > 0.0 else x
            residual = float(np.abs(wt @ tension - w).max())
            if bound_violation <= self.tolerance_n and residual <= self.tolerance_n:
                if self.warm_start:
                    qp.settings.initial_guess = _proxqp.WARM_START_WITH_PREVIOUS_RESULT
                    self._qp = qp
                # proxsuite's last bits vary from one QP object to another (a warm-started
                # solve of equal data differs by ~1e-13 N): the answer is the exact KKT
                # solution on its active set, so equal inputs give equal tensions everywhere
                polished = (None if self._h is None else
                            self._active_set(wt, w, start, self._active_of(tension)))
                if polished is not None:
                    tension, residual = polished.tension_n, polished.residual_n
                elif self.warm_start and self._h is not None:
                    self._active = self._active_of(tension)
                return TensionResult(tension, 'solved', True, residual, iterations, '',
                                     time.perf_counter() - start, self.tolerance_n)
            status = 'infeasible'  # 'solved' by proxsuite but outside Eqs. 11-12
        self._qp = None  # the next solve starts cold: a failed iterate is a poor warm start
        self._active = None
        return TensionResult(x, status, False, np.nan, iterations, status,
                             time.perf_counter() - start, self.tolerance_n)

    def _units(self) -> str:
        return 'N' if self.ndof == 3 else 'N, N m'

    def _bounds(self) -> str:
        return f'tensions in [{self.t_min_n:g}, {self.t_max_n:g}] N'

    def _row_reason(self, wt, w, excess) -> str:
        j = int(np.argmax(excess))
        centre = wt[j] @ self._mid
        half = np.abs(wt[j]) @ self._half
        axis = WRENCH_AXES[j]
        return (f'wrench {_fmt(w)} {self._units()} outside the feasible set for {self._bounds()}: '
                f'{axis} {w[j]:.4g} is outside the reachable [{centre - half:.4g}, '
                f'{centre + half:.4g}]')

    def _residual_reason(self, wt, w, residual) -> str:
        text = (f'wrench {_fmt(w)} {self._units()} outside the feasible set for '
                f'{self._bounds()} (closest tensions miss it by {residual:.4g})')
        u, sing, _ = np.linalg.svd(wt)
        rank = int(np.sum(sing > 1e-9 * max(1.0, sing[0])))
        if rank < self.ndof:
            null = u[:, rank:]
            unreachable = null @ (null.T @ w)
            size = float(np.linalg.norm(unreachable))
            text += f'; the structure matrix has rank {rank} < {self.ndof}'
            if size > self.tolerance_n:
                text += (f' and the wrench has a part {size:.4g} along {_fmt(unreachable / size)} '
                         f'that no tensions can produce')
        return text


def closest_tensions(structure_matrix, wrench, t_min_n, t_max_n, tolerance_n=1e-4) -> np.ndarray:
    """Tensions (n,) N in [T_min, T_max] whose wrench is closest to w; they always exist.

        minimise 1/2 |W^T T - w|^2 + eps/2 |T - T_mid|^2  subject to  T_min <= T_i <= T_max,

    with a tiny eps (1e-12 of the Hessian's scale) that picks one answer when W^T is wide.
    Doubles as an exact feasibility test of Eqs. 11-12: the residual max |W^T T - w| is ~0
    (below ``tolerance_n``, N) exactly when Eq. 12 has a solution in the box.

    Bounded in time for any finite wrench: a w farther than ``FAR_FACTOR`` times the extent
    r = sum_i |g_i| (T_max - T_min)/2 of the reachable set from its centre c = W^T T_mid is
    first pulled in along its direction, w' = c + (w - c) FAR_FACTOR r / |w - c| (such a wrench
    is out of reach by orders of magnitude; the closest tensions then lie where the set reaches
    furthest towards w, and without the pull a w of 1e100 N overflows the QP's gradient and ran
    proxsuite for 20-30 s). The QP's outer and inner iterations are capped (1000 each).
    """
    wt = np.asarray(structure_matrix, dtype=float)
    w = np.asarray(wrench, dtype=float).reshape(-1)
    n = wt.shape[1]
    w = _pull_in(wt, w, t_min_n, t_max_n)
    gram = wt.T @ wt
    eps = 1e-12 * max(1.0, np.abs(gram).max())
    mid = np.full(n, 0.5 * (t_min_n + t_max_n))
    qp = _proxqp.dense.QP(n, 0, 0, True)
    qp.settings.eps_abs = 1e-3 * tolerance_n
    qp.settings.eps_rel = 0.0
    qp.settings.max_iter = 1000
    qp.settings.max_iter_in = 1000
    qp.init(gram + eps * np.eye(n), -(wt.T @ w) - eps * mid, None, None, None, None, None,
            np.full(n, float(t_min_n)), np.full(n, float(t_max_n)))
    qp.solve()
    return np.clip(qp.results.x, t_min_n, t_max_n)


#: a wrench farther than this many extents of the reachable set is pulled in (closest_tensions)
FAR_FACTOR = 1e3


def _pull_in(wt: np.ndarray, w: np.ndarray, t_min_n: float, t_max_n: float) -> np.ndarray:
    """w, or w pulled in along its direction to FAR_FACTOR extents of the reachable set."""
    centre = wt @ np.full(wt.shape[1], 0.5 * (t_min_n + t_max_n))
    extent = max(float(np.linalg.norm(wt, axis=0).sum()) * 0.5 * abs(t_max_n - t_min_n),
                 float(np.linalg.norm(centre)), 1.0)
    away = w - centre
    scale = float(np.abs(away).max(initial=0.0))
    if not np.isfinite(scale) or scale <= FAR_FACTOR * extent / np.sqrt(w.size):
        return w
    direction = away / scale                    # two steps: |w - c| itself may overflow
    return centre + direction * (FAR_FACTOR * extent / np.linalg.norm(direction))


def solve_tensions(structure_matrix, wrench, t_min_n, t_max_n, weights=None,
                   linear=None, **options) -> TensionResult:
    """One-shot tension distribution (Eqs. 10-12) with a fresh :class:`TensionSolver`.

    W^T (ndof, n), w (ndof,) in N (and N m), bounds in N; see :class:`TensionSolver` for
    ``weights``, ``linear`` and the keyword ``options``.
    """
    wt = np.asarray(structure_matrix, dtype=float)
    if wt.ndim != 2:
        raise ValueError(f'structure matrix must be 2-D (ndof, n), got shape {wt.shape}')
    solver = TensionSolver(wt.shape[1], wt.shape[0], t_min_n, t_max_n, weights, linear,
                           **options)
    return solver.solve(wt, wrench)


def solve_tensions_qpsolvers(structure_matrix, wrench, t_min_n, t_max_n, weights=None,
                             linear=None, solver='proxqp') -> TensionResult:
    """The same QP through ``qpsolvers`` (bounds as ``lb``/``ub``), for cross-checks only.

    ``solver`` must be in ``qpsolvers.available_solvers``; with ``'proxqp'`` the sparse ProxQP
    backend is used, where the bounds become general inequality rows: a different code path from
    :class:`TensionSolver`'s dense QP with native box constraints. No warm start, no diagnosis.
    """
    import qpsolvers

    wt = np.asarray(structure_matrix, dtype=float)
    w = np.asarray(wrench, dtype=float).reshape(-1)
    n = wt.shape[1]
    c_mat, c_vec = _objective(n, weights, linear)
    lo, hi = _box(n, t_min_n, t_max_n)
    tolerance = 1e-7 * max(1.0, abs(lo), abs(hi))
    problem = qpsolvers.Problem(c_mat, c_vec, None, None, wt, w, np.full(n, lo), np.full(n, hi))
    options = {'backend': 'sparse', 'eps_abs': 1e-5 * tolerance} if solver == 'proxqp' else {}
    start = time.perf_counter()
    solution = qpsolvers.solve_problem(problem, solver=solver, **options)
    elapsed = time.perf_counter() - start
    if not solution.found or solution.x is None:
        return TensionResult(np.full(n, np.nan), 'infeasible', False, np.nan, 0,
                             f'qpsolvers/{solver} found no solution', elapsed, tolerance)
    tension = np.asarray(solution.x, dtype=float)
    residual = float(np.abs(wt @ tension - w).max())
    feasible = bool(residual <= tolerance and tension.min() >= lo - tolerance
                    and tension.max() <= hi + tolerance)
    return TensionResult(tension, 'solved' if feasible else 'infeasible', feasible, residual, 0,
                         '' if feasible else f'qpsolvers/{solver} answer violates Eqs. 11-12',
                         elapsed, tolerance)
