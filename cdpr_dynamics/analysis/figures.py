"""The figures of ``cdpr_analyze`` and ``cdpr_tradeoff`` (matplotlib, Agg, no pyplot state).

Two floors:

* **drawing functions** take plain arrays (or the JSON's mode dicts) and draw on a given
  Axes: :func:`draw_frf` (|H| on log-log axes, optional phase panel, modes marked by kind),
  :func:`mark_modes`, :func:`shade_intervals`, :func:`draw_geometry` (3D frame, cables coloured
  by tension, platform), :func:`draw_mode` (one deformed mode shape);
* **figure functions** compose them and write a PNG: :func:`frf_figure`,
  :func:`time_history_figure`, :func:`geometry_figure`, :func:`modes_figure`,
  :func:`tradeoff_figure`.

Data helpers turn the JSON or the model into those arrays: :func:`receptance_curve` (|H| in
m/N = amplitude / |F| for a translation, the direct receptance H_jj in rad/(N m) for a
rotation), :func:`scene` and :func:`mode_shapes` (world-frame cable shapes, sagged where the
model's statics sag, and the displacement of every drawn point in a mode).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.artist import Artist
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, NullFormatter
from mpl_toolkits.mplot3d.art3d import Line3DCollection

from cdpr_dynamics.mechanics.robot import DOF_NAMES
from cdpr_dynamics.dynamics.slack import intervals

DIRECTIONS = DOF_NAMES
DPI = 120
#: Curves whose |H| differ by less than this (max relative difference, %) are called coincident.
COINCIDE_PCT = 5.0
#: The largest displacement of a drawn mode shape, as a fraction of the frame's largest extent:
#: of the platform in a platform or mixed mode, of anything in a cable mode.
MODE_SCALE_FRACTION = 0.08
#: The cables of a platform or mixed mode bow at most this fraction of the frame's extent
#: (their mass-normalised motion can be several times the platform's).
MODE_CABLE_CAP_FRACTION = 0.25
#: Modes with less platform energy never stand in for platform modes (:func:`pick_modes`).
PLATFORM_MIN_FRACTION = 1e-3
MODE_STYLES = {'platform': dict(color='tab:red', ls='-', lw=1.5, alpha=0.9),
               'mixed': dict(color='tab:purple', ls='-.', lw=1.1, alpha=0.8),
               'cable': dict(color='0.45', ls=':', lw=0.9, alpha=0.8),
               None: dict(color='0.45', ls='--', lw=0.9, alpha=0.8)}
MODE_LABELS = {'platform': 'platform mode', 'mixed': 'mixed mode', 'cable': 'cable mode',
               None: 'mode (unclassified)'}
# stacked styles for curves that may coincide: wide solid under narrower dashes and dots
CURVE_STYLES = (dict(ls='-', lw=3.2, alpha=0.55), dict(ls=(0, (7, 3)), lw=1.8),
                dict(ls=(0, (2, 2)), lw=1.6), dict(ls=(0, (1, 4)), lw=2.2),
                dict(ls=(0, (9, 2, 1, 2)), lw=1.3), dict(ls='-', lw=0.9))
FAMILIES = {'spring': ('spring', 'tab:gray', 'o'), 'fem': ('fem (straight)', 'tab:blue', 'o'),
            'catenary': ('catenary', 'tab:olive', 'D'),
            'catenary_exact': ('catenary_exact', 'tab:green', 'D'),
            'fem_sag': ('fem_sag', 'tab:red', 's'), 'dsm': ('dsm', 'black', 'P')}


class FigureError(ValueError):
    """A figure that cannot be drawn from this data; the message is one line."""


def _figure(width_in: float, height_in: float) -> Figure:
    fig = Figure(figsize=(width_in, height_in))
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path) -> Figure:
    """Write ``fig`` to ``path`` (PNG, :data:`DPI`), making its folder; returns ``fig``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return fig


def method_name(method: str, elements_per_cable=None) -> str:
    """``fem n=16`` for a discretised method (fem, fem_sag), the method's name otherwise."""
    if method in ('fem', 'fem_sag') and elements_per_cable:
        return f'{method} n={elements_per_cable}'
    return method


def method_label(doc: dict) -> str:
    """``fem n=16 (363 DOFs)`` for a JSON document of one method."""
    n = (doc.get('model_choice') or {}).get('elements_per_cable')
    return f"{method_name(doc['method'], n)} ({doc['dofs']} DOFs)"


# ----------------------------------------------------------------------------------- FRF

def _array(values) -> np.ndarray:
    """JSON lists (None for a non-finite entry) as a float array (None -> nan)."""
    return np.array(values, dtype=float)


def load_magnitude(doc: dict) -> float:
    """|F| (N) of the FRF load ``frf.force_n`` of a JSON document."""
    force = doc['frf'].get('force_n')
    if force is None:
        raise FigureError('the JSON has no frf.force_n: cannot give |H| per newton')
    return float(np.linalg.norm(force))


def receptance_curve(doc: dict, direction: str = 'z'):
    """(frequency_hz, |H|, phase_deg, unit) of one JSON document along ``direction``.

    Translation j (x, y, z): |H_j| = |A_j| / |F| (m/N), the amplitude of the point
    ``frf.point_m`` along j per newton of the load ``frf.force_n`` (whatever its direction),
    phase of A_j. Rotation j (rx, ry, rz): the direct receptance H_jj of the platform
    rotation about j per unit moment about j, rad/(N m), from ``frf.receptance``.
    """
    if direction not in DIRECTIONS:
        raise FigureError(f'direction {direction!r} is not one of {", ".join(DIRECTIONS)}')
    frf = doc['frf']
    f = _array(frf['frequency_hz'])
    axis = DIRECTIONS.index(direction)
    if axis < 3:
        load = load_magnitude(doc)
        if not load > 0:
            raise FigureError('frf.force_n is zero: no response per newton to plot')
        return (f, _array(frf['amplitude_m'])[:, axis] / load,
                np.degrees(_array(frf['phase_rad'])[:, axis]), 'm/N')
    real, imag = _array(frf['receptance']['real']), _array(frf['receptance']['imag'])
    if real.shape[1] < 6:
        raise FigureError(f'direction {direction} needs a 6-DOF platform: this one is a point '
                          f'mass ({real.shape[1]} DOFs)')
    h = real[:, axis, axis] + 1j * imag[:, axis, axis]
    return f, np.abs(h), np.degrees(np.angle(h)), 'rad/(N m)'


def max_relative_difference(a, b) -> float:
    """max over finite entries of |a - b| / |b| (inf where nothing is comparable)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b) & (np.abs(b) > 0)
    return float(np.max(np.abs(a[ok] - b[ok]) / np.abs(b[ok]))) if np.any(ok) else np.inf


def coincident_groups(values: list[np.ndarray], tolerance_pct: float = COINCIDE_PCT):
    """Groups (lists of indices, each of 2 or more) of curves that coincide, and per group the
    largest pairwise max relative difference (%). A curve joins the first group whose first
    member it is within ``tolerance_pct`` of."""
    groups: list[list[int]] = []
    for i, v in enumerate(values):
        for g in groups:
            if 100 * max_relative_difference(v, values[g[0]]) < tolerance_pct:
                g.append(i)
                break
        else:
            groups.append([i])
    out = []
    for g in (g for g in groups if len(g) > 1):
        spread = max(100 * max_relative_difference(values[i], values[j])
                     for i in g for j in g if i != j)
        out.append((g, spread))
    return out


def percent_text(value: float) -> str:
    return f'{value:.2g} %' if value >= 0.01 else f'{value:.1e} %'


LABEL_ROW_PT = 9.0      # the next row of labels, where one would overlap another (pt)
LABEL_GAP_PT = 1.5      # the least gap kept between two labels' text (pt)


class ModeLabels(Artist):
    """The platform-mode labels of one Axes, stacked in rows when the Axes is drawn.

    It holds the labels (ascending frequency) and, drawn before them (lowest zorder), places
    each in the first row below the top where its text, measured by the renderer at the
    Axes' final size, keeps :data:`LABEL_GAP_PT` from every label placed before it; a label
    in the right 15 % of the Axes reads leftwards of its line. Layout changes after
    :func:`mark_modes` (``tight_layout``, another size or dpi) cannot make labels overlap."""

    def __init__(self, notes):
        super().__init__()
        self.notes = list(notes)
        self.set_zorder(-1e9)

    def draw(self, renderer):
        if not self.get_visible() or not self.notes:
            return
        ax = self.axes
        box = ax.get_window_extent(renderer)
        gap = renderer.points_to_pixels(LABEL_GAP_PT)
        placed = []
        for note in self.notes:
            right = ax.transData.transform((note.xy[0], 1.0))[0] > box.x0 + 0.85 * box.width
            note.set_horizontalalignment('right' if right else 'left')
            for row in range(len(self.notes)):
                note.xyann = (-3 if right else 3, -3 - LABEL_ROW_PT * row)
                extent = note.get_window_extent(renderer).padded(gap / 2)
                if not any(extent.overlaps(other) for other in placed):
                    break
            placed.append(extent)


def mark_modes(ax, modes: list[dict], f_min_hz: float = 0.0, f_max_hz: float = np.inf,
               suffix: str = '', annotate_platform: bool = True) -> dict:
    """A vertical line per mode (dicts with ``frequency_hz`` and ``kind``, as the JSON's
    ``modes``) in [f_min, f_max] and above 0 Hz, a style per kind (:data:`MODE_STYLES`), one
    legend entry per kind (with the count); platform modes labelled with their frequency
    (coincident ones once, with the multiplicity), stacked so that no two labels overlap
    (:class:`ModeLabels`). Lines carry gid ``mode-<kind>``, labels ``mode-label``.
    Returns {kind: [frequencies drawn]}."""
    drawn: dict = {}
    for kind in ('cable', 'mixed', None, 'platform'):        # platform lines on top
        freqs = [float(m['frequency_hz']) for m in modes if m.get('kind') == kind
                 and 0 < m['frequency_hz'] and f_min_hz <= m['frequency_hz'] <= f_max_hz]
        for i, f in enumerate(freqs):
            label = f'{MODE_LABELS[kind]}s{suffix} ({len(freqs)})' if i == 0 else '_nolegend_'
            ax.axvline(f, label=label, gid=f'mode-{kind}', zorder=1, **MODE_STYLES[kind])
        if freqs:
            drawn[kind] = freqs
    if annotate_platform and drawn.get('platform'):
        notes = [ax.annotate(f'{f:.1f} Hz' + (f' (x{count})' if count > 1 else ''), (f, 1.0),
                             xycoords=('data', 'axes fraction'), xytext=(3, -3),
                             textcoords='offset points', va='top', fontsize=7, gid='mode-label',
                             color=MODE_STYLES['platform']['color'],
                             bbox=dict(facecolor='white', edgecolor='none', alpha=0.8, pad=0.5))
                 for f, count in _clusters(drawn['platform'])]
        ax.add_artist(ModeLabels(notes))
    return drawn


def _clusters(freqs, relative: float = 1e-3):
    """(first frequency, count) of runs of frequencies within ``relative`` of each other."""
    out = []
    for f in sorted(freqs):
        if out and f - out[-1][0] <= relative * out[-1][0]:
            out[-1][1] += 1
        else:
            out.append([f, 1])
    return [tuple(c) for c in out]


def draw_frf(ax, frequency_hz, curves, modes=None, ax_phase=None, unit: str = 'm/N',
             ylabel: str | None = None, modes_suffix: str = '', legend: bool = True) -> list[str]:
    """|H| of ``curves`` ([(label, |H|, phase_deg)], phase may be None) on log-log axes ``ax``
    and the phase (degrees) on ``ax_phase`` (if given), modes (the JSON's mode dicts) marked
    (:func:`mark_modes`). Curves that coincide (:func:`coincident_groups`) get stacked dash
    styles and a legend entry "a, b coincide within x %". Draws the legend where ``legend``
    (else the caller places it). Returns those notes. Lines carry gid ``frf-<i>``."""
    f = np.asarray(frequency_hz, dtype=float)
    for i, (label, h, phase) in enumerate(curves):
        style = dict(CURVE_STYLES[i % len(CURVE_STYLES)], color=f'C{i}')
        with np.errstate(invalid='ignore'):
            ax.plot(f, np.asarray(h, float), label=label, gid=f'frf-{i}', **style)
        if ax_phase is not None and phase is not None:
            ax_phase.plot(f, np.asarray(phase, float), gid=f'phase-{i}', **style)
    notes = [', '.join(curves[i][0].split(' (')[0] for i in g)
             + f' coincide within {percent_text(s)}'
             for g, s in coincident_groups([np.asarray(c[1], float) for c in curves])]
    for note in notes:
        ax.plot([], [], ' ', label=note)
    ax.set_xscale('log')
    with np.errstate(invalid='ignore'):
        positive = any(np.any(np.asarray(c[1], float) > 0) for c in curves)
    if positive:
        ax.set_yscale('log')
    else:       # e.g. a cross response a symmetric robot does not have
        ax.text(0.5, 0.5, 'no response along this direction to this load', ha='center',
                transform=ax.transAxes, fontsize=9, color='0.3')
    if modes:
        mark_modes(ax, modes, f.min(), f.max(), modes_suffix)
        if ax_phase is not None:
            mark_modes(ax_phase, modes, f.min(), f.max(), annotate_platform=False)
    for a in (ax, ax_phase):
        if a is None:
            continue
        a.set_xlim(f.min(), f.max())
        a.grid(True, which='both', alpha=0.25)
        a.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f'{v:g}'))
        a.xaxis.set_minor_formatter(FuncFormatter(
            lambda v, _: f'{v:g}' if f'{v:.0e}'[0] in '25' else ''))
    ax.set_ylabel(ylabel or f'|H| ({unit})')
    if ax_phase is not None:
        ax_phase.set_ylabel('phase (deg)')
        ax_phase.set_xlabel('excitation frequency (Hz)')
        ax_phase.set_yticks([-180, -90, 0, 90, 180])
        ax_phase.set_ylim(-190, 190)
    else:
        ax.set_xlabel('excitation frequency (Hz)')
    if legend:
        ax.legend(fontsize=7, loc='best', framealpha=0.9)
    return notes


def _direction_text(vector) -> str:
    v = np.asarray(vector, dtype=float)
    if np.count_nonzero(v) == 1:
        i = int(np.flatnonzero(v)[0])
        return f"{'+' if v[i] > 0 else '-'}{'xyz'[i]}"
    return f'({", ".join(f"{c:g}" for c in v / np.linalg.norm(v))})'


def frf_figure(documents: list[dict], path: Path, direction: str = 'z') -> Figure:
    """``frf.png``: |H| of every method's document along ``direction`` with its phase below,
    the modes of the first document marked by kind."""
    curves, f = [], None
    for doc in documents:
        f, h, phase, unit = receptance_curve(doc, direction)
        curves.append((method_label(doc), h, phase))
    first = documents[0]
    fig = _figure(8.0, 6.4)
    ax, ax_phase = fig.subplots(2, 1, sharex=True, gridspec_kw={'height_ratios': [3, 1.3]})
    axis = DIRECTIONS.index(direction)
    if axis < 3:
        point = np.asarray(first['frf'].get('point_m', [0, 0, 0]), dtype=float)
        where = 'centroid' if not np.any(point) else f'point {point.tolist()} m (platform frame)'
        force = first['frf']['force_n']
        ylabel = f'|u_{direction} / F| (m/N)'
        title = (f'Receptance: {direction} response of the {where}\nper newton of the load '
                 f'F = {np.linalg.norm(force):g} N along {_direction_text(force)}')
    else:
        ylabel = f'|theta_{direction[1]} / M_{direction[1]}| (rad/(N m))'
        title = (f'Receptance: platform rotation about {direction[1]} per unit moment about '
                 f'{direction[1]}')
    damping = first.get('damping') or {}
    if damping:
        ratio = damping.get('modal_ratio') or 0.0
        title += ('; damping ' + (f'{100 * ratio:g} % modal (' if ratio > 0 else '')
                  + f"C = {damping['mass_factor']:.3g} M + {damping['stiffness_factor']:.3g} K"
                  + (')' if ratio > 0 else ''))
    suffix = f' of {first["method"]}' if len(documents) > 1 else ''
    draw_frf(ax, f, curves, first.get('modes'), ax_phase, unit, ylabel, suffix)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


# -------------------------------------------------------------------------- time history

def shade_intervals(ax, spans, color='tab:red', alpha=0.15, label=None, hatch=None,
                    gid='slack'):
    """Shade each (start, end) span of ``spans`` (s) over the full height of ``ax`` (filled,
    or hatched in ``color`` where ``hatch``); the patches carry ``gid``, the first ``label``."""
    style = (dict(facecolor='none', edgecolor=color, hatch=hatch) if hatch
             else dict(facecolor=color))
    return [ax.axvspan(start, end, alpha=alpha, lw=0, gid=gid,
                       label=label if i == 0 else '_nolegend_', **style)
            for i, (start, end) in enumerate(spans)]


def load_along(force_n) -> np.ndarray:
    """(nt,) the load (nt, 3) along its direction at its largest (N); zero for no load."""
    force = np.asarray(force_n, dtype=float)
    size = np.linalg.norm(force, axis=1)
    if not np.any(size > 0):
        return np.zeros(len(force))
    return force @ (force[np.argmax(size)] / size.max())


def time_history_figure(documents: list[dict], path: Path, axis: int = 2,
                        tension_min_n: float | None = None) -> Figure | None:
    """``time_history.png``: per excitation frequency the displacement along ``axis`` (mm),
    the load along its direction (N) and the lowest cable tension (N) against time, one colour
    per method (each distinct slack-aware run once, dotted with markers). Shaded on all three
    panels: red where the first method's linear lowest tension is <= 0 (a cable would push),
    grey where the first slack-aware run has a slack cable. None without time histories."""
    excitations = sorted({h['excitation_hz'] for doc in documents for h in doc['time_history']})
    if not excitations:
        return None
    fig = _figure(10.0, 1.0 + 5.0 * len(excitations))
    outer = fig.add_gridspec(len(excitations), 1, hspace=0.13)
    name = 'xyz'[axis]
    first_ax = None
    for row, f_exc in enumerate(excitations):
        inner = outer[row].subgridspec(3, 1, height_ratios=[2.2, 1.0, 1.3], hspace=0.08)
        ax_u, ax_f, ax_t = panels = [fig.add_subplot(inner[k], sharex=first_ax)
                                     for k in range(3)]
        first_ax = first_ax or ax_u
        shaded, aware_seen = False, set()
        for i, doc in enumerate(documents):
            style = dict(CURVE_STYLES[i % len(CURVE_STYLES)], color=f'C{i}')
            for h in (h for h in doc['time_history'] if h['excitation_hz'] == f_exc):
                t = _array(h['t_s'])
                ax_u.plot(t, 1e3 * _array(h['u_m'])[:, axis], label=method_label(doc), **style)
                if 'force_n' in h and i == 0:
                    ax_f.plot(t, load_along(h['force_n']), color='k', lw=1.0)
                if 'lowest_tension_n' in h:
                    lowest = _array(h['lowest_tension_n'])
                    ax_t.plot(t, lowest, label=f"{doc['method']}: T + dT (linear, elastic)",
                              **style)
                    if not shaded:
                        shaded = True
                        for ax in panels:
                            shade_intervals(ax, intervals(t, lowest <= 0.0), 'tab:red', 0.16,
                                            f'{doc["method"]}: lowest tension <= 0 (linear)'
                                            if ax is ax_u else None)
                aware = h.get('slack_aware')
                if not aware or aware['method'] in aware_seen:
                    continue
                first_aware = not aware_seen
                aware_seen.add(aware['method'])
                k = len(aware_seen) - 1
                every = max(1, len(t) // 40)
                marks = dict(color=f'C{len(documents) + k}', lw=1.1,
                             ls=((0, (1, 1)), (0, (4, 2)), (0, (6, 2, 1, 2)))[k % 3],
                             marker='.x+'[k % 3], ms=4,
                             markevery=(k * every // 3 % every, every))
                aware_name = method_name(aware['method'], aware.get('elements_per_cable')) \
                    + ', slack-aware'
                ax_u.plot(t, 1e3 * _array(aware['u_m'])[:, axis], label=aware_name, **marks)
                if 'lowest_tension_n' in aware:
                    low = _array(aware['lowest_tension_n'])
                    ax_t.plot(t, low, label=f'{aware_name}: cable force\n(with its damper)',
                              **marks)
                    if first_aware:
                        for ax in panels:
                            shade_intervals(ax, intervals(t, low <= 0.0), '0.35', 0.18,
                                            f'{aware_name}: a cable slack'
                                            if ax is ax_u else None, gid='slack-aware')
        ax_t.axhline(0.0, color='k', lw=0.7)
        if tension_min_n is not None:
            ax_t.axhline(tension_min_n, color='0.4', lw=0.8, ls='--', label='tension.min_n')
            ax_t.legend(fontsize=7, loc='upper left', bbox_to_anchor=(1.01, 1.0),
                        frameon=False)
        ax_u.set_title(f'{f_exc:g} Hz harmonic load', fontsize=9, loc='left')
        ax_u.set_ylabel(f'u_{name} (mm)')
        ax_f.set_ylabel('load (N)')
        ax_t.set_ylabel('lowest\ntension (N)')
        for ax in panels:
            ax.grid(True, alpha=0.3)
            if ax is not ax_t or row < len(excitations) - 1:
                ax.tick_params(labelbottom=False)
        ax_u.legend(fontsize=7, loc='upper left', bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax_t.set_xlabel('time (s)')
    fig.suptitle(f'Time history of the platform (Newmark): displacement along {name}, the '
                 'load, the lowest cable tension', fontsize=10)
    fig.subplots_adjust(left=0.09, right=0.72, top=1 - 0.55 / fig.get_figheight(),
                        bottom=0.45 / fig.get_figheight())
    return _save(fig, path)


# ------------------------------------------------------------------------------ geometry

@dataclass(frozen=True, eq=False)
class Scene:
    """What the geometry figure draws, world frame (m): ``anchors_m`` (n, 3);
    ``cable_points_m`` (n, s, 3) each cable's static shape from its attachment (point 0) to
    its anchor (point s-1); ``tension_n`` (n,); ``centroid_m`` (3,); ``attachments_m`` (n, 3)
    (all at the centroid for a point mass); ``point_mass``."""

    anchors_m: np.ndarray
    cable_points_m: np.ndarray
    tension_n: np.ndarray
    centroid_m: np.ndarray
    attachments_m: np.ndarray
    point_mass: bool
    statics: str = 'chord'


def scene(settings, eq, samples: int = 65) -> Scene:
    """The :class:`Scene` of equilibrium ``eq`` (already the method's statics, e.g. from
    :func:`cdpr_dynamics.mechanics.statics.equilibrium_for`): cables along
    :func:`cdpr_dynamics.analysis.pipeline.cable_shapes` (the elastic catenary where the statics
    sag)."""
    from cdpr_dynamics.analysis.pipeline import cable_shapes
    geo = eq.geometry
    attachments = geo.position_m + geo.lever_m
    return Scene(np.asarray(settings.robot.anchors_m, float),
                 attachments[:, None, :] + cable_shapes(eq, samples),
                 np.asarray(eq.tensions.tension_n, float), np.asarray(geo.position_m, float),
                 attachments, bool(settings.robot.point_mass), eq.statics)


def box_edges(points) -> np.ndarray:
    """(12, 2, 3) edges of the axis-aligned box around ``points`` (n, 3)."""
    lo, hi = np.min(points, axis=0), np.max(points, axis=0)
    corners = np.array([[(lo, hi)[(k >> a) & 1][a] for a in range(3)] for k in range(8)])
    return np.array([(corners[i], corners[i | 1 << a]) for i in range(8) for a in range(3)
                     if not i >> a & 1])


def hull_edges(points) -> list[tuple[int, int]]:
    """Index pairs of the edges of the convex hull of ``points`` (k, 3), without the diagonals
    of flat faces; a flat set: its polygon (points ordered by angle in their plane)."""
    from scipy.spatial import ConvexHull, QhullError
    pts = np.asarray(points, float)
    unique = np.unique(np.round(pts, 12), axis=0, return_index=True)[1]
    if unique.size < 2:
        return []
    try:
        hull = ConvexHull(pts[unique])
    except (QhullError, ValueError):
        centred = pts[unique] - pts[unique].mean(axis=0)
        _, _, vt = np.linalg.svd(centred)
        angle = np.arctan2(centred @ vt[1], centred @ vt[0])
        order = unique[np.argsort(angle)]
        return [(int(order[i]), int(order[(i + 1) % len(order)])) for i in range(len(order))]
    faces: dict = {}
    for simplex, normal in zip(hull.simplices, hull.equations[:, :3]):
        for a, b in ((0, 1), (1, 2), (0, 2)):
            edge = tuple(sorted((int(unique[simplex[a]]), int(unique[simplex[b]]))))
            faces.setdefault(edge, []).append(normal)
    return [e for e, normals in faces.items()
            if len(normals) < 2 or abs(float(np.dot(normals[0], normals[1]))) < 1 - 1e-9]


def _equal_box(ax, points, zoom: float = 1.0) -> None:
    """Equal scales on the three axes: limits and box aspect from the data ranges."""
    lo, hi = np.min(points, axis=0), np.max(points, axis=0)
    span = hi - lo
    pad = np.maximum(span, 0.05 * span.max()) * 0.04 + 1e-9
    lo, hi = lo - pad, hi + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(hi - lo, zoom=zoom)


def _tension_norm(tension_n) -> Normalize:
    lo, hi = float(np.min(tension_n)), float(np.max(tension_n))
    return Normalize(lo, hi if hi > lo else lo + 1.0)


def draw_geometry(ax, sc: Scene, cmap: str = 'viridis', labels: bool = True) -> ScalarMappable:
    """The frame (the anchors' box edges), the anchors (numbered), each cable along its
    static shape coloured by its tension (the returned mappable, range min..max tension), the
    platform (its attachments' hull, or a point for a point mass) on a 3D Axes. Cable lines
    carry gid ``cable-<i>``."""
    norm = _tension_norm(sc.tension_n)
    colours = ScalarMappable(norm, cmap)
    colours.set_array(sc.tension_n)
    ax.add_collection3d(Line3DCollection(box_edges(sc.anchors_m), colors='0.6', lw=0.8,
                                         linestyles='--'))
    ax.scatter(*sc.anchors_m.T, color='k', marker='^', s=22, depthshade=False, label='anchors')
    for i, points in enumerate(sc.cable_points_m):
        ax.plot(*points.T, color=colours.to_rgba(sc.tension_n[i]), lw=2.0, gid=f'cable-{i}')
        if labels:
            ax.text(*sc.anchors_m[i], f' {i}', fontsize=7)
    _draw_platform(ax, sc.centroid_m, sc.attachments_m, sc.point_mass, 'platform',
                   'tab:orange', 1.8)
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_zlabel('z (m)')
    _equal_box(ax, np.concatenate([sc.anchors_m, sc.cable_points_m.reshape(-1, 3)]))
    return colours


def _draw_platform(ax, centroid, attachments, point_mass: bool, gid: str, color, lw=1.5,
                   alpha=1.0):
    """The platform as one line (gid ``gid``): a square marker at the centroid for a point
    mass, else the edges of its attachments' hull (segments separated by NaN) with a marker
    at each attachment."""
    if point_mass:
        ax.plot(*np.asarray(centroid, float)[:, None], ls='none', marker='s', ms=7, color=color,
                alpha=alpha, gid=gid)
        return
    attachments = np.asarray(attachments, float)
    gap = np.full(3, np.nan)
    path = np.array([p for i, j in hull_edges(attachments)
                     for p in (attachments[i], attachments[j], gap)]).reshape(-1, 3)
    ax.plot(*path.T, color=color, lw=lw, alpha=alpha, marker='.', ms=4, gid=gid)


def geometry_figure(sc: Scene, path: Path, title: str = '') -> Figure:
    """``geometry.png``: :func:`draw_geometry` with a tension colour bar (N)."""
    fig = _figure(8.0, 6.6)
    ax = fig.add_subplot(projection='3d')
    colours = draw_geometry(ax, sc)
    bar = fig.colorbar(colours, ax=ax, shrink=0.65, pad=0.1)
    bar.set_label('cable tension at the platform end (N)')
    sag = ' (static catenary shapes)' if sc.statics == 'sag' else ' (straight chords)'
    ax.set_title((title + '\n' if title else '') + 'frame, anchors (numbered), cables' + sag
                 + ', platform', fontsize=9)
    ax.view_init(elev=22, azim=-58)
    fig.subplots_adjust(left=0.0, right=0.95, top=0.93, bottom=0.03)
    return _save(fig, path)


# --------------------------------------------------------------------------------- modes

@dataclass(frozen=True, eq=False)
class ModeShape:
    """One mode as drawn: its JSON-like data and, world frame (m), the static cable points
    (n, s, 3) from attachment to anchor with their displacements, and the platform's
    centroid and attachments (k, 3) with theirs (mass-normalised shape: 1/sqrt(kg) units)."""

    index: int
    frequency_hz: float
    kind: str
    cable: int | None
    platform_fraction: float
    cable_points_m: np.ndarray
    cable_displacement: np.ndarray
    centroid_m: np.ndarray
    centroid_displacement: np.ndarray
    attachments_m: np.ndarray
    attachment_displacement: np.ndarray
    point_mass: bool
    multiplicity: int = 1


def multiplicity(frequency_hz, relative: float = 1e-4) -> np.ndarray:
    """(k,) how many of the modes lie within ``relative`` of each mode's frequency."""
    f = np.asarray(frequency_hz, dtype=float)
    return np.sum(np.abs(f[:, None] - f[None, :]) <= relative * np.maximum(f[:, None], 1e-12),
                  axis=1)


def pick_modes(kinds, fractions, platform: int = 3, cable: int = 3,
               frequency_hz=None) -> list[int]:
    """Indices of the ``platform`` lowest platform modes (topped up, where the band has fewer,
    with the other modes of the largest platform energy ``fractions``, those with at least
    :data:`PLATFORM_MIN_FRACTION` of it) and then of the
    ``cable`` lowest cable modes not already picked, one per repeated frequency where
    ``frequency_hz`` is given (the first transverse modes of symmetric cables come in sets);
    each group ascending."""
    kinds, fractions = list(kinds), np.asarray(fractions, dtype=float)
    plat = [i for i, k in enumerate(kinds) if k == 'platform'][:platform]
    rest = [int(i) for i in np.argsort(-fractions, kind='stable')
            if int(i) not in plat and fractions[i] >= PLATFORM_MIN_FRACTION]
    plat += rest[:max(0, platform - len(plat))]
    cab: list[int] = []
    for i, k in enumerate(kinds):
        if k != 'cable' or i in plat or len(cab) == cable:
            continue
        if frequency_hz is not None and any(
                abs(frequency_hz[i] - frequency_hz[j]) <= 1e-4 * frequency_hz[i] for j in cab):
            continue
        cab.append(i)
    return sorted(plat) + sorted(cab)


def mode_shapes(settings, eq, system, found, indices, samples: int = 33) -> list[ModeShape]:
    """World-frame drawings of modes ``indices`` of ``found``
    (:func:`cdpr_dynamics.dynamics.modes.modes`
    of ``system`` at ``eq``, the method's statics).

    Platform DOFs q = phi[:ndof] move the centroid by u and attachment i by G_i q
    (u + theta x r_i). With interior nodes (fem, fem_sag: n elements, interior node j from the
    anchor side at unstrained fraction (j+1)/n of the cable from the anchor) the cable points
    are the nodes (:func:`cdpr_dynamics.analysis.pipeline.cable_shapes` at n + 1 points) with the
    mode's nodal displacements; without (massless models) the static shape moves with the
    platform end, linearly in the fraction along the cable (0 at the anchor).
    """
    from cdpr_dynamics.analysis.pipeline import cable_shapes
    if found.shapes is None:
        raise FigureError('no mode shapes to draw: compute the modes with shapes=True')
    geo = eq.geometry
    nd = system.platform_dofs
    g = geo.attachment_map()                                     # (n, 3, nd)
    attachments = geo.position_m + geo.lever_m
    ncab = geo.n_cables
    interior = system.assembly.interior_dofs // ncab // 3        # interior nodes per cable
    n_el = interior + 1
    shape = cable_shapes(eq, n_el + 1 if interior else samples)  # from the attachment
    points = attachments[:, None, :] + shape
    out = []
    repeats = multiplicity(found.frequency_hz)
    for k in indices:
        phi = np.asarray(found.shapes[:, k], dtype=float)
        q = phi[:nd]
        ends = np.einsum('cia,a->ci', g, q)                      # (n, 3)
        if interior:
            nodes = phi[nd:].reshape(ncab, interior, 3)          # anchor side first
            disp = np.concatenate([ends[:, None], nodes[:, ::-1], np.zeros((ncab, 1, 3))],
                                  axis=1)
        else:
            t = np.linspace(0.0, 1.0, shape.shape[1])
            disp = (1.0 - t)[None, :, None] * ends[:, None, :]
        cable = int(found.cable[k])
        out.append(ModeShape(int(k), float(found.frequency_hz[k]), found.kind[k],
                             cable if cable >= 0 else None, float(found.platform_fraction[k]),
                             points, disp, np.asarray(geo.position_m, float), q[:3].copy(),
                             attachments, ends, bool(settings.robot.point_mass),
                             int(repeats[k])))
    return out


def mode_scale(mode: ModeShape, size_m: float, fraction: float = MODE_SCALE_FRACTION,
               cable_cap: float = MODE_CABLE_CAP_FRACTION) -> float:
    """The factor that draws the mode visibly: a platform or mixed mode with the platform's
    largest displacement ``fraction * size_m`` (the cables' at most ``cable_cap * size_m``),
    a cable mode with its largest displacement ``fraction * size_m``."""
    platform = max(np.linalg.norm(mode.attachment_displacement, axis=-1).max(initial=0.0),
                   float(np.linalg.norm(mode.centroid_displacement)))
    cables = np.linalg.norm(mode.cable_displacement, axis=-1).max(initial=0.0)
    if mode.kind in ('platform', 'mixed') and platform > 0:
        return min(fraction * size_m / platform,
                   cable_cap * size_m / cables if cables > 0 else np.inf)
    largest = max(platform, cables)
    return fraction * size_m / largest if largest > 0 else 0.0


def draw_mode(ax, mode: ModeShape, scale: float, anchors_m) -> None:
    """One mode on a 3D Axes: the undeformed cables and platform faint, the deformed ones
    (static positions + ``scale`` x displacement) drawn; the cable carrying a cable mode in
    red. Deformed cable lines carry gid ``mode-cable-<i>``, the deformed platform
    ``platform-deformed`` (the centroid for a point mass, else the attachments' hull)."""
    ax.add_collection3d(Line3DCollection(box_edges(anchors_m), colors='0.75', lw=0.6,
                                         linestyles='--'))
    for i, (pts, d) in enumerate(zip(mode.cable_points_m, mode.cable_displacement)):
        ax.plot(*pts.T, color='0.7', lw=0.8, alpha=0.6)
        colour = 'tab:red' if i == mode.cable else 'tab:blue'
        ax.plot(*(pts + scale * d).T, color=colour, lw=1.6 if i == mode.cable else 1.1,
                gid=f'mode-cable-{i}')
    _draw_platform(ax, mode.centroid_m, mode.attachments_m, mode.point_mass, 'platform', '0.6',
                   1.0, 0.5)
    ax.quiver(*mode.centroid_m, *(scale * mode.centroid_displacement), color='k', lw=1.0,
              arrow_length_ratio=0.25)
    _draw_platform(ax, mode.centroid_m + scale * mode.centroid_displacement,
                   mode.attachments_m + scale * mode.attachment_displacement, mode.point_mass,
                   'platform-deformed', 'tab:orange', 1.8)
    ax.set_xlabel('x (m)', fontsize=7, labelpad=-8)
    ax.set_ylabel('y (m)', fontsize=7, labelpad=-8)
    ax.set_zlabel('z (m)', fontsize=7, labelpad=-8)
    ax.tick_params(labelsize=6, pad=-2)
    _equal_box(ax, np.concatenate([np.asarray(anchors_m, float),
                                   mode.cable_points_m.reshape(-1, 3)]), zoom=1.0)


def mode_title(mode: ModeShape) -> str:
    """``32.40 Hz, platform`` / ``14.46 Hz, cable 3`` and the platform energy fraction."""
    what = mode.kind + (f' (cable {mode.cable})' if mode.cable is not None else '')
    repeated = f', one of {mode.multiplicity} at this frequency' if mode.multiplicity > 1 else ''
    percent = 100 * mode.platform_fraction
    energy = f'{percent:.3g} %' if percent >= 1e-3 else '< 0.001 %'
    return (f'{mode.frequency_hz:.2f} Hz, {what}\n'
            f'platform energy {energy}{repeated}')


def modes_figure(modes: list[ModeShape], anchors_m, path: Path, title: str = '') -> Figure:
    """``modes.png``: one small 3D panel per mode (three per row), each deformation scaled to
    :data:`MODE_SCALE_FRACTION` of the frame's largest extent."""
    if not modes:
        raise FigureError('no modes to draw')
    anchors = np.asarray(anchors_m, float)
    size = float(np.ptp(anchors, axis=0).max())
    cols = min(3, len(modes))
    rows = -(-len(modes) // cols)
    fig = _figure(3.6 * cols, 3.5 * rows + 0.8)
    for i, mode in enumerate(modes):
        ax = fig.add_subplot(rows, cols, i + 1, projection='3d')
        draw_mode(ax, mode, mode_scale(mode, size), anchors)
        ax.set_title(mode_title(mode), fontsize=8)
        ax.view_init(elev=20, azim=-58)
    fig.suptitle((title + '\n' if title else '') + 'mode shapes drawn with the platform (platform'
                 f' and mixed modes; cables at most {100 * MODE_CABLE_CAP_FRACTION:g} %) or the '
                 f'largest displacement (cable modes) at {100 * MODE_SCALE_FRACTION:g} % of the '
                 "frame size;\nundeformed grey, platform orange (arrow: centroid motion), the "
                 "mode's cable red", fontsize=9)
    fig.subplots_adjust(left=0.02, right=0.96, bottom=0.02, top=1 - 1.0 / fig.get_figheight(),
                        wspace=0.08, hspace=0.15)
    return _save(fig, path)


# ------------------------------------------------------------------------------ trade-off

FLOOR_PCT = 1e-5      # errors below this are drawn at it (log axes)
CAP_PCT = 100.0       # errors above this are drawn at it, labelled with their value


def pareto(times, errors) -> np.ndarray:
    """Indices of the points no other point beats in both time and error, by time."""
    times, errors = np.asarray(times, float), np.asarray(errors, float)
    order = np.lexsort((errors, times))
    front, best = [], np.inf
    for i in order:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return np.array(front, dtype=int)


def row_label(row) -> str:
    """``fem 16`` for a discretised method's row, the method's name otherwise."""
    n = row['elements_per_cable']
    return f"{row['method']} {n}" if row['method'] in ('fem', 'fem_sag') else row['method']


# label offsets (points) tried in turn, and their alignment
_OFFSETS = [((5, 3), 'left', 'bottom'), ((5, -3), 'left', 'top'), ((-5, 3), 'right', 'bottom'),
            ((-5, -3), 'right', 'top'), ((0, 7), 'center', 'bottom'),
            ((0, -7), 'center', 'top'), ((9, 12), 'left', 'bottom'),
            ((9, -12), 'left', 'top'), ((-9, 12), 'right', 'bottom'),
            ((-9, -12), 'right', 'top'), ((0, 18), 'center', 'bottom'),
            ((0, -18), 'center', 'top')]


def place_labels(ax, points, labels, must, renderer, obstacles=()) -> list:
    """Annotate ``points`` (data coordinates) with ``labels``, trying the offsets of
    :data:`_OFFSETS` in turn and keeping the first whose text box overlaps no earlier label,
    no marker and no box of ``obstacles`` and stays inside the axes. Labels where ``must`` is
    true are placed even when all collide (at the least overlap; far offsets with a leader
    line); the others take only the six near offsets, or are dropped.
    Returns the annotations kept."""
    frame = ax.get_window_extent(renderer)
    xy = ax.transData.transform(np.asarray(points, float))
    radius = 5.0
    taken = [np.array([x - radius, y - radius, x + radius, y + radius]) for x, y in xy]
    taken += [np.array([b.x0, b.y0, b.x1, b.y1]) for b in obstacles]
    kept = []
    order = sorted(range(len(labels)), key=lambda i: not must[i])
    for i in order:
        best, best_cost = None, np.inf
        for offset, ha, va in _OFFSETS:
            far = max(abs(offset[0]), abs(offset[1])) > 8
            if far and not must[i]:
                break               # only the near places: a far label may name a neighbour
            note = ax.annotate(labels[i], points[i], textcoords='offset points', xytext=offset,
                               ha=ha, va=va, fontsize=7, arrowprops=dict(
                                   arrowstyle='-', lw=0.5, color='0.5', shrinkA=0,
                                   shrinkB=3) if far else None)
            b = note.get_window_extent(renderer)
            box = np.array([b.x0, b.y0, b.x1, b.y1])
            cost = sum(_overlap(box, other) for k, other in enumerate(taken) if k != i)
            cost += 1e6 * (b.x0 < frame.x0 or b.x1 > frame.x1 or b.y0 < frame.y0
                           or b.y1 > frame.y1)
            if cost < best_cost:
                if best is not None:
                    best[0].remove()
                best, best_cost = (note, box), cost
            else:
                note.remove()
            if cost == 0:
                break
        if best_cost > 0 and not must[i]:
            best[0].remove()
            continue
        taken.append(best[1])
        kept.append(best[0])
    return kept


def _overlap(a, b) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return w * h if w > 0 and h > 0 else 0.0


def tradeoff_figure(rows: list[dict], path: Path, title: str,
                    tolerance: float | None = None) -> Figure:
    """Two log-log panels (frequency error, FRF error, %) against compute time (ms): a colour
    and marker per method family (legend), marker size growing with the elements per cable,
    the Pareto front, ``auto``'s pick starred. Errors are drawn between :data:`FLOOR_PCT` and
    :data:`CAP_PCT` (above: a triangle, the value in its label). Labels: every Pareto point
    and the pick always; the others where they fit without overlapping (:func:`place_labels`)."""
    ok = [r for r in rows if 'time_s' in r]
    fig = _figure(13.0, 5.8)
    axes = fig.subplots(1, 2, sharex=True)
    times = 1e3 * np.array([r['time_s'] for r in ok])
    pending = []
    for ax, key, what in ((axes[0], 'freq_error_pct', 'natural frequencies in the band'),
                          (axes[1], 'frf_error_pct', 'damped FRF of the centroid')):
        values = np.array([r[key] for r in ok], dtype=float)
        errors = np.clip(values, FLOOR_PCT, CAP_PCT)
        front = pareto(times, errors)
        ax.step(times[front], errors[front], where='post', color='tab:orange', lw=1.5,
                zorder=2, label='Pareto front')
        seen = set()
        for r, t, e, v in zip(ok, times, errors, values):
            name, colour, marker = FAMILIES.get(r['method'], (r['method'], 'tab:purple', 'o'))
            n = max(1, int(r['elements_per_cable'] or 1))
            ax.scatter(t, e, color=colour, s=14 + 7 * np.log2(n), zorder=3,
                       marker='^' if v > CAP_PCT else marker,
                       label=name if name not in seen else '_nolegend_')
            seen.add(name)
        for i in [i for i, r in enumerate(ok) if r.get('auto')]:
            ax.scatter(times[i], errors[i], marker='*', s=260, facecolor='none',
                       edgecolor='tab:purple', zorder=4, label='auto' + (
                           f' at {100 * tolerance:g} %' if tolerance else ''))
        ax.axhline(CAP_PCT, color='0.6', lw=0.8, ls=':')
        ax.set_xscale('log')
        ax.set_yscale('log')
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f'{v:g}'))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel('compute time: build + FRF + modes in the band (ms)')
        ax.set_ylabel(f'max relative error, {what} (%)')
        ax.grid(True, which='both', alpha=0.25)
        ax.set_ylim(errors.min() / 3.0, CAP_PCT * 4.0)
        ax.set_xlim(times.min() / 1.4, times.max() * 1.6)
        legend = ax.legend(loc='lower left', fontsize=7, title='method family (size: n)',
                           title_fontsize=7, framealpha=0.9)
        labels = [row_label(r) + (f' ({v:.0f} %)' if v > CAP_PCT else '')
                  for r, v in zip(ok, values)]
        must = [i in set(front.tolist()) or bool(r.get('auto')) for i, r in enumerate(ok)]
        pending.append((ax, np.column_stack([times, errors]), labels, must, legend))
    axes[0].text(0.99, 0.99, '100 % = modes missed', transform=axes[0].transAxes,
                 ha='right', va='top', fontsize=7, color='0.4')
    axes[1].text(0.99, 0.99, 'triangles: off by more than 100 % (value in the label)',
                 transform=axes[1].transAxes, ha='right', va='top', fontsize=7, color='0.4')
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    renderer = fig.canvas.get_renderer()
    for ax, points, labels, must, legend in pending:
        place_labels(ax, [tuple(p) for p in points], labels, must, renderer,
                     [legend.get_window_extent(renderer)])
    return _save(fig, path)
