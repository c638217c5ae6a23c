#!/usr/bin/env python3
"""Modal identification head to head: cdpr_calibrate's own against pyOMA-2 and sdypy-EMA.

    pip install pyoma-2==1.4.3 sdypy-EMA==0.31.0      # not dependencies of the package
    python scripts/compare_identification.py [--seeds N] [--json PATH]

The same synthetic records (the package's Newmark free decays plus noise at 100 Hz:
:mod:`cdpr_dynamics.analysis.synthetic`) go through the same ``identify_record`` (gaps,
resampling, rest detection, decay spans) and only the identification of each decay differs:

* ``own``: channels weighted by their noise level, covariance-driven SSI over model orders,
  poles tracked over the orders by frequency and shape, variable-projection
  Levenberg-Marquardt refinement, a residual search for missed poles
  (:func:`~cdpr_dynamics.analysis.identification.identify_decay`);
* ``pyoma2-ssi-dat``, ``pyoma2-ssi-cov``: pyOMA-2's SSI, data-driven (13 block rows, orders
  up to 40, its poles picked by its automatic clustering ``Kvaale``) and covariance-driven
  (60 block rows, orders up to 60, clustering ``hdbscan``): of 18 settings tried on the first
  two cases (data-driven with 13 and 30 block rows, covariance-driven with 60, each with its
  six automatic clusterings), those that found the most true modes with the fewest spurious
  ones;
* ``sdypy-lscf``: sdypy-EMA's LSCF on the decay's spectrum (a free decay's Fourier transform
  has the poles of the FRF), polynomial orders up to 60, poles picked stable over the orders
  as ``own`` picks its subspace poles (sdypy-EMA picks them by hand or near given
  frequencies).

Per case and method: the true modes found (within 2 %, an assignment: a mode reported twice
is paired with a neighbouring true mode where one lies within 2 %), those of them within
0.5 % in frequency and 20 % in damping, the largest frequency and damping errors of those
found, the modes reported that are no true mode (spurious) and the identification time
(median over the seeds).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import os
import time
import warnings
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

import numpy as np  # noqa: E402
from scipy.optimize import linear_sum_assignment  # noqa: E402

from cdpr_dynamics.analysis import identification as ident  # noqa: E402
from cdpr_dynamics.analysis.config import read_params_file, settings_from_params  # noqa: E402
from cdpr_dynamics.analysis.synthetic import free_decay, pose_rows  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
U6 = np.array([0.004, -0.003, 0.005, 0.012, -0.010, 0.015])
MATCH = 0.02
#: The issue's tolerances: a found mode within them is right, not merely near.
TOLERANCE_F, TOLERANCE_ZETA = 0.005, 0.2


def robots() -> dict:
    """Soft robots whose platform modes lie below the 50 Hz Nyquist frequency of 100 Hz."""
    rigid = read_params_file(ROOT / 'test' / 'data' / 'rigid_cdpr.yaml')
    rigid.update({'model.method': 'spring', 'cable.youngs_modulus_pa': 2.01e8})
    point = read_params_file(ROOT / 'config' / 'paper_cdpr.yaml')
    point.update({'model.method': 'spring', 'cable.youngs_modulus_pa': 2.01e8})
    sag = read_params_file(ROOT / 'test' / 'data' / 'sagging_6dof.yaml')
    sag.update({'model.method': 'catenary', 'cable.youngs_modulus_pa': 2.0e9})
    return {name: settings_from_params(flat) for name, flat in
            (('rigid', rigid), ('point', point), ('sag', sag))}


def cases(settings: dict):
    """(name, settings, position, u0, duration s, noise m, modal damping ratio, messy)."""
    rigid, point, sag = settings['rigid'], settings['point'], settings['sag']
    at = [0.1, -0.05, 1.3]
    near = list(point.initial_position_m + [0.2, 0.1, 0.1])
    yield 'rigid, 6 modes 2.3-15 Hz, 0.1 mm', rigid, at, U6, 20.0, 1e-4, 0.02, False
    yield 'rigid, 6 modes, 1 mm', rigid, at, U6, 20.0, 1e-3, 0.02, False
    yield 'rigid, mid-motion start, 3 % dropped, 0.1 mm', rigid, at, U6, 20.0, 1e-4, 0.02, True
    yield 'rigid, 100 s record, 0.1 mm', rigid, at, U6, 100.0, 1e-4, 0.02, False
    yield 'sagging, 6 modes 2.0-12 Hz, 0.1 mm', sag, \
        list(sag.initial_position_m + [0.1, -0.1, 0.0]), U6, 20.0, 1e-4, 0.02, False
    yield 'point mass, 3 modes within 1.5 %, 0.2 % damping, 0.1 mm', point, near, U6[:3], \
        40.0, 1e-4, 0.002, False
    yield 'point mass, 3 modes within 1.5 %, 0.5 % damping, 0.1 mm', point, near, U6[:3], \
        40.0, 1e-4, 0.005, False
    yield 'point mass, 3 modes within 1.5 %, 2 % damping, 0.1 mm', point, near, U6[:3], \
        20.0, 1e-4, 0.02, False


def record(case, seed: int):
    """(t, rows, true frequencies, true damping ratios) of one case and noise draw."""
    _, settings, position, u0, duration, noise, ratio, messy = case
    decay = free_decay(settings, position, u0, duration, ratio)
    rng = np.random.default_rng(seed)
    t, rows = decay.t_s, pose_rows(position, decay.u, noise, rng)
    if messy:
        ramp_t = np.arange(0.0, 1.5, 0.01)
        start = np.asarray(position) - [0.3, 0.0, 0.0]
        shape = np.sin(0.5 * np.pi * (ramp_t + 0.5) / 2.0)[:, None] ** 2
        ramp = np.hstack([start + (np.asarray(position) - start) * shape,
                          np.tile([0.0, 0.0, 0.0, 1.0], (ramp_t.size, 1))])
        t = np.concatenate([ramp_t, t + ramp_t[-1] + 0.01])
        rows = np.concatenate([ramp, rows])
        keep = rng.random(t.size) > 0.03
        t, rows = t[keep], rows[keep]
    return t, rows, decay.frequency_hz, decay.damping_ratio


# --------------------------------------------------------------------------- the methods

def _mode(f: float, zeta: float) -> ident.Mode:
    return ident.Mode(float(f), np.nan, float(zeta), np.nan, np.full(6, np.nan))


#: pyOMA-2 settings per SSI variant: block rows, highest order, automatic clustering.
PYOMA2 = {'dat': (13, 40, 'Kvaale'), 'cov': (60, 60, 'hdbscan')}


def pyoma2_ssi(variant: str):
    """pyOMA-2's SSI ``variant`` ('dat' or 'cov') with its automatic clustering."""
    rows, order, clustering = PYOMA2[variant]
    from pyoma2.algorithms import SSI
    from pyoma2.algorithms.data.run_params import Clustering
    from pyoma2.setup import SingleSetup

    def identify(t, y, kind, options, f_max):
        y = y - y.mean(axis=0)
        y = y[:, np.std(y, axis=0) > 1e-12 * np.std(y, axis=0).max()]
        with contextlib.redirect_stderr(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter('ignore')
            setup = SingleSetup(y, fs=1.0 / (t[1] - t[0]))
            ssi = SSI(name='ssi', method=variant, br=rows, ordmax=order)
            setup.add_algorithms(ssi)
            setup.run_by_name('ssi')
            ssi.add_clustering(Clustering(name='auto', quick=clustering,
                                          freqlim=(options.f_min_hz, f_max)))
            try:
                ssi.run_clustering('auto')
            except Exception:       # its clustering refuses too few poles: no mode found
                return []
            found = ssi.result.clustering_results['auto']
        return sorted((_mode(f, z) for f, z in zip(found.Fn, found.Xi)
                       if options.f_min_hz <= f <= f_max and 0 < z < options.max_damping_ratio),
                      key=lambda m: m.frequency_hz)
    return identify


def sdypy_lscf(t, y, kind, options, f_max):
    """sdypy-EMA's LSCF on the decay's spectrum, poles stable over the orders."""
    from sdypy import EMA

    y = y - y.mean(axis=0)
    y = y[:, np.std(y, axis=0) > 1e-12 * np.std(y, axis=0).max()]
    dt = t[1] - t[0]
    spectrum = np.fft.rfft(y, axis=0).T
    freq = np.fft.rfftfreq(y.shape[0], dt)
    with contextlib.redirect_stderr(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter('ignore')
        model = EMA.Model(frf=spectrum, freq=freq, lower=options.f_min_hz, upper=f_max,
                          pol_order_high=60, frf_type='receptance')
        model.get_poles(show_progress=False)
    per_order = []
    for f, xi in zip(model.pole_freq, model.pole_xi):
        f, xi = np.asarray(f, dtype=float), np.asarray(xi, dtype=float)
        w = 2 * np.pi * f
        per_order.append((-xi * w + 1j * w * np.sqrt(np.clip(1 - xi ** 2, 0, None)), None))
    poles = ident.stable_poles(per_order, options.f_min_hz, f_max, options.max_damping_ratio)
    return [_mode(abs(p) / (2 * np.pi), -p.real / abs(p)) for p in poles]


METHODS = ('own', 'pyoma2-ssi-dat', 'pyoma2-ssi-cov', 'sdypy-lscf')


def method(name: str):
    """The per-decay identification ``name`` (one of :data:`METHODS`)."""
    if name.startswith('pyoma2-ssi-'):
        return pyoma2_ssi(name.rsplit('-', 1)[1])
    return sdypy_lscf if name == 'sdypy-lscf' else ident.identify_decay


# --------------------------------------------------------------------------- scoring

def score(found_f, found_z, f_true, z_true) -> dict:
    """True modes matched (within :data:`MATCH`, least total |ln f ratio|), their errors,
    the found modes matching none."""
    found_f, found_z = np.asarray(found_f), np.asarray(found_z)
    if found_f.size == 0:
        none = np.zeros(f_true.size, bool)
        return {'found': none, 'within': none, 'f_err': [], 'z_err': [], 'spurious': 0}
    cost = np.abs(np.log(found_f[None, :] / f_true[:, None]))
    rows, cols = linear_sum_assignment(cost)
    ok = cost[rows, cols] < MATCH
    rows, cols = rows[ok], cols[ok]
    found = np.zeros(f_true.size, bool)
    found[rows] = True
    f_err, z_err = found_f[cols] / f_true[rows] - 1, found_z[cols] / z_true[rows] - 1
    within = np.zeros(f_true.size, bool)
    within[rows] = (np.abs(f_err) < TOLERANCE_F) & (np.abs(z_err) < TOLERANCE_ZETA)
    return {'found': found, 'within': within, 'f_err': f_err.tolist(),
            'z_err': z_err.tolist(), 'spurious': int(found_f.size - rows.size)}


def run(names, seeds: int) -> list[dict]:
    logging.disable(logging.WARNING)
    settings = robots()
    out = []
    for case in cases(settings):
        draws = [record(case, seed) for seed in range(seeds)]
        f_true = draws[0][2]
        for name in names:
            identify = method(name)
            found, within = np.zeros(f_true.size, int), np.zeros(f_true.size, int)
            f_err, z_err, spurious, seconds = [], [], 0, []
            for t, rows, f, z in draws:
                start = time.perf_counter()
                result = ident.identify_record(t, rows, options=ident.Options(f_min_hz=1.0),
                                               method=identify)
                seconds.append(time.perf_counter() - start)
                modes = [m for s in result.stretches for m in s.modes]
                s = score([m.frequency_hz for m in modes], [m.damping_ratio for m in modes],
                          f, z)
                found += s['found']
                within += s['within']
                f_err += s['f_err']
                z_err += s['z_err']
                spurious += s['spurious']
            row = {'case': case[0], 'method': name, 'true_hz': f_true.round(3).tolist(),
                   'found_of_draws': found.tolist(), 'within_of_draws': within.tolist(),
                   'draws': seeds,
                   'max_freq_err_pct': 100 * max(map(abs, f_err), default=np.nan),
                   'max_damping_err_pct': 100 * max(map(abs, z_err), default=np.nan),
                   'spurious': spurious, 'median_s': float(np.median(seconds))}
            out.append(row)
            print(markdown_row(row), flush=True)
    return out


def markdown_row(row: dict) -> str:
    found = ' / '.join(str(n) for n in row['found_of_draws'])
    within = ' / '.join(str(n) for n in row['within_of_draws'])
    return (f"| {row['case']} | {row['method']} | {found} (of {row['draws']}) | {within} | "
            f"{row['max_freq_err_pct']:.2f} % | {row['max_damping_err_pct']:.1f} % | "
            f"{row['spurious']} | {row['median_s']:.2f} s |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, default=3, help='noise draws per case')
    parser.add_argument('--methods', nargs='+', default=list(METHODS), choices=METHODS)
    parser.add_argument('--json', type=Path, help='write the rows to this JSON file')
    args = parser.parse_args()
    print('| case | method | true modes found | of them within 0.5 % and 20 % | largest '
          'frequency error | largest damping error | spurious modes | time (median) |')
    print('|---|---|---|---|---|---|---|---|')
    rows = run(args.methods, args.seeds)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
