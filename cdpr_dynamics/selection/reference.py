"""The yardstick of ``auto``: a reference solution of a scene and the measured error of a model.

:func:`reference_solution` is ``dsm`` (exact straight continuous cables) where the sag is
negligible (its estimated effect below a tenth of ``model.tolerance``), otherwise ``fem_sag`` at
n and 2n elements, Richardson-extrapolated (its n^-2 error removed). :func:`measure_error`
solves a model (FRF on the sweep, modes in the band) and compares: natural frequencies paired in
ascending order (a missed mode 100 %) and the damped complex FRF of the centroid, max relative
error over the sweep and over the loads the estimates cover (the configured force and unit
forces along x, y, z: :func:`cdpr_dynamics.selection.estimates.frf_loads`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics import models
from cdpr_dynamics.selection.closed_forms import Scene, SelectionError, largest_phase
from cdpr_dynamics.dynamics.system import (DENSE_EIGEN_DOFS, Damping, PlatformSystem,
                                           platform_system)
from cdpr_dynamics.selection.estimates import (MISSED, Estimator, band_damping, load_responses,
                                               percent)
from cdpr_dynamics.dynamics.modes import natural_frequencies
from cdpr_dynamics.mechanics.statics import equilibrium_for

SAG_NEGLIGIBLE = 0.1          # sag negligible for the yardstick below this fraction of tolerance
REFERENCE_DISPERSION = 1e-3   # fem_sag reference: dispersion error at n before extrapolation
REFERENCE_MIN_ELEMENTS = 32
REFERENCE_MAX_ELEMENTS = 512
BEYOND_BAND = 1.5             # reference modes are computed up to this times f_max


@dataclass(frozen=True, eq=False)
class Reference:
    """The solution models are measured against, on the band [0, f_max].

    ``frequencies_hz`` holds every natural frequency up to ``BEYOND_BAND * f_max`` (ascending),
    ``response`` the damped complex FRF of the centroid (nf, 3, 4: per load of
    :func:`~cdpr_dynamics.selection.estimates.frf_loads`) on ``frequency_grid_hz``;
    ``uncertainty`` is the estimated relative error of the reference itself.
    """

    label: str
    method: str
    elements_per_cable: int
    f_max_hz: float
    frequencies_hz: np.ndarray
    frequency_grid_hz: np.ndarray
    response: np.ndarray
    damping: Damping
    sag_effect: float             # estimated error of straight exact cables (dsm) on this band
    uncertainty: float

    @property
    def modes_in_band(self) -> int:
        return int(np.sum(self.frequencies_hz <= self.f_max_hz))


@dataclass(frozen=True, eq=False)
class Solution:
    """One model's answer: its system, FRF (nf, 3, 4) complex and lowest natural frequencies."""

    system: PlatformSystem
    response: np.ndarray
    frequencies_hz: np.ndarray


@dataclass(frozen=True)
class Measured:
    """Errors of one model against a :class:`Reference`, relative: the frequency error counts a
    missed mode 100 % (ascending pairs mean nothing past one), the FRF error is not capped."""

    method: str
    elements_per_cable: int
    dofs: int
    freq_error: float
    frf_error: float
    modes_in_band: int            # the reference's
    missed_modes: int             # pairs without a counterpart, or off by 100 % or more
    valid: bool = True
    note: str = ''

    @property
    def error(self) -> float:
        return max(self.freq_error, self.frf_error)


def solve(settings, eq, method: str, n: int, frequency_grid_hz, damping: Damping,
          f_max_hz: float, at_least: int = 0) -> Solution:
    """Build ``method`` (n elements), its FRF on the grid and its modes up to ``f_max_hz``.

    At least ``at_least`` modes (when the model has that many DOFs), and always one beyond
    ``f_max_hz`` when the model has it, so that modes can be paired.
    """
    eq = equilibrium_for(settings, eq, method)       # sag-aware models: sag-consistent statics
    system = platform_system(settings.robot, eq.geometry, models.build(method, eq.cables, n))
    omega = 2.0 * math.pi * np.asarray(frequency_grid_hz, dtype=float)
    response = load_responses(system.dynamic_stiffness(omega, damping), settings)[:, :3]
    if system.assembly.blocks is None:
        freqs = natural_frequencies(system, 0, f_max_hz)
        if freqs.size < at_least + 1:
            freqs = natural_frequencies(system, at_least + 1)
    else:
        # the sparse eigen-solver of natural_frequencies takes at most dofs - 1 modes
        most = system.dofs if system.dofs <= DENSE_EIGEN_DOFS else system.dofs - 1
        count = min(most, max(at_least, 3) + 8)
        while True:
            freqs = natural_frequencies(system, count)
            if freqs[-1] > f_max_hz or count >= most:
                break
            count = min(most, 2 * count)
    return Solution(system, response, freqs)


def pair_errors(frequencies_hz, reference_hz, f_max_hz: float) -> tuple[float, int]:
    """(max relative error, missed pairs) of modes paired in ascending order.

    Over the band the first N of each list are paired, N the larger number of modes in the band;
    a mode without a counterpart, or off by 100 % or more, is missed and makes the error 100 %.
    """
    model = np.sort(np.asarray(frequencies_hz, dtype=float))
    ref = np.sort(np.asarray(reference_hz, dtype=float))
    count = max(int(np.sum(ref <= f_max_hz)), int(np.sum(model <= f_max_hz)))
    both = min(count, model.size, ref.size)
    errors = np.abs(model[:both] - ref[:both]) / ref[:both]
    missed = count - both + int(np.sum(errors >= MISSED))
    worst = float(errors.max(initial=0.0))
    return (MISSED if missed else min(worst, MISSED)), missed


def frf_error(response, reference_response) -> float:
    """max_f |A(f) - A_ref(f)| / |A_ref(f)| of complex centroid responses (nf, 3) or
    (nf, 3, loads), the largest over the loads too."""
    diff = np.linalg.norm(np.asarray(response) - reference_response, axis=1)
    ref = np.linalg.norm(reference_response, axis=1)
    with np.errstate(all='ignore'):
        rel = diff / ref
    return float(np.max(np.where(np.isfinite(rel), rel, np.inf), initial=0.0))


def reference_elements(sc: Scene, f_hi_hz: float) -> int:
    """Power of two n >= 32 whose dispersion error on the cables' top mode below f_hi is
    below :data:`REFERENCE_DISPERSION` (at most :data:`REFERENCE_MAX_ELEMENTS`)."""
    top = float(np.max(f_hi_hz / sc.transverse_hz))
    t = largest_phase(REFERENCE_DISPERSION)
    n = REFERENCE_MIN_ELEMENTS
    while n < REFERENCE_MAX_ELEMENTS and math.pi * top / n > t:
        n *= 2
    return n


def reference_solution(settings, eq, f_max_hz: float | None = None,
                       damping: Damping | None = None) -> Reference:
    """``dsm`` where sag is negligible at the tolerance, else Richardson-extrapolated fem_sag.

    Negligible: the estimated error of exact straight cables over the band (sag, tension
    varying along the cable) is below ``SAG_NEGLIGIBLE * model.tolerance``.
    """
    f_max = settings.f_max_hz if f_max_hz is None else float(f_max_hz)
    damping = band_damping(settings, eq) if damping is None else damping
    grid = settings.frequencies_hz
    grid = grid[grid <= f_max]
    est = Estimator(settings, eq, f_max, damping)
    sag_effect = est.estimate('dsm', 0).error
    f_hi = BEYOND_BAND * f_max
    if sag_effect <= SAG_NEGLIGIBLE * settings.tolerance:
        sol = solve(settings, eq, 'dsm', 0, grid, damping, f_hi)
        freqs = sol.frequencies_hz
        return Reference('dsm (exact straight cables; sag negligible: estimated '
                         f'{percent(sag_effect)} %)', 'dsm', 0, f_max, freqs[freqs <= f_hi],
                         grid, sol.response, damping, sag_effect, 1e-9)
    n = reference_elements(est.scene, f_hi)
    dsm = solve(settings, eq, 'dsm', 0, grid[:1], damping, f_hi)
    count = int(np.sum(dsm.frequencies_hz <= f_hi)) + 8
    coarse = solve(settings, eq, 'fem_sag', n, grid, damping, f_hi, count)
    fine = solve(settings, eq, 'fem_sag', 2 * n, grid, damping, f_hi, count)
    if not (coarse.system.assembly.valid and fine.system.assembly.valid):
        raise SelectionError('no sag-aware reference: ' + '; '.join(fine.system.assembly.warnings))
    k = min(coarse.frequencies_hz.size, fine.frequencies_hz.size)
    freqs = (4.0 * fine.frequencies_hz[:k] - coarse.frequencies_hz[:k]) / 3.0
    response = (4.0 * fine.response - coarse.response) / 3.0
    keep = freqs <= f_hi
    in_band = freqs <= f_max
    uncertainty = max(float(np.max(np.abs(fine.frequencies_hz[:k] - freqs)[in_band]
                                   / freqs[in_band], initial=0.0)),
                      frf_error(fine.response, response))
    return Reference(f'fem_sag n={n}/{2 * n} Richardson (sag not negligible: straight cables '
                     f'off by ~{percent(sag_effect)} %)', 'fem_sag', 2 * n, f_max, freqs[keep],
                     grid, response, damping, sag_effect, uncertainty)


def measure_error(settings, eq, method: str, n: int, reference: Reference,
                  solution: Solution | None = None) -> Measured:
    """Real errors of ``method`` (n elements) against ``reference`` (see the module doc)."""
    if solution is None:
        solution = solve(settings, eq, method, n, reference.frequency_grid_hz,
                         reference.damping, reference.f_max_hz, reference.modes_in_band)
    assembly = solution.system.assembly
    freq, missed = pair_errors(solution.frequencies_hz, reference.frequencies_hz,
                               reference.f_max_hz)
    frf = frf_error(solution.response, reference.response)
    return Measured(method, assembly.elements_per_cable, solution.system.dofs, freq, frf,
                    reference.modes_in_band, missed, assembly.valid,
                    '; '.join(assembly.warnings))
