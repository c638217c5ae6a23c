"""Synthetic measurements of the package's own model: free decays and modes tables.

What ``cdpr_calibrate`` is checked and benchmarked on (tests, ``cdpr_bench --calibration``,
``scripts/compare_identification.py``): :func:`free_decay` integrates the platform's free
vibration with the package's Newmark integrator from an initial displacement and gives the
truth beside it (the eigensolution of the same K and M, the damping's modal ratios);
:func:`pose_rows` turns it into the poses a motion-capture system would record;
:func:`campaign` draws a modes table at random poses.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from cdpr_dynamics.analysis.config import settings_from_params
from cdpr_dynamics.analysis.modes_table import ModesTable
from cdpr_dynamics.analysis.pipeline import AnalysisError, build_system, equilibrium
from cdpr_dynamics.dynamics.system import Damping, Newmark, rayleigh_from_modal_ratio
from cdpr_dynamics.mechanics.robot import (matrix_to_quaternion, quaternion_to_matrix,
                                           rotation_vector_quaternion)


@dataclass(frozen=True)
class Decay:
    """A free decay sampled at ``t_s`` (n,): displacement, velocity and acceleration (n, dofs)
    of the platform, and the truth: the frequencies the record holds (Hz, ascending), the
    modal damping ratios and the mass-normalised mode shapes (dofs, dofs)."""

    t_s: np.ndarray
    u: np.ndarray
    v: np.ndarray
    acc: np.ndarray
    frequency_hz: np.ndarray
    damping_ratio: np.ndarray
    shapes: np.ndarray


def free_decay(settings, position_m, u0, duration_s: float, ratio: float = 0.02,
               dt_s: float = 1e-3, rate_hz: float = 100.0, rotation=None) -> Decay:
    """The free decay of the platform at ``position_m`` released at rest from ``u0`` (dofs,),
    Rayleigh damping of ``ratio`` at the lowest and highest mode, Newmark (average
    acceleration, ``dt_s``) sampled at ``rate_hz``."""
    system = build_system(settings, equilibrium(settings, np.asarray(position_m, dtype=float),
                                                np.eye(3) if rotation is None else rotation))
    k, m = system.static_stiffness(), system.platform_mass
    lam, phi = scipy.linalg.eigh(k, m)
    f = np.sqrt(lam) / (2 * np.pi)
    damping = rayleigh_from_modal_ratio(ratio, f[0], f[-1])
    integrator = Newmark(k, m, damping, dt_s)
    integrator.u = np.asarray(u0, dtype=float)
    integrator.acc = np.linalg.solve(m, -k @ integrator.u)     # at rest: no damping force
    every = int(round(1.0 / (rate_hz * dt_s)))
    out = [np.stack([integrator.u, integrator.v, integrator.acc])]
    zero = np.zeros(k.shape[0])
    for i in range(1, int(round(duration_s / dt_s)) + 1):
        integrator.step(zero)
        if i % every == 0:
            out.append(np.stack([integrator.u, integrator.v, integrator.acc]))
    states = np.array(out)
    # the average-acceleration rule rings at w' with tan(w' dt / 2) = w dt / 2 (its period
    # elongation): the frequency the record holds
    f_record = np.arctan(np.pi * f * dt_s) / (np.pi * dt_s)
    return Decay(np.arange(len(states)) / rate_hz, states[:, 0], states[:, 1], states[:, 2],
                 f_record, damping.ratios(f), phi)


def pose_rows(position_m, u, noise_m: float, rng) -> np.ndarray:
    """(n, 7) poses x y z qx qy qz qw of the platform displaced by ``u`` (n, 3 or 6:
    translations, small rotations) plus white noise of ``noise_m`` (m, and rad on the
    rotations)."""
    u = np.asarray(u, dtype=float)
    if u.shape[1] == 3:
        u = np.hstack([u, np.zeros_like(u)])
    u = u + noise_m * rng.standard_normal(u.shape)
    quats = [matrix_to_quaternion(quaternion_to_matrix(rotation_vector_quaternion(th)))
             for th in u[:, 3:]]
    return np.hstack([np.asarray(position_m, dtype=float) + u[:, :3], quats])


def campaign(flat: dict, poses: int, modes: int, noise: float = 0.01, seed: int = 1,
             spread_m: float = 0.4, tilt_rad: float = 0.0, damping: Damping | None = None,
             directions: bool = False) -> ModesTable:
    """A modes table of the model ``flat`` at ``poses`` random poses: the ``modes`` lowest
    platform modes with relative noise ``noise`` (``std_hz`` says so), damping ratios of the
    Rayleigh ``damping`` with 5 % noise, the model's mode directions where ``directions``.
    A pose the model refuses is drawn again; an underactuated robot's pose is where it hangs."""
    settings = settings_from_params(flat)
    rng = np.random.default_rng(seed)
    rows, pose_id = [], 0
    centre = np.asarray(flat['robot.initial_position'], dtype=float)
    while pose_id < poses:
        position = centre + rng.uniform(-spread_m, spread_m, 3)
        quaternion = rotation_vector_quaternion(rng.uniform(-tilt_rad, tilt_rad, 3))
        try:
            eq = equilibrium(settings, position, quaternion_to_matrix(quaternion))
            system = build_system(settings, eq)
        except AnalysisError:
            continue
        position = eq.geometry.position_m
        quaternion = matrix_to_quaternion(eq.geometry.rotation)
        lam, shapes = scipy.linalg.eigh(system.static_stiffness(), system.platform_mass)
        freqs = np.sqrt(np.clip(lam, 0.0, None))[:modes] / (2 * np.pi)
        for j, f in enumerate(freqs):
            zeta = damping.ratios(f) * (1 + 0.05 * rng.standard_normal()) if damping else np.nan
            direction = np.full(6, np.nan)
            if directions:
                direction[:shapes.shape[0]] = shapes[:, j] / np.linalg.norm(shapes[:, j])
            rows.append((pose_id, *position, *quaternion, f * (1 + noise * rng.standard_normal()),
                         noise * f, zeta, 0.05 * zeta, *direction))
        pose_id += 1
    a = np.array(rows)
    return ModesTable(a[:, 0].astype(int), a[:, 1:8], a[:, 8], a[:, 9], a[:, 10], a[:, 11],
                      a[:, 12:18])
