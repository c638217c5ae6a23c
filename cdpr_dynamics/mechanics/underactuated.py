"""Underactuated robots: fewer cables than platform DOFs, held where gravity and cables balance.

A robot with n cables on a platform of d DOFs (d = 6 rigid, 3 point mass), n < d, has a
structure matrix W^T (d, n) whose range misses d - n wrench directions: the balance
W^T T = w (w = -(m g + f_e, (R c) x m g + tau_e), c the centre of mass in the platform frame)
holds only at poses where gravity and the static load fall in that range. Here:

* :func:`balance_tensions`: T by least squares, and the residual W^T T - w (the net force and
  moment on the platform); the pose is an equilibrium where it vanishes (``BALANCE_RTOL`` of
  the weight).
* :func:`geometrico_static`: elsewhere, the direct geometrico-static problem. The cable lengths
  L_i of the given pose are kept (inextensible cables) and the platform goes to the stable
  equilibrium with those lengths, a minimum of its potential energy

      U(q) = -m g . (p + R c) - f_e . p - tau_e . theta   subject to   |l_i(q)| = L_i,

  the tensions being the constraints' multipliers. Solved by a reduced Newton method: on the
  constraint manifold (each step restored onto it by Gauss-Newton on the lengths) the reduced
  force Z^T r (Z an orthonormal basis of the directions that keep every length to first order,
  r the net wrench) is driven to zero with the reduced Hessian Z^T K_g Z, K_g the loaded
  stiffness of rigid cables (:func:`loaded_stiffness` without the axial term), and a
  backtracking line search on U; a reduced Hessian that is not positive definite is shifted so
  that every step goes downhill.
* :func:`unstable_direction`: the full stiffness (the cables' axial and geometric stiffness and
  gravity's load stiffness: :func:`loaded_stiffness` with the axial term, or a model's static
  stiffness) must be positive definite; the direction where it is not is named.

Platform DOFs q = (u, theta): translation of the reference point and small rotation about it
(world frame), as in :mod:`cdpr_dynamics.dynamics.system`. The loaded stiffness is

    K = sum_i G_i^T (EA/L_i u_i u_i^T + T_i/L_i (I - u_i u_i^T)) G_i
        - sym(sum_i [f_i]x [r_i]x + [m g]x [R c]x)     (rotation block),

G_i = [I, -[r_i]x], f_i = T_i u_i: the cables' axial and geometric stiffness, the cable forces
turning with the platform and gravity's moment about the reference point (the load stiffness).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.mechanics.robot import (DOF_NAMES, Geometry, GeometryError, Robot, geometry,
                                           required_wrench, skew)
from cdpr_dynamics.models.base import axial_transverse

#: the pose is an equilibrium where |W^T T - w| is below this fraction of the weight
BALANCE_RTOL = 1e-9
#: the geometrico-static solve stops where the reduced force is below this fraction of it
SOLVE_RTOL = 1e-11
MAX_ITERATIONS = 100
MAX_HALVINGS = 30
RESTORE_ITERATIONS = 20
RESTORE_RTOL = 1e-13      # lengths kept to this fraction of each length
#: a pose this close to its equilibrium (m, rad) is taken without a warning (the JSON still
#: reports the distance)
CLOSE_M, CLOSE_RAD = 1e-4, 1e-4
#: the full stiffness is positive definite where its Jacobi-scaled eigenvalues all exceed this
STABILITY_RTOL = 1e-9


class UnderactuatedError(ValueError):
    """An underactuated pose with no usable equilibrium; the message is one line."""


@dataclass(frozen=True, eq=False)
class Balance:
    """The equilibrium an underactuated robot takes for a given pose.

    ``geometry`` at the equilibrium pose, ``tension_n`` (n,) its tensions, ``residual`` (d,)
    the net wrench W^T T - w left (N, N m), ``distance_m`` and ``angle_rad`` how far the
    equilibrium is from the given pose (0 where the given pose is one), ``iterations`` of the
    geometrico-static solve (0: the given pose balanced as it is).
    """

    geometry: Geometry
    tension_n: np.ndarray
    residual: np.ndarray
    distance_m: float
    angle_rad: float
    iterations: int

    @property
    def moved(self) -> bool:
        return self.iterations > 0

    @property
    def far(self) -> bool:
        """Further from the given pose than :data:`CLOSE_M` or :data:`CLOSE_RAD`."""
        return self.distance_m > CLOSE_M or self.angle_rad > CLOSE_RAD


def is_underactuated(robot: Robot) -> bool:
    """Fewer cables than platform DOFs (n < 6 on a rigid platform, n < 3 on a point mass)."""
    return robot.n_cables < robot.platform_dofs


def balance_tensions(structure_matrix: np.ndarray, wrench: np.ndarray):
    """(T (n,), residual (d,)): the least-squares tensions of W^T T = w (W^T of full column
    rank: the normal equations) and W^T T - w."""
    tension = np.linalg.solve(structure_matrix.T @ structure_matrix,
                              structure_matrix.T @ wrench)
    return tension, structure_matrix @ tension - wrench


def loaded_stiffness(robot: Robot, geo: Geometry, tension_n: np.ndarray,
                     ea_n: float | None = None) -> np.ndarray:
    """(d, d) stiffness of the platform on its cables and gravity (module docstring);
    ``ea_n`` None: inextensible cables (no axial term: the geometric and load stiffness).
    Pulleys and winch-side cable (``geo.anchor_end``) as the ``spring`` model takes them."""
    unit, length, end = geo.unit, geo.length_m, geo.anchor_end
    axial = 0.0 if ea_n is None else ea_n / (length if end is None
                                             else length + end.series_length_m)
    per_cable = axial_transverse(unit, axial, tension_n / length,
                                 None if end is None else end.plane_normal,
                                 None if end is None else tension_n / (length + end.pivot_m))
    g = geo.attachment_map()
    k = np.einsum('cia,cij,cjb->ab', g, per_cable, g)
    if not robot.point_mass:
        force = tension_n[:, None] * unit
        turn = np.einsum('cij,cjk->ik', skew(force), skew(geo.lever_m))
        weight = robot.mass_kg * np.asarray(robot.gravity_m_s2, dtype=float)
        turn += skew(weight) @ skew(geo.rotation @ robot.center_of_mass_m)
        k[3:, 3:] -= 0.5 * (turn + turn.T)
    return 0.5 * (k + k.T)


def unstable_direction(stiffness: np.ndarray) -> str:
    """'' where ``stiffness`` is positive definite, else a one-line reason naming the
    direction of its least (Jacobi-scaled) eigenvalue and the DOF it is mostly along."""
    diag = np.diag(stiffness).copy()
    if np.all(diag > 0.0):
        scale = 1.0 / np.sqrt(diag)
        values, vectors = np.linalg.eigh(stiffness * scale[:, None] * scale[None, :])
        if values[0] > STABILITY_RTOL:
            return ''
        direction = vectors[:, 0] * scale
        direction /= np.linalg.norm(direction)
        level = f'{values[0]:.3g} of its scale'
    else:
        k = int(np.argmin(diag))
        direction = np.eye(diag.size)[k]
        level = f'{diag[k]:.3g} on its diagonal'
    direction = direction * (1.0 if direction[np.argmax(np.abs(direction))] > 0 else -1.0)
    axis = DOF_NAMES[int(np.argmax(np.abs(direction)))]
    return (f'unstable: the loaded stiffness (cables and gravity) is not positive definite '
            f'along {np.round(direction, 3).tolist()} (mostly {axis}; {level}): the platform '
            'is not held in that direction')


def _rotation_matrix(theta_rad: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``theta_rad`` (Rodrigues)."""
    angle = float(np.linalg.norm(theta_rad))
    if angle < 1e-300:
        return np.eye(3)
    k = skew(np.asarray(theta_rad, dtype=float) / angle)
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


class _Pose:
    """A trial pose of the geometrico-static solve: position, rotation, accumulated rotation
    vector (for the external moment's work) and its geometry."""

    def __init__(self, robot: Robot, position, rotation, theta):
        self.position, self.rotation, self.theta = position, rotation, theta
        self.geo = geometry(robot, position, None if robot.point_mass else rotation)

    def moved(self, robot: Robot, step: np.ndarray) -> '_Pose':
        if robot.point_mass:
            return _Pose(robot, self.position + step, self.rotation, self.theta)
        return _Pose(robot, self.position + step[:3],
                     _rotation_matrix(step[3:]) @ self.rotation, self.theta + step[3:])


def _restore(robot: Robot, pose: _Pose, lengths_m: np.ndarray) -> _Pose | None:
    """The pose moved back onto the cable lengths L_i by Gauss-Newton (least-norm steps), or
    None."""
    for _ in range(RESTORE_ITERATIONS):
        miss = pose.geo.cable_length_m - lengths_m
        if np.all(np.abs(miss) <= RESTORE_RTOL * lengths_m):
            return pose
        wt = pose.geo.structure_matrix                # dL/dq = -W: W dq = miss
        step = wt @ np.linalg.solve(wt.T @ wt, miss)
        try:
            pose = pose.moved(robot, step)
        except GeometryError:
            return None
    return None


def _energy(robot: Robot, pose: _Pose, force_n: np.ndarray, moment_nm: np.ndarray) -> float:
    """Potential energy (J) of gravity at the centre of mass and of the static load."""
    weight = robot.mass_kg * np.asarray(robot.gravity_m_s2, dtype=float)
    energy = -float((weight + force_n) @ pose.position)
    if not robot.point_mass:
        energy -= float(weight @ (pose.rotation @ robot.center_of_mass_m))
        energy -= float(moment_nm @ pose.theta)
    return energy


def _scale(robot: Robot, geo: Geometry, wrench: np.ndarray) -> np.ndarray:
    """(d,) the size of the net wrench's components that counts as zero: the weight (N) and
    the weight times the largest lever arm (N m)."""
    weight = max(float(np.linalg.norm(wrench[:3])), 1e-12)
    arm = max(float(np.max(np.linalg.norm(geo.lever_m, axis=1), initial=0.0)),
              float(np.linalg.norm(robot.center_of_mass_m)), 1e-3)
    return np.array([weight] * 3 + [weight * arm] * (wrench.size - 3))


def geometrico_static(robot: Robot, position_m, rotation=None,
                      external_force_n=(0.0, 0.0, 0.0),
                      external_moment_nm=(0.0, 0.0, 0.0)) -> Balance:
    """The stable equilibrium with the cable lengths of pose (p, R) (module docstring).

    Raises :class:`UnderactuatedError` where the solve does not converge or a cable would
    leave its constraint (a length that cannot be kept)."""
    force = np.asarray(external_force_n, dtype=float)
    moment = np.asarray(external_moment_nm, dtype=float)
    start = _Pose(robot, np.asarray(position_m, dtype=float).reshape(3),
                  np.eye(3) if rotation is None else np.asarray(rotation, dtype=float),
                  np.zeros(3))
    lengths = start.geo.cable_length_m.copy()
    weight = robot.mass_kg * np.asarray(robot.gravity_m_s2, dtype=float)
    round_off = 1e-13 * float(np.linalg.norm(weight + force)) * float(lengths.max())
    pose, iterations = start, 0
    while True:
        geo = pose.geo
        wrench = required_wrench(robot, force, moment, pose.rotation)
        tension, residual = balance_tensions(geo.structure_matrix, wrench)
        free = np.linalg.svd(geo.structure_matrix)[0][:, robot.n_cables:]   # lengths kept
        reduced = free.T @ residual
        if np.all(np.abs(free @ reduced) <= SOLVE_RTOL * _scale(robot, geo, wrench)):
            break
        if iterations == MAX_ITERATIONS:
            raise UnderactuatedError(
                f'the geometrico-static solve did not converge in {MAX_ITERATIONS} iterations '
                f'(net wrench {np.round(residual, 6).tolist()} left)')
        iterations += 1
        hessian = free.T @ loaded_stiffness(robot, geo, tension) @ free
        values, vectors = np.linalg.eigh(hessian)
        floor = 1e-8 * max(float(np.abs(values).max()), 1e-12)
        values = np.maximum(np.abs(values), floor)      # downhill along every eigenvector
        step = free @ (vectors @ ((vectors.T @ reduced) / values))
        energy = _energy(robot, pose, force, moment)
        slope = -float(residual @ step)                 # dU along the step
        alpha = 1.0
        for _ in range(MAX_HALVINGS):
            try:
                trial = _restore(robot, pose.moved(robot, alpha * step), lengths)
            except GeometryError:
                trial = None
            if trial is not None and _energy(robot, trial, force, moment) \
                    <= energy + 1e-4 * alpha * slope + round_off:
                break
            alpha *= 0.5
        else:
            raise UnderactuatedError('the geometrico-static solve found no downhill step from '
                                     f'{np.round(pose.position, 4).tolist()} m')
        pose = trial
    turn = start.rotation.T @ pose.rotation
    angle = math.acos(min(1.0, max(-1.0, (float(np.trace(turn)) - 1.0) / 2.0)))
    return Balance(pose.geo, tension, residual,
                   float(np.linalg.norm(pose.position - start.position)), angle, iterations)


def balance(robot: Robot, geo: Geometry, tension_min_n: float, tension_max_n: float,
            external_force_n=(0.0, 0.0, 0.0), external_moment_nm=(0.0, 0.0, 0.0)) -> Balance:
    """The equilibrium of an underactuated robot for the pose of ``geo``: that pose where it
    balances, else :func:`geometrico_static`'s; checked for slack and the tension bound
    (raises :class:`UnderactuatedError` naming the cable). Its stability is the caller's
    check, on the stiffness of its model (:func:`unstable_direction`)."""
    wrench = required_wrench(robot, external_force_n, external_moment_nm, geo.rotation)
    tension, residual = balance_tensions(geo.structure_matrix, wrench)
    if np.all(np.abs(residual) <= BALANCE_RTOL * _scale(robot, geo, wrench)):
        found = Balance(geo, tension, residual, 0.0, 0.0, 0)
    else:
        found = geometrico_static(robot, geo.position_m, geo.rotation, external_force_n,
                                  external_moment_nm)
    low = int(np.argmin(found.tension_n))
    if not found.tension_n[low] >= tension_min_n:
        where = ('at the equilibrium with the cable lengths of the pose, '
                 f'{found.distance_m:.4g} m away, ' if found.moved else '')
        raise UnderactuatedError(
            f'cable {low} is slack {where}(tension {found.tension_n[low]:.4g} N < '
            f'tension.min_n {tension_min_n:g} N)')
    high = int(np.argmax(found.tension_n))
    if found.tension_n[high] > tension_max_n:
        raise UnderactuatedError(f'infeasible tension distribution: cable {high} needs '
                                 f'{found.tension_n[high]:.4g} N > tension.max_n '
                                 f'{tension_max_n:g} N to hold the platform')
    return found


class HeldWrenchSet:
    """The external wrenches an underactuated robot's cables hold at an equilibrium, with the
    interface of :class:`~cdpr_dynamics.mechanics.feasibility.WrenchSet`.

    n < d cables produce only the wrenches in the range of W^T; the rest of an external wrench
    moves the platform along the directions they leave free, where gravity's restoring
    stiffness takes it. The part in the range fixes the tensions, T = (W^T)^+ (w - f) (unique:
    W^T has full column rank), and the wrench is held while they stay in [T_min, T_max].
    """

    exact = True

    def __init__(self, structure_matrix, t_min_n: float, t_max_n: float, required,
                 tolerance_n: float = 1e-6):
        self.wt = np.asarray(structure_matrix, dtype=float)
        self.required = np.asarray(required, dtype=float)
        self.t_min_n, self.t_max_n = float(t_min_n), float(t_max_n)
        self._pinv = np.linalg.pinv(self.wt)
        self.tension_n = self._pinv @ self.required
        self.tolerance = tolerance_n * max(1.0, float(np.abs(self.required).max()), t_max_n)
        self.lp_calls = 0

    def _external(self, force_n, moment_nm) -> np.ndarray:
        f = np.concatenate([np.asarray(force_n, dtype=float).reshape(3),
                            np.asarray(moment_nm, dtype=float).reshape(3)])
        return f[:self.required.size]

    def tensions(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> np.ndarray:
        """(n,) the tensions holding the external wrench's part in the range of W^T."""
        return self.tension_n - self._pinv @ self._external(force_n, moment_nm)

    def margin(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> float:
        """Least distance (N) of a tension from the box; < 0: outside."""
        t = self.tensions(force_n, moment_nm)
        return float(min(np.min(t - self.t_min_n), np.min(self.t_max_n - t)))

    def reason(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> str:
        """Why the cables cannot hold the external wrench within the box, or ``''``."""
        t = self.tensions(force_n, moment_nm)
        if not np.isfinite(t).all():
            return 'wrench is not finite'
        low, high = int(np.argmin(t)), int(np.argmax(t))
        if t[low] < self.t_min_n - self.tolerance:
            return (f'wrench outside the feasible set: cable {low} would need {t[low]:.4g} N '
                    f'< tension.min_n {self.t_min_n:g} N')
        if t[high] > self.t_max_n + self.tolerance:
            return (f'wrench outside the feasible set: cable {high} would need {t[high]:.4g} N '
                    f'> tension.max_n {self.t_max_n:g} N')
        return ''

    def symmetric_limit(self, force_n, moment_nm=(0.0, 0.0, 0.0)) -> float:
        """The largest s >= 0 with both +s f and -s f held (closed form per cable)."""
        room = np.minimum(self.tension_n - self.t_min_n, self.t_max_n - self.tension_n)
        if room.min() < 0.0:
            return 0.0
        change = np.abs(self._pinv @ self._external(force_n, moment_nm))
        bounded = change > 1e-12 * max(float(change.max(initial=0.0)), 1e-300)
        if not np.any(bounded):
            return math.inf
        return float(np.min(room[bounded] / change[bounded]))
