"""What a controller takes from the prediction: the modes as numbers, input shapers and notch
filters for the lowest platform modes, and the cables' length offsets (SPEC section 5:
``vibration_modes``, ``input_shaper``, ``notch_filter``, ``cable_length_offsets``).

* :func:`mode_table`: a row per mode up to ``frf.f_max_hz``: :data:`MODE_COLUMNS`, then the
  mode's direction at a point of the platform (unit vector: the point's translation, plus the
  rotation for a rigid platform), signed so that its largest component is positive.
* :func:`controller_shaping`: the ``node.shaper`` shaper convolved over the
  ``node.shaper_modes`` lowest underdamped platform modes
  (:mod:`cdpr_dynamics.dynamics.shapers`) and a notch biquad per mode.
* :func:`length_offsets`: per cable its unstretched length minus its straight chord (m),
  what a winch adds to the rigid-cable kinematics: -T L0 / EA for a taut straight cable, the
  catenary's L0 - chord for a sagged one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.analysis.pipeline import Equilibrium, point_displacement
from cdpr_dynamics.dynamics import shapers
from cdpr_dynamics.dynamics.modes import Modes
from cdpr_dynamics.dynamics.system import Damping, PlatformSystem

MODE_COLUMNS = ('frequency_hz', 'damping_ratio', 'platform_energy_fraction', 'kind')
KIND_CODES = {'platform': 0, 'cable': 1, 'mixed': 2}
DIRECTION_COLUMNS = ('dx', 'dy', 'dz', 'rx', 'ry', 'rz')


def mode_labels(platform_dofs: int) -> tuple[str, ...]:
    """Column labels of :func:`mode_table` for 3 or 6 platform DOFs."""
    return MODE_COLUMNS + DIRECTION_COLUMNS[:platform_dofs]


def mode_table(system: PlatformSystem, found: Modes, damping: Damping, f_max_hz: float,
               point_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(k, 4 + nd): a row per mode of ``found`` in [0, ``f_max_hz``] (module docstring);
    directions NaN where ``found`` has no shapes (``dsm``)."""
    keep = found.frequency_hz <= f_max_hz
    freqs = found.frequency_hz[keep]
    nd = system.platform_dofs
    ratios = damping.ratios(freqs)
    kinds = [KIND_CODES[k] for k, kept in zip(found.kind, keep) if kept]
    table = np.full((freqs.size, 4 + nd), np.nan)
    table[:, 0], table[:, 1] = freqs, ratios
    table[:, 2], table[:, 3] = found.platform_fraction[keep], kinds
    if found.shapes is not None and freqs.size:
        q = found.shapes[:nd, keep].T                                         # (k, nd)
        direction = point_displacement(q, system.geometry.rotation, point_m)  # (k, 3)
        if nd == 6:
            direction = np.concatenate([direction, q[:, 3:]], axis=1)
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        direction = np.divide(direction, norm, out=np.zeros_like(direction), where=norm > 0)
        biggest = np.argmax(np.abs(direction), axis=1)
        sign = np.sign(direction[np.arange(freqs.size), biggest])
        table[:, 4:] = direction * np.where(sign == 0, 1.0, sign)[:, None]
    return table


@dataclass(frozen=True, eq=False)
class Shaping:
    """``frequency_hz``, ``damping_ratio`` (m,) of the shaped modes, the convolved
    ``shaper`` (None when no mode qualifies), ``notches`` (m', 6) b0 b1 b2 a0 a1 a2 of the
    modes below Nyquist, and ``skipped``: why a mode got no shaper or notch."""

    frequency_hz: np.ndarray
    damping_ratio: np.ndarray
    shaper: shapers.Shaper | None
    notches: np.ndarray
    skipped: tuple[str, ...]


def controller_shaping(found: Modes, damping: Damping, kind: str, count: int,
                       sample_rate_hz: float) -> Shaping:
    """The ``kind`` shaper and notches for the ``count`` lowest platform modes of ``found``
    that ring (0 < zeta < 1; an overdamped mode needs no shaping)."""
    platform = np.array([k == 'platform' for k in found.kind], dtype=bool)
    freqs = found.frequency_hz[platform & (found.frequency_hz > 0)]
    ratios = damping.ratios(freqs)
    skipped = [f'{f:.4g} Hz is overdamped (zeta = {z:.3g}): not shaped'
               for f, z in zip(freqs, ratios) if not z < 1.0]
    ring = ratios < 1.0
    freqs, ratios = freqs[ring][:count], ratios[ring][:count]
    shaper = shapers.design(kind, freqs, ratios) if freqs.size else None
    notches = []
    for f in freqs:
        try:
            notches.append(shapers.notch_biquad(float(f), sample_rate_hz))
        except ValueError as exc:
            skipped.append(str(exc))
    return Shaping(freqs, ratios, shaper, np.reshape(notches, (-1, 6)), tuple(skipped))


def length_offsets(eq: Equilibrium) -> np.ndarray:
    """(n,) unstretched length minus straight chord per cable (m; module docstring)."""
    return np.asarray(eq.unstretched_length_m, dtype=float) - eq.geometry.length_m
