"""ROS-free core of the live node: the model at the current pose and a running integrator.

The node and ``cdpr_replay`` both feed poses and wrenches through :class:`LivePredictor`, so an
offline replay and the live node give the same numbers by construction.

* :meth:`LivePredictor.update_pose`: a pose that moved more than the tolerance re-solves the
  tensions (warm-started QP), rebuilds the cable model and refactorises the Newmark matrix;
  otherwise nothing is recomputed. A failure leaves the last good state in place.
* :meth:`LivePredictor.advance`: zero-order hold of the wrench: the wrench received at
  ``t_k`` acts from ``t_k`` until the next one; advancing to ``t_{k+1}`` integrates
  ``floor((t_{k+1} - t_k)/dt)`` Newmark steps of ``newmark.dt_s`` (the remainder carries over)
  and returns the centroid's displacement from equilibrium at ``t_{k+1}``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from cdpr_dynamics.analysis import (AnalysisError, Equilibrium, build_system, damping_for,
                                    equilibrium, new_tension_solver, sag_warnings)
from cdpr_dynamics.config import Settings
from cdpr_dynamics.dynamics import DynamicsError, Newmark, PlatformSystem
from cdpr_dynamics.feasibility import WrenchSet, cable_crossing
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.robot import GeometryError, geometry, quaternion_to_matrix, required_wrench

FALLBACK_METHOD = 'spring'
MAX_GAP_S = 1.0
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
        self.update_pose(settings.initial_position_m, rotation=settings.initial_rotation,
                         force=True)

    # ----------------------------------------------------------------------------- state

    def _moved(self, position, rotation) -> bool:
        if self.position_m is None:
            return True
        turn = np.arccos(np.clip((np.trace(self.rotation.T @ rotation) - 1) / 2, -1, 1))
        return (np.linalg.norm(position - self.position_m) > self.pose_tolerance_m
                or turn > self.angle_tolerance_rad)

    def update_pose(self, position_m, quaternion=None, rotation=None,
                    force: bool = False) -> PoseUpdate:
        """Move to a pose; raise :class:`AnalysisError` (state unchanged) if it cannot be used."""
        position = np.asarray(position_m, dtype=float)
        if rotation is None:
            rotation = np.eye(3) if quaternion is None else quaternion_to_matrix(quaternion)
        if not force and not self._moved(position, rotation):
            return PoseUpdate(False, self.last_update.method, self.last_update.dofs,
                              sag_parameter=self.last_update.sag_parameter)
        timings = {}
        start = time.perf_counter()
        self._check_cables(position, rotation)
        eq = equilibrium(self.settings, position, rotation, self._solver)
        s = self.settings        # the wrenches the cables can hold here (per state, not per wrench)
        wrench_set = WrenchSet(eq.geometry.structure_matrix, s.tension_min_n, s.tension_max_n,
                               required_wrench(s.robot, s.external_force_n, s.external_moment_nm))
        timings['tensions'] = time.perf_counter() - start
        start = time.perf_counter()
        system, warnings = self._build(eq)
        timings['model'] = time.perf_counter() - start
        start = time.perf_counter()
        integrator = self._integrator(system)
        timings['factorisation'] = time.perf_counter() - start
        self.eq, self.system, self.position_m, self.rotation = eq, system, position, rotation
        self.integrator = integrator
        self.wrench_set = wrench_set
        sag = sag_parameter(eq.cables)
        warnings += sag_warnings(self.settings, system.assembly.method, sag)
        self.last_update = PoseUpdate(True, system.assembly.method, system.dofs, timings,
                                      tuple(warnings), tuple(sag.tolist()))
        return self.last_update

    def _check_cables(self, position, rotation) -> None:
        """Raise :class:`AnalysisError` where cables would cross (clearance: cable diameter).

        Cables of a point mass all end at one point and cannot cross: nothing to check.
        """
        robot = self.settings.robot
        if robot.point_mass:
            return
        try:
            geo = geometry(robot, position, rotation)
        except GeometryError as exc:
            raise AnalysisError(str(exc)) from None
        clearance = 2.0 * np.sqrt(self.settings.cable.area_m2 / np.pi)
        reason = cable_crossing(robot.anchors_m, geo.position_m + geo.lever_m, clearance)
        if reason:
            raise AnalysisError(reason)

    def wrench_reason(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> str:
        """Why the cables cannot hold this external wrench at the current pose, or ''."""
        return self.wrench_set.reason(force_n, moment_nm)

    def _resolved_settings(self, eq: Equilibrium) -> Settings:
        """Settings with ``auto`` replaced by its choice, re-chosen only after the pose moved
        more than ``AUTO_RECHOOSE_M`` (the choice costs 10-20 ms; it varies slowly)."""
        s = self.settings
        if s.method != 'auto':
            return s
        moved = (self._choice is None or np.linalg.norm(eq.geometry.position_m
                                                         - self._choice_position) > AUTO_RECHOOSE_M)
        if moved:
            from cdpr_dynamics.selection import choose_model
            self._choice = choose_model(s, eq)
            self._choice_position = eq.geometry.position_m
        return s.replace(method=self._choice.method,
                         elements_per_cable=self._choice.elements_per_cable)

    def _build(self, eq: Equilibrium):
        """The configured model, or the spring fallback (with a warning) where it is invalid."""
        warnings = []
        try:
            system = build_system(self._resolved_settings(eq), eq)
            if system.assembly.valid:
                return system, list(system.assembly.warnings)
            warnings += system.assembly.warnings
            failed = system.assembly.method
        except (AnalysisError, DynamicsError, ValueError) as exc:
            warnings.append(str(exc))
            failed = self.settings.method
        system = build_system(self.settings, eq, method=FALLBACK_METHOD)
        if not system.assembly.valid:
            raise AnalysisError('no valid model for this pose: ' + '; '.join(
                system.assembly.warnings))
        warnings.append(f'method {failed} failed for this state; fell back to '
                        f'{FALLBACK_METHOD}')
        return system, warnings

    def _integrator(self, system: PlatformSystem) -> Newmark:
        s = self.settings
        k, m = system.matrices(dense=system.dofs <= DENSE_NEWMARK_DOFS)
        integrator = Newmark(k, m, damping_for(s, system), s.dt_s, s.newmark_alpha,
                             s.newmark_beta)
        old = self.integrator
        if old is not None and old.u.shape == integrator.u.shape:
            integrator.u, integrator.v, integrator.acc = old.u, old.v, old.acc
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
        older than the last one. A gap over ``MAX_GAP_S`` restarts from rest (the transient of
        an old wrench is long gone or meaningless).
        """
        stamp_ns = int(stamp_ns)
        nd = self.system.platform_dofs
        load = np.zeros(self.integrator.u.shape)
        load[:3] = force_n
        if nd == 6:
            load[3:6] = moment_nm
        if self._t_ns is not None and stamp_ns < self._t_ns:
            raise ValueError(f'stamp {stamp_ns * 1e-9:.9f} s is older than the last wrench '
                             f'({self._t_ns * 1e-9:.9f} s)')
        if self._t_ns is None or stamp_ns - self._t_ns > MAX_GAP_S * 1e9 or self._load is None \
                or self._load.shape != load.shape:
            self.integrator.reset()
            self._remainder_ns = 0
        else:
            dt_ns = max(1, round(self.settings.dt_s * 1e9))
            steps, self._remainder_ns = divmod(stamp_ns - self._t_ns + self._remainder_ns, dt_ns)
            for _ in range(steps):
                self.integrator.step(self._load)
        self._t_ns = stamp_ns
        self._load = load
        return self.integrator.u[:3].copy()

    def reset_time(self) -> None:
        """Forget the wrench history (e.g. after a jump back in time)."""
        self._t_ns = None
        self._load = None
