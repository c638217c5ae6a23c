"""``cdpr_bench --calibration``: what ``cdpr_calibrate`` costs, on synthetic measurements.

* **fit**: 9 parameters (EA, the six inertia components, the centre of mass's x and y) of the
  rigid 6-DOF robot (``spring``) fitted to 50 poses x 4 modes of a campaign of the package's
  own model with 1 % noise (:func:`~cdpr_dynamics.analysis.synthetic.campaign`), from the
  config's values; the time of :func:`~cdpr_dynamics.analysis.calibration.fit` (one run: a
  fit is seconds) and its iterations;
* **identify**: a 100 s record at 100 Hz (a Newmark free decay of the softened robot plus
  0.1 mm of noise, :func:`~cdpr_dynamics.analysis.synthetic.free_decay`) written as
  PoseStamped to an MCAP file: reading it (``read_samples``) and identifying it
  (``identify_record``), p50 of a few runs.

Both run in a child process with one BLAS thread, as ``cdpr_calibrate`` runs (its small
eigenproblems and thin least squares gain nothing from BLAS threads and lose to their spinning
on a busy host). ``--quick`` fits 10 poses and identifies a 20 s record (CI proves the command
works).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.analysis.calibration import fit
from cdpr_dynamics.analysis.config import read_params_file, settings_from_params
from cdpr_dynamics.analysis.identification import Options, identify_record
from cdpr_dynamics.analysis.synthetic import campaign, free_decay, pose_rows
from cdpr_dynamics.cli.bench_workspace import six_dof_config

FIT_TARGETS = ('cable.youngs_modulus_pa', 'robot.inertia_kg_m2', 'robot.center_of_mass_m[0]',
               'robot.center_of_mass_m[1]')
RELEASE = np.array([0.004, -0.003, 0.005, 0.012, -0.010, 0.015])


def _rigid(config: Path) -> dict:
    flat = read_params_file(config)
    flat['model.method'] = 'spring'
    return flat


def bench_fit(config: Path, poses: int, modes: int = 4) -> dict:
    """One fit of :data:`FIT_TARGETS` to ``poses`` x ``modes`` measured modes."""
    flat = _rigid(config)
    truth = dict(flat, **{'cable.youngs_modulus_pa': 1.15 * flat['cable.youngs_modulus_pa'],
                          'robot.inertia_kg_m2': [0.26, 0.21, 0.16, 0.0, 0.0, 0.0],
                          'robot.center_of_mass_m': [0.01, -0.015, 0.0]})
    table = campaign(truth, poses, modes, tilt_rad=0.15)
    start = time.perf_counter()
    report = fit(flat, table, FIT_TARGETS).report
    seconds = time.perf_counter() - start
    fitted = sum(p['fitted'] is not None for p in report['parameters'])
    return {'config': config.name, 'poses': poses, 'modes_per_pose': modes,
            'parameters': len(report['parameters']), 'fitted': fitted, 'seconds': seconds,
            'iterations': report['iterations'],
            'rms_error_pct_after': report['rms_error_pct']['fit']['after']}


def _write_record(path: Path, t_s, rows) -> None:
    from cdpr_dynamics.recording.writer import RecordingWriter
    from msg_adapters.pose import pose_message
    from msg_adapters.validation import ns_to_stamp
    origin = 1_700_000_000 * 10 ** 9
    with RecordingWriter(path) as writer:
        writer.add_topic('/measured_pose', 'geometry_msgs/msg/PoseStamped')
        for t, row in zip(t_s, rows):
            ns = origin + int(round(t * 1e9))
            writer.write('/measured_pose', pose_message(row[:3], row[3:], 'world',
                                                        ns_to_stamp(ns)), ns)


def bench_identify(config: Path, duration_s: float, repeat: int) -> dict:
    """Read and identify a ``duration_s`` record at 100 Hz, p50 of ``repeat`` runs."""
    from cdpr_dynamics.recording.measurements import read_samples
    flat = _rigid(config)
    flat['cable.youngs_modulus_pa'] = 2.01e8       # modes at 2-15 Hz, below 50 Hz
    position = np.array([0.1, -0.05, 1.3])
    decay = free_decay(settings_from_params(flat), position, RELEASE, duration_s)
    rows = pose_rows(position, decay.u, 1e-4, np.random.default_rng(0))
    options = Options(f_min_hz=1.0)
    read_s, identify_s = [], []
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / 'decay.mcap'
        _write_record(path, decay.t_s, rows)
        for _ in range(repeat):
            start = time.perf_counter()
            samples = read_samples(path)
            middle = time.perf_counter()
            result = identify_record(samples.t_s, samples.rows, samples.kind, options)
            read_s.append(middle - start)
            identify_s.append(time.perf_counter() - middle)
    modes = [m for s in result.stretches for m in s.modes]
    return {'duration_s': duration_s, 'samples': int(decay.t_s.size), 'rate_hz': 100.0,
            'read_p50_s': float(np.median(read_s)),
            'identify_p50_s': float(np.median(identify_s)),
            'total_p50_s': float(np.median(np.add(read_s, identify_s))), 'repeat': repeat,
            'modes_found': len(modes), 'true_modes': int(decay.frequency_hz.size)}


def measure(config: str | None, quick: bool) -> dict:
    """Both rows, in this process."""
    path = Path(config) if config else six_dof_config()
    return {'quick': quick, 'fit': bench_fit(path, 10 if quick else 50),
            'identify': bench_identify(path, 20.0 if quick else 100.0, 1 if quick else 3)}


def run(config: str | None, quick: bool) -> dict:
    """Both rows, in a child process with one BLAS thread (its JSON on stdout); a config
    that does not parse is refused here (:class:`ConfigError`)."""
    read_params_file(Path(config) if config else six_dof_config())
    env = dict(os.environ, OPENBLAS_NUM_THREADS='1', OMP_NUM_THREADS='1', MKL_NUM_THREADS='1')
    args = [sys.executable, '-m', 'cdpr_dynamics.cli.bench_calibration', config or '']
    done = subprocess.run(args + (['--quick'] if quick else []), env=env, check=True,
                          stdout=subprocess.PIPE, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def summary(result: dict) -> str:
    f, i = result['fit'], result['identify']
    return '\n'.join([
        f"cdpr_calibrate fit: {f['parameters']} parameters ({f['fitted']} fitted) to "
        f"{f['poses']} poses x {f['modes_per_pose']} modes of {f['config']} (spring): "
        f"{f['seconds']:.2f} s, {f['iterations']} iterations, rms error after "
        f"{f['rms_error_pct_after']:.2f} % (1 % noise)",
        f"cdpr_calibrate identify: a {i['duration_s']:.0f} s record at {i['rate_hz']:.0f} Hz "
        f"({i['samples']} PoseStamped in MCAP): read p50 {i['read_p50_s']:.2f} s, identify "
        f"p50 {i['identify_p50_s']:.2f} s, total {i['total_p50_s']:.2f} s "
        f"({i['modes_found']} of {i['true_modes']} modes found)"])


if __name__ == '__main__':
    print(json.dumps(measure(sys.argv[1] or None, '--quick' in sys.argv[2:])))
