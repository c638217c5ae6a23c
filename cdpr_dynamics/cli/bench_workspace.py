"""``cdpr_bench --workspace``: what a ``cdpr_workspace`` run costs, to size a cluster.

Measured in one run, so the ratios hold even on a loaded machine (the absolute numbers do
not):

* **poses per second per worker** for spring, fem 16 and fem_sag 16 (its sag-consistent
  statics included) on the paper robot and a 6-DOF robot: one chunk computed in this process
  (one BLAS thread) exactly as a worker does, auto's choice off, and auto's choice alone;
* **scaling** from 1 to 2 LocalCluster workers on the same tasks (wall time from the first
  submission to the last result; the cluster's start-up excluded);
* **engine overhead per chunk size**: the wall time of one LocalCluster worker over the
  poses' own compute time (the rows' ``compute_s``, timed inside the worker), per chunk size
  (spring: the cheapest poses, where the overhead weighs most); what is left is the engine's
  and the chunk's set-up (settings, QP); the smallest chunk with overhead under 5 % is
  reported;
* the time a 50^3 grid would take per worker, per method.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.analysis.config import default_config_path, read_params_file
from cdpr_dynamics.analysis.workspace import chunk_tasks, compute_chunk, grid_poses, serpentine

METHODS = (('spring', 1), ('fem', 16), ('fem_sag', 16))
GRID_50 = 50 ** 3
OVERHEAD_TARGET = 0.05


def six_dof_config() -> Path:
    """The paper frame with a rigid platform (test/data/rigid_cdpr.yaml in the source tree),
    else the installed heavy-sag 6-DOF robot."""
    source = Path(__file__).resolve().parents[2] / 'test' / 'data' / 'rigid_cdpr.yaml'
    return source if source.is_file() else default_config_path().with_name(
        'heavy_sag_6dof.yaml')


def _poses(params: dict, count: int) -> np.ndarray:
    """``count`` poses on a small grid around the initial position (all feasible for the
    robots here), in the serpentine order a chunk walks."""
    centre = np.asarray(params['robot.initial_position'], dtype=float)
    q = np.asarray(params.get('robot.initial_orientation', [0, 0, 0, 1]), dtype=float)
    side = int(np.ceil(count ** (1 / 3)))
    axes = [np.linspace(c - 0.08, c + 0.08, side) for c in centre]
    poses = grid_poses(*axes, q)
    return poses[serpentine((side, side, side))][:count]


def _tasks(params, method, n, poses, chunk, auto=False):
    flat = {**params, 'model.method': method, 'model.elements_per_cable': n}
    return chunk_tasks(flat, poses, np.arange(poses.shape[0]), [{}], chunk, auto_columns=auto)


def per_worker(config: Path, count: int) -> list[dict]:
    """Poses/s of one worker per method (auto off), and of auto's choice alone."""
    params = read_params_file(config)
    poses = _poses(params, count)
    rows = []
    for method, n in METHODS:
        task = _tasks(params, method, n, poses, count)[0]
        compute_chunk(_tasks(params, method, n, poses[:1], 1)[0])      # warm-up
        start = time.perf_counter()
        columns = compute_chunk(task)
        seconds = time.perf_counter() - start
        ok = columns['status'].count('ok')
        rows.append({'config': config.name, 'method': method, 'elements_per_cable': n,
                     'poses': count, 'ok': ok, 'seconds': seconds,
                     'poses_per_s': count / seconds,
                     'grid_50_cubed_hours_per_worker': GRID_50 * seconds / count / 3600})
    task = _tasks(params, 'spring', 1, poses, count, auto=True)[0]
    start = time.perf_counter()
    compute_chunk(task)
    with_auto = time.perf_counter() - start
    spring = rows[0]['seconds']
    rows.append({'config': config.name, 'method': 'auto choice alone', 'poses': count,
                 'seconds': with_auto - spring, 'seconds_per_pose': (with_auto - spring) / count})
    return rows


def _wall(client, tasks) -> tuple[float, float]:
    """(wall time of ``tasks`` on ``client`` from submission to the last result, the poses'
    own compute time summed over the rows, measured inside the workers)."""
    start = time.perf_counter()
    results = client.gather(client.map(compute_chunk, tasks, pure=False))
    elapsed = time.perf_counter() - start
    return elapsed, float(sum(sum(r['compute_s']) for r in results))


def engine(config: Path, quick: bool) -> dict:
    """1 -> 2 worker scaling (fem 16) and the engine's overhead per chunk size (spring).

    Both clusters are started first; then 1-worker and 2-worker runs alternate ``repeat``
    times and each keeps its fastest, so a load that comes and goes on a shared machine
    biases no side."""
    import logging

    from dask.distributed import Client, LocalCluster
    params = read_params_file(config)
    repeat = 1 if quick else 3
    scaling_poses = _poses(params, 16 if quick else 48)
    overhead_poses = _poses(params, 32 if quick else 128)
    scaling_tasks = _tasks(params, 'fem', 16, scaling_poses, 4 if quick else 6)
    sizes = (1, 4, 16, 64)
    overhead_tasks = {c: _tasks(params, 'spring', 1, overhead_poses, c) for c in sizes}
    clusters, clients = {}, {}
    try:
        for workers in (1, 2):
            clusters[workers] = LocalCluster(n_workers=workers, threads_per_worker=1,
                                             processes=True, host='127.0.0.1',
                                             dashboard_address='127.0.0.1:0',
                                             silence_logs=logging.CRITICAL)
            clients[workers] = Client(clusters[workers])
            _wall(clients[workers], scaling_tasks[:workers])             # warm the workers
        best = {}

        def keep(name, seconds):
            best[name] = min(best.get(name, (np.inf, 0.0)), seconds)
        for _ in range(repeat):
            keep('scaling_1', _wall(clients[1], scaling_tasks))
            keep('scaling_2', _wall(clients[2], scaling_tasks))
            for chunk, tasks in overhead_tasks.items():
                keep(f'engine_{chunk}', _wall(clients[1], tasks))
    finally:
        logging.getLogger('distributed').setLevel(logging.ERROR)
        for workers in clients:
            clients[workers].close()
        for workers in clusters:
            clusters[workers].close()
    rows = []
    for chunk, tasks in overhead_tasks.items():
        wall, poses = best[f'engine_{chunk}']
        rows.append({'chunk_size': chunk, 'tasks': len(tasks), 'wall_s': wall,
                     'pose_compute_s': poses, 'overhead_fraction': wall / poses - 1.0,
                     'overhead_per_task_ms': 1e3 * (wall - poses) / len(tasks)})
    good = [r['chunk_size'] for r in rows if r['overhead_fraction'] < OVERHEAD_TARGET]
    return {'scaling_method': 'fem 16', 'scaling_poses': int(scaling_poses.shape[0]),
            'wall_1_worker_s': best['scaling_1'][0], 'wall_2_workers_s': best['scaling_2'][0],
            'speedup_1_to_2': best['scaling_1'][0] / best['scaling_2'][0], 'overhead': rows,
            'smallest_chunk_under_5_percent': min(good) if good else None,
            'cores': os.cpu_count(), 'repeat': repeat,
            'load_average': os.getloadavg()[0]}


def run(config: str | None, quick: bool) -> dict:
    paper = Path(config) if config else default_config_path()
    count = 4 if quick else 16
    return {'per_worker': per_worker(paper, count) + per_worker(six_dof_config(), count),
            'engine': engine(paper, quick),
            'note': 'one run on a shared machine: compare the ratios, not the absolute times'}


def summary(result: dict) -> str:
    lines = ['cdpr_workspace cost (one worker, one BLAS thread; auto columns off):']
    for row in result['per_worker']:
        if 'poses_per_s' in row:
            lines.append(f"  {row['config']:>18} {row['method']:>8} "
                         f"n={row['elements_per_cable']:<3} {row['poses_per_s']:7.2f} poses/s "
                         f"({row['ok']}/{row['poses']} ok); "
                         f"50^3 grid: {row['grid_50_cubed_hours_per_worker']:.1f} h per worker")
        else:
            lines.append(f"  {row['config']:>18} auto's choice adds "
                         f"{1e3 * row['seconds_per_pose']:.0f} ms per pose")
    eng = result['engine']
    lines.append(f"  scaling 1 -> 2 LocalCluster workers ({eng['scaling_method']}, "
                 f"{eng['scaling_poses']} poses): {eng['wall_1_worker_s']:.2f} s -> "
                 f"{eng['wall_2_workers_s']:.2f} s, x{eng['speedup_1_to_2']:.2f} "
                 f"({eng['cores']} cores, load average {eng['load_average']:.1f})")
    for row in eng['overhead']:
        lines.append(f"  chunk {row['chunk_size']:>3} (spring): engine overhead "
                     f"{100 * row['overhead_fraction']:6.1f} % "
                     f"({row['overhead_per_task_ms']:.1f} ms per task)")
    lines.append(f"  smallest chunk with overhead under 5 %: "
                 f"{eng['smallest_chunk_under_5_percent']}")
    return '\n'.join(lines)
