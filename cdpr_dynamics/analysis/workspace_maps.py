"""PNG maps and the one-page summary of a ``cdpr_workspace`` table.

Maps: for each design variant and each slice axis, one figure with a row per quantity
(:data:`QUANTITIES`: the lowest platform mode, the peak receptance, the tension margin) and a
column per slice (at most :data:`MAX_SLICES`, evenly spread, ends included). A quantity has
one colour scale in every variant's figure (:func:`colour_limits`), so variants compare by
colour. Poses whose status is not ``ok`` are hatched (white where they leave no value),
feasible poses without a value (e.g. no platform mode in the band) white; the legend says so.
The frame's outline and the anchors (projected on the slice plane) are drawn. Maps need a grid
(not ``--poses``).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

MAX_SLICES = 5
#: (column, colour-bar label, transform, colour map)
QUANTITIES = (('lowest_platform_hz', 'lowest platform mode (Hz)', None, 'viridis'),
              ('peak_receptance_m_per_n', 'log10 peak receptance (m/N)', np.log10, 'magma_r'),
              ('tension_margin_n', 'tension margin (N)', None, 'RdYlGn'))
_AXES = 'xyz'


def slice_indices(count: int, most: int = MAX_SLICES) -> list[int]:
    """At most ``most`` indices of ``count``, evenly spread, both ends included."""
    if count <= most:
        return list(range(count))
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, most)})


def variant_labels(run) -> list[str]:
    return [', '.join(f'{k} = {v}' for k, v in values.items()) for values in run.variant_list]


def transformed(name: str, data) -> np.ndarray:
    """The values of quantity ``name`` as mapped (its transform applied), NaN where none."""
    transform = {q[0]: q[2] for q in QUANTITIES}[name]
    data = np.asarray(data, dtype=float)
    if transform is not None:
        with np.errstate(divide='ignore', invalid='ignore'):
            data = transform(data)
    return np.where(np.isfinite(data), data, np.nan)


def colour_limits(table) -> dict:
    """Per quantity of :data:`QUANTITIES` its (vmin, vmax) over every row of ``table``, all
    variants together ((0, 1) where it has no value)."""
    limits = {}
    for name, *_ in QUANTITIES:
        finite = transformed(name, _column(table, name))
        finite = finite[np.isfinite(finite)]
        limits[name] = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    return limits


def write_maps(table, run, axes=('z',)) -> list[Path]:
    """The map PNGs of ``table`` (a grid run), one per variant and slice axis."""
    if run.grid is None:
        return []
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    n = run.poses.shape[0]
    status = np.asarray(table.column('status').to_pylist(), dtype=object)
    paths = []
    labels = variant_labels(run)
    limits = colour_limits(table)
    for v, label in enumerate(labels):
        rows = slice(v * n, (v + 1) * n)
        bad = (status[rows] != 'ok').reshape(run.shape)
        values = {name: _column(table, name)[rows].reshape(run.shape) for name, *_ in
                  QUANTITIES}
        for axis in axes:
            fig = map_figure(plt, run, values, bad, _AXES.index(axis), limits)
            fig.suptitle(f'{run.config_path.name}: workspace maps across {axis}\n'
                         f'({"; ".join(filter(None, [_model(run), label]))})',
                         fontsize='medium')
            suffix = f'_v{v}' if len(labels) > 1 else ''
            path = run.out / f'maps_{axis}{suffix}.png'
            fig.savefig(path, dpi=110)
            plt.close(fig)
            paths.append(path)
    return paths


def _model(run) -> str:
    """The model of the maps' title ('' where --vary changes it)."""
    if 'model.method' in run.vary:
        return ''
    s = run.settings
    sized = s.method in ('fem', 'fem_sag') and 'model.elements_per_cable' not in run.vary
    return f'{s.method} n = {s.elements_per_cable}' if sized else s.method


def _column(table, name: str) -> np.ndarray:
    return np.asarray([math.nan if x is None else x for x in table.column(name).to_pylist()],
                      dtype=float)


def _edges(centres: np.ndarray, fallback: float) -> np.ndarray:
    if centres.size == 1:
        return np.array([centres[0] - fallback, centres[0] + fallback])
    mid = 0.5 * (centres[1:] + centres[:-1])
    return np.concatenate([[2 * centres[0] - mid[0]], mid, [2 * centres[-1] - mid[-1]]])


def map_figure(plt, run, values, bad, axis: int, limits: dict):
    """The figure of one variant across ``axis``: ``values`` {quantity: grid-shaped array},
    ``bad`` (grid-shaped) where the status is not ok, ``limits`` {quantity: (vmin, vmax)}."""
    from matplotlib.patches import Rectangle
    plane = [a for a in range(3) if a != axis]
    grid = run.grid
    lo, hi = run.settings.robot.frame_bounds_m
    fallback = 0.02 * float(np.max(hi - lo))
    edges = [_edges(grid[a], fallback) for a in plane]
    picks = slice_indices(grid[axis].size)
    fig, panels = plt.subplots(len(QUANTITIES), len(picks), squeeze=False,
                               figsize=(2.9 * len(picks) + 1.2, 2.7 * len(QUANTITIES)),
                               constrained_layout=True)
    anchors = run.settings.robot.anchors_m
    no_value = False
    for row, (name, label, _, cmap) in enumerate(QUANTITIES):
        shown = transformed(name, values[name])
        no_value |= bool(np.any(np.isnan(shown) & ~bad))
        vmin, vmax = limits[name]
        norm = None
        if name == 'tension_margin_n' and vmin < 0 < vmax:
            from matplotlib.colors import TwoSlopeNorm
            norm = TwoSlopeNorm(0.0, vmin, vmax)
        mesh = None
        for col, k in enumerate(picks):
            ax = panels[row, col]
            cut = np.take(shown, k, axis=axis)          # (n_plane0, n_plane1)
            hatch = np.take(bad, k, axis=axis)
            mesh = ax.pcolormesh(edges[0], edges[1], cut.T, cmap=cmap, shading='flat',
                                 **({'norm': norm} if norm else {'vmin': vmin, 'vmax': vmax}))
            for i, j in zip(*np.nonzero(hatch)):
                ax.add_patch(Rectangle((edges[0][i], edges[1][j]), edges[0][i + 1] -
                                       edges[0][i], edges[1][j + 1] - edges[1][j],
                                       fill=False, hatch='///', edgecolor='0.35',
                                       linewidth=0.0))
            ax.add_patch(Rectangle((lo[plane[0]], lo[plane[1]]), hi[plane[0]] - lo[plane[0]],
                                   hi[plane[1]] - lo[plane[1]], fill=False, edgecolor='k',
                                   linewidth=0.8))
            ax.plot(anchors[:, plane[0]], anchors[:, plane[1]], 'k^', markersize=6,
                    label='anchors (projected)')
            ax.set_aspect('equal')
            pad = 0.06 * float(np.max(hi - lo))
            ax.set_xlim(lo[plane[0]] - pad, hi[plane[0]] + pad)
            ax.set_ylim(lo[plane[1]] - pad, hi[plane[1]] + pad)
            ax.tick_params(labelsize='small')
            if row == 0:
                ax.set_title(f'{_AXES[axis]} = {grid[axis][k]:.3g} m', fontsize='medium')
            if row == len(QUANTITIES) - 1:
                ax.set_xlabel(f'{_AXES[plane[0]]} (m)')
            if col == 0:
                ax.set_ylabel(f'{_AXES[plane[1]]} (m)')
        fig.colorbar(mesh, ax=panels[row, :].tolist(), label=label, shrink=0.9)
    handles = [panels[0, 0].lines[-1],
               Rectangle((0, 0), 1, 1, facecolor='white', hatch='///', edgecolor='0.35',
                         label='hatched: status != ok (infeasible, crossing, ...);\n'
                               'white where it leaves no result')]
    if no_value:
        handles.append(Rectangle((0, 0), 1, 1, facecolor='white', edgecolor='0.35',
                                 label='white, not hatched: no value at a feasible pose\n'
                                       '(e.g. no platform mode in the band)'))
    fig.legend(handles=handles, loc='outside lower center', ncols=1 if len(picks) < 3 else 3,
               fontsize='small', frameon=False)
    return fig


def summary_text(table, run) -> str:
    """The one-page summary (Markdown) of a finished table."""
    n = run.poses.shape[0]
    status = np.asarray(table.column('status').to_pylist(), dtype=object)
    meta = json.loads(table.schema.metadata[b'cdpr_workspace'])
    lines = ['# cdpr_workspace summary', '', f'`{meta["command"]}`', '',
             f'{n} poses x {len(run.variant_list)} variant(s) = {run.rows} rows; config '
             f'`{meta["config_path"]}`, method `{run.settings.method}`.', '']
    columns = {name: _column(table, name) for name in
               ('lowest_platform_hz', 'peak_receptance_m_per_n', 'tension_margin_n',
                'min_stiffness_n_per_m', 'compute_s', 'x_m', 'y_m', 'z_m')}
    auto = table.column('auto_method').to_pylist()
    auto_n = table.column('auto_elements').to_pylist()
    for v, label in enumerate(variant_labels(run)):
        rows = np.arange(v * n, (v + 1) * n)
        ok = rows[status[rows] == 'ok']
        lines.append(f'## Variant {v}' + (f': {label}' if label else ''))
        counts = {s: int(np.sum(status[rows] == s)) for s in dict.fromkeys(status[rows])}
        lines.append(f'- feasible (status ok): {ok.size} of {n} poses '
                     f'({100.0 * ok.size / n:.1f} %); ' + ', '.join(f'{s} {c}' for s, c in
                                                                    counts.items()))

        def where(i):
            return (f'({columns["x_m"][i]:.3g}, {columns["y_m"][i]:.3g}, '
                    f'{columns["z_m"][i]:.3g}) m')
        for name, text, pick, unit in (
                ('lowest_platform_hz', 'lowest platform mode', np.nanargmin, 'Hz'),
                ('peak_receptance_m_per_n', 'peak receptance', np.nanargmax, 'm/N'),
                ('tension_margin_n', 'tension margin', np.nanargmin, 'N'),
                ('min_stiffness_n_per_m', 'static stiffness', np.nanargmin, 'N/m')):
            values = columns[name][ok]
            if not np.any(np.isfinite(values)):
                lines.append(f'- {text}: no value')
                continue
            i = ok[pick(values)]
            extreme = 'lowest' if pick is np.nanargmin else 'highest'
            lines.append(f'- {text}: {np.nanmin(values):.4g} .. {np.nanmax(values):.4g} '
                         f'{unit}; {extreme} at {where(i)}')
        picks = {}
        for i in ok:
            if auto[i] is not None:
                key = f'{auto[i]} n={auto_n[i]}'
                picks[key] = picks.get(key, 0) + 1
        if picks:
            lines.append('- auto picks: ' + ', '.join(f'{k} ({c})' for k, c in
                                                      sorted(picks.items(),
                                                             key=lambda kv: -kv[1])))
        spent = columns['compute_s'][rows]
        lines.append(f'- compute: {np.nansum(spent):.1f} s in all, '
                     f'{1e3 * np.nanmean(spent):.1f} ms per pose')
        lines.append('')
    return '\n'.join(lines)


def write_summary(table, run) -> Path:
    path = run.out / 'summary.md'
    path.write_text(summary_text(table, run))
    return path
