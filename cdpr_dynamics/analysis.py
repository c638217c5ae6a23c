"""The analysis pipeline shared by the node, the service, cdpr_analyze and cdpr_replay.

pose -> geometry -> tensions (QP) -> cable model -> platform system -> FRF, modes, time history.
Every step raises :class:`AnalysisError` with a one-line reason that names the cause.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics import models
from cdpr_dynamics.config import Settings
from cdpr_dynamics.dynamics import (Damping, DynamicsError, PlatformSystem, frequency_response,
                                    natural_frequencies, platform_frequencies, platform_system,
                                    rayleigh_from_modal_ratio)
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.robot import Geometry, GeometryError, geometry, required_wrench
from cdpr_dynamics.tensions import TensionResult, TensionSolver

HEAVY_DAMPING_RATIO = 1.0


class AnalysisError(RuntimeError):
    """An analysis that cannot be done for this scene; the message is one line."""


@dataclass(frozen=True, eq=False)
class Equilibrium:
    """Static state at one pose: geometry, tension distribution, and the cables for a model."""

    geometry: Geometry
    tensions: TensionResult
    cables: CableSet


def new_tension_solver(settings: Settings) -> TensionSolver:
    """A warm-startable QP for the robot of ``settings`` (C = I, c = 0)."""
    robot = settings.robot
    return TensionSolver(robot.n_cables, robot.platform_dofs, settings.tension_min_n,
                         settings.tension_max_n)


def equilibrium(settings: Settings, position_m=None, rotation=None,
                solver: TensionSolver | None = None) -> Equilibrium:
    """Tensions balancing gravity and the static ``load.*`` wrench at pose (p, R) (Eqs. 8-12)."""
    position = settings.initial_position_m if position_m is None else position_m
    rotation = settings.initial_rotation if rotation is None else rotation
    try:
        geo = geometry(settings.robot, position, rotation)
    except GeometryError as exc:
        raise AnalysisError(str(exc)) from None
    wrench = required_wrench(settings.robot, settings.external_force_n,
                             settings.external_moment_nm)
    result = (solver or new_tension_solver(settings)).solve(geo.structure_matrix, wrench)
    if not result.feasible:
        raise AnalysisError(f'infeasible tension distribution: {result.reason}')
    cables = CableSet(geo.chord_m, result.tension_n, settings.cable.ea_n,
                      settings.cable.weight_per_length_n_per_m, settings.robot.gravity_m_s2)
    return Equilibrium(geo, result, cables)


def build_system(settings: Settings, eq: Equilibrium, method: str | None = None,
                 elements_per_cable: int | None = None) -> PlatformSystem:
    """The platform system of ``method`` (default ``settings.method``) at ``eq``."""
    method = method or settings.method
    elements = elements_per_cable or settings.elements_per_cable
    if method == 'auto':
        from cdpr_dynamics.selection import choose_model
        choice = choose_model(settings, eq)
        method, elements = choice.method, choice.elements_per_cable
    try:
        assembly = models.build(method, eq.cables, elements)
    except ValueError as exc:
        raise AnalysisError(str(exc)) from None
    return platform_system(settings.robot, eq.geometry, assembly)


def damping_for(settings: Settings, system: PlatformSystem | None = None) -> Damping:
    """Rayleigh damping of the settings, or fitted to ``damping.modal_ratio`` when it is > 0.

    The fit puts the ratio at the lowest and at the highest platform mode below
    ``frf.f_max_hz`` (modes in between are damped a little less): the modes of the platform
    mass on the model's statically condensed cables, so every model of a scene gets the same
    damping (to the ~1 % its static stiffness differs by) and no cable mode decides it.
    """
    if settings.damping_modal_ratio <= 0.0:
        return Damping(settings.damping_mass_factor, settings.damping_stiffness_factor)
    if system is None:
        raise AnalysisError('damping.modal_ratio needs the model to fit Rayleigh factors')
    freqs = platform_frequencies(system)
    freqs = freqs[freqs > 0]
    if freqs.size == 0:
        raise AnalysisError('no positive platform mode to fit damping.modal_ratio to')
    in_band = freqs[freqs <= settings.f_max_hz]
    high = in_band[-1] if in_band.size else freqs[0]
    return rayleigh_from_modal_ratio(settings.damping_modal_ratio, freqs[0], high)


def damping_warnings(damping: Damping, frequency_hz: np.ndarray) -> list[str]:
    """Warn when modes are overdamped (zeta >= 1) by the damping setting."""
    ratios = damping.ratios(frequency_hz)
    heavy = frequency_hz[ratios >= HEAVY_DAMPING_RATIO]
    if heavy.size == 0:
        return []
    return [f'heavy damping: {heavy.size} of {frequency_hz.size} modes are overdamped '
            f'(zeta >= 1 from {heavy.min():.3g} Hz; zeta = {ratios.max():.3g} at '
            f'{frequency_hz[np.argmax(ratios)]:.3g} Hz)']


def sag_warnings(settings: Settings, method: str, sag_parameter: np.ndarray) -> list[str]:
    """Warn when a straight model ignores sag that matters at ``model.tolerance``.

    Irvine's effective modulus E/(1 + lambda^2/12) gives the axial stiffness a straight cable
    model overestimates by about lambda^2/12 (Irvine, Cable Structures, 1981, sec. 3.4).
    """
    worst = float(np.max(sag_parameter, initial=0.0))
    if method not in models.STRAIGHT_METHODS or not worst / 12.0 > settings.tolerance:
        return []
    error = f'~{100 * worst / 12.0:.3g} %' if worst < 12.0 else 'more than 100 %'
    return [f'sag: lambda^2 up to {worst:.3g}; {method} ignores sag and overestimates the axial '
            f'stiffness by {error} (> model.tolerance {100 * settings.tolerance:g} %): use '
            'catenary_exact or fem_sag']


FRF_ARRAYS = ('frequency_hz', 'amplitude_x_m', 'amplitude_y_m', 'amplitude_z_m', 'phase_x_rad',
              'phase_y_rad', 'phase_z_rad', 'log10_amplitude_z', 'natural_frequencies_hz')


def frf_arrays(settings: Settings, system: PlatformSystem) -> dict[str, np.ndarray]:
    """The FRF arrays of the service contract (SPEC section 5) for the settings' sweep."""
    damping = damping_for(settings, system)
    response = frequency_response(system, settings.frequencies_hz, settings.frf_force_n,
                                  damping=damping)
    amplitude, phase = response.amplitude_m, response.phase_rad
    with np.errstate(divide='ignore'):
        log_z = np.log10(amplitude[:, 2])
    return {
        'frequency_hz': response.frequency_hz,
        'amplitude_x_m': amplitude[:, 0], 'amplitude_y_m': amplitude[:, 1],
        'amplitude_z_m': amplitude[:, 2],
        'phase_x_rad': phase[:, 0], 'phase_y_rad': phase[:, 1], 'phase_z_rad': phase[:, 2],
        'log10_amplitude_z': log_z,
        'natural_frequencies_hz': natural_frequencies(system, 12),
    }


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
