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
  motion carries over pose updates and model changes (:func:`carry_state`).
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
from cdpr_dynamics.dynamics.system import ChainNewmark, DynamicsError, Newmark, PlatformSystem
from cdpr_dynamics.mechanics.feasibility import WrenchSet
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.mechanics.robot import (matrix_to_quaternion, quaternion_product,
                                           quaternion_to_matrix, required_wrench,
                                           rotation_vector_quaternion, row_norm)
from cdpr_dynamics.selection.auto import choose_model
from cdpr_dynamics.mechanics.statics import structure_of

FALLBACK_METHOD = 'spring'
MAX_STEPS_PER_WRENCH = 1000    # default of node.max_steps_per_wrench (1 s at dt = 1 ms)
TYPICAL_INTERVAL_S = 0.01      # a wrench interval the step cap should cover (100 Hz input)
STEPS_PER_PERIOD = 20          # Newmark steps per period that resolve a mode to ~1 %
AUTO_RECHOOSE_M = 0.05
DENSE_NEWMARK_DOFS = 100    # up to this size dense matrices are cheaper to build and solve


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
    """The predicted state of a point of the platform (SPEC section 5).

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


class LivePredictor:
    """Current equilibrium, model and integrator of a robot; see the module docstring."""

    def __init__(self, settings: Settings, pose_tolerance_m: float = 1e-4,
                 angle_tolerance_rad: float = 1e-4):
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
        sag = sag_parameter(eq.cables)
        self.last_update = PoseUpdate(True, system.assembly.method, system.dofs, timings,
                                      tuple(warnings), tuple(sag.tolist()))
        return self.last_update

    def wrench_reason(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> str:
        """Why the cables cannot hold this external wrench at the current pose, or ''."""
        return self.wrench_set.reason(force_n, moment_nm)

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
        integrator = newmark_for(system, damping_for(self.settings, system), self.settings)
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
            cap = self.max_steps_per_wrench
            if steps > cap:
                self.notice = (f'{(stamp_ns - self._t_ns) * 1e-9:.6g} s since the last wrench '
                               f'would take {steps} Newmark steps of {self.settings.dt_s:g} s; '
                               f'integrated {cap} ({cap * self.settings.dt_s:.6g} s) of the held '
                               f'wrench (node.max_steps_per_wrench) and skipped the rest, state '
                               f'kept')
                steps, self._remainder_ns = cap, 0
            step = self.integrator.step
            for _ in range(steps):
                step(held)
        self._t_ns = stamp_ns
        # two load vectors swap roles (no allocation per wrench): the one just integrated takes
        # the next wrench (only its entries of the platform DOFs are ever written)
        self._spare_load, self._spare_dofs = ((held, self._load_dofs) if held is self._load
                                              else (None, 0))
        self._load, self._load_dofs = load, nd
        return self.integrator.u[:3].copy()

    def prediction(self, point_m=(0.0, 0.0, 0.0)) -> Prediction:
        """The integrator's current state at the point ``point_m`` (platform frame, m):
        :class:`Prediction`; the default (the centroid) gives :meth:`advance`'s displacement."""
        nd = self.system.platform_dofs
        q = self.integrator.u[:nd]
        point = point_m if type(point_m) is tuple else tuple(map(float, point_m))
        pose = self._pose_of
        if (pose is None or pose[0] is not self.rotation or pose[1] is not self.position_m
                or pose[2] != point):
            pose = self._pose_of = self._pose_parts(point)
        if nd == 3:        # a point mass: u itself, the equilibrium orientation
            displacement = q[:3].copy()
            return Prediction(displacement, pose[3] + displacement, pose[4])
        displacement = point_displacement(q, self.rotation, point_m)
        return Prediction(displacement, pose[3] + displacement,
                          rotated_quaternion(self.rotation, q[3:6], pose[4]))

    def _pose_parts(self, point_m) -> tuple:
        """What :meth:`prediction` takes from the pose, kept until the pose or the point
        changes: (rotation, position, point, p + R b (3,) m, R's quaternion (4,))."""
        arm = self.rotation @ np.asarray(point_m, dtype=float)
        return (self.rotation, self.position_m, point_m, self.position_m + arm,
                matrix_to_quaternion(self.rotation))

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
        if self.integrator is not None:
            self.integrator.reset()


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
        k = new.k
        interior = k[platform_dofs:, platform_dofs:]
        coupling = k[platform_dofs:, :nd] @ platform
        if sp.issparse(k):
            state[platform_dofs:] = -np.asarray(spla.splu(sp.csc_matrix(interior)).solve(
                np.asarray(coupling)))
        else:
            state[platform_dofs:] = -np.linalg.solve(interior, coupling)
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
    the sagged cables' end tangents (:func:`_tangent_structure`)."""
    s = settings
    chord = eq.statics == 'chord'
    return WrenchSet(eq.geometry.structure_matrix if chord else _tangent_structure(eq),
                     s.tension_min_n, s.tension_max_n,
                     required_wrench(s.robot, s.external_force_n, s.external_moment_nm),
                     full_rank=chord)


def _tangent_structure(eq: Equilibrium) -> np.ndarray:
    """W^T of the forces along each cable's end direction at ``eq`` (the chord for chord
    statics, the catenary's end tangent for sagged cables): wrench per unit tension."""
    force = eq.end_force_n
    unit = force / row_norm(force)[:, None]
    return structure_of(unit, eq.geometry.lever_m, eq.geometry.structure_matrix.shape[0])
