"""The figure of ``cdpr_demo``: the load and the predicted displacement along it, the cable
tensions with the lowest one under the load and the slack intervals, the FRF |H| (m/N,
log-log) with the platform modes marked (:mod:`cdpr_dynamics.analysis.figures` draws the FRF and
the
shading). Legends beside the axes, markers where predictions are sparse."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from cdpr_dynamics.cli.demo_plan import Trajectory
from cdpr_dynamics.cli.demo_results import along, Received, SlackComparison, TensionEstimate


def _runs(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """(nt,) True before each gap longer than 5 periods (where a line is broken)."""
    return np.append(np.diff(t_s) > 5 * period_s, True)


def _broken(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """``t_s`` with NaN after each gap longer than 5 periods: a line drawn on it stops at gaps
    instead of bridging them."""
    x = t_s.astype(float).copy()
    x[1:][_runs(t_s, period_s)[:-1]] = np.nan
    return x


def _lonely(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """(nt,) True for points with no neighbour within 5 periods: where predictions are sparse
    (drawn as markers, a line would not show them)."""
    gap = _runs(t_s, period_s)
    return gap & np.insert(gap[:-1], 0, True)


def _spans(t_s: np.ndarray, mask: np.ndarray, period_s: float) -> list[tuple[float, float]]:
    """(start, end) s of the runs of ``mask`` between gaps, each widened by half a period."""
    spans, start = [], None
    ends = _runs(t_s, period_s)
    for k, (t, m) in enumerate(zip(t_s, mask)):
        if m and start is None:
            start = t
        if start is not None and (not m or ends[k]):
            stop = t if m else t_s[k - 1]
            spans.append((start - period_s / 2, stop + period_s / 2))
            start = None
    return spans


def _frf_modes(frf: dict) -> list[dict]:
    """The service's modes as figures.mark_modes takes them: kind from
    ``mode_platform_fraction`` (:func:`cdpr_dynamics.dynamics.modes.classify`), else platform where
    listed in ``platform_natural_frequencies_hz``."""
    from cdpr_dynamics.dynamics.modes import classify
    natural = np.asarray(frf.get('natural_frequencies_hz', []), dtype=float)
    fraction = frf.get('mode_platform_fraction')
    if fraction is not None and len(fraction) == natural.size:
        kinds = classify(np.asarray(fraction, dtype=float))
    else:
        platform = np.asarray(frf.get('platform_natural_frequencies_hz', []), dtype=float)
        kinds = ['platform' if np.any(np.isclose(f, platform, rtol=1e-6)) else None
                 for f in natural]
    return [{'frequency_hz': float(f), 'kind': k} for f, k in zip(natural, kinds)]


def plot(path: Path, result: dict, got: Received, plan: Trajectory, frf: dict,
         spring: dict | None, tensions: TensionEstimate | str, t0_ns: int,
         comparison: SlackComparison | None = None) -> None:
    """The demo's PNG at ``path``: ``got`` (what arrived), the node's ``frf`` and the
    ``spring`` override (per unit force along the load), ``tensions`` (or why there are none),
    times from ``t0_ns``; ``result`` gives the model and the counts of the title;
    ``comparison``: the slack-aware and linear predictions of the same inputs, both drawn, the
    slack intervals shaded."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from cdpr_dynamics.analysis.figures import draw_frf, shade_intervals

    args, load = plan.args, plan.load
    d, period = load.direction, 1.0 / args.wrench_rate
    stamps = np.array(sorted(got.predictions), dtype=np.int64)
    t = (stamps - t0_ns) * 1e-9
    u = np.array([got.predictions[s][1:] for s in stamps]).reshape(-1, 3) @ d
    fig, axes = plt.subplots(3, 1, figsize=(11, 12), layout='constrained')
    side = dict(loc='upper left', bbox_to_anchor=(1.08, 1.0), fontsize=8, borderaxespad=0.0)
    load_text = (f'{load.amplitude_n:g} N along {np.round(d, 3).tolist()}'
                 + (f' and {np.round(load.moment_nm, 3).tolist()} N m' if np.any(load.moment_nm)
                    else ''))

    ax = axes[0]
    mode = result.get('slack_mode', 'aware')
    ax.plot(_broken(t, period), u * 1e3, lw=0.8, color='C0',
            label=f'predicted displacement\nalong the load (node, {mode})')
    slack_spans = []
    if comparison is not None and comparison.t_s.size:
        other = comparison.u_linear if mode == 'aware' else comparison.u_aware
        ax.plot(_broken(comparison.t_s, period), other @ d * 1e3, lw=0.8, ls='--',
                color='C1', label='linear prediction' if mode == 'aware'
                else 'slack-aware prediction')
        slack_spans = _spans(comparison.t_s, comparison.slack, period)
        shade_intervals(ax, slack_spans, label='a cable slack\n(slack-aware)')
    lonely = _lonely(t, period)
    if lonely.any():
        ax.plot(t[lonely], u[lonely] * 1e3, '.', ms=4, color='C0',
                label='sparse predictions (markers)')
    ax.set_xlim(0, args.duration)
    ax.set_xlabel('time since the first wrench (s)')
    ax.set_ylabel('displacement along the load (mm)')
    ax.grid(True, alpha=0.3)
    twin = ax.twinx()
    tt = np.linspace(0, args.duration, 4000)
    twin.plot(tt, load.at(tt)[0] @ d, color='0.55', lw=0.6, ls=':', label='load (N, right axis)')
    twin.set_ylabel('load along its direction (N)')
    lines, more = ax.get_legend_handles_labels(), twin.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], **side)
    ax.set_title(f'live prediction: {load_text} at {load.excitation_hz:g} Hz, '
                 f'{args.wrench_rate:g} wrenches/s, moving on a {args.radius * 100:g} cm circle '
                 f'(poses at {args.pose_rate:g} Hz)', fontsize=10)

    ax = axes[1]
    if isinstance(tensions, TensionEstimate):
        rows = np.array(sorted(got.tensions))
        rows[:, 0] -= t0_ns * 1e-9                       # the one in force at t0, and later
        rows = rows[max(int(np.searchsorted(rows[:, 0], 0.0, side='right')) - 1, 0):]
        rows[:, 0] = np.maximum(rows[:, 0], 0.0)
        for i in range(1, rows.shape[1]):
            ax.plot(np.append(rows[:, 0], args.duration),
                    np.append(rows[:, i], rows[-1, i]), lw=0.8, alpha=0.7,
                    drawstyle='steps-post', label=f'cable {i - 1}, static')
        x = _broken(tensions.t_s, period)
        low = tensions.total_n.min(axis=1)
        ax.plot(x, low, color='k', lw=1.0, ls='--', label='lowest cable force,\nlinear')
        if comparison is not None and comparison.t_s.size:
            ax.plot(_broken(comparison.t_s, period), comparison.force_aware.min(axis=1),
                    color='C0', lw=1.0, label='lowest cable force,\nslack-aware')
        lonely = _lonely(tensions.t_s, period)
        if lonely.any():
            ax.plot(tensions.t_s[lonely], low[lonely], '.', ms=4, color='k')
        ax.axhline(tensions.tension_min_n, color='C3', ls='--', lw=0.8, label='tension.min_n')
        ax.axhline(0.0, color='0.3', lw=0.6)
        shade_intervals(ax, slack_spans or _spans(tensions.t_s, low <= 0.0, period),
                        label='a cable slack' if slack_spans else 'a cable would be slack')
        ax.set_title('cable tensions: static (cable_tensions) and the lowest cable force under '
                     'the load (its damper included)', fontsize=10)
    else:
        ax.text(0.5, 0.5, str(tensions), ha='center', va='center', transform=ax.transAxes)
        ax.set_title('cable tensions', fontsize=10)
    ax.set_xlim(0, args.duration)
    ax.set_xlabel('time since the first wrench (s)')
    ax.set_ylabel('cable tension (N)')
    ax.grid(True, alpha=0.3)
    ax.legend(**side)

    ax = axes[2]
    curves = [(f'{result["method"]} (service)', along(frf, d), None)]
    if spring:
        curves.append(('method=spring (override)', along(spring, d), None))
    draw_frf(ax, frf['frequency_hz'], curves, _frf_modes(frf), unit='m/N',
             ylabel='|H| along the load (m/N)')
    ax.legend(**side)
    ax.set_title(f'frequency_response per unit force along the load, at the final pose '
                 f'({frf["frequency_hz"].size} points)', fontsize=10)
    fig.suptitle(f'cdpr_demo: {result["method"]} model, {result["dofs"]} DOFs; '
                 f'{result["wrenches_predicted"]} of {result["wrenches_published"]} wrenches '
                 f'predicted ({100 * result["prediction_ratio"]:.2f} %)', fontsize=11)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
