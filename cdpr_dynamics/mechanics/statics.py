"""Sag-consistent statics: cable tensions whose sagged end forces hold the platform.

The tension distribution of Eqs. 8-12 puts each tension T_i along the chord u_i. A cable with
weight leaves the platform along its catenary's end tangent instead, up to tens of degrees off
the chord for slack-ish cables, so the chord tensions do not balance the platform once the
cables sag. Here T_i is the tension at the platform end of the elastic catenary that spans the
chord (:func:`cdpr_dynamics.models.catenary.solve`), f_i(T_i) = -F_i the force it exerts on the
platform, and the tensions solve

    minimise    1/2 |T|^2                                           (Eq. 10, C = I, c = 0)
    subject to  max(T_min, T_exist,i) <= T_i <= T_max              (Eq. 11)
                sum_i [f_i(T_i); r_i x f_i(T_i)] = w                (Eq. 12 on the sagged cables)

with w = -(m g + f_e, tau_e) the wrench the cables must supply and T_exist,i the lowest end
tension at which a taut catenary spans cable i's chord (it exists for every T above it, on the
taut branch). The constraint is solved by sequential QPs (SQP): at T^k the end forces are
linearised, f_i(T) ~ f_i(T^k) + d_i (T_i - T^k_i) with d_i = -dF_i/dT_i
(:func:`~cdpr_dynamics.models.catenary.tension_sensitivity`: the end tangent plus its turn as
the sag changes), and the QP

    minimise 1/2 |T|^2   subject to   A T = w - sum_i [f_i - d_i T^k_i; r_i x (f_i - d_i T^k_i)],
    box as above,   A = [d_1 ... d_n; r_1 x d_1 ... r_n x d_n]

is solved with proxsuite (:class:`~cdpr_dynamics.mechanics.tensions.TensionSolver`, warm-started).
Its
answer is taken as the next iterate, with the step halved while a cable's catenary would not
exist or the residual would grow tenfold. A fixed point of the iteration satisfies the KKT
conditions of the problem above (the QP's constraint gradients are the exact ones), so the
paper's objective chooses among the equilibria. Iterations stop when the residual is below
``rtol`` of the weight |w_force| (moments: of |w_force| times the platform's largest lever arm)
and the QP no longer moves the tensions (by more than ``OPTIMALITY_RTOL`` = 1e-6 of T_max).
Straight cables (gamma = 0) converge in one step to the chord answer.

Cables whose catenary does not exist at T_min get the lower bound 1.01 T_exist,i (found by
bisection on the existence of a solution): the least tension the cable can have at this pose;
a warning says so. The QP works on s in [T_min, T_max] with T = a + b s, so the same proxsuite
set-up serves per-cable lower bounds.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.models import catenary
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.mechanics.robot import WRENCH_AXES, Geometry, cross, required_wrench, row_norm
from cdpr_dynamics.mechanics.tensions import TensionResult, TensionSolver

#: Methods linearised about the sag-consistent state; the others use the chord statics.
SAG_METHODS = ('catenary_exact', 'fem_sag')
EXIST_MARGIN = 1.01
MAX_ITERATIONS = 60
PROBE_ITERATIONS, PROBE_HALVINGS = 12, 6   # existence probes of lowest_tension
FEASIBLE_HALVINGS = 8       # from a balanced state, at most this many halvings of a step
OPTIMALITY_RTOL = 1e-6     # converged when the QP moves no tension by more than this x T_max
UNREACHED_RTOL = 1e-6      # warned: n < d sagged cables leave more than this x the weight


class StaticsError(ValueError):
    """No sag-consistent tension distribution; the message is one line naming the cause."""


@dataclass(frozen=True, eq=False)
class SagStatics:
    """A sag-consistent equilibrium; arrays stacked over cables, SI units.

    ``tension_n`` the platform-end tensions T_i, ``end_force_n`` (n, 3) the force of each cable
    on the platform (along its end tangent), ``state`` the catenaries, ``residual`` (ndof,) the
    wrench the cables miss (N, then N m), ``lower_bound_n`` the lower bounds used (T_min, or the
    lifted one), ``iterations`` the SQP iterations, ``warnings`` one line each; ``step_qp``
    the warm-started QP of the SQP steps, which the next pose's :func:`sag_equilibrium`
    (``start``) reuses where the lower bounds are the same (its answers are KKT-checked: a warm
    start only shortens the path); ``chord_tension_n`` the first iterate it was given (the
    chord tensions), whose change to the next pose's predicts that pose's tensions.
    """

    tension_n: np.ndarray
    end_force_n: np.ndarray
    state: catenary.CatenaryState
    residual: np.ndarray
    lower_bound_n: np.ndarray
    iterations: int
    warnings: tuple[str, ...]
    step_qp: object = None      # the SQP's warm QP (_StepQP): reused by the next pose
    chord_tension_n: np.ndarray | None = None


#: the ufunc reductions behind ndarray.all/max/sum and np.clip, without their Python wrappers
#: (the same numbers; the SQP calls them on a few cables many times per pose)
_all, _max, _sum = np.logical_and.reduce, np.maximum.reduce, np.add.reduce


def _clip(x, low, high):
    """np.clip(x, low, high) for low <= high (the same numbers, NaN kept)."""
    return np.minimum(np.maximum(x, low), high)


def cable_wrench(end_force_n: np.ndarray, lever_m: np.ndarray, ndof: int) -> np.ndarray:
    """Wrench (ndof,) of the cable forces on the platform: sum f_i, then sum r_i x f_i."""
    force = _sum(end_force_n, axis=0)
    if ndof == 3:
        return force
    return np.concatenate([force, _sum(cross(lever_m, end_force_n), axis=0)])


def structure_of(direction: np.ndarray, lever_m: np.ndarray, ndof: int) -> np.ndarray:
    """(ndof, n): the wrench per unit tension of forces along ``direction`` (n, 3)."""
    if ndof == 3:
        return direction.T
    return np.concatenate([direction.T, cross(lever_m, direction).T])


def lowest_tension(cables: CableSet, which: np.ndarray, t_high_n: float,
                   bisections: int = 20) -> np.ndarray:
    """(n,) lowest end tension (N) at which a taut catenary spans each chord, for ``which``.

    Bisection between a tension where no solution is found (``cables.tension_n``) and one where
    it is (found by doubling up to ``t_high_n``), to 2^-20 of that bracket: an upper estimate
    (within ~1e-6 relative) that ``EXIST_MARGIN`` covers. Each probe is warm-started from the
    solution at the lowest tension found so far (continuation along the taut branch); every
    probe is capped at ``PROBE_ITERATIONS`` Newton steps of ``PROBE_HALVINGS`` halvings (a
    missing solution then costs little; one missed near the fold only raises the estimate).
    NaN for cables not in ``which``, inf where no tension up to ``t_high_n`` has a solution.
    """
    tension = np.asarray(cables.tension_n, dtype=float)
    lo = np.where(which, np.maximum(tension, 0.0), np.nan)
    hi = np.where(which, np.maximum(2.0 * lo, 1e-6 * cables.ea_n), np.nan)
    found = ~which.copy()
    best = None                     # the valid solutions at the lowest tensions found
    for _ in range(64):
        state = catenary.solve(cables.with_tension(np.where(found, tension, hi)),
                               max_iterations=PROBE_ITERATIONS, max_halvings=PROBE_HALVINGS)
        found = found | state.valid
        best = state if best is None else _merge(best, state, state.valid & which)
        if found.all() or np.all(hi[~found] >= t_high_n):
            break
        lo = np.where(found, lo, hi)
        hi = np.where(found, hi, np.minimum(2.0 * hi, t_high_n))
    out = np.where(which, np.where(found, hi, np.inf), np.nan)
    todo = which & found
    for _ in range(bisections if todo.any() else 0):
        mid = 0.5 * (lo + out)
        probe = catenary.solve(cables.with_tension(np.where(todo, mid, tension)),
                               max_iterations=PROBE_ITERATIONS, start=best,
                               max_halvings=PROBE_HALVINGS)
        ok = todo & probe.valid
        best = _merge(best, probe, ok)
        out = np.where(ok, mid, out)
        lo = np.where(todo & ~probe.valid, mid, lo)
    return out


def _merge(old: catenary.CatenaryState, new: catenary.CatenaryState, take: np.ndarray):
    """``old`` with the cables of ``take`` from ``new`` (force, L0 and validity)."""
    return old._replace(force_n=np.where(take[:, None], new.force_n, old.force_n),
                        unstrained_length_m=np.where(take, new.unstrained_length_m,
                                                     old.unstrained_length_m),
                        valid=old.valid | take)


def sag_equilibrium(cables: CableSet, lever_m, wrench, t_min_n: float, t_max_n: float, *,
                    start: SagStatics | None = None, rtol: float = 1e-9,
                    max_iterations: int = MAX_ITERATIONS) -> SagStatics:
    """Sag-consistent tensions (module docstring) starting from ``cables.tension_n``.

    ``cables`` at the pose, their ``tension_n`` the first iterate (e.g. the chord solution);
    ``lever_m`` (n, 3) r_i = R b_i; ``wrench`` (ndof,) what the cables must supply;
    ``start`` a nearby solution (the previous pose) whose tensions and catenaries warm-start the
    iteration: its tensions moved by the change of the first iterates (start's
    ``chord_tension_n`` to ``cables.tension_n``), a first-order prediction that ends the SQP
    an iteration earlier along a path (not where start lifted a lower bound: near the fold of
    a catenary the prediction can overshoot). Raises :class:`StaticsError` when no
    distribution exists in the box.
    """
    wrench = np.asarray(wrench, dtype=float)
    lever = np.asarray(lever_m, dtype=float)
    ndof = wrench.size
    n = cables.n_cables
    lower = np.full(n, float(t_min_n))
    warnings = []
    first = np.asarray(cables.tension_n, dtype=float)
    if start is None:
        tension = first
    elif (start.chord_tension_n is None or start.chord_tension_n.shape != first.shape
          or np.any(start.lower_bound_n > t_min_n)):
        tension = np.asarray(start.tension_n, dtype=float)
    else:
        tension = start.tension_n + (first - start.chord_tension_n)
    tension = _clip(tension, lower, t_max_n)
    state, d_force, d_length = catenary.solve_with_sensitivity(
        cables.with_tension(tension), start=None if start is None else start.state)
    lift = ~state.valid          # and the cables lifted at the previous pose: lifted again here
    if start is not None:
        lift |= start.lower_bound_n > t_min_n
    if any(lift.tolist()):
        lower, state, tension, text = _lift(cables, lift, tension, lower, t_max_n)
        d_force, d_length = catenary.tension_sensitivity(state, cables)     # (its chords)
        warnings += text

    force = wrench[:3]              # |f| and max |r_i| as np.linalg.norm computes them
    force_scale = max(math.sqrt(force.dot(force)), 1e-9 * float(t_max_n))
    arm = max(float(_max(row_norm(lever), initial=0.0)), 1e-3)
    tol = rtol * force_scale * np.where(np.arange(ndof) < 3, 1.0, arm)
    step_tol = OPTIMALITY_RTOL * float(t_max_n)
    qp = None if start is None else start.step_qp        # the previous pose's, if it fits
    if (qp is None or qp.shape != (n, ndof, t_min_n, t_max_n)
            or not np.array_equal(qp.lower, lower)):
        qp = _StepQP(n, ndof, lower, t_min_n, t_max_n)
    residual = cable_wrench(-state.force_n, lever, ndof) - wrench
    rho = 0.0                       # proximal weight: grows while steps are cut, falls after
    iterations = 0
    reach = None                    # underactuated: the projector on what the cables reach
    for iterations in range(1, max_iterations + 1):
        a_mat = structure_of(-d_force, lever, ndof)
        if not _all(np.isfinite(a_mat), axis=None):
            i = int(np.flatnonzero(~np.all(np.isfinite(d_force), axis=1))[0])
            raise StaticsError(f'no sag-consistent tension distribution: cable {i} is at the '
                               f'fold of its catenary (T = {tension[i]:.4g} N: the least '
                               'tension it can have at this pose)')
        if n < ndof:
            basis = np.linalg.svd(a_mat, full_matrices=False)[0]         # (d, n)
            reach = basis @ basis.T
            residual_in = reach @ residual
            a_qp = _rows(basis, a_mat)
        else:
            residual_in, a_qp, basis = residual, a_mat, None
        proposal = qp.solve(a_qp, _rows(basis, a_mat @ tension - residual), rho, tension)
        if not proposal.feasible:
            raise StaticsError(f'no sag-consistent tension distribution in [{t_min_n:g}, '
                               f'{t_max_n:g}] N (sagged cables, SQP iteration {iterations}): '
                               f'{proposal.reason}')
        step = proposal.tension_n - tension
        size = _max(np.abs(residual_in) / tol)
        if size <= 1.0 and _max(np.abs(step)) <= step_tol and rho > 0.0:
            rho = 0.0           # a proximal step is short by 1/(1 + rho): judge the plain one
            proposal = qp.solve(a_qp, _rows(basis, a_mat @ tension - residual), rho, tension)
            step = proposal.tension_n - tension
        if size <= 1.0 and _max(np.abs(step)) <= step_tol:
            return SagStatics(tension, -state.force_n, state, residual, lower, iterations,
                              tuple(warnings) + _unreached(residual, tol / rtol), qp, first)
        alpha = 1.0
        for _ in range(30 if size > 1.0 else FEASIBLE_HALVINGS):
            trial = _clip(tension + alpha * step, lower, t_max_n)
            change = trial - tension        # first-order prediction of the catenaries there
            guess = state._replace(force_n=state.force_n + change[:, None] * d_force,
                                   unstrained_length_m=state.unstrained_length_m
                                   + change * d_length)
            trial_state, *trial_sensitivity = catenary.solve_with_sensitivity(
                cables.with_tension(trial), start=guess, warm_only=True)
            if all(trial_state.valid.tolist()):
                trial_residual = cable_wrench(-trial_state.force_n, lever, ndof) - wrench
                trial_size = _max(np.abs(trial_residual if reach is None
                                         else reach @ trial_residual) / tol)
                if trial_size <= max((1.0 - 1e-4 * alpha) * size, 1.0):
                    break
            alpha *= 0.5
        else:
            break               # no progress along the QP's direction: judged below (an
            #                     already balanced state is kept, with a warning)
        tension, state, residual = trial, trial_state, trial_residual
        d_force, d_length = trial_sensitivity
        rho = rho / 4.0 if alpha == 1.0 else max(4.0 * rho, 1.0) if alpha < 0.25 else rho
        rho = 0.0 if rho < 1e-3 else rho
    reached = residual if reach is None else reach @ residual
    worst = int(np.argmax(np.abs(reached) / tol))
    converged = bool(np.all(np.abs(reached) <= tol))
    held = np.flatnonzero((lower > t_min_n) & (tension <= 1.1 * lower))
    cause = (f'; cable {held[0]} is at {tension[held[0]]:.4g} N, near the least tension '
             f'({lower[held[0]] / EXIST_MARGIN:.4g} N) at which a taut catenary spans its chord, '
             'where its end force turns sharply with tension: raise tension.min_n above it'
             if held.size else '')
    if converged:       # an equilibrium in the box; only the objective's choice is unsettled
        warnings.append(f'sag statics: the tensions balance the platform (residual '
                        f'{np.abs(residual[:3]).max():.2g} N) but the SQP did not settle on the '
                        f'least-norm distribution in {iterations} iterations{cause}')
        return SagStatics(tension, -state.force_n, state, residual, lower, iterations,
                          tuple(warnings) + _unreached(residual, tol / rtol), qp, first)
    raise StaticsError(f'no sag-consistent tension distribution: the SQP did not converge in '
                       f'{iterations} iterations (residual {WRENCH_AXES[worst]} '
                       f'{reached[worst]:.3g}){cause}')


def _rows(basis: np.ndarray | None, rows: np.ndarray) -> np.ndarray:
    """``rows`` (d, ...) on the columns of ``basis`` (d, n), the directions n < d cables reach,
    then d - n rows of zeros (the balance the step QP can meet exactly); or as they are."""
    if basis is None:
        return rows
    out = np.zeros(rows.shape)
    out[:basis.shape[1]] = basis.T @ rows
    return out


def _unreached(residual: np.ndarray, scale: np.ndarray) -> tuple[str, ...]:
    """The warning on the net wrench fewer cables than DOFs leave, where above
    ``UNREACHED_RTOL`` of ``scale`` (the weight, and the weight times the largest arm)."""
    if np.all(np.abs(residual) <= UNREACHED_RTOL * scale):
        return ()
    force = float(np.linalg.norm(residual[:3]))
    moment = float(np.linalg.norm(residual[3:])) if residual.size > 3 else 0.0
    return (f'underactuated: the sagged cables leave a net {force:.3g} N, {moment:.3g} N m on '
            'the platform along directions they cannot pull (the equilibrium of the sagged '
            'cables lies that much off the chord one)',)


def _lift(cables, candidates, tension, lower, t_max_n):
    """Raise the lower bound of those ``candidates`` that have no catenary at their lower bound
    to ``EXIST_MARGIN`` times the least tension one exists at (module docstring).

    Returns (lower bounds, catenaries at the tensions, tensions raised to the bounds, warnings).
    """
    at_lower = catenary.solve(cables.with_tension(np.where(candidates, lower, tension)),
                              max_iterations=PROBE_ITERATIONS, max_halvings=PROBE_HALVINGS).valid
    bad = candidates & ~at_lower
    exist = lowest_tension(cables.with_tension(lower), bad, t_max_n)
    if np.any(bad & ~np.isfinite(exist)):
        i = int(np.flatnonzero(bad & ~np.isfinite(exist))[0])
        raise StaticsError(f'no sag-consistent tension distribution: cable {i} has no taut '
                           f'catenary spanning its chord of {cables.length_m[i]:.4g} m at any '
                           f'tension up to tension.max_n = {t_max_n:g} N')
    lifted = np.where(bad, EXIST_MARGIN * exist, lower)
    if np.any(lifted > t_max_n):
        i = int(np.argmax(lifted - t_max_n))
        raise StaticsError(f'no sag-consistent tension distribution: cable {i} needs at least '
                           f'{lifted[i]:.4g} N for a taut catenary over its chord of '
                           f'{cables.length_m[i]:.4g} m, above tension.max_n = {t_max_n:g} N')
    warnings = [f'cable {i}: no taut catenary spans its chord below {exist[i]:.4g} N '
                f'(tension.min_n = {lower[i]:g} N); its lower bound is {lifted[i]:.4g} N'
                for i in np.flatnonzero(bad)]
    tension = np.maximum(tension, lifted)
    state = catenary.solve(cables.with_tension(tension))
    if not state.valid.all():
        raise StaticsError('no sag-consistent tension distribution: ' + state.reasons[0])
    return lifted, state, tension, warnings


class _StepQP:
    """The QP of one SQP step on s in [T_min, T_max] with T = a + b s (module docstring).

    With a proximal weight rho the objective is 1/2 |T|^2 + rho/2 |T - T_k|^2, i.e. on s
    the Hessian (1 + rho) diag(b^2) and the linear term b ((1 + rho) a - rho T_k); the
    constraint A T = w is (A b) s = w - A a. Without rho one warm-started solver serves
    every step; with it each step sets up its own.
    """

    def __init__(self, n, ndof, lower, t_min_n, t_max_n):
        span = t_max_n - t_min_n
        self.lower = np.array(lower, dtype=float)
        self.b = (t_max_n - lower) / span if span > 0 else np.ones(n)
        self.a = lower - self.b * t_min_n
        self.shape = (n, ndof, t_min_n, t_max_n)
        self.warm = self._solver(0.0, None)

    def _solver(self, rho, center) -> TensionSolver:
        n, ndof, lo, hi = self.shape
        linear = self.b * ((1.0 + rho) * self.a - (0.0 if center is None else rho * center))
        return TensionSolver(n, ndof, lo, hi, weights=(1.0 + rho) * self.b ** 2, linear=linear)

    def solve(self, a_mat, target, rho, center) -> '_Proposal':
        solver = self.warm if rho == 0.0 else self._solver(rho, center)
        result = solver.solve(a_mat * self.b[None, :], target - a_mat @ self.a)
        return _Proposal(self.a + self.b * result.tension_n, result.feasible, result.reason)


@dataclass(frozen=True)
class _Proposal:
    tension_n: np.ndarray
    feasible: bool
    reason: str


# --------------------------------------------------------------------------- equilibria

@dataclass(frozen=True, eq=False)
class Equilibrium:
    """Static state at one pose: geometry, tension distribution, and the cables for a model.

    ``statics`` says which: ``'chord'`` (Eqs. 8-12, tensions along the chords: straight models
    and the paper's ``catenary``) or ``'sag'`` (:mod:`cdpr_dynamics.mechanics.statics`: the sagged
    end
    forces balance the platform; ``catenary_exact`` and ``fem_sag``). ``tensions.tension_n``
    and ``cables.tension_n`` are the platform-end tensions T_i of that statics;
    ``end_force_n`` (n, 3) the force of each cable on the platform; ``unstretched_length_m``
    L0 per cable (straight: L EA/(EA + T); sagged: the catenary's); ``residual`` (ndof,) the
    wrench the cables miss (N, then N m); ``iterations`` of the QP (chord) or the SQP (sag);
    ``sag`` the sag solution (warm start of the next pose), else None; ``balance`` an
    underactuated robot's equilibrium (:mod:`cdpr_dynamics.mechanics.underactuated`), else
    None.
    """

    geometry: Geometry
    tensions: TensionResult
    cables: CableSet
    statics: str = 'chord'
    end_force_n: np.ndarray | None = None
    unstretched_length_m: np.ndarray | None = None
    residual: np.ndarray | None = None
    iterations: int = 0
    warnings: tuple[str, ...] = ()
    sag: SagStatics | None = None
    balance: object = None


def equilibrium_for(settings, eq: Equilibrium, method: str | None,
                    start: Equilibrium | None = None) -> Equilibrium:
    """``eq`` (of the robot and static load of ``settings``, a
    :class:`~cdpr_dynamics.analysis.config.Settings`) in the statics ``method`` needs: the
    sag-consistent one for :data:`SAG_METHODS`
    (from ``eq``'s chord tensions, or warm-started from ``start``), else ``eq`` as it is.
    Raises :class:`StaticsError` where no sag-consistent distribution exists."""
    if method not in SAG_METHODS or eq.statics == 'sag':
        return eq
    begin = time.perf_counter()
    wrench = required_wrench(settings.robot, settings.external_force_n,
                             settings.external_moment_nm, eq.geometry.rotation)
    sag = sag_equilibrium(eq.cables, eq.geometry.lever_m, wrench, settings.tension_min_n,
                          settings.tension_max_n, start=None if start is None else start.sag)
    result = TensionResult(sag.tension_n, 'solved', True, float(np.abs(sag.residual).max()),
                           sag.iterations, '', time.perf_counter() - begin,
                           eq.tensions.tolerance_n)
    cables = CableSet(eq.cables.chord_m, sag.tension_n, eq.cables.ea_n,
                      eq.cables.weight_per_length_n_per_m, eq.cables.gravity_m_s2,
                      sag_state=sag.state, anchor_end=eq.cables.anchor_end)
    return Equilibrium(eq.geometry, result, cables, 'sag', sag.end_force_n,
                       sag.state.unstrained_length_m, sag.residual, sag.iterations,
                       eq.warnings + sag.warnings, sag, eq.balance)
