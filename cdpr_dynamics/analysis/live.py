"""ROS-free core of the live node: the model at the current pose and a running integrator.

The node and ``cdpr_replay`` both feed poses and wrenches through :class:`LivePredictor`, so an
offline replay and the live node give the same numbers by construction.

* :meth:`LivePredictor.update_pose`: a pose that moved more than the tolerance re-solves the
  tensions (warm-started QP), rebuilds the cable model and refactorises the Newmark matrix;
  otherwise nothing is recomputed. A failure leaves the last good state in place.
* :meth:`LivePredictor.advance`: zero-order hold of the wrench: the wrench received at
  ``t_k`` acts from ``t_k`` until the next one; advancing to ``t_{k+1}`` integrates
  ``floor((t_{k+1} - t_k)/dt)`` Newmark steps of ``newmark.dt_s`` (the remainder carries over),
  at most ``max_steps_per_wrench`` of them (the rest of a longer interval is dropped, the state
  kept), and returns the centroid's displacement from equilibrium at ``t_{k+1}``. The state of
  motion carries over pose updates and model changes (:func:`carry_state`). An interval of more
  than ``max(CLOSED_FORM_STEPS, dofs)`` steps is stepped in closed form
  (:class:`~cdpr_dynamics.dynamics.held_load.HeldLoadSteps`: the same state, at a cost that does
  not grow with the interval) where the model has at most ``held_load.MAX_DOFS`` DOFs.
* :meth:`LivePredictor.advance_run` (the offline replay): many wrenches at once, the numbers
  of :meth:`~LivePredictor.advance`; a run of at least n^2 / ``MODAL_RUN_PAYBACK`` steps of a
  model with cable interiors steps in the model's modes (the same
  :class:`~cdpr_dynamics.dynamics.held_load.HeldLoadSteps`, made once per model), to
  round-off.
* Slack (``slack='aware'``): after each linear step the cables' quasi-static tensions
  T_i + dT_i(q) are checked; where one would fall to zero or below, the step is taken again
  with the compression-free platform of :mod:`cdpr_dynamics.dynamics.slack` (the same
  :class:`~cdpr_dynamics.dynamics.slack.SlackStepper` as ``cdpr_analyze --slack-aware``; for a
  model with cable DOFs its platform-only form, :func:`~cdpr_dynamics.dynamics.slack.
  platform_only_method`), which carries on until every cable has been taut for ``SETTLE_S``;
  then the linear model takes over from its state (cable interiors quasi-static).
  ``slack='linear'`` keeps the linear model and only flags the cables.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cdpr_dynamics.analysis.pipeline import (AnalysisError, Equilibrium, build_system, damping_for,
                                             equilibrium, equilibrium_for, model_warnings,
                                             new_tension_solver, point_displacement)
from cdpr_dynamics.analysis.config import Settings
from cdpr_dynamics.dynamics import held_load
from cdpr_dynamics.dynamics.held_load import HeldLoadSteps
from cdpr_dynamics.dynamics.slack import SlackStepper, platform_only_method
from cdpr_dynamics.dynamics.system import ChainNewmark, DynamicsError, Newmark, PlatformSystem
from cdpr_dynamics.mechanics.feasibility import WrenchSet
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.mechanics.robot import (matrix_to_quaternion, quaternion_product,
                                           quaternion_to_matrix, required_wrench,
                                           rotation_vector_quaternion, row_norm)
from cdpr_dynamics.selection.auto import choose_model
from cdpr_dynamics.mechanics.statics import structure_of
from cdpr_dynamics.mechanics.underactuated import HeldWrenchSet, is_underactuated

FALLBACK_METHOD = 'spring'
MAX_STEPS_PER_WRENCH = 1000    # default of node.max_steps_per_wrench (1 s at dt = 1 ms)
TYPICAL_INTERVAL_S = 0.01      # a wrench interval the step cap should cover (100 Hz input)
STEPS_PER_PERIOD = 20          # Newmark steps per period that resolve a mode to ~1 %
AUTO_RECHOOSE_M = 0.05
DENSE_NEWMARK_DOFS = 100    # up to this size dense matrices are cheaper to build and solve
SLACK_MODES = ('aware', 'linear')
SETTLE_S = 0.05             # every cable taut this long: back from the compression-free model
CLOSED_FORM_STEPS = 100     # longer intervals (and longer than the DOFs) in closed form
SLACK_MARGIN = 1e-9          # advance_run leaves to advance a tension this near to zero
MODAL_RUN_PAYBACK = 200     # a run of n^2/200 steps pays for the modes of n DOFs (advance_run)


@dataclass(frozen=True)
class PoseUpdate:
    """What a pose update did: ``rebuilt`` False when the pose had not moved enough."""

    rebuilt: bool
    method: str = ''
    dofs: int = 0
    timings_s: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    sag_parameter: tuple[float, ...] = ()     # Irvine's lambda^2 per cable


@dataclass(frozen=True, eq=False)
class PoseStatics:
    """The first half of a pose update (:meth:`LivePredictor.statics`), plain picklable data.

    ``eq``: the chord equilibrium (tensions by the QP); ``resolved``: the settings with auto's
    choice (None: the predictor's own, no choice made);
    ``model_eq``: the model's own equilibrium (sag-consistent where the model sags, else
    ``eq``), None with ``error`` its reason; ``choice_warnings``: auto's; ``timings_s``:
    'tensions', 'statics' and 'wrench_set' (s); ``wrench_set``: the external wrenches the cables
    can hold at ``model_eq`` (:func:`wrench_set_at`).
    """

    position_m: np.ndarray
    rotation: np.ndarray
    eq: Equilibrium
    resolved: Settings | None
    model_eq: Equilibrium | None
    error: str
    choice_warnings: tuple[str, ...]
    timings_s: dict
    wrench_set: WrenchSet | None = None


@dataclass(frozen=True, eq=False)
class Prediction:
    """The predicted state of a point of the platform (doc/node_interface.md).

    ``displacement_m`` (3,): its displacement from equilibrium, u + theta x R b;
    ``position_m`` (3,): its predicted position p + R b + displacement; ``quaternion`` (4,)
    qx qy qz qw: the platform's predicted orientation, the small rotation theta (world frame)
    composed with the equilibrium orientation, exp([theta]x) R (R for a point mass).
    """

    displacement_m: np.ndarray
    position_m: np.ndarray
    quaternion: np.ndarray


def rotated_quaternion(rotation: np.ndarray, theta_rad, base=None) -> np.ndarray:
    """Quaternion (qx, qy, qz, qw) of exp([theta]x) R: the rotation vector ``theta_rad``
    (world frame, rad) applied after ``rotation``; exactly R's quaternion for theta = 0.
    ``base``: R's quaternion where the caller has it already."""
    base = matrix_to_quaternion(rotation) if base is None else base
    if not np.asarray(theta_rad).any():          # the method: no np.any dispatch per wrench
        return base
    return quaternion_product(rotation_vector_quaternion(theta_rad), base)


@dataclass(frozen=True, eq=False)
class Checkpoint:
    """What :meth:`LivePredictor.advance` carries from one wrench to the next, copied, and the
    model it steps at the pose ``position_m``, ``rotation`` (``integrator`` and ``eq`` by
    reference: a rebuild makes new ones). :meth:`LivePredictor.restore` continues from it."""

    position_m: np.ndarray
    rotation: np.ndarray
    integrator: object
    eq: object
    state: np.ndarray                # (3, n) u, v, a
    t_ns: int | None
    remainder_ns: int
    load: np.ndarray | None          # the held wrench's load vector
    load_dofs: int
    last_step_load: np.ndarray | None
    slack_forces: np.ndarray | None
    slack_time_s: float

    #: the fields :meth:`LivePredictor.restore` needs (the model references aside)
    STATE_FIELDS = ('position_m', 'rotation', 'state', 't_ns', 'remainder_ns', 'load',
                    'load_dofs', 'last_step_load', 'slack_forces', 'slack_time_s')


def same_model(predictor: 'LivePredictor', checkpoint: Checkpoint) -> bool:
    """Whether ``predictor`` steps the model of ``checkpoint`` bit for bit: the same
    equilibrium (pose, tensions, end forces) and integrator (stiffness, mass, damping)."""
    def equal(a, b) -> bool:
        return a.shape == b.shape and np.array_equal(a, b)

    mine, theirs = predictor.integrator, checkpoint.integrator
    if theirs is None or type(mine) is not type(theirs) or mine.damping != theirs.damping:
        return False
    for a, b in ((mine.k, theirs.k), (mine.m, theirs.m)):
        if not (equal(a.data, b.data) and equal(a.indices, b.indices)
                and equal(a.indptr, b.indptr)):
            return False
    eq, other = predictor.eq, checkpoint.eq
    return (equal(eq.tensions.tension_n, other.tensions.tension_n)
            and equal(eq.end_force_n, other.end_force_n)
            and equal(eq.geometry.position_m, other.geometry.position_m)
            and equal(eq.geometry.rotation, other.geometry.rotation))


class LivePredictor:
    """Current equilibrium, model and integrator of a robot; see the module docstring."""

    def __init__(self, settings: Settings, pose_tolerance_m: float = 1e-4,
                 angle_tolerance_rad: float = 1e-4, slack: str = 'aware'):
        if slack not in SLACK_MODES:
            raise ValueError(f'slack must be one of {", ".join(SLACK_MODES)}, not {slack!r}')
        self.slack = slack
        self.pose_tolerance_m = pose_tolerance_m
        self.angle_tolerance_rad = angle_tolerance_rad
        self.settings = settings
        self._solver = new_tension_solver(settings)
        self.eq: Equilibrium | None = None
        self.system: PlatformSystem | None = None
        self.integrator: Newmark | None = None
        self.position_m = None
        self.rotation = None
        self.last_update = PoseUpdate(False)
        self.wrench_set: WrenchSet | None = None
        self._choice = None            # the model auto chose, and where
        self._choice_position = None
        self._t_ns: int | None = None    # stamp of the held wrench
        self._remainder_ns = 0
        self._load = None
        self._load_dofs = 0              # the platform DOFs _load was written for
        self._spare_load, self._spare_dofs = None, 0     # the other load vector (advance)
        self.max_steps_per_wrench = MAX_STEPS_PER_WRENCH
        self.notice = ''                 # what the last advance() left out, or ''
        self._pose_of = None             # the pose's part of a prediction (_pose_parts)
        self._stepper: SlackStepper | None = None    # the compression-free model, while slack
        self._taut_steps = 0
        self._last_step_load = None      # the load of the last step (platform DOFs)
        self._slack_forces = None        # cable forces of the last slack step, or None
        self.slack_time_s = 0.0          # predicted time with a slack cable, in total
        self.update_pose(settings.initial_position_m, rotation=settings.initial_rotation,
                         force=True)

    # ----------------------------------------------------------------------------- state

    def moved(self, position, rotation) -> bool:
        """Whether the pose is further than the tolerances from the current one."""
        if self.position_m is None:
            return True
        step = position - self.position_m
        if math.sqrt(step @ step) > self.pose_tolerance_m:     # |step|, as np.linalg.norm
            return True
        turn = np.arccos(np.clip((np.trace(self.rotation.T @ rotation) - 1) / 2, -1, 1))
        return turn > self.angle_tolerance_rad

    def update_pose(self, position_m, quaternion=None, rotation=None,
                    force: bool = False) -> PoseUpdate:
        """Move to a pose; raise :class:`AnalysisError` (state unchanged) if it cannot be used:
        :meth:`statics` then :meth:`apply`, where the pose moved (or ``force``)."""
        position = np.asarray(position_m, dtype=float)
        if rotation is None:
            rotation = np.eye(3) if quaternion is None else quaternion_to_matrix(quaternion)
        if not force and not self.moved(position, rotation):
            return PoseUpdate(False, self.last_update.method, self.last_update.dofs,
                              sag_parameter=self.last_update.sag_parameter)
        return self.apply(self.statics(position, rotation))

    def statics(self, position_m, rotation) -> PoseStatics:
        """The first half of a pose update, the part that needs no model: the tensions and,
        for sag-aware models, the sag-consistent equilibrium (warm-started from :attr:`eq`),
        auto's choice. Changes nothing but the warm starts (the tension QP's, auto's choice),
        so a worker process can run it on a predictor of its own (the node's
        ``node.rebuild: worker``). Raises :class:`AnalysisError` where the pose has no
        equilibrium."""
        position = np.asarray(position_m, dtype=float)
        timings = {}
        start = time.perf_counter()
        eq = equilibrium(self.settings, position, rotation, self._solver)
        timings['tensions'] = time.perf_counter() - start
        start = time.perf_counter()
        resolved, model_eq, error = self.settings, None, ''
        try:
            resolved = self._resolved_settings(eq)
            model_eq = equilibrium_for(resolved, eq, resolved.method, start=self.eq)
        except (AnalysisError, DynamicsError, ValueError) as exc:
            error = str(exc)
        timings['statics'] = time.perf_counter() - start
        start = time.perf_counter()
        wrench_set = None if model_eq is None else wrench_set_at(self.settings, model_eq)
        timings['wrench_set'] = time.perf_counter() - start
        return PoseStatics(position, rotation, eq,
                           None if resolved is self.settings else resolved, model_eq, error,
                           tuple(self._choice_warnings()) if not error else (), timings,
                           wrench_set)

    def apply(self, statics: PoseStatics) -> PoseUpdate:
        """The second half: build the model of :meth:`statics`' answer (or the spring fallback),
        its wrench set and Newmark factorisation, and make them current, the state of motion
        carried over (:meth:`_integrator`). Raises :class:`AnalysisError` (state unchanged)
        where no model is valid."""
        timings = dict(statics.timings_s)
        start = time.perf_counter()
        eq, system, warnings = self._build(statics)
        timings['model'] = time.perf_counter() - start
        wrench_set = statics.wrench_set
        if eq is not statics.model_eq or wrench_set is None:     # the spring fallback's
            start = time.perf_counter()
            wrench_set = wrench_set_at(self.settings, eq)
            timings['wrench_set'] = time.perf_counter() - start
        start = time.perf_counter()
        integrator = self._integrator(system)
        timings['factorisation'] = time.perf_counter() - start
        self.eq, self.system = eq, system
        self.position_m, self.rotation = statics.position_m, statics.rotation
        self.integrator = integrator
        self.wrench_set = wrench_set
        self._at_pose(system)
        sag = sag_parameter(eq.cables)
        self.last_update = PoseUpdate(True, system.assembly.method, system.dofs, timings,
                                      tuple(warnings), tuple(sag.tolist()))
        return self.last_update

    def wrench_reason(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> str:
        """Why the cables cannot hold this external wrench at the current pose, or ''."""
        return self.wrench_set.reason(force_n, moment_nm)

    def wrenches_clear(self, force_n: np.ndarray, moment_nm: np.ndarray) -> np.ndarray:
        """(k,) True for the external wrenches (rows of (k, 3) arrays) that
        :meth:`wrench_reason` accepts at the current pose by its first test alone (one
        product for all); False: ask :meth:`wrench_reason`."""
        inside = getattr(self.wrench_set, 'inside_many', None)
        if inside is None:
            return np.zeros(len(force_n), dtype=bool)
        return inside(force_n, moment_nm)

    def _resolved_settings(self, eq: Equilibrium) -> Settings:
        """Settings with ``auto`` replaced by its choice, re-chosen only after the pose moved
        more than ``AUTO_RECHOOSE_M`` (the choice costs 0.1-0.2 s; it varies slowly). The
        choice keeps within ``model.max_dofs``: 600 DOFs factorise in ~7 ms (3102 in ~21 ms)."""
        s = self.settings
        if s.method != 'auto':
            return s
        moved = (self._choice is None
                 or np.linalg.norm(eq.geometry.position_m - self._choice_position)
                 > AUTO_RECHOOSE_M)
        if moved:
            self._choice = choose_model(s, eq)
            self._choice_position = eq.geometry.position_m
        return s.replace(method=self._choice.method,
                         elements_per_cable=self._choice.elements_per_cable)

    def _choice_warnings(self) -> list[str]:
        """auto's warning when no model within model.max_dofs meets model.tolerance."""
        return list(self._choice.warnings) if self.settings.method == 'auto' else []

    def _build(self, statics: PoseStatics):
        """(equilibrium, system, warnings) of the configured model at :meth:`statics`' answer
        (sag-consistent for sag-aware models), or of the spring fallback at the chord
        equilibrium (with a warning) where the model is invalid."""
        warnings = []
        eq = statics.eq
        failed = self.settings.method
        if statics.error:
            warnings.append(statics.error)
        else:
            resolved, model_eq = statics.resolved or self.settings, statics.model_eq
            try:
                system = build_system(resolved, model_eq)
                if system.assembly.valid:
                    return model_eq, system, (list(system.assembly.warnings)
                                              + list(statics.choice_warnings)
                                              + model_warnings(resolved, model_eq,
                                                               system.assembly))
                warnings += system.assembly.warnings
                failed = system.assembly.method
            except (AnalysisError, DynamicsError, ValueError) as exc:
                warnings.append(str(exc))
        system = build_system(self.settings, eq, method=FALLBACK_METHOD)
        if not system.assembly.valid:
            raise AnalysisError('no valid model for this pose: ' + '; '.join(
                system.assembly.warnings))
        warnings.append(f'method {failed} failed for this state; fell back to '
                        f'{FALLBACK_METHOD}')
        return eq, system, warnings + model_warnings(self.settings, eq, system.assembly)

    def _integrator(self, system: PlatformSystem) -> Newmark:
        """A Newmark integrator of ``system`` that carries on from the current one's state.

        Same DOFs (a pose update): u, v, a are kept as they are. Other DOFs (a model change,
        e.g. fem_sag <-> spring): the platform DOFs (the first ``platform_dofs`` entries) are
        kept and the cable interior follows them quasi-statically, u_i = -K_ii^-1 K_ip u_p
        (likewise v, a), so a method toggle never restarts the prediction from rest.
        """
        damping = damping_for(self.settings, system)
        integrator = newmark_for(system, damping, self.settings)
        integrator.damping = damping
        old = self.integrator
        if old is not None:
            carry_state(old, integrator, system.platform_dofs)
        return integrator

    def set_settings(self, settings: Settings) -> PoseUpdate:
        """Apply new settings (method, damping, ...): rebuild at the current pose."""
        old = (self.settings, self._solver)
        self.settings = settings
        self._solver = new_tension_solver(settings)
        self._choice = None
        try:
            return self.update_pose(self.position_m, rotation=self.rotation, force=True)
        except Exception:
            self.settings, self._solver = old
            raise

    # ----------------------------------------------------------------------------- time

    def advance(self, stamp_ns: int, force_n, moment_nm=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Integrate to ``stamp_ns`` under the held previous wrench, then hold the new one.

        Time is kept in integer nanoseconds: float seconds of a wall-clock stamp (~1.7e9 s)
        resolve only ~0.2 us and would miscount the Newmark steps of a 5 ms interval.
        Returns the centroid displacement (3,) m at the stamp. Raises ``ValueError`` for a stamp
        older than the last one (:meth:`rebase_time` first where the clock jumped back).

        Bounded work: at most ``max_steps_per_wrench`` Newmark steps per call. A longer interval
        (the input stalled, a long service call held the node) steps the held wrench that many
        times and drops the rest of the interval: the state is kept, never reset to rest (under
        a constant wrench it stays at the static deflection), and :attr:`notice` says how much
        was dropped ('' otherwise).
        """
        stamp_ns = int(stamp_ns)
        self.notice = ''
        n = self.integrator.u.shape[0]
        nd = self.system.platform_dofs
        load = self._spare_load
        if load is None or load.shape[0] != n or self._spare_dofs != nd:
            load = np.zeros(n)
        load[:3] = force_n
        if nd == 6:
            load[3:6] = moment_nm
        if self._t_ns is not None and stamp_ns < self._t_ns:
            raise ValueError(f'stamp {stamp_ns * 1e-9:.9f} s is older than the last wrench '
                             f'({self._t_ns * 1e-9:.9f} s)')
        held = self._load
        if self._t_ns is None or held is None:
            self._remainder_ns = 0
        else:
            if held.shape != load.shape:          # the model changed: platform DOFs carry on
                held = np.zeros(n)
                held[:nd] = self._load[:nd]
            dt_ns = max(1, round(self.settings.dt_s * 1e9))
            steps, self._remainder_ns = divmod(stamp_ns - self._t_ns + self._remainder_ns, dt_ns)
            if not self._held_closed_form(held, steps):
                cap = self.max_steps_per_wrench
                if steps > cap:
                    self.notice = (f'{(stamp_ns - self._t_ns) * 1e-9:.6g} s since the last '
                                   f'wrench would take {steps} Newmark steps of '
                                   f'{self.settings.dt_s:g} s; integrated {cap} '
                                   f'({cap * self.settings.dt_s:.6g} s) of the held wrench '
                                   f'(node.max_steps_per_wrench) and skipped the rest, state '
                                   f'kept')
                    steps, self._remainder_ns = cap, 0
                self._step(held, steps)
        self._t_ns = stamp_ns
        # two load vectors swap roles (no allocation per wrench): the one just integrated takes
        # the next wrench (only its entries of the platform DOFs are ever written)
        self._spare_load, self._spare_dofs = ((held, self._load_dofs) if held is self._load
                                              else (None, 0))
        self._load, self._load_dofs = load, nd
        return self.platform_state()[0][:3].copy()

    def advance_run(self, stamps_ns: np.ndarray, force_n: np.ndarray,
                    moment_nm: np.ndarray) -> tuple[int, np.ndarray]:
        """:meth:`advance` of the first k wrenches of a run (stamps (m,) int ns, non-
        decreasing, rows of (m, 3) forces and moments), in one loop of the same Newmark
        steps: (k, their platform states (k, nd), :meth:`platform_state`'s q after each).

        The same numbers: bit for bit where the steps are the integrator's own, on the same
        load vectors; to round-off where a long run of a model with cable interiors steps in
        its modes (:meth:`_run_steps`). The run stops (k < m) before a wrench that
        :meth:`advance` must take alone:
        the first after a reset or a model change, one whose interval is stepped in closed
        form or capped (``max_steps_per_wrench``), one in whose steps a cable goes slack or
        comes within :data:`SLACK_MARGIN` of it (``slack='aware'``), and one at whose stamp
        it is not clear whether a cable is slack (``'linear'``: a cable within the margin; the
        wrenches clearly slack are counted as :meth:`advance` counts them); the steps taken
        past it are taken back.
        """
        integrator = self.integrator
        nd = self.system.platform_dofs
        n = integrator.u.shape[0]
        held = self._load
        count = len(stamps_ns)
        if (not count or self._t_ns is None or held is None or held.shape[0] != n
                or self._stepper is not None):
            return 0, np.empty((0, nd))
        dt_ns = max(1, round(self.settings.dt_s * 1e9))
        elapsed = np.asarray(stamps_ns, dtype=np.int64) - self._t_ns + self._remainder_ns
        done_steps, remainders = np.divmod(elapsed, dt_ns)   # advance's divmod, chained
        steps = np.diff(done_steps, prepend=0)
        plain = ((steps <= min(max(CLOSED_FORM_STEPS, n), self.max_steps_per_wrench))
                 & (elapsed >= np.maximum.accumulate(elapsed)) & (elapsed >= 0))
        count = count if plain.all() else int(plain.argmin())
        loads = np.zeros((count, n))
        loads[:, :3] = force_n[:count]
        if nd == 6:
            loads[:, 3:6] = moment_nm[:count]
        start = integrator._state.copy()
        taken = self._run_steps(held, loads, steps[:count])
        total = int(done_steps[count - 1]) if count else 0
        slack = np.zeros(count, dtype=bool)
        if total:                         # a cable slack, or too near it: take back
            bad, slack = self._slack_in(taken, np.cumsum(steps[:count]))
            if bad < count:
                integrator._state[:] = start
                count, total = bad, int(done_steps[bad - 1]) if bad else 0
                taken = self._run_steps(held, loads, steps[:count])
        if not count:
            return 0, np.empty((0, nd))
        history = np.concatenate([start[None, 0, :nd], taken[:, 0]])
        q = history[done_steps[:count]]
        if total:
            last = int(np.flatnonzero(steps[:count])[-1])      # the last wrench with steps
            if self.slack == 'aware':
                self._last_step_load = (held if last == 0 else loads[last - 1])[:nd].copy()
                self._slack_forces = None
            else:                         # advance's count, wrench by wrench (its sum order)
                dt_s = self.settings.dt_s
                for times in steps[:count][slack[:count]].tolist():
                    self.slack_time_s += times * dt_s
                self._slack_forces = self.cable_force_n() if slack[last] else None
        elif self.slack == 'aware':
            self._slack_forces = None
        self._t_ns = int(stamps_ns[count - 1])
        self._remainder_ns = int(remainders[count - 1])
        self._load, self._load_dofs = loads[count - 1].copy(), nd
        self._spare_load, self._spare_dofs = None, 0
        self.notice = ''
        return count, q

    def _run_steps(self, held: np.ndarray, loads: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """``steps[k]`` linear steps under the load held over the k-th wrench's interval
        (``held``, then ``loads[k - 1]``: (n,) and (k, n) load vectors), in turn; the platform
        rows (u, v) after every step (s, 2, nd). In the model's modes where that pays
        (:meth:`_modal_for`: the same steps to round-off), else the integrator's own steps
        (bit for bit)."""
        integrator = self.integrator
        nd = self.system.platform_dofs
        count = len(steps)
        total = int(steps.sum())
        modal = self._modal_for(total) if count and not held[nd:].any() else None
        if modal is not None:
            platform = np.concatenate([held[None, :nd], loads[:count - 1, :nd]])
            taken, after = modal.run(integrator._state, platform, steps, nd)
            integrator._state[:] = after
            return taken
        state, step = integrator._state, integrator.step
        taken = np.empty((total, 2, nd))
        row = 0
        for load, times in zip([held, *loads[:count - 1]], steps.tolist()):
            for _ in range(times):
                step(load)
                taken[row] = state[:2, :nd]
                row += 1
        return taken

    def _modal_for(self, steps: int) -> HeldLoadSteps | None:
        """The model's modes (:meth:`_held_steps`) where a run of ``steps`` linear steps takes
        them, or None: a model with cable interiors (a chain solve a step; a massless model's
        step is a small product already) and a run that pays for the eigenproblem alone, at
        least n^2 / ``MODAL_RUN_PAYBACK`` steps (later runs of the model reuse it). The choice
        depends on the model and the run only, so a replay resumed from a checkpoint takes the
        path the uninterrupted one took."""
        n = self.integrator.u.shape[0]
        if n == self.system.platform_dofs or steps * MODAL_RUN_PAYBACK < n * n:
            return None
        return self._held_steps()

    def _held_steps(self) -> HeldLoadSteps | None:
        """The model's :class:`HeldLoadSteps` (its modes), made on first use; None where it
        has none: more than ``held_load.MAX_DOFS`` DOFs, matrices not finite, damping not
        Rayleigh (then the integrator steps)."""
        if self._held is None:
            integrator = self.integrator
            self._held = False
            if integrator.u.shape[0] <= held_load.MAX_DOFS:
                try:
                    self._held = HeldLoadSteps(integrator.k, integrator.m, integrator.damping,
                                               integrator.a)
                except (DynamicsError, ValueError, np.linalg.LinAlgError):
                    pass
        return self._held or None

    def _slack_in(self, taken: np.ndarray, ends: np.ndarray) -> tuple[int, np.ndarray]:
        """The check :meth:`_step` makes of a run's steps (``taken``, wrench k's ending at step
        ``ends[k]``), with a margin: (the first wrench that :meth:`advance` must take alone,
        or the number of wrenches; (k,) whether each wrench ends slack).

        ``slack='aware'`` checks after each step: a cable within :data:`SLACK_MARGIN` of slack
        stops the run (the compression-free model takes over), so no wrench of it ends slack.
        ``'linear'`` checks at each stamp whether the lowest tension is <= 0 (slack: counted):
        only where that is not clear by the margin (every cable above it, or one below minus
        it) does the run stop, so a long slack stretch is one run."""
        dk = self.integrator.damping.stiffness_factor
        slack = np.zeros(len(ends), dtype=bool)
        stepped = np.diff(ends, prepend=0) > 0           # the wrenches with steps
        at = ends[stepped] - 1 if self.slack == 'linear' else np.arange(len(taken))
        x = taken[at, 0] + dk * taken[at, 1]
        tension = self._tension0 + x @ self._tension_map.T
        bound = SLACK_MARGIN * (np.abs(self._tension0) + np.abs(x) @ np.abs(self._tension_map).T)
        clear = (tension > bound).all(axis=1)
        if self.slack == 'linear':
            below = (tension < -bound).any(axis=1)
            slack[stepped] = below
            clear |= below
        if clear.all():
            return len(ends), slack
        return int(np.searchsorted(ends, at[int(clear.argmin())] + 1)), slack

    # ----------------------------------------------------------------------------- slack

    def platform_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(q, q') (nd,) of the platform DOFs: the compression-free model's while a cable is
        slack (``slack='aware'``), else the linear integrator's (views: copy to keep)."""
        if self._stepper is not None:
            return self._stepper.q, self._stepper.v
        nd = self.system.platform_dofs
        return self.integrator.u[:nd], self.integrator.v[:nd]

    def cable_force_n(self) -> np.ndarray:
        """(n,) predicted cable forces (N), the cables' dampers included: the compression-free
        model's (0 while slack) or the linear quasi-static T_i + dT_i(q + dK q')
        (:mod:`cdpr_dynamics.dynamics.slack`: Rayleigh's stiffness part is the cables' own
        damping)."""
        if self._stepper is not None:
            return self._stepper.pull.copy()
        nd = self.system.platform_dofs
        u, v = self.integrator.u[:nd], self.integrator.v[:nd]
        return self._tension0 + self._tension_map @ (u + self.integrator.damping.stiffness_factor
                                                     * v)

    def stretch_rate_m_s(self) -> np.ndarray:
        """(n,) predicted rate of each cable's stretch (m/s): d(chord length)/dt of the
        platform's motion, -u_i . G_i q' (the anchor-ward unit vector u_i)."""
        return self._stretch_map @ self.platform_state()[1]

    def set_slack(self, slack: str) -> None:
        """Switch ``node.slack`` (aware, linear); to linear while slack: the linear model takes
        over the compression-free state."""
        if slack not in SLACK_MODES:
            raise ValueError(f'slack must be one of {", ".join(SLACK_MODES)}, not {slack!r}')
        if slack == 'linear' and self._stepper is not None:
            self._leave_slack()
        self.slack = slack

    def _at_pose(self, system: PlatformSystem) -> None:
        """Per-pose data of the slack check and the closed form (after a rebuild)."""
        g = system.geometry.attachment_map()
        unit = system.geometry.unit
        k_end = system.assembly.static_end_stiffness()
        k_axial = np.einsum('ci,cij,cj->c', unit, k_end, unit)
        self._stretch_map = -np.einsum('ci,cia->ca', unit, g)               # (n, nd)
        self._tension_map = k_axial[:, None] * self._stretch_map            # dT/dq
        self._tension0 = row_norm(system.assembly.end_force_n)
        self._saved = np.empty_like(self.integrator._state)
        self._held = None        # HeldLoadSteps of this model, made on first use (False: none)
        self._slack_stepper = None          # the compression-free model's, on first use
        self._interior = None               # interior_map of the model, on first use
        self._settle_steps = max(1, math.ceil(SETTLE_S / self.settings.dt_s - 1e-9))
        if self._stepper is not None:       # slack across the pose update: carry on there
            stepper = self._stepper
            self._stepper = None
            self._enter_slack(stepper.q, stepper.v, stepper.acc)

    def _step(self, load: np.ndarray, steps: int) -> None:
        """``steps`` steps under ``load``: linear, or compression-free while a cable is slack
        (module docstring)."""
        integrator = self.integrator
        nd = self.system.platform_dofs
        if self.slack == 'linear':
            for _ in range(steps):
                integrator.step(load)
            if steps:
                forces = self.cable_force_n()
                self._slack_forces = forces if forces.min() <= 0.0 else None
                if self._slack_forces is not None:
                    self.slack_time_s += steps * self.settings.dt_s
            return
        state, saved = integrator._state, self._saved
        tension0, tension_map = self._tension0, self._tension_map
        dk = integrator.damping.stiffness_factor
        previous = self._last_step_load          # the load of the step before (platform)
        for _ in range(steps):
            if self._stepper is None:
                np.copyto(saved, state)
                integrator.step(load)
                if (tension0 + tension_map @ (state[0, :nd] + dk * state[1, :nd])).min() > 0.0:
                    previous = load
                    continue
                np.copyto(state, saved)        # a cable would slacken in this step: again
                self._enter_slack(saved[0, :nd], saved[1, :nd], None,
                                  (load if previous is None else previous)[:nd])
            self._slack_step(load)
            previous = load
        if steps:
            self._last_step_load = load[:nd].copy()
        if self._stepper is None:
            self._slack_forces = None

    def _enter_slack(self, q, v, acc=None, force=None) -> None:
        """Switch to the compression-free model at (q, q') (and q'' or the load ``force``
        whose balance gives it)."""
        stepper = self._slack_stepper           # one per pose: made on the first slack
        if stepper is None:
            method = platform_only_method(self.system.assembly.method)
            system = self.system
            if system.assembly.interior_dofs or system.assembly.method != method:
                system = build_system(self.settings, self.eq, method, 1)
            s = self.settings
            stepper = self._slack_stepper = SlackStepper(
                system, self.integrator.damping, s.dt_s, s.newmark_alpha, s.newmark_beta)
        if acc is None:
            stepper.start(q, v, force)
        else:
            stepper.start(q, v, np.zeros_like(stepper.q))
            stepper.acc = np.array(acc, dtype=float)
        self._stepper = stepper
        self._taut_steps = 0

    @property
    def slack_cables(self) -> tuple[int, ...]:
        """The cables slack at the last stamp (their indices)."""
        forces = self._slack_forces
        return () if forces is None else tuple(np.flatnonzero(forces <= 0.0).tolist())

    def _slack_step(self, load: np.ndarray) -> None:
        """One compression-free step; back to the linear model once settled. Where the
        step fails (the platform flung beyond the model, Newton lost), the motion is
        forgotten: the next wrench starts from rest, not from the failed state."""
        stepper = self._stepper
        try:
            stepper.step(load[:stepper.cables.nd])
        except DynamicsError as exc:
            self.reset_time()
            raise DynamicsError(f'{exc}; the next wrench starts from rest') from None
        if not stepper.pull.min() > 0.0:
            self._taut_steps = 0
            self.slack_time_s += self.settings.dt_s
            self._slack_forces = stepper.pull
            return
        self._slack_forces = None
        self._taut_steps += 1
        if self._taut_steps >= self._settle_steps:
            self._leave_slack()

    def _leave_slack(self) -> None:
        """The linear integrator takes over the compression-free state (interior
        quasi-static)."""
        stepper, self._stepper = self._stepper, None
        platform = np.column_stack([stepper.q, stepper.v, stepper.acc])
        state = self.integrator._state
        nd = platform.shape[0]
        state[:, :nd] = platform.T
        if state.shape[1] > nd:
            if self._interior is None:
                self._interior = interior_map(self.integrator.k, nd)
            state[:, nd:] = (self._interior @ platform).T

    def _held_closed_form(self, load: np.ndarray, steps: int) -> bool:
        """Take ``steps`` linear steps under ``load`` in closed form where that pays and is
        exact (no slack now, at the end or in the static deflection); False: step them."""
        integrator = self.integrator
        n = integrator.u.shape[0]
        if (steps <= max(CLOSED_FORM_STEPS, n) or n > held_load.MAX_DOFS
                or self._stepper is not None):
            return False
        modes = self._held_steps()
        if modes is None:
            return False
        after = modes.advance(integrator._state, load, steps)
        nd = self.system.platform_dofs
        if self.slack == 'aware':
            dk = integrator.damping.stiffness_factor
            ends = np.stack([after[0, :nd] + dk * after[1, :nd], modes.static(load)[:nd]])
            if (self._tension0 + ends @ self._tension_map.T).min() <= 0.0:
                return False
        integrator._state[:] = after
        self._last_step_load = load[:nd].copy()
        self._slack_forces = None
        return True

    def prediction(self, point_m=(0.0, 0.0, 0.0)) -> Prediction:
        """The integrator's current state at the point ``point_m`` (platform frame, m):
        :class:`Prediction`; the default (the centroid) gives :meth:`advance`'s displacement."""
        return self._predict(self.platform_state()[0], point_m)

    def _predict(self, q: np.ndarray, point_m) -> Prediction:
        """:meth:`prediction` of the platform state ``q`` (nd,)."""
        pose = self._pose(point_m)
        if q.shape[0] == 3:        # a point mass: u itself, the equilibrium orientation
            displacement = q[:3].copy()
            return Prediction(displacement, pose[3] + displacement, pose[4])
        rotation = pose[0]
        displacement = point_displacement(q, rotation, point_m)
        return Prediction(displacement, pose[3] + displacement,
                          rotated_quaternion(rotation, q[3:6], pose[4]))

    def _pose(self, point_m) -> tuple:
        """:meth:`_pose_parts`, kept until the pose or the point changes."""
        point = point_m if type(point_m) is tuple else tuple(map(float, point_m))
        pose = self._pose_of
        rotation, position = self.eq.geometry.rotation, self.eq.geometry.position_m
        if (pose is None or pose[0] is not rotation or pose[1] is not position
                or pose[2] != point):
            pose = self._pose_of = self._pose_parts(point)
        return pose

    def predictions(self, q: np.ndarray, point_m=(0.0, 0.0, 0.0)) -> tuple:
        """:meth:`prediction` of platform states ``q`` (k, nd) (:meth:`advance_run`'s) at the
        current pose: (displacements (k, 3), positions (k, 3), quaternions (k, 4)), the
        same numbers."""
        if self.system.platform_dofs != 3:
            rows = [self._predict(row, point_m) for row in q]
            return tuple(np.array([getattr(r, name) for r in rows]).reshape(len(q), -1)
                         for name in ('displacement_m', 'position_m', 'quaternion'))
        pose = self._pose(point_m)
        displacement = q[:, :3].copy()
        return (displacement, pose[3] + displacement,
                np.broadcast_to(pose[4], (len(q), 4)))

    def _pose_parts(self, point_m) -> tuple:
        """What :meth:`prediction` takes from the equilibrium pose (the given pose, or an
        underactuated robot's equilibrium with its cable lengths), kept until it or the point
        changes: (rotation, position, point, p + R b (3,) m, R's quaternion (4,))."""
        rotation, position = self.eq.geometry.rotation, self.eq.geometry.position_m
        arm = rotation @ np.asarray(point_m, dtype=float)
        return (rotation, position, point_m, position + arm, matrix_to_quaternion(rotation))

    def checkpoint(self) -> Checkpoint | None:
        """The state to continue from (:meth:`restore`), or None while a cable is slack (the
        compression-free model's state is not kept)."""
        if self._stepper is not None or self.integrator is None:
            return None

        def copied(array):
            return None if array is None else np.array(array, dtype=float)
        return Checkpoint(copied(self.position_m), copied(self.rotation), self.integrator,
                          self.eq, self.integrator._state.copy(), self._t_ns,
                          self._remainder_ns, copied(self._load), self._load_dofs,
                          copied(self._last_step_load), copied(self._slack_forces),
                          float(self.slack_time_s))

    def restore(self, checkpoint: Checkpoint) -> None:
        """Continue from ``checkpoint``: the model rebuilt at its pose, then its state of
        motion and wrench history. Raises ``ValueError`` where the model built here differs
        from the checkpoint's (:func:`same_model`; a checkpoint without model references is
        taken as checked)."""
        self.update_pose(checkpoint.position_m, rotation=checkpoint.rotation, force=True)
        if checkpoint.integrator is not None and not same_model(self, checkpoint):
            raise ValueError('the model rebuilt at the checkpoint\'s pose differs from the '
                             'one it was taken on')
        if checkpoint.state.shape != self.integrator._state.shape:
            raise ValueError(f'a checkpoint of {checkpoint.state.shape[1]} DOFs for a model '
                             f'of {self.integrator._state.shape[1]}')
        self.reset_time()
        self.integrator._state[:] = checkpoint.state
        self._t_ns, self._remainder_ns = checkpoint.t_ns, checkpoint.remainder_ns
        self._load = None if checkpoint.load is None else checkpoint.load.copy()
        self._load_dofs = checkpoint.load_dofs
        self._spare_load, self._spare_dofs = None, 0
        self._last_step_load = (None if checkpoint.last_step_load is None
                                else checkpoint.last_step_load.copy())
        self._slack_forces = (None if checkpoint.slack_forces is None
                              else checkpoint.slack_forces.copy())
        self.slack_time_s = checkpoint.slack_time_s
        self.notice = ''

    def rebase_time(self) -> None:
        """Take the next wrench's stamp as the new time origin, keeping the state of motion
        (after the input's clock jumped back: the platform did not stop)."""
        self._t_ns = None
        self._remainder_ns = 0

    def reset_time(self) -> None:
        """Forget the wrench history and the motion: the next wrench starts from rest."""
        self._t_ns = None
        self._load = None
        self._remainder_ns = 0
        self._stepper = None
        self._last_step_load = None
        self._slack_forces = None
        if self.integrator is not None:
            self.integrator.reset()


@dataclass(frozen=True, eq=False)
class LiveHistory:
    """A :class:`LivePredictor`'s response to a sampled load: ``t_s`` (nt,), platform DOFs
    ``u`` (nt, nd), predicted ``cable_force_n`` (nt, n), ``method`` and
    ``elements_per_cable`` of the linear model, ``slack_method`` of the compression-free one."""

    t_s: np.ndarray
    u: np.ndarray
    cable_force_n: np.ndarray
    method: str
    elements_per_cable: int
    slack_method: str

    @property
    def slack(self) -> np.ndarray:
        """(nt, n) True where a cable carries no tension."""
        return ~(self.cable_force_n > 0.0)


def harmonic_history(settings: Settings, excitation_hz: float, duration_s: float,
                     slack: str = 'aware') -> LiveHistory:
    """The response from rest at the initial pose to ``frf.force_n sin(2 pi f t)`` (and
    ``frf.moment_nm``), fed to a :class:`LivePredictor` as a wrench stream: the wrench stamped
    t_k carries the load at t_{k+1} = t_k + dt, so each Newmark step ends on the load of the
    offline history (``cdpr_analyze``). A replay of that stream gives the same numbers."""
    predictor = LivePredictor(settings, slack=slack)
    dt = settings.dt_s
    dt_ns = max(1, round(dt * 1e9))
    steps = int(round(duration_s / dt))
    t = np.arange(steps + 1) * dt
    w = 2.0 * math.pi * excitation_hz
    nd = predictor.system.platform_dofs
    u = np.zeros((steps + 1, nd))
    forces = np.zeros((steps + 1, predictor.eq.geometry.length_m.size))
    for k in range(steps + 1):
        load = math.sin(w * (k + 1) * dt)
        predictor.advance(k * dt_ns, load * settings.frf_force_n, load * settings.frf_moment_nm)
        u[k] = predictor.platform_state()[0]
        forces[k] = predictor.cable_force_n()
    method = predictor.system.assembly.method
    return LiveHistory(t, u, forces, method, predictor.system.assembly.elements_per_cable,
                       platform_only_method(method))


def newmark_for(system: PlatformSystem, damping, settings: Settings) -> Newmark:
    """The integrator of ``system`` with the ``newmark.*`` settings: factorised through its
    cable chains (:class:`~cdpr_dynamics.dynamics.system.ChainNewmark`, no global matrices), or
    from
    the global matrices (dense up to ``DENSE_NEWMARK_DOFS``, else a sparse LU) where a chain
    band is not positive definite."""
    s = settings
    try:
        return ChainNewmark(system, damping, s.dt_s, s.newmark_alpha, s.newmark_beta)
    except np.linalg.LinAlgError:
        k, m = system.matrices(dense=system.dofs <= DENSE_NEWMARK_DOFS)
        return Newmark(k, m, damping, s.dt_s, s.newmark_alpha, s.newmark_beta)


def interior_map(k, platform_dofs: int) -> np.ndarray:
    """(ni, nd) Z = -K_ii^-1 K_ip: the cable interior's quasi-static displacement per
    platform DOF of the stiffness ``k`` (dense or sparse)."""
    interior = k[platform_dofs:, platform_dofs:]
    coupling = k[platform_dofs:, :platform_dofs]
    if sp.issparse(k):
        coupling = coupling.toarray()
        return -np.asarray(spla.splu(sp.csc_matrix(interior)).solve(coupling))
    return -np.linalg.solve(interior, coupling)


def carry_state(old: Newmark, new: Newmark, platform_dofs: int) -> None:
    """Give ``new`` the state of ``old`` (see :meth:`LivePredictor._integrator`)."""
    if old.u.shape == new.u.shape:
        new.u, new.v, new.acc = old.u, old.v, old.acc
        return
    nd = min(platform_dofs, old.u.size, new.u.size)
    platform = np.column_stack([old.u[:nd], old.v[:nd], old.acc[:nd]])     # (nd, 3)
    state = np.zeros((new.u.size, 3))
    state[:nd] = platform
    if new.u.size > platform_dofs:
        state[platform_dofs:] = interior_map(new.k, platform_dofs)[:, :nd] @ platform
    new.u, new.v, new.acc = (np.ascontiguousarray(state[:, i]) for i in range(3))


def time_step_warnings(settings: Settings, system: PlatformSystem, lowest_hz: float,
                       max_steps: int) -> list[str]:
    """Warnings, with numbers, where ``newmark.dt_s`` does not suit the model.

    * Too fine: ``max_steps`` steps cover less than ``TYPICAL_INTERVAL_S`` of input, so wrenches
      further apart are integrated only in part; the highest natural frequency f_max of the
      model says what is needed (``STEPS_PER_PERIOD`` steps per period: dt = 1/(20 f_max)).
    * Too coarse: the average-acceleration scheme lengthens the period of a mode by
      (w dt/2) / arctan(w dt/2); over 1 % for the lowest mode ``lowest_hz`` is reported.
    """
    from cdpr_dynamics.dynamics.system import _largest_eigenvalue
    dt = settings.dt_s
    warnings = []
    if dt * max_steps < TYPICAL_INTERVAL_S:
        try:
            k, m = system.matrices(dense=system.dofs <= DENSE_NEWMARK_DOFS)
            f_max = np.sqrt(max(_largest_eigenvalue(k, m), 0.0)) / (2 * np.pi)
            need = f' (its highest mode, {f_max:.4g} Hz, needs only dt = ' \
                   f'{1 / (STEPS_PER_PERIOD * f_max):.3g} s)' if f_max > 0 else ''
        except (DynamicsError, ValueError, np.linalg.LinAlgError):
            need = ''
        warnings.append(f'newmark.dt_s = {dt:g} s: node.max_steps_per_wrench = {max_steps} '
                        f'steps cover only {dt * max_steps * 1e3:.3g} ms of input, wrenches '
                        f'further apart are integrated in part{need}')
    if np.isfinite(lowest_hz) and lowest_hz > 0:
        half = np.pi * lowest_hz * dt
        elongation = half / np.arctan(half) - 1.0
        if elongation > 0.01:
            warnings.append(f'newmark.dt_s = {dt:g} s takes {1 / (lowest_hz * dt):.3g} steps per '
                            f'period of the lowest mode ({lowest_hz:.4g} Hz): its period comes '
                            f'out {100 * elongation:.2g} % long')
    return warnings


def wrench_set_at(settings: Settings, eq: Equilibrium) -> WrenchSet:
    """The external wrenches the cables can hold at ``eq`` within the tension box (per state,
    not per wrench): W^T itself for chord statics (its rank checked by ``equilibrium``), else
    the sagged cables' end tangents (:func:`_tangent_structure`); an underactuated robot's
    is a :class:`~cdpr_dynamics.mechanics.underactuated.HeldWrenchSet`."""
    s = settings
    chord = eq.statics == 'chord'
    if is_underactuated(s.robot):
        return HeldWrenchSet(eq.geometry.structure_matrix if chord else _tangent_structure(eq),
                             s.tension_min_n, s.tension_max_n,
                             required_wrench(s.robot, s.external_force_n,
                                             s.external_moment_nm, eq.geometry.rotation))
    return WrenchSet(eq.geometry.structure_matrix if chord else _tangent_structure(eq),
                     s.tension_min_n, s.tension_max_n,
                     required_wrench(s.robot, s.external_force_n, s.external_moment_nm,
                                     eq.geometry.rotation),
                     full_rank=chord)


def _tangent_structure(eq: Equilibrium) -> np.ndarray:
    """W^T of the forces along each cable's end direction at ``eq`` (the chord for chord
    statics, the catenary's end tangent for sagged cables): wrench per unit tension."""
    force = eq.end_force_n
    unit = force / row_norm(force)[:, None]
    return structure_of(unit, eq.geometry.lever_m, eq.geometry.structure_matrix.shape[0])
