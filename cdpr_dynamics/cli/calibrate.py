"""``cdpr_calibrate``: identify modes from recordings and fit the robot to measured modes.

    cdpr_calibrate identify RECORDING.mcap [--topic /measured_pose] [--f-max HZ] [--f-min HZ]
                            [--min-duration S] [--max-amplitude M] --output MODES.csv
    cdpr_calibrate fit --config ROBOT.yaml --measurements MODES.csv --fit NAME [NAME ...]
                       --output CALIBRATED.yaml [--holdout FRACTION] [--report DIR]

``identify`` writes the modes table of every free decay at rest it finds,
and says on stderr (and in the table's comments) what it skipped and why. ``fit`` writes the
config with the fitted values (a comment with each one's standard uncertainty), and in
``--report DIR`` ``report.json``, ``frequencies.png`` (measured against predicted, before and
after) and ``residuals.png`` (relative errors over the poses). Errors end with one line and
exit status 1.
"""
from __future__ import annotations

from cdpr_dynamics.cli import blas_threads  # noqa: F401  (before numpy: one BLAS thread)

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.analysis.calibration import (DAMPING_PARAMETERS, CalibrationError,
                                                calibrated_yaml, current_value, fit)
from cdpr_dynamics.analysis.config import ConfigError, read_params_file
from cdpr_dynamics.analysis.identification import (IdentificationError, Options,
                                                   identify_record)
from cdpr_dynamics.analysis.modes_table import (ModesTable, TableError, read_modes_table,
                                                write_modes_table)
from cdpr_dynamics.cli import interruptible

PROG = 'cdpr_calibrate'


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description='Identify modes from recordings '
                                     'and fit the robot parameters to measured modes.')
    sub = parser.add_subparsers(dest='command', required=True)
    ident = sub.add_parser('identify', help='modes of the free decays in a recording')
    ident.add_argument('recording', metavar='RECORDING.mcap')
    ident.add_argument('--topic', help='geometry_msgs/PoseStamped or sensor_msgs/Imu topic '
                       '(default: /measured_pose, else the only pose or IMU topic)')
    defaults = Options()
    ident.add_argument('--f-max', type=float, help='highest frequency identified (Hz; '
                       'default 0.4 x the sample rate)')
    ident.add_argument('--f-min', type=float, default=defaults.f_min_hz,
                       help='lowest frequency identified (Hz); the rest detection low-passes '
                       'the pose at half of it')
    ident.add_argument('--min-duration', type=float, default=defaults.min_duration_s,
                       help='shortest free decay used (s)')
    ident.add_argument('--max-amplitude', type=float, default=defaults.max_amplitude_m,
                       help='oscillations farther than this from the rest pose are skipped '
                       '(m, beyond the linear model)')
    ident.add_argument('--output', required=True, metavar='MODES.csv')
    fitp = sub.add_parser('fit', help='fit parameters to a modes table')
    fitp.add_argument('--config', required=True, metavar='ROBOT.yaml')
    fitp.add_argument('--measurements', required=True, metavar='MODES.csv')
    fitp.add_argument('--fit', required=True, nargs='+', metavar='NAME',
                      help='parameters of the config table, whole or one component name[i]')
    fitp.add_argument('--output', required=True, metavar='CALIBRATED.yaml')
    fitp.add_argument('--holdout', type=float, default=0.0, metavar='FRACTION',
                      help='fraction of the poses left out of the fit and used to validate it')
    fitp.add_argument('--seed', type=int, default=0, help='seed of the held-out pose draw')
    fitp.add_argument('--report', metavar='DIR', help='report.json and figures here')
    return parser


def identify_main(args) -> int:
    from cdpr_dynamics.recording.base import RecordingError
    from cdpr_dynamics.recording.measurements import read_samples
    options = Options(f_min_hz=args.f_min, f_max_hz=args.f_max,
                      min_duration_s=args.min_duration, max_amplitude_m=args.max_amplitude)
    if options.f_min_hz <= 0 or (options.f_max_hz is not None
                                 and options.f_max_hz <= options.f_min_hz):
        raise IdentificationError('--f-min must be positive and below --f-max')
    started = time.perf_counter()
    try:
        samples = read_samples(args.recording, args.topic)
    except RecordingError as exc:
        raise IdentificationError(str(exc)) from None
    if samples.t_s.size < 3:
        raise IdentificationError(f'{samples.topic} has {samples.t_s.size} messages')
    if samples.kind == 'imu' and samples.poses is None:
        raise IdentificationError(f'{samples.topic} is an IMU topic and the recording has no '
                                  'pose topic to place its stretches')
    read_s = time.perf_counter() - started
    result = identify_record(samples.t_s, samples.rows, samples.kind, options, samples.poses)
    seconds = time.perf_counter() - started
    t0 = float(samples.t_s.min())
    comments = [f'cdpr_calibrate identify {Path(args.recording).name} topic {samples.topic} '
                f'({samples.kind}, {samples.t_s.size} samples, {result.filled_samples} '
                f'dropped samples filled by interpolation)',
                f'time in s from the first sample; read {read_s:.2f} s, identified in '
                f'{seconds - read_s:.2f} s']
    for start, end, reason in result.skipped:
        line = f'skipped {start - t0:.2f}-{end - t0:.2f} s: {reason}'
        comments.append(line)
        sys.stderr.write(f'{PROG}: {line}\n')
    rows = []
    for pose_id, stretch in enumerate(result.stretches):
        comments.append(f'pose {pose_id}: free decay {stretch.start_s - t0:.2f}-'
                        f'{stretch.end_s - t0:.2f} s, {len(stretch.modes)} modes')
        for mode in stretch.modes:
            rows.append((pose_id, stretch.pose, mode))
    if not rows:
        raise IdentificationError(f'no free decay at rest found in {samples.topic} '
                                  f'({len(result.skipped)} stretches skipped, see above)')
    table = ModesTable(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                       np.array([r[2].frequency_hz for r in rows]),
                       np.array([r[2].std_hz for r in rows]),
                       np.array([r[2].damping_ratio for r in rows]),
                       np.array([r[2].damping_ratio_std for r in rows]),
                       np.array([r[2].direction for r in rows]))
    write_modes_table(args.output, table, comments)
    print(f'{PROG}: {len(result.stretches)} free decays, {len(rows)} modes -> {args.output} '
          f'({seconds:.2f} s)')
    return 0


def _figures(report: dict, folder: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    modes = report['modes']
    measured = np.array([m['measured_hz'] for m in modes])
    held = np.array([m['holdout'] for m in modes])
    series = {label: np.array([np.nan if m[key] is None else m[key] for m in modes])
              for label, key in (('before', 'before_hz'), ('after', 'after_hz'))}
    fig = Figure(figsize=(6.0, 5.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for label, style in (('before', dict(marker='x', color='tab:gray')),
                         ('after', dict(marker='o', color='tab:blue', mfc='none'))):
        for part, mask in (('fit', ~held), ('held out', held)):
            if mask.any():
                ax.plot(measured[mask], series[label][mask], ls='none', alpha=0.8,
                        label=f'{label} ({part})', **dict(style, color='tab:red')
                        if part == 'held out' and label == 'after' else style)
    span = [np.nanmin(measured) * 0.95, np.nanmax(measured) * 1.05]
    ax.plot(span, span, color='k', lw=0.8)
    ax.set_xlabel('measured frequency (Hz)')
    ax.set_ylabel('predicted frequency (Hz)')
    ax.set_title('measured against predicted, before and after the fit')
    ax.legend(fontsize=8)
    fig.savefig(folder / 'frequencies.png', dpi=120)
    fig = Figure(figsize=(8.0, 4.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    pose = np.array([m['pose_id'] for m in modes])
    for label, style in (('before', dict(marker='x', color='tab:gray')),
                         ('after', dict(marker='o', color='tab:blue', mfc='none'))):
        ax.plot(pose, 100 * (series[label] / measured - 1.0), ls='none', label=label, **style)
    if held.any():
        ax.plot(pose[held], 100 * (series['after'][held] / measured[held] - 1.0), ls='none',
                marker='o', color='tab:red', label='after (held out)')
    ax.axhline(0.0, color='k', lw=0.8)
    ax.set_xlabel('pose id')
    ax.set_ylabel('predicted / measured - 1 (%)')
    ax.set_title('frequency residuals over the poses')
    ax.legend(fontsize=8)
    fig.savefig(folder / 'residuals.png', dpi=120)


def fit_main(args) -> int:
    flat = read_params_file(args.config)
    table = read_modes_table(args.measurements)
    result = fit(flat, table, args.fit, args.holdout, args.seed)
    report = result.report
    changed = {name: result.flat[name] for name in result.values}
    for name in DAMPING_PARAMETERS:     # the kind of damping not fitted, set to 0 by the fit
        if name in result.flat and result.flat[name] != current_value(flat, name):
            changed[name] = result.flat[name]
    text = Path(args.config).read_text(encoding='utf-8')
    Path(args.output).write_text(calibrated_yaml(text, changed, result.values),
                                 encoding='utf-8')
    if args.report:
        folder = Path(args.report)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / 'report.json').write_text(json.dumps(report, indent=1), encoding='utf-8')
        _figures(report, folder)
    for p in report['parameters']:
        if p['fitted'] is None:
            print(f'{p["name"]}: left at {p["initial"]:.6g} ({p["note"]})')
        else:
            print(f'{p["name"]}: {p["initial"]:.6g} -> {p["fitted"]:.6g} +- {p["std"]:.2g}')
    for item in report['unidentifiable']:
        print(f'unidentifiable: {item["combination_text"]} (singular value '
              f'{item["singular_value_ratio"]:.2g} of the largest): {item["left_unfitted"]} '
              'left unfitted')
    for item in report.get('correlations', [])[:3]:
        print(f'correlation {item["a"]} ~ {item["b"]}: {item["correlation"]:+.3f}')
    for part, errors in report['rms_error_pct'].items():
        print(f'rms frequency error ({part}, {errors["modes"]} modes): {errors["before"]:.3g} % '
              f'-> {errors["after"]:.3g} %')
    if report['unpaired_modes']['after']:
        print(f'{report["unpaired_modes"]["after"]} measured modes have no model mode within '
              'a factor 1.28 and are left out')
    for skipped in report['skipped_poses']:
        print(f'pose {skipped["pose_id"]} skipped: {skipped["reason"]}')
    print(f'{PROG}: fitted in {report["timings_s"]["fit"]:.2f} s -> {args.output}')
    return 0


@interruptible(PROG)
def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        return identify_main(args) if args.command == 'identify' else fit_main(args)
    except (ConfigError, CalibrationError, TableError, IdentificationError, OSError) as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        sys.stderr.write(f'{PROG}: {text}\n')
        return 1


if __name__ == '__main__':
    sys.exit(main())
