"""``auto``'s estimates against the measured errors: the table that sets ``selection.SAFETY``.

    cdpr_estimate_table [CONFIG[@F_MAX_HZ] ...] [--json PATH]

For each robot (default :data:`ROBOTS`; ``CONFIG@F`` is the robot over [0, F Hz], its
``frf.f_max_hz`` set to F) and each model of :data:`MODELS`: the estimated
(:class:`~cdpr_dynamics.selection.estimates.Estimator`) and the measured
(:func:`~cdpr_dynamics.selection.reference.measure_error`) errors of the natural frequencies in
the band
and of the damped FRF, over each robot's [0, ``frf.f_max_hz``], and their ratio
measured / estimated (the larger of the two; estimates and measurements not capped, a missed
mode 100 %). Prints a Markdown table and the largest ratio; ``--json`` also writes the entries
(:data:`TABLE` is the committed one, which the docs show and the tests recompute); exit status 1
with one line on a bad config, 130 on Ctrl-C.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from cdpr_dynamics.analysis.pipeline import AnalysisError, equilibrium
from cdpr_dynamics.cli import interruptible, plain
from cdpr_dynamics.analysis.config import ConfigError, Settings, load_settings
from cdpr_dynamics.dynamics.system import DynamicsError
from cdpr_dynamics.selection.estimates import Estimator
from cdpr_dynamics.selection.reference import measure_error, reference_solution
from cdpr_dynamics.selection.auto import SAFETY, SelectionError

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = ('config/paper_cdpr.yaml', 'config/low_tension_cdpr.yaml', 'test/data/rigid_cdpr.yaml',
          'test/data/sagging_6dof.yaml', 'test/data/cogiro_heavy_sag.yaml',
          'test/data/cogiro_heavy_sag.yaml@3', 'test/data/cogiro_heavy_sag.yaml@4',
          'test/data/cogiro_heavy_sag.yaml@10',
          'config/paper_pulleys.yaml', 'config/suspended_3cable.yaml',
          'config/suspended_4cable.yaml')
TABLE = ROOT / 'doc' / 'estimates' / 'table.json'   # the committed table of ROBOTS x MODELS
MODELS = (('spring', 1), ('fem', 4), ('fem', 8), ('fem', 16), ('catenary_exact', 1),
          ('fem_sag', 4), ('fem_sag', 8), ('fem_sag', 16))


@dataclass(frozen=True)
class Entry:
    """One model on one robot: estimated and measured relative errors (1 = 100 %)."""

    robot: str
    method: str
    elements_per_cable: int
    dofs: int
    estimated_freq_error: float
    estimated_frf_error: float
    measured_freq_error: float
    measured_frf_error: float
    floor: float                   # below this a measured error is the reference's own

    @property
    def ratio(self) -> float:
        """max(measured / estimated) over both errors, counting measured errors at or below
        :attr:`floor` as 0 (inf where a measured error above it was estimated 0)."""
        pairs = ((self.measured_freq_error, self.estimated_freq_error),
                 (self.measured_frf_error, self.estimated_frf_error))
        return max((m / e if e > 0 else math.inf) if m > self.floor else 0.0 for m, e in pairs)


def robot_settings(entry: str, root: Path | None = None) -> tuple[str, Settings]:
    """(name, settings) of a robot of the table: ``PATH`` (named by its stem) or ``PATH@F``,
    the robot over [0, F Hz] (``frf.f_max_hz`` F; named ``STEM_Fhz``); a relative PATH from
    ``root`` where given."""
    head, at, band = entry.rpartition('@')
    try:
        f_max_hz = float(band) if at else None
    except ValueError:
        f_max_hz = None
    path = Path(head if f_max_hz is not None else entry)
    settings = load_settings(root / path if root is not None else path)
    if f_max_hz is None:
        return path.stem, settings
    if not (math.isfinite(f_max_hz) and f_max_hz > 0):
        raise ConfigError(f'{entry}: the band must end at a positive frequency (Hz)')
    return f'{path.stem}_{f_max_hz:g}hz', settings.replace(f_max_hz=f_max_hz)


def robot_entries(robot: str, settings, models=MODELS, eq=None,
                  reference=None) -> list[Entry]:
    """The table's rows for one robot (its equilibrium, band and damping as configured; the
    equilibrium and the reference solved here unless given)."""
    eq = equilibrium(settings) if eq is None else eq
    reference = reference_solution(settings, eq) if reference is None else reference
    estimator = Estimator(settings, eq, reference.f_max_hz, reference.damping)
    floor = max(10.0 * reference.uncertainty, 1e-6)
    rows = []
    for method, n in models:
        e = estimator.estimate(method, n)
        m = measure_error(settings, eq, method, n, reference)
        rows.append(Entry(robot, method, n, m.dofs, e.freq_error, e.frf_error, m.freq_error,
                          m.frf_error, floor))
    return rows


def markdown(entries: list[Entry]) -> str:
    """The table as Markdown (errors in %), and a last line with the largest ratio."""
    lines = ['| robot | model | DOFs | modes est. % | modes meas. % | FRF est. % | FRF meas. % '
             '| meas./est. |', '|---|---|---:|---:|---:|---:|---:|---:|']
    for r in entries:
        name = f'{r.method} {r.elements_per_cable}' if r.method in ('fem', 'fem_sag') \
            else r.method
        lines.append(f'| {r.robot} | {name} | {r.dofs} | {100 * r.estimated_freq_error:.3g} | '
                     f'{100 * r.measured_freq_error:.3g} | {100 * r.estimated_frf_error:.3g} | '
                     f'{100 * r.measured_frf_error:.3g} | {r.ratio:.2f} |')
    worst = max(entries, key=lambda r: r.ratio)
    lines.append(f'\nlargest measured/estimated ratio {worst.ratio:.2f} ({worst.robot}, '
                 f'{worst.method} {worst.elements_per_cable}); SAFETY = {SAFETY:g}')
    return '\n'.join(lines)


def write_json(entries: list[Entry], path) -> None:
    """The entries as JSON: ``{"safety": SAFETY, "entries": [{field: value}, ...]}``."""
    rows = [dataclasses.asdict(e) for e in entries]
    Path(path).write_text(json.dumps({'safety': SAFETY, 'entries': rows}, indent=1) + '\n')


def read_json(path=TABLE) -> list[Entry]:
    """The entries of a file of :func:`write_json`."""
    return [Entry(**row) for row in json.loads(Path(path).read_text())['entries']]


@interruptible('estimate_table')
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='cdpr_estimate_table',
                                     description=plain(__doc__.split('\n')[0]))
    parser.add_argument('configs', nargs='*', metavar='CONFIG[@F_MAX_HZ]',
                        help='robots, each over [0, F_MAX_HZ] where given (default: the '
                        'ROBOTS of the table)')
    parser.add_argument('--json', metavar='PATH', help='also write the entries as JSON (the '
                        f'docs\' table: {TABLE.relative_to(ROOT)})')
    args = parser.parse_args(argv)
    entries = []
    try:
        for name, settings in (robot_settings(entry) for entry in args.configs) if args.configs \
                else (robot_settings(entry, ROOT) for entry in ROBOTS):
            entries += robot_entries(name, settings)
    except (ConfigError, AnalysisError, SelectionError, DynamicsError) as exc:
        print(f'estimate_table: error: {str(exc).splitlines()[0]}', file=sys.stderr)
        return 1
    print(markdown(entries))
    if args.json:
        try:
            write_json(entries, args.json)
        except OSError as exc:
            print(f'estimate_table: error: cannot write {args.json}: {exc.strerror}',
                  file=sys.stderr)
            return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
