"""What a controller takes from the prediction: the modes as numbers, input shapers and notch
filters for the lowest platform modes, and the cables' length offsets (doc/node_interface.md:
``vibration_modes``, ``input_shaper``, ``notch_filter``, ``cable_length_offsets``).

* :func:`mode_table`: a row per mode up to ``frf.f_max_hz``: :data:`MODE_COLUMNS`, then the
  mode's direction at a point of the platform (unit vector: the point's translation, plus the
  rotation for a rigid platform), signed so that its largest component is positive; the
  platform part of a mode is the null vector of the condensed dynamic stiffness at its
  frequency (:func:`platform_shapes`).
* :func:`controller_shaping`: the ``node.shaper`` shaper convolved over the
  ``node.shaper_modes`` lowest underdamped platform modes
  (:mod:`cdpr_dynamics.dynamics.shapers`) and a notch biquad per mode.
* :func:`length_offsets`: per cable its unstretched length minus its rigid straight-line
  length from its anchor (m), what a winch adds to the rigid-cable kinematics: -T L0 / EA for
  a taut straight cable, the catenary's L0 - chord for a sagged one; over a pulley also the
  wrap (r beta + |B - A| - |D - A|) and, with cable between winch and anchor, its stretch.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.analysis.pipeline import Equilibrium, point_displacement
from cdpr_dynamics.dynamics import shapers
from cdpr_dynamics.dynamics.modes import Modes
from cdpr_dynamics.dynamics.system import Damping, PlatformSystem
from cdpr_dynamics.mechanics.robot import Robot, row_norm

MODE_COLUMNS = ('frequency_hz', 'damping_ratio', 'platform_energy_fraction', 'kind')
KIND_CODES = {'platform': 0, 'cable': 1, 'mixed': 2}
DIRECTION_COLUMNS = ('dx', 'dy', 'dz', 'rx', 'ry', 'rz')


def mode_labels(platform_dofs: int) -> tuple[str, ...]:
    """Column labels of :func:`mode_table` for 3 or 6 platform DOFs."""
    return MODE_COLUMNS + DIRECTION_COLUMNS[:platform_dofs]


def mode_table(system: PlatformSystem, found: Modes, damping: Damping, f_max_hz: float,
               point_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(k, 4 + nd): a row per mode of ``found`` in [0, ``f_max_hz``] (module docstring)."""
    keep = found.frequency_hz <= f_max_hz
    freqs = found.frequency_hz[keep]
    nd = system.platform_dofs
    table = np.full((freqs.size, 4 + nd), np.nan)
    table[:, 0], table[:, 1] = freqs, damping.ratios(freqs)
    table[:, 2] = found.platform_fraction[keep]
    table[:, 3] = [KIND_CODES[k] for k, kept in zip(found.kind, keep) if kept]
    if not freqs.size:
        return table
    q = platform_shapes(system, freqs)                                       # (k, nd)
    direction = point_displacement(q, system.geometry.rotation, point_m)     # (k, 3)
    if nd == 6:
        direction = np.concatenate([direction, q[:, 3:]], axis=1)
    norm = np.linalg.norm(direction, axis=1, keepdims=True)
    direction = np.divide(direction, norm, out=np.zeros_like(direction), where=norm > 0)
    biggest = np.argmax(np.abs(direction), axis=1)
    sign = np.sign(direction[np.arange(freqs.size), biggest])
    table[:, 4:] = direction * np.where(sign == 0, 1.0, sign)[:, None]
    return table


def platform_shapes(system: PlatformSystem, frequency_hz, rtol: float = 1e-6) -> np.ndarray:
    """(k, nd) the platform part of each mode: the null vectors of the condensed undamped
    dynamic stiffness Z(w) at its frequency (every model, ``dsm`` included, no eigenvectors
    of the full model needed). A frequency repeated m times (within ``rtol``) gets the
    min(m, nd) smallest right singular vectors, so repeated modes get orthogonal directions;
    the rest of such a group (modes of symmetric cables beyond the platform's DOFs) and
    frequencies where Z is not finite (a clamped cable's own mode) get zeros: no platform
    motion."""
    freqs = np.asarray(frequency_hz, dtype=float)
    nd = system.platform_dofs
    with np.errstate(all='ignore'):
        z = system.dynamic_stiffness(2.0 * np.pi * freqs).real
    finite = np.isfinite(z).all(axis=(1, 2))
    vt = np.zeros((freqs.size, nd, nd))
    if finite.any():
        vt[finite] = np.linalg.svd(z[finite])[2]
    shapes = np.zeros((freqs.size, nd))
    i = 0
    while i < freqs.size:
        j = i + 1
        while j < freqs.size and abs(freqs[j] - freqs[i]) <= rtol * max(freqs[i], 1e-12):
            j += 1
        m = min(j - i, nd)
        shapes[i:i + m] = vt[i, ::-1][:m]
        i = j
    return shapes


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


def length_offsets(robot: Robot, eq: Equilibrium) -> np.ndarray:
    """(n,) per cable: its unstretched length from the winch minus the rigid-cable length, the
    winch side plus the straight line |D - A| from its anchor D to its attachment A (m; module
    docstring). The free span contributes its own unstretched length (straight or sagged);
    the cable in series at the anchor end (wrapped on the pulley, winch side) carries the
    span's anchor-end tension T_a: its length S unstretched is S EA / (EA + T_a)."""
    geo = eq.geometry
    span = np.asarray(eq.unstretched_length_m, dtype=float)
    if geo.anchor_end is None:
        return span - geo.length_m
    tension = eq.sag.state.anchor_tension_n if eq.statics == 'sag' else eq.tensions.tension_n
    ea = eq.cables.ea_n
    series = geo.anchor_end.series_length_m
    straight = row_norm(robot.anchors_m - (geo.position_m + geo.lever_m))
    return span + series * ea / (ea + tension) - robot.winch_side_lengths_m - straight


def controller_document(robot: Robot, system: PlatformSystem, found: Modes, damping: Damping,
                        eq: Equilibrium, f_max_hz: float, kind: str, count: int,
                        sample_rate_hz: float, point_m=(0.0, 0.0, 0.0)) -> dict:
    """What the node publishes for a controller, as JSON: ``vibration_modes`` (labels,
    rows), the ``kind`` shaper (``none``: none), its notches and the length offsets."""
    table = mode_table(system, found, damping, f_max_hz, point_m)
    doc = {'vibration_modes': {'labels': list(mode_labels(system.platform_dofs)),
                               'rows': table.tolist()},
           'length_offsets_m': length_offsets(robot, eq).tolist()}
    if kind != 'none':
        shaping = controller_shaping(found, damping, kind, count, sample_rate_hz)
        doc['shaper'] = {'kind': kind, 'modes_hz': shaping.frequency_hz.tolist(),
                         'damping_ratios': shaping.damping_ratio.tolist(),
                         'times_s': [] if shaping.shaper is None
                         else shaping.shaper.times_s.tolist(),
                         'amplitudes': [] if shaping.shaper is None
                         else shaping.shaper.amplitudes.tolist(),
                         'notch_sample_rate_hz': sample_rate_hz,
                         'notches': shaping.notches.tolist(),
                         'skipped': list(shaping.skipped)}
    return doc


def controller_lines(doc: dict) -> list[str]:
    """Lines a tool prints of :func:`controller_document`."""
    lines = [f'length offsets (unstretched - straight, mm): '
             f'{np.round(np.asarray(doc["length_offsets_m"]) * 1e3, 4).tolist()}']
    shaper = doc.get('shaper')
    if shaper is None:
        return lines
    if not shaper['times_s']:
        return lines + [f'{shaper["kind"]} shaper: no underdamped platform mode to shape'
                        + ''.join(f'; {s}' for s in shaper['skipped'])]
    modes = ', '.join(f'{f:.4g} Hz (zeta {z:.3g})'
                      for f, z in zip(shaper['modes_hz'], shaper['damping_ratios']))
    lines.append(f'{shaper["kind"]} shaper for {modes}: {len(shaper["times_s"])} impulses, '
                 f'{shaper["times_s"][-1] * 1e3:.2f} ms')
    lines += [f'  t = {t:.6f} s  a = {a:.6f}'
              for t, a in zip(shaper['times_s'], shaper['amplitudes'])]
    for f, c in zip(shaper['modes_hz'], shaper['notches']):
        lines.append(f'notch {f:.4g} Hz at {shaper["notch_sample_rate_hz"]:g} Hz: b = '
                     f'{np.round(c[:3], 9).tolist()}, a = {np.round(c[3:], 9).tolist()}')
    lines += [f'  {s}' for s in shaper['skipped']]
    return lines
