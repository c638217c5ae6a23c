"""cdpr_workspace: rows equal cdpr_analyze, statuses, variants, and the engine with real
processes (a LocalCluster, `dask scheduler` + `dask worker` CLIs, a killed worker, Ctrl-C and
--resume). Small grids, fem with 4 elements: about a minute and a half on an idle machine."""
from __future__ import annotations

import functools
import glob
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from conftest import installed, wait_until
from cdpr_dynamics.cli.analyze import parse_args as analyze_args, run as analyze_run
from cdpr_dynamics.cli.workspace import Run, chunk_result, parse_args, run_tasks
from cdpr_dynamics.analysis.config import read_params_file, settings_from_params
from cdpr_dynamics.analysis.workspace import COLUMNS, chunk_tasks, compute_chunk, pose_row

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / 'config' / 'paper_cdpr.yaml'
RIGID = REPO / 'test' / 'data' / 'rigid_cdpr.yaml'
SUSPENDED = REPO / 'config' / 'suspended_3cable.yaml'
BIN = Path(sys.executable).parent      # the dask command line, of this Python's venv
#: the grid of the engine tests: 3 x 3 x 3 poses, 2 of them infeasible, fem 4, chunks of 3
GRID = ['--x', '-1', '1', '3', '--y', '-0.6', '0.6', '3', '--z', '0.4', '2.2', '3',
        '--method', 'fem', '--elements', '4', '--skip-auto', '--chunk-size', '3']
#: GRID with fem_sag n = 64 (~0.3 s a chunk): slow enough for a Ctrl-C to land mid-run
SLOW_GRID = [*GRID[:GRID.index('--method')], '--method', 'fem_sag', '--elements', '64',
             *GRID[GRID.index('--skip-auto'):]]
ENV = {**os.environ, 'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1',
       'PYTHONUNBUFFERED': '1'}


def workspace(*args, timeout=240) -> subprocess.CompletedProcess:
    return subprocess.run([installed('cdpr_workspace'), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=ENV)


def table_rows(path: Path) -> dict:
    """The table's columns without the timing, NaN spelled 'nan' so that == compares."""
    table = pq.read_table(path)
    return {name: _canonical(table.column(name).to_pylist()) for name in table.column_names
            if name != 'compute_s'}


def assert_rows_close(rows: dict, reference: dict, rtol: float = 1e-9) -> None:
    """``rows`` equal ``reference`` (:func:`table_rows` form) column by column, floats to
    ``rtol``: fem_sag's Newton statics end 1e-13 apart from one process to another (numpy's
    SIMD loops round by the buffers' alignment), where fem's rows come out bit-identical."""
    assert rows.keys() == reference.keys()
    for name in rows:
        _assert_close(rows[name], reference[name], rtol, name)


def _assert_close(got, want, rtol: float, where: str) -> None:
    if isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for k, (g, w) in enumerate(zip(got, want)):
            _assert_close(g, w, rtol, f'{where}[{k}]')
    elif isinstance(want, float) and isinstance(got, float):
        assert abs(got - want) <= rtol * abs(want), (where, got, want)
    else:
        assert got == want, (where, got, want)


def _canonical(value):
    if isinstance(value, list):
        return [_canonical(v) for v in value]
    return 'nan' if isinstance(value, float) and value != value else value


class Processes:
    """Started processes (each in its own session), all killed at the end of the test."""

    def __init__(self):
        self.items = []

    def start(self, args, **kwargs) -> subprocess.Popen:
        proc = subprocess.Popen([str(a) for a in args], env=ENV, start_new_session=True,
                                **kwargs)
        self.items.append(proc)
        return proc

    def kill(self, proc) -> None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=30)

    def close(self):
        for proc in self.items:
            if proc.poll() is None:
                self.kill(proc)
            else:   # its children (a dask worker's nanny, ...) may outlive it
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass


@pytest.fixture
def processes():
    procs = Processes()
    yield procs
    procs.close()


@pytest.fixture(scope='module')
def serial(tmp_path_factory) -> dict:
    """The engine grid computed in this process (--workers 0): the reference table."""
    out = tmp_path_factory.mktemp('serial') / 'run'
    done = workspace(*GRID, '--output', out, '--workers', '0', '--no-maps')
    assert done.returncode == 0, done.stderr
    return table_rows(out / 'workspace.parquet')


@pytest.fixture(scope='module')
def slow_serial(tmp_path_factory) -> dict:
    """SLOW_GRID computed in this process's CLI with --workers 0: the reference of the tests
    that interrupt or kill a run (its chunks take long enough for that to land mid-run)."""
    out = tmp_path_factory.mktemp('slow_serial') / 'run'
    done = workspace(*SLOW_GRID, '--output', out, '--workers', '0', '--no-maps')
    assert done.returncode == 0, done.stderr
    return table_rows(out / 'workspace.parquet')


# --------------------------------------------------------------------------- rows

POSES = [(0.0, 0.0, 1.25), (0.5, -0.3, 0.8), (-0.9, 0.6, 1.9)]
NEAR_CENTRE = [(0.0, 0.0, 1.25), (0.3, -0.2, 1.1), (0.2, 0.1, 1.3)]
HANGING = [(0.0, 0.0, 1.0), (0.05, -0.03, 1.0), (-0.1, 0.05, 0.9)]   # not equilibria but one


@pytest.mark.parametrize('config, method, n, quaternion, points', [
    (PAPER, 'fem', 4, (0, 0, 0, 1), POSES), (PAPER, 'fem_sag', 4, (0, 0, 0, 1), POSES),
    (PAPER, 'auto', 4, (0, 0, 0, 1), POSES),
    (RIGID, 'spring', 1, (0.0, 0.0, np.sin(0.1), np.cos(0.1)), NEAR_CENTRE),
    (RIGID, 'fem', 3, (0.0, np.sin(0.05), 0.0, np.cos(0.05)), NEAR_CENTRE),
    (SUSPENDED, 'fem', 4, (0, 0, 0, 1), HANGING)])
def test_rows_equal_cdpr_analyze(tmp_path, config, method, n, quaternion, points):
    """One chunk along the poses (warm-started as on a worker) against cdpr_analyze run at
    each pose by itself."""
    params = read_params_file(config)
    poses = np.array([(*p, *quaternion) for p in points])
    task = chunk_tasks({**params, 'model.method': method, 'model.elements_per_cable': n},
                       poses, np.arange(3), [{}], chunk_size=3)[0]
    rows = compute_chunk(task)
    for i, pose in enumerate(poses):
        cfg = _config_at(tmp_path, params, pose, method, n)
        doc = analyze_run(analyze_args(['--config', str(cfg), '--excitation-hz', '5',
                                        '--duration', '0.002']))
        assert rows['status'][i] == 'ok', rows['reason'][i]
        np.testing.assert_allclose(rows['tensions_n'][i], doc['tensions_n'], rtol=1e-6,
                                   atol=1e-6)
        assert rows['method'][i] == doc['model_choice']['method']
        assert rows['elements_per_cable'][i] == doc['model_choice']['elements_per_cable']
        amplitude = np.linalg.norm(np.asarray(doc['frf']['amplitude_m']), axis=1)
        force = np.linalg.norm(settings_from_params(params).frf_force_n)
        np.testing.assert_allclose(rows['peak_receptance_m_per_n'][i], amplitude.max() / force,
                                   rtol=1e-6)
        np.testing.assert_allclose(rows['structure_matrix_condition'][i],
                                   doc['geometry']['structure_matrix_condition'], rtol=1e-9)
        np.testing.assert_allclose(rows['max_sag_parameter'][i], max(doc['sag_parameter']),
                                   rtol=1e-6)
        listed = np.asarray(doc['natural_frequencies_hz'])     # the 12 lowest
        for f in [rows['lowest_platform_hz'][i], rows['first_cable_mode_hz'][i]]:
            if np.isfinite(f) and f <= listed[-1]:
                assert np.min(np.abs(listed - f)) <= 1e-6 * f, (f, listed)
        if rows['method'][i] == 'spring':       # massless: the platform modes are all modes
            np.testing.assert_allclose(rows['platform_modes_hz'][i], listed, rtol=1e-9)
        if method == 'auto':
            assert rows['auto_method'][i] == doc['model_choice']['method']
        # where the row's equilibrium lies: an underactuated robot settles away from the pose
        held = doc['equilibrium'].get('underactuated') or {'distance_m': 0.0, 'angle_rad': 0.0}
        assert rows['equilibrium_distance_m'][i] == pytest.approx(held['distance_m'], rel=1e-6,
                                                                  abs=1e-12)
        assert rows['equilibrium_angle_rad'][i] == pytest.approx(held['angle_rad'], rel=1e-6,
                                                                 abs=1e-12)
    if config == SUSPENDED:
        assert min(rows['equilibrium_distance_m'][1:]) > 1e-3


def _config_at(tmp_path, params, pose, method, n) -> Path:
    import yaml
    flat = {**{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in params.items()},
            'robot.initial_position': [float(v) for v in pose[:3]],
            'robot.initial_orientation': [float(v) for v in pose[3:]],
            'model.method': method, 'model.elements_per_cable': n}
    tree: dict = {}
    for name, value in flat.items():
        section, key = name.split('.', 1)
        tree.setdefault(section, {})[key] = value
    path = tmp_path / 'at_pose.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': tree}}))
    return path


def test_every_refusal_is_a_row_with_its_kind():
    paper = read_params_file(PAPER)
    rigid = read_params_file(RIGID)
    turned = (0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8))       # 45 degrees about z
    cases = [
        (paper, 'spring', (0.0, 0.0, 1.25, 0, 0, 0, 1), 'ok', ''),
        (paper, 'spring', (1.25, 1.25, 2.5, 0, 0, 0, 1), 'outside', 'zero length'),
        (paper, 'spring', (2.0, 0.0, 1.0, 0, 0, 0, 1), 'infeasible', 'infeasible tension'),
        (paper, 'spring', (1.0, 0.0, 2.2, 0, 0, 0, 1), 'infeasible', 'infeasible tension'),
        ({**paper, 'robot.anchors': [-1.25, 0, 1.0, -2.5, 0, 1.0], 'robot.attachments': []},
         'spring', (0.0, 0.0, 1.0, 0, 0, 0, 1), 'rank_deficient', 'rank 1 < 2'),
        ({**paper, 'robot.anchors': [-1.25, 0, 2.5, 1.25, 0, 2.5], 'robot.attachments': [],
          'tension.min_n': 1.0}, 'spring', (0.0, 0.0, 1.0, 0, 0, 0, 1), 'ok', ''),
        (rigid, 'spring', (0.0, 0.0, 1.25, *turned), 'crossing', 'cross'),
        ({**paper, 'tension.min_n': 0.0}, 'spring', (0.3, 0.2, 1.0, 0, 0, 0, 1),
         'method_invalid', 'slack'),
        ({**paper, 'tension.min_n': 1.0, 'cable.weight_per_length_n_per_m': 30.0}, 'catenary',
         (0.3, 0.2, 1.0, 0, 0, 0, 1), 'method_invalid', 'no taut elastic catenary'),
    ]
    for params, method, pose, status, words in cases:
        settings = settings_from_params({**params, 'model.method': method})
        row, _, _ = pose_row(settings, np.array(pose, dtype=float), auto_columns=False)
        assert set(row) == set(COLUMNS)
        assert row['status'] == status, (status, row['reason'])
        assert words in row['reason'] and '\n' not in row['reason']
        assert row['compute_s'] > 0
    # an infeasible pose still maps its margin: negative, how far outside
    settings = settings_from_params({**paper, 'model.method': 'spring'})
    row, _, _ = pose_row(settings, np.array([1.0, 0.0, 2.2, 0, 0, 0, 1.0]), auto_columns=False)
    assert row['tension_margin_n'] < 0 and np.isnan(row['lowest_platform_hz'])
    # dsm has no finite mode shapes: a row with its FRF and stiffness, the modes unclassified
    dsm = settings_from_params({**paper, 'model.method': 'dsm'})
    row, _, _ = pose_row(dsm, np.array([0.0, 0.0, 1.25, 0, 0, 0, 1.0]), auto_columns=False)
    assert row['status'] == 'ok' and row['peak_receptance_m_per_n'] > 0
    assert np.isnan(row['lowest_platform_hz']) and row['platform_modes_hz'] == []


def test_an_unexpected_failure_is_a_row_too(monkeypatch):
    import cdpr_dynamics.analysis.workspace as ws

    def broken(*args, **kwargs):
        raise RuntimeError('solver exploded\nsecond line')
    monkeypatch.setattr(ws, 'frequency_response', broken)
    settings = settings_from_params({**read_params_file(PAPER), 'model.method': 'spring'})
    row, _, _ = pose_row(settings, np.array([0.0, 0.0, 1.25, 0, 0, 0, 1.0]), auto_columns=False)
    assert row['status'] == 'error' and row['reason'] == 'RuntimeError: solver exploded'
    assert row['tensions_n'] and np.isfinite(row['tension_margin_n'])


@pytest.mark.slow
def test_vary_multiplies_the_grid_with_a_column_per_name(tmp_path):
    out = tmp_path / 'vary'
    done = workspace('--x', '0', '0.5', '2', '--y', '0', '0', '1', '--z', '1.25', '1.25', '1',
                     '--method', 'spring', '--skip-auto', '--vary', 'cable.area_m2=5e-5,1e-4',
                     '--vary', 'tension.min_n=50,100', '--output', out, '--workers', '0')
    assert done.returncode == 0, done.stderr
    table = pq.read_table(out / 'workspace.parquet')
    assert table.num_rows == 2 * 2 * 2
    area, t_min = table.column('cable.area_m2').to_pylist(), table.column('tension.min_n') \
        .to_pylist()
    assert sorted(set(zip(area, t_min))) == [(5e-5, 50.0), (5e-5, 100.0), (1e-4, 50.0),
                                             (1e-4, 100.0)]
    params = read_params_file(PAPER)
    rows = table.to_pylist()
    for row in rows:
        settings = settings_from_params({**params, 'model.method': 'spring',
                                         'cable.area_m2': row['cable.area_m2'],
                                         'tension.min_n': row['tension.min_n']})
        pose = np.array([row[c] for c in ('x_m', 'y_m', 'z_m', 'qx', 'qy', 'qz', 'qw')])
        expected, _, _ = pose_row(settings, pose, auto_columns=False)
        np.testing.assert_allclose(row['tensions_n'], expected['tensions_n'], rtol=1e-9)
        np.testing.assert_allclose(row['min_stiffness_n_per_m'],
                                   expected['min_stiffness_n_per_m'], rtol=1e-12)
    # a stiffer cable is stiffer: the static stiffness grows with the area
    by_area = {a: [r['min_stiffness_n_per_m'] for r in rows if r['cable.area_m2'] == a]
               for a in (5e-5, 1e-4)}
    assert min(by_area[1e-4]) > max(by_area[5e-5])
    meta = json.loads(table.schema.metadata[b'cdpr_workspace'])
    assert meta['vary'] == {'cable.area_m2': [5e-5, 1e-4], 'tension.min_n': [50, 100]}
    assert '--vary cable.area_m2=5e-5,1e-4' in meta['command']
    assert 'robot.anchors' in meta['config'] and 'anchors' in meta['config_text']


@pytest.mark.parametrize('args, words', [
    (['--x', '0', '1', '0', '--y', '0', '0', '1', '--z', '1', '1', '1'], '--x: the number'),
    (['--x', '1', '0', '3', '--y', '0', '0', '1', '--z', '1', '1', '1'], 'inverted'),
    (['--x', '0', '0', '3', '--y', '0', '0', '1', '--z', '1', '1', '1'], 'empty range'),
    (['--x', '0', '1', '2', '--y', '0', '0', '1'], 'missing --z'),
    (['--x', '0', '1', '2', '--y', '0', '0', '1', '--z', '1', '1', '1', '--vary',
      'cable.area_m3=1e-5,2e-5'], 'unknown parameter cable.area_m3 (did you mean '
     'cable.area_m2?)'),
    (['--x', '0', '1', '2', '--y', '0', '0', '1', '--z', '1', '1', '1', '--vary',
      'tension.min_n=-5,10'], 'tension.min_n = -5.0 is outside'),
    (['--x', '0', '1', '2', '--y', '0', '0', '1', '--z', '1', '1', '1', '--resume'],
     'holds no run'),
    (['--poses', '/nonexistent/poses.csv'], 'cannot read --poses'),
    (['--x', '0', '1', '2', '--y', '0', '0', '1', '--z', '1', '1', '1', '--orientation', '0',
      '0', '0', '2'], 'not a unit quaternion'),
])
def test_bad_arguments_end_with_one_line(tmp_path, args, words):
    done = workspace(*args, '--output', tmp_path / 'out', '--workers', '0', timeout=60)
    assert done.returncode == 1
    assert done.stderr.count('\n') == 1 and done.stderr.startswith('cdpr_workspace: error: ')
    assert words in done.stderr, done.stderr
    assert 'Traceback' not in done.stderr


@pytest.mark.slow
def test_poses_file_and_a_second_run_into_the_same_folder(tmp_path):
    csv = tmp_path / 'poses.csv'
    csv.write_text('x_m,y_m,z_m\n0,0,1.25\n0.4,0.1,0.9\n')
    out = tmp_path / 'run'
    args = ['--poses', csv, '--method', 'spring', '--skip-auto', '--output', out,
            '--workers', '0']
    done = workspace(*args)
    assert done.returncode == 0, done.stderr
    table = pq.read_table(out / 'workspace.parquet')
    assert table.column('x_m').to_pylist() == [0.0, 0.4]
    assert table.column('qw').to_pylist() == [1.0, 1.0]
    again = workspace(*args)
    assert again.returncode == 1 and 'holds a run already (1 of 1 chunks done)' in again.stderr


# --------------------------------------------------------------------------- the engine

@pytest.mark.slow
def test_local_cluster_of_two_processes_equals_serial(tmp_path, serial):
    out = tmp_path / 'cluster'
    done = workspace(*GRID, '--output', out, '--workers', '2')
    assert done.returncode == 0, done.stderr
    rows = table_rows(out / 'workspace.parquet')
    assert rows == serial
    statuses = rows['status']
    assert len(statuses) == 27 and 1 <= statuses.count('infeasible') == 27 - statuses.count('ok')
    assert (out / 'maps_z.png').stat().st_size > 10000
    assert 'feasible (status ok)' in (out / 'summary.md').read_text()


def _scheduler(processes, tmp_path) -> str:
    info = tmp_path / 'scheduler.json'
    processes.start([BIN / 'dask', 'scheduler', '--host', '127.0.0.1', '--port', '0',
                     '--dashboard-address', '127.0.0.1:0', '--scheduler-file', info],
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_until(lambda: info.exists() and info.stat().st_size > 0, 60, 'the dask scheduler')
    address = json.loads(info.read_text())['address']
    assert address.startswith('tcp://127.0.0.1:')
    return address


def _worker(processes, address, log) -> subprocess.Popen:
    return processes.start([BIN / 'dask', 'worker', address, '--host', '127.0.0.1',
                            '--nworkers', '1', '--nthreads', '1', '--no-dashboard'],
                           stdout=subprocess.DEVNULL, stderr=open(log, 'w'))


def test_existing_cluster_with_a_worker_killed_mid_run(tmp_path, processes, slow_serial):
    """`dask scheduler` and two `dask worker` processes as a user's cluster would be; one
    worker is killed outright once chunks come back: its chunks are rerun elsewhere and
    every pose ends up exactly once, equal to the serial run."""
    address = _scheduler(processes, tmp_path)
    first = _worker(processes, address, tmp_path / 'w1.log')
    _worker(processes, address, tmp_path / 'w2.log')
    out = tmp_path / 'remote'
    client = processes.start([installed('cdpr_workspace'), *SLOW_GRID, '--output', out,
                              '--scheduler', address], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    wait_until(lambda: glob.glob(str(out / 'chunks' / '*.parquet')) or client.poll()
               is not None, 180, 'the first chunk')
    processes.kill(first)
    stdout, stderr = client.communicate(timeout=240)
    assert client.returncode == 0, stderr
    assert_rows_close(table_rows(out / 'workspace.parquet'), slow_serial)
    assert '27 poses: ' in stdout


@pytest.mark.slow
def test_a_result_lost_with_its_worker_is_computed_again_not_failed(tmp_path):
    """The race the killed-worker test met in CI: a chunk finished on a worker that then
    died before its result was fetched. Its future is 'lost' (neither finished nor failed);
    chunk_result waits for the recomputation on the other worker."""
    from dask.distributed import Client, LocalCluster
    args = parse_args([*GRID, '--output', str(tmp_path / 'unused')])
    task = Run(args).tasks[4]
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host='127.0.0.1',
                      dashboard_address='127.0.0.1:0') as cluster, Client(cluster) as client:
        first = sorted(client.scheduler_info()['workers'])[0]
        future = client.submit(compute_chunk, task, workers=[first], allow_other_workers=True,
                               pure=False)
        wait_until(lambda: future.status == 'finished', 120, 'the chunk on the first worker')
        assert first in client.who_has(future)[future.key]
        from distributed.comm.core import CommClosedError
        with pytest.raises(CommClosedError):   # the worker holding the result dies mid-call
            client.run(os._exit, 1, workers=[first])
        wait_until(lambda: future.status != 'finished', 60, 'the scheduler to lose the result')
        columns = chunk_result(future, task, 2)
    reference = compute_chunk(task)
    assert {k: _canonical(v) for k, v in columns.items() if k != 'compute_s'} == \
        {k: _canonical(v) for k, v in reference.items() if k != 'compute_s'}
    assert 'failed' not in columns['status']


def test_interrupt_kill_then_resume_computes_each_pose_once(tmp_path, processes, slow_serial):
    """Ctrl-C (SIGINT to the process group), then a resumed run whose client is killed
    outright (its LocalCluster workers go with it), then --resume to the end. On SLOW_GRID:
    on GRID a fast host finished all 9 chunks before the Ctrl-C of the first one arrived."""
    out = tmp_path / 'interrupted'
    chunks = str(out / 'chunks' / '*.parquet')
    run = processes.start([installed('cdpr_workspace'), *SLOW_GRID, '--output', out,
                           '--workers', '2'],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_until(lambda: glob.glob(chunks) or run.poll() is not None, 180, 'the first chunk')
    os.killpg(run.pid, signal.SIGINT)           # Ctrl-C reaches the whole process group
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 130 and stderr == 'cdpr_workspace: interrupted\n', stderr
    kept = {p: os.stat(p).st_mtime_ns for p in glob.glob(chunks)}
    assert 1 <= len(kept) < 9 and not (out / 'workspace.parquet').exists()
    again = processes.start([installed('cdpr_workspace'), *SLOW_GRID, '--output', out,
                             '--workers', '2', '--resume'],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_until(lambda: len(glob.glob(chunks)) > len(kept) or again.poll() is not None, 180,
               'a chunk of the resumed run')
    os.kill(again.pid, signal.SIGKILL)          # the client alone: no clean-up of its own
    again.wait(timeout=30)
    wait_until(lambda: not _group_alive(again.pid), 60, 'the killed client\'s workers to exit')
    kept.update({p: os.stat(p).st_mtime_ns for p in glob.glob(chunks) if p not in kept})
    done = workspace(*SLOW_GRID, '--output', out, '--workers', '2', '--resume')
    assert done.returncode == 0, done.stderr
    after = glob.glob(chunks)
    assert len(after) == 9
    assert all(os.stat(p).st_mtime_ns == t for p, t in kept.items())   # not recomputed
    rows = table_rows(out / 'workspace.parquet')
    assert rows['pose_id'] == list(range(27))
    assert_rows_close(rows, slow_serial)
    print(f'resume: {len(kept)} of 9 chunks kept over an interruption and a killed client, '
          f'{9 - len(kept)} computed by the last --resume')


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _flaky(log: str, task):
    with open(log, 'a') as stream:
        stream.write(f'{task.chunk}\n')
    if task.chunk == 1:
        raise RuntimeError('boom: a task that always fails')
    return compute_chunk(task)


@pytest.mark.slow
def test_a_task_that_keeps_failing_is_retried_then_its_poses_fail(tmp_path):
    import cloudpickle
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    args = parse_args(['--x', '0', '0.5', '2', '--y', '0', '0', '1', '--z', '1', '1.2', '2',
                       '--method', 'spring', '--skip-auto', '--chunk-size', '2',
                       '--output', str(tmp_path / 'unused')])
    tasks = Run(args).tasks
    log = tmp_path / 'attempts.log'
    got = {}
    run_tasks(tasks, lambda task, columns: got.update({task.chunk: columns}), workers=1,
              retries=2, compute=functools.partial(_flaky, str(log)))
    attempts = log.read_text().split()
    assert attempts.count('1') == 3 and attempts.count('0') == 1      # 1 + 2 retries
    assert got[1]['status'] == ['failed', 'failed']
    assert 'after 2 retries: RuntimeError: boom' in got[1]['reason'][0]
    assert got[0]['status'] == ['ok', 'ok']


def test_bench_workspace_measures_every_method_on_both_robots():
    """cdpr_bench --workspace's per-worker stage on two poses (its numbers are not read)."""
    from cdpr_dynamics.cli import bench_workspace
    rows = bench_workspace.per_worker(PAPER, 2) + bench_workspace.per_worker(RIGID, 2)
    measured = [(r['config'], r['method']) for r in rows if 'poses_per_s' in r]
    assert measured == [(c, m) for c in ('paper_cdpr.yaml', 'rigid_cdpr.yaml')
                        for m in ('spring', 'fem', 'fem_sag')]
    assert all(r['ok'] == 2 and r['grid_50_cubed_hours_per_worker'] > 0 for r in rows
               if 'poses_per_s' in r)
    text = bench_workspace.summary({'per_worker': rows, 'engine': {
        'scaling_method': 'fem 16', 'scaling_poses': 2, 'wall_1_worker_s': 2.0,
        'wall_2_workers_s': 1.0, 'speedup_1_to_2': 2.0, 'cores': 2, 'load_average': 0.0,
        'overhead': [], 'smallest_chunk_under_5_percent': None}})
    assert text.count('poses/s') == 6 and "auto's choice adds" in text
