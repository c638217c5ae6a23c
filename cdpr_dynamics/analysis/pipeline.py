"""The analysis pipeline shared by the node, the service, cdpr_analyze and cdpr_replay.

pose -> geometry -> tensions (QP) -> cable model -> platform system -> FRF, modes, time history.
Every step raises :class:`AnalysisError` with a one-line reason that names the cause.
"""
from __future__ import annotations

import math
import time

import numpy as np

from cdpr_dynamics import models
from cdpr_dynamics.analysis.config import Settings
from cdpr_dynamics.dynamics.system import (Damping, DynamicsError, PlatformSystem,
                                           configured_damping, frequency_response, platform_system)
from cdpr_dynamics.mechanics.feasibility import cable_crossing
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.models.catenary import (end_position, paper_misclosure, sag_parameter,
                                           up_and_weight)
from cdpr_dynamics.mechanics.robot import (WRENCH_AXES, Geometry, GeometryError, geometry,
                                           matrix_to_quaternion, required_wrench,
                                           singular_values, skew)
from cdpr_dynamics.selection.auto import choose_model
from cdpr_dynamics.mechanics.statics import Equilibrium, StaticsError, equilibrium_for
from cdpr_dynamics.mechanics.tensions import TensionResult, TensionSolver
from cdpr_dynamics.mechanics.underactuated import (Balance, UnderactuatedError, balance,
                                                   is_underactuated, unstable_direction)

HEAVY_DAMPING_RATIO = 1.0


class AnalysisError(RuntimeError):
    """An analysis that cannot be done for this scene; the message is one line."""


def new_tension_solver(settings: Settings) -> TensionSolver:
    """A warm-startable QP for the robot of ``settings`` (C = I, c = 0)."""
    robot = settings.robot
    return TensionSolver(robot.n_cables, robot.platform_dofs, settings.tension_min_n,
                         settings.tension_max_n)


RANK_TOLERANCE = 1e-9     # singular values below this times the largest count as zero


def structure_rank(structure_matrix: np.ndarray) -> tuple[int, float, np.ndarray]:
    """(rank, condition number, the least reachable unit wrench direction) of W^T."""
    u, sing, _ = np.linalg.svd(structure_matrix)
    rank = int(np.sum(sing > RANK_TOLERANCE * sing[0])) if sing.size else 0
    condition = float(sing[0] / sing[-1]) if sing.size and sing[-1] > 0 else float('inf')
    return rank, condition, u[:, -1]


def _check_design(settings: Settings, geo: Geometry) -> None:
    """Refuse a structure matrix of rank below min(cables, platform DOFs) (fewer cables than
    DOFs is an underactuated robot, held by gravity), and crossing cables."""
    full = min(settings.robot.platform_dofs, settings.robot.n_cables)
    sing = singular_values(geo.structure_matrix).tolist()                  # descending
    if len(sing) < full or not sing[full - 1] > RANK_TOLERANCE * sing[0]:    # rank short:
        rank, _, direction = structure_rank(geo.structure_matrix)      # only then the vectors
        axis = WRENCH_AXES[int(np.argmax(np.abs(direction)))]
        raise AnalysisError(f'the structure matrix has rank {rank} < {full} '
                            f'(min of {settings.robot.n_cables} cables and '
                            f'{settings.robot.platform_dofs} platform DOFs): no '
                            f'cable tensions produce a wrench along '
                            f'{np.round(direction, 3).tolist()} (mostly {axis}), so the '
                            'platform is not held in that direction')
    if not settings.robot.point_mass:   # a point mass's cables all end at one point
        clearance = 2.0 * np.sqrt(settings.cable.area_m2 / np.pi)
        attachments = geo.position_m + geo.lever_m
        # the free spans: from each attachment to its exit point (the anchor without a pulley)
        reason = cable_crossing(attachments + geo.chord_m, attachments, clearance)
        if reason:
            raise AnalysisError(reason)


def equilibrium(settings: Settings, position_m=None, rotation=None,
                solver: TensionSolver | None = None, method: str | None = None,
                start: Equilibrium | None = None) -> Equilibrium:
    """Tensions balancing gravity and the static ``load.*`` wrench at pose (p, R).

    The chord statics of Eqs. 8-12, and for a sag-aware ``method`` (:data:`SAG_METHODS`) the
    sag-consistent statics started from it (warm-started from ``start``, e.g. the previous
    pose). An underactuated robot (:mod:`cdpr_dynamics.mechanics.underactuated`) takes its
    tensions from the balance, at the equilibrium with the pose's cable lengths where the pose
    is not one (``balance``, warned). Refuses (AnalysisError) a zero-length cable, crossing
    cables, a structure matrix of rank below min(cables, DOFs), an infeasible distribution
    and, underactuated, a slack cable or an unstable equilibrium.
    """
    position = settings.initial_position_m if position_m is None else position_m
    rotation = settings.initial_rotation if rotation is None else rotation
    try:
        geo = geometry(settings.robot, position, rotation)
    except GeometryError as exc:
        raise AnalysisError(str(exc)) from None
    _check_design(settings, geo)
    held = None
    if is_underactuated(settings.robot):
        held = _underactuated_balance(settings, geo)
        geo, residual = held.geometry, held.residual
        result = TensionResult.solved(held.tension_n, float(np.abs(residual).max()), 0.0, 0.0)
    else:
        wrench = required_wrench(settings.robot, settings.external_force_n,
                                 settings.external_moment_nm, geo.rotation)
        result = (solver or new_tension_solver(settings)).solve(geo.structure_matrix, wrench)
        if not result.feasible:
            raise AnalysisError(f'infeasible tension distribution: {result.reason}')
        residual = geo.structure_matrix @ result.tension_n - wrench
    cables = CableSet(geo.chord_m, result.tension_n, settings.cable.ea_n,
                      settings.cable.weight_per_length_n_per_m, settings.robot.gravity_m_s2,
                      anchor_end=geo.anchor_end)
    # its cached length_m and unit are the geometry's (the same numbers: |l_i|, l_i / |l_i|)
    cables.__dict__.update(length_m=geo.length_m, unit=geo.unit)
    ea = settings.cable.ea_n
    chord = Equilibrium(geo, result, cables, 'chord', result.tension_n[:, None] * geo.unit,
                        geo.length_m * ea / (ea + result.tension_n),
                        residual, result.iterations, balance_warnings(held), balance=held)
    if held is not None:        # gravity and the cables hold the free directions?
        spring = platform_system(settings.robot, geo, models.build('spring', cables))
        reason = unstable_direction(spring.static_stiffness())
        if reason:
            raise AnalysisError(reason)
    try:
        return equilibrium_for(settings, chord, method, start)
    except StaticsError as exc:
        raise AnalysisError(str(exc)) from None


def _underactuated_balance(settings: Settings, geo: Geometry) -> Balance:
    """:func:`cdpr_dynamics.mechanics.underactuated.balance` for ``settings``' robot, its
    refusals as AnalysisError; the equilibrium's geometry checked as the given pose's is."""
    try:
        held = balance(settings.robot, geo, settings.tension_min_n, settings.tension_max_n,
                       settings.external_force_n, settings.external_moment_nm)
    except (UnderactuatedError, GeometryError) as exc:
        raise AnalysisError(str(exc)) from None
    if held.moved:
        _check_design(settings, held.geometry)
    return held


def balance_warnings(held: Balance | None) -> tuple[str, ...]:
    """The warning that the pose was not an equilibrium of the underactuated robot, with the
    distance to the one analysed (not where it is within 0.1 mm and 0.1 mrad)."""
    if held is None or not held.far:
        return ()
    return (f'underactuated: the pose is not an equilibrium; analysed at the equilibrium with '
            f'its cable lengths, {np.round(held.geometry.position_m, 4).tolist()} m, '
            f'{held.distance_m:.4g} m and {math.degrees(held.angle_rad):.3g} deg away',)


def equilibrium_summary(settings: Settings, eq: Equilibrium) -> dict:
    """The JSON ``equilibrium`` block of ``cdpr_analyze``: residuals and per-cable statics."""
    residual = np.asarray(eq.residual, dtype=float)
    weight = float(np.linalg.norm(required_wrench(settings.robot, settings.external_force_n,
                                                  settings.external_moment_nm)[:3]))
    arm = float(np.linalg.norm(eq.geometry.lever_m, axis=1).max(initial=0.0))
    force = float(np.linalg.norm(residual[:3]))
    moment = float(np.linalg.norm(residual[3:])) if residual.size > 3 else 0.0
    scale = weight if weight > 0 else settings.tension_max_n
    relative = max(force, moment / arm if arm > 0 else 0.0) / scale
    summary = {'statics': eq.statics, 'residual_n': force, 'residual_nm': moment,
               'relative_residual': relative, 'iterations': int(eq.iterations),
               'end_force_n': np.asarray(eq.end_force_n).tolist(),
               'unstretched_length_m': np.asarray(eq.unstretched_length_m).tolist()}
    if eq.balance is not None:
        held = eq.balance
        summary['underactuated'] = {
            'position_m': held.geometry.position_m.tolist(),
            'orientation': matrix_to_quaternion(held.geometry.rotation).tolist(),
            'distance_m': held.distance_m, 'angle_rad': held.angle_rad,
            'moved': held.moved, 'iterations': held.iterations}
    return summary


def build_system(settings: Settings, eq: Equilibrium, method: str | None = None,
                 elements_per_cable: int | None = None) -> PlatformSystem:
    """The platform system of ``method`` (default ``settings.method``) at ``eq``, linearised
    about the statics the method needs (:func:`equilibrium_for`: a sag-aware model at a chord
    equilibrium is built at the sag-consistent one; callers that report tensions convert
    ``eq`` themselves first)."""
    method = method or settings.method
    elements = elements_per_cable or settings.elements_per_cable
    if method == 'auto':
        choice = choose_model(settings, eq)
        method, elements = choice.method, choice.elements_per_cable
    try:
        eq = equilibrium_for(settings, eq, method)
        assembly = models.build(method, eq.cables, elements)
    except ValueError as exc:           # StaticsError too
        raise AnalysisError(str(exc)) from None
    return platform_system(settings.robot, eq.geometry, assembly)


def damping_for(settings: Settings, system: PlatformSystem | None = None) -> Damping:
    """:func:`cdpr_dynamics.dynamics.system.configured_damping`, its failures as AnalysisError."""
    try:
        return configured_damping(settings, system)
    except DynamicsError as exc:
        raise AnalysisError(str(exc)) from None


def damping_warnings(damping: Damping, frequency_hz: np.ndarray) -> list[str]:
    """Warn when modes are overdamped (zeta >= 1) by the damping setting."""
    ratios = damping.ratios(frequency_hz)
    heavy = frequency_hz[ratios >= HEAVY_DAMPING_RATIO]
    if heavy.size == 0:
        return []
    return [f'heavy damping: {heavy.size} of {frequency_hz.size} modes are overdamped '
            f'(zeta >= 1 from {heavy.min():.3g} Hz; zeta = {ratios.max():.3g} at '
            f'{frequency_hz[np.argmax(ratios)]:.3g} Hz)']


def geometry_summary(eq: Equilibrium, samples: int = 65) -> dict:
    """The JSON ``geometry`` block: structure-matrix rank and condition number, and per cable
    the largest distance (m) of its static shape from the chord (0 for straight statics; the
    elastic catenary at the sag-consistent tensions), sampled at ``samples`` points."""
    rank, condition, _ = structure_rank(eq.geometry.structure_matrix)
    sag = np.zeros(eq.cables.n_cables)
    if eq.statics == 'sag':
        shape = cable_shapes(eq, samples)                  # (n, samples, 3), from the platform
        chord = np.asarray(eq.cables.chord_m)
        along = np.clip(np.einsum('nsk,nk->ns', shape, chord) / np.sum(chord * chord, axis=1)
                        [:, None], 0.0, 1.0)
        sag = np.linalg.norm(shape - along[..., None] * chord[:, None, :], axis=2).max(axis=1)
    return {'structure_matrix_rank': rank, 'structure_matrix_condition': condition,
            'max_sag_m': sag.tolist()}


def cable_shapes(eq: Equilibrium, samples: int = 65) -> np.ndarray:
    """(n, samples, 3) points of each cable's static shape relative to its attachment, from
    the platform end (point 0) to the anchor: the elastic catenary of a sag equilibrium, the
    chord otherwise."""
    t = np.linspace(0.0, 1.0, samples)
    chord = np.asarray(eq.cables.chord_m, dtype=float)
    if eq.statics != 'sag':
        return t[None, :, None] * chord[:, None, :]
    state = eq.sag.state
    up, gamma = up_and_weight(eq.cables)
    sigma = state.unstrained_length_m[:, None] * t[None, :]
    force = np.broadcast_to(state.force_n[:, None, :], sigma.shape + (3,))
    return -end_position(force, sigma, eq.cables.ea_n, gamma, up)


def model_warnings(settings: Settings, eq: Equilibrium, assembly) -> list[str]:
    """Warnings on how well the model of ``assembly`` describes the state ``eq``.

    The statics' own warnings (e.g. a lifted lower tension bound), and where its error exceeds
    ``model.tolerance``:

    * a straight model (spring, fem, dsm) ignores sag: Irvine's effective modulus
      E/(1 + lambda^2/12) says it overestimates the axial stiffness by about lambda^2/12
      (Irvine, Cable Structures, 1981, sec. 3.4);
    * fem_sag with n elements resolves the sag compliance up to (1 - 1/n^2) (the midpoint rule
      of n straight elements), an axial stiffness error of
      (lambda^2/(12 n^2)) / (1 + lambda^2 (1 - 1/n^2)/12): n = 1 is the straight chord;
    * the paper's catenary takes L0 = chord and the end force along the chord: its catenary
      misses the anchor by :func:`~cdpr_dynamics.models.catenary.paper_misclosure`, warned
      above ``model.tolerance`` of the chord.
    """
    warnings = list(eq.warnings)
    lam2 = sag_parameter(eq.cables)
    worst = float(lam2.max(initial=0.0))
    tol = settings.tolerance
    method, n = assembly.method, assembly.elements_per_cable
    if method in models.STRAIGHT_METHODS and worst / 12.0 > tol:
        error = f'~{100 * worst / 12.0:.3g} %' if worst < 12.0 else 'more than 100 %'
        warnings.append(f'sag: lambda^2 up to {worst:.3g}; {method} ignores sag and '
                        f'overestimates the axial stiffness by {error} (> model.tolerance '
                        f'{100 * tol:g} %): use catenary_exact or fem_sag')
    if method == 'fem_sag' and math.isfinite(worst):
        error = (worst / (12.0 * n * n)) / (1.0 + worst * (1.0 - 1.0 / (n * n)) / 12.0)
        if error > tol:
            size = f'~{100 * error:.3g} %' if error < 1.0 else 'more than 100 %'
            warnings.append(f'sag: lambda^2 up to {worst:.3g}; fem_sag with {n} element'
                            f'{"s" if n > 1 else ""} per cable under-resolves the sag and '
                            f'overestimates the axial stiffness by {size} (> model.tolerance '
                            f'{100 * tol:g} %): use more elements')
    if method == 'catenary':
        miss = paper_misclosure(eq.cables) / eq.geometry.length_m
        i = int(np.argmax(miss))
        if miss[i] > tol:
            warnings.append(f'catenary: the paper\'s assumed catenary of cable {i} (L0 = chord, '
                            f'end force along the chord) misses its anchor by '
                            f'{miss[i] * eq.geometry.length_m[i]:.3g} m ({100 * miss[i]:.3g} % '
                            f'of the chord > model.tolerance {100 * tol:g} %): use '
                            'catenary_exact')
    return warnings


ROTATION_ARRAYS = ('rotation_x_rad', 'rotation_y_rad', 'rotation_z_rad')
MODE_ARRAYS = ('platform_natural_frequencies_hz', 'mode_platform_fraction')
FRF_ARRAYS = ('frequency_hz', 'amplitude_x_m', 'amplitude_y_m', 'amplitude_z_m', 'phase_x_rad',
              'phase_y_rad', 'phase_z_rad', 'log10_amplitude_z',
              'natural_frequencies_hz') + ROTATION_ARRAYS + MODE_ARRAYS
POINT_MASS_ROTATION = 'a point-mass platform has no rotation DOFs'


def point_map(rotation: np.ndarray, point_m, platform_dofs: int) -> np.ndarray:
    """(3, ndof) map of the platform DOFs q = (u, theta) to the displacement of a point.

    d = u + theta x r = [I, -[r]x] q with r = R b the point ``point_m`` (b, platform frame,
    m) in the world frame; a point-mass platform (3 DOFs) moves every point by u.
    """
    out = np.zeros((3, platform_dofs))
    out[:, :3] = np.eye(3)
    if platform_dofs == 6:
        out[:, 3:] = -skew(np.asarray(rotation, dtype=float) @ np.asarray(point_m, dtype=float))
    return out


def point_displacement(q, rotation: np.ndarray, point_m) -> np.ndarray:
    """Displacement (..., 3) of the point ``point_m`` (platform frame, m) for platform
    DOFs ``q`` (..., ndof): u + theta x (R b); exactly u where b = 0."""
    q = np.asarray(q)
    if q.shape[-1] == 3 or not np.any(point_m):
        return q[..., :3].copy()
    out = np.einsum('ia,...a->...i', point_map(rotation, point_m, q.shape[-1]), q)
    singular = ~np.all(np.isfinite(q), axis=-1)         # an undamped resonance: inf, not nan
    out[singular] = np.inf
    return out


def receptance(system: PlatformSystem, frequency_hz, damping) -> np.ndarray:
    """H(w) = Z(w)^-1 (nf, ndof, ndof) complex: platform-DOF response per unit force (N) and
    moment (N m), m/N, m/(N m), rad/N, rad/(N m); inf where Z(w) is singular (undamped, at a
    resonance). Symmetric (reciprocity): Z is."""
    f = np.atleast_1d(np.asarray(frequency_hz, dtype=float))
    nd = system.platform_dofs
    columns = [frequency_response(system, f, np.eye(6)[j, :3], np.eye(6)[j, 3:],
                                  damping=damping) for j in range(nd)]
    return np.stack([c.response for c in columns], axis=2)


def frf_response(settings: Settings, system: PlatformSystem, damping=None):
    """The platform-DOF response (nf, ndof) to ``frf.force_n`` and ``frf.moment_nm`` over the
    settings' sweep, and the point ``frf.point_m``'s translation (nf, 3)."""
    damping = damping_for(settings, system) if damping is None else damping
    response = frequency_response(system, settings.frequencies_hz, settings.frf_force_n,
                                  settings.frf_moment_nm, damping=damping)
    point = point_displacement(response.response, system.geometry.rotation,
                               settings.frf_point_m)
    return response, point


def system_modes(settings: Settings, system: PlatformSystem, shapes: bool = False):
    """Classified modes (:func:`cdpr_dynamics.dynamics.modes.modes`) up to ``frf.f_max_hz``, at
    least
    the 12 lowest, by Wittrick-Williams counting (every model, ``dsm`` included); ``shapes``:
    with the mode shapes of every DOF (dense or Lanczos path; not for ``dsm``)."""
    from cdpr_dynamics.dynamics.modes import modes
    return modes(system, settings.f_max_hz, shapes=shapes)


def frf_arrays(settings: Settings, system: PlatformSystem, found=None) -> dict:
    """The FRF arrays of the service contract (doc/node_interface.md) for the settings' sweep.

    Amplitudes and phases are those of ``frf.point_m`` (u + theta x R b); rotations (6-DOF
    platforms) of the platform; a name whose array cannot exist maps to its reason (str).
    ``found``: the system's modes (:func:`system_modes`) where the caller has them.
    """
    response, point = frf_response(settings, system)
    amplitude, phase = np.abs(point), np.angle(point)
    with np.errstate(divide='ignore'):
        log_z = np.log10(amplitude[:, 2])
    found = system_modes(settings, system) if found is None else found
    arrays = {
        'frequency_hz': response.frequency_hz,
        'amplitude_x_m': amplitude[:, 0], 'amplitude_y_m': amplitude[:, 1],
        'amplitude_z_m': amplitude[:, 2],
        'phase_x_rad': phase[:, 0], 'phase_y_rad': phase[:, 1], 'phase_z_rad': phase[:, 2],
        'log10_amplitude_z': log_z,
    }
    arrays['natural_frequencies_hz'] = found.frequency_hz
    arrays['platform_natural_frequencies_hz'] = found.platform_hz
    arrays['mode_platform_fraction'] = found.platform_fraction
    for axis, name in enumerate(ROTATION_ARRAYS):
        arrays[name] = (np.abs(response.response[:, 3 + axis]) if system.platform_dofs == 6
                        else POINT_MASS_ROTATION)
    return arrays


class Stopwatch:
    """Accumulates wall-clock seconds per named stage."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def __call__(self, name: str):
        watch = self

        class _Stage:
            def __enter__(self):
                self.start = time.perf_counter()

            def __exit__(self, *exc):
                watch.seconds[name] = watch.seconds.get(name, 0.0) + time.perf_counter() - \
                    self.start
        return _Stage()


def safe(call, *args, **kwargs):
    """Run a library call, turning numerical failures into :class:`AnalysisError`."""
    try:
        return call(*args, **kwargs)
    except (DynamicsError, np.linalg.LinAlgError, ValueError) as exc:
        raise AnalysisError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) \
            from None
