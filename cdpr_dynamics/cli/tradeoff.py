"""``cdpr_tradeoff``: speed against accuracy of every cable model for one scene.

    cdpr_tradeoff [--config PATH] [--f-max HZ] [--tolerance TOL] [--repeat N]
                  --csv PATH --plot PATH

For spring, fem n = 1 ... 64, catenary, catenary_exact, fem_sag n = 4 ... 64 and dsm: the error
against the reference over the band [0, f_max] (natural frequencies in the band, paired in
ascending order, a missed mode counting 100 %; the damped FRF of the centroid, max relative
error of the complex response over the sweep, which bounds the error of |A|) against the
compute time (build + FRF + modes in the band, median of ``--repeat`` runs). The reference is
``dsm`` where sag is negligible and Richardson-extrapolated ``fem_sag`` where it is not
(:func:`cdpr_dynamics.selection.reference.reference_solution`); the chart's title says which. The
CSV
also has ``auto``'s estimates of both errors, so the estimates can be read against the truth,
and the chart marks what ``auto`` picks at ``model.tolerance``.

Timings are wall-clock in this process; run with OMP_NUM_THREADS=1 on a shared machine.
Errors end with one line naming the cause and exit status 1.
"""
from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.analysis.pipeline import AnalysisError, equilibrium
from cdpr_dynamics.cli import interruptible, plain
from cdpr_dynamics.analysis.config import ConfigError, load_settings
from cdpr_dynamics.dynamics.system import DynamicsError
from cdpr_dynamics.selection.estimates import Estimator
# re-exported for the tests
from cdpr_dynamics.analysis.figures import CAP_PCT, pareto, tradeoff_figure  # noqa: F401
from cdpr_dynamics.selection.reference import measure_error, reference_solution, solve
from cdpr_dynamics.selection.auto import SelectionError, choose_model

SWEEP = ([('spring', 1)] + [('fem', n) for n in (1, 2, 4, 8, 16, 32, 64)]
         + [('catenary', 1), ('catenary_exact', 1)]
         + [('fem_sag', n) for n in (4, 8, 16, 32, 64)] + [('dsm', 0)])
COLUMNS = ('method', 'elements_per_cable', 'dofs', 'freq_error_pct', 'frf_error_pct', 'time_s',
           'modes_in_band', 'missed_modes', 'estimated_freq_error_pct',
           'estimated_frf_error_pct', 'valid', 'note')


def time_solution(settings, eq, method, n, reference, repeat: int):
    """(median seconds, last solution) of build + FRF + modes over ``repeat`` runs."""
    samples, solution = [], None
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        solution = solve(settings, eq, method, n, reference.frequency_grid_hz,
                         reference.damping, reference.f_max_hz, reference.modes_in_band)
        samples.append(time.perf_counter() - start)
    return float(np.median(samples)), solution


def sweep(settings, eq, reference, repeat: int = 3, progress=None, choice=None) -> list[dict]:
    """One row (dict of :data:`COLUMNS`) per method and discretisation of :data:`SWEEP`, and
    one for ``auto``'s ``choice`` when the sweep does not have it (``auto`` True on its row)."""
    estimator = Estimator(settings, eq, reference.f_max_hz, reference.damping)
    entries = list(SWEEP)
    picked = None if choice is None else (choice.method, choice.elements_per_cable)
    if picked is not None and picked not in entries:
        entries.append(picked)
    rows = []
    for method, n in (progress or iter)(entries):
        row = {'method': method, 'elements_per_cable': n, 'auto': (method, n) == picked}
        try:
            seconds, solution = time_solution(settings, eq, method, n, reference, repeat)
            measured = measure_error(settings, eq, method, n, reference, solution)
        except (DynamicsError, ValueError, np.linalg.LinAlgError) as exc:
            rows.append({**row, 'valid': False, 'note': str(exc).splitlines()[0]})
            continue
        estimate = estimator.estimate(method, n)
        note = measured.note
        if row['auto']:
            note = f"auto's pick at model.tolerance {100 * settings.tolerance:g} %" \
                + (f'; {note}' if note else '')
        row.update(dofs=measured.dofs, freq_error_pct=100 * measured.freq_error,
                   frf_error_pct=100 * measured.frf_error, time_s=seconds,
                   modes_in_band=measured.modes_in_band, missed_modes=measured.missed_modes,
                   estimated_freq_error_pct=100 * estimate.freq_error,
                   estimated_frf_error_pct=100 * estimate.frf_error, valid=measured.valid,
                   note=note)
        rows.append(row)
    return rows


def write_csv(rows: list[dict], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'w', newline='', encoding='utf-8') as stream:
        writer = csv.DictWriter(stream, fieldnames=COLUMNS, extrasaction='ignore')
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (f'{v:.6g}' if isinstance(v, float) else v)
                             for k, v in row.items()})


def plot(rows: list[dict], reference, path: Path, scene_name: str,
         tolerance: float | None = None):
    """The chart (:func:`cdpr_dynamics.analysis.figures.tradeoff_figure`), titled with the scene,
    the
    band and the reference; errors capped at :data:`CAP_PCT` for the drawing only (the CSV
    and the estimates are not)."""
    return tradeoff_figure(rows, path, f'{scene_name}: error over 0-{reference.f_max_hz:g} Hz '
                           f'against {reference.label}', tolerance)


def summary(rows: list[dict], reference) -> str:
    lines = [f'reference: {reference.label}; {reference.modes_in_band} modes in '
             f'0-{reference.f_max_hz:g} Hz',
             f"{'method':>15} {'n':>3} {'dofs':>5} {'freq err %':>11} {'FRF err %':>10} "
             f"{'time ms':>8}"]
    for r in rows:
        if 'time_s' not in r:
            lines.append(f"{r['method']:>15} {r['elements_per_cable']:>3} failed: {r['note']}")
            continue
        lines.append(f"{r['method']:>15} {r['elements_per_cable']:>3} {r['dofs']:>5} "
                     f"{r['freq_error_pct']:>11.4g} {r['frf_error_pct']:>10.4g} "
                     f"{1e3 * r['time_s']:>8.2f}" + ('  <- auto' if r.get('auto') else ''))
    return '\n'.join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='cdpr_tradeoff',
                                     description=plain(__doc__.split('\n')[0]))
    parser.add_argument('--config', help='ROS 2 parameter YAML (default: the paper robot)')
    parser.add_argument('--f-max', type=float, help='top of the band (Hz; default frf.f_max_hz)')
    parser.add_argument('--tolerance', type=float,
                        help='model.tolerance for the auto pick marked on the chart')
    parser.add_argument('--repeat', type=int, default=3, help='timed runs per model (median)')
    parser.add_argument('--csv', type=Path, required=True, help='write the table here')
    parser.add_argument('--plot', type=Path, required=True, help='write the PNG chart here')
    return parser.parse_args(argv)


def run(args: argparse.Namespace, progress=None):
    settings = load_settings(args.config)
    changes = {'f_max_hz': args.f_max, 'tolerance': args.tolerance}
    settings = settings.replace(**{k: v for k, v in changes.items() if v is not None})
    if args.repeat < 1:
        raise ConfigError('--repeat must be at least 1')
    eq = equilibrium(settings)
    try:
        reference = reference_solution(settings, eq)
        choice = choose_model(settings, eq, damping=reference.damping)
    except (DynamicsError, ValueError) as exc:
        raise AnalysisError(f'no reference for this scene: {str(exc).splitlines()[0]}') \
            from None
    rows = sweep(settings, eq, reference, args.repeat, progress, choice)
    return settings, reference, choice, rows


@interruptible('cdpr_tradeoff')
def main(argv=None) -> int:
    args = parse_args(argv)
    from tqdm import tqdm

    def progress(items):
        return tqdm(items, desc='models', unit='model', leave=False, disable=None)
    try:
        settings, reference, choice, rows = run(args, progress)
    except (ConfigError, AnalysisError, SelectionError) as exc:
        print(f'cdpr_tradeoff: error: {exc}', file=sys.stderr)
        return 1
    name = Path(args.config).stem if args.config else 'paper_cdpr'
    try:
        write_csv(rows, args.csv)
        plot(rows, reference, args.plot, name, settings.tolerance)
    except OSError as exc:
        print(f'cdpr_tradeoff: error: cannot write {exc.filename or ""}: {exc.strerror}',
              file=sys.stderr)
        return 1
    print(summary(rows, reference))
    print(choice.reason)
    print(f'wrote {args.csv} and {args.plot}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
