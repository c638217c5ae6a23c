"""``cdpr_workspace``: vibration and feasibility maps over a grid of poses, on Dask.

    cdpr_workspace [--config PATH] (--x X0 X1 NX --y Y0 Y1 NY --z Z0 Z1 NZ | --poses CSV)
                   [--orientation QX QY QZ QW] [--method M] [--elements N]
                   [--vary NAME=V1,V2,...]... --output DIR [--scheduler tcp://HOST:PORT]
                   [--workers N] [--chunk-size K] [--retries R] [--resume]
                   [--maps-axis {x,y,z} ...] [--no-maps] [--skip-auto]

Writes ``DIR/workspace.parquet`` (one row per pose and design variant, the
columns of doc/tools/cdpr_workspace.md; the
config, the varied values and the command in its metadata under ``cdpr_workspace``), PNG maps
of slices (:mod:`cdpr_dynamics.analysis.workspace_maps`) and ``DIR/summary.md``.

Engine. By default a ``dask.distributed.LocalCluster`` of ``--workers`` processes (one
thread each; default: the cores of this machine) on 127.0.0.1; ``--scheduler ADDRESS`` sends
the same tasks to an existing Dask cluster (its workers need cdpr_dynamics installed);
``--workers 0`` computes in this process, without Dask. A task is a chunk of neighbouring
poses (:func:`cdpr_dynamics.analysis.workspace.chunk_tasks`); a task that raises is retried
``--retries`` times by Dask (a worker that dies is replaced and its tasks rerun, up to the
scheduler's ``allowed-failures``), then its poses get ``status = failed`` with the reason
(the table is still written; the exit status is then 1 and ``--resume`` recomputes them).

Nothing lost. ``DIR/plan.json`` fingerprints the run (config, poses, variants, chunk size);
each finished chunk is written at once to ``DIR/chunks/`` (write, then rename); ``--resume``
with the same arguments computes only the chunks not on disk (and those whose poses failed)
and then assembles the table from the chunk files, every pose exactly once. Ctrl-C ends with
the one line ``cdpr_workspace: interrupted`` and status 130, keeping the finished chunks.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import shlex
import signal
import sys
from pathlib import Path

import numpy as np

from cdpr_dynamics.cli import interruptible, plain
from cdpr_dynamics.analysis.config import (METHODS, ConfigError, default_config_path,
                                           read_params_file, settings_from_params)
from cdpr_dynamics.analysis.workspace import (DEFAULT_CHUNK, WorkspaceError, axis_values,
                                              chunk_table, chunk_tasks, compute_chunk,
                                              failed_columns, grid_poses, parse_vary,
                                              read_poses_csv, serpentine, unit_quaternion,
                                              variants)

PROG = 'cdpr_workspace'
PLAN_VERSION = 1
CONNECT_TIMEOUT_S = 20


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROG, description=plain(__doc__.split('\n')[0]))
    parser.add_argument('--config', help='ROS 2 parameter YAML (default: the paper robot)')
    for axis in 'xyz':
        parser.add_argument(f'--{axis}', nargs=3, type=float, metavar=(f'{axis.upper()}0',
                            f'{axis.upper()}1', f'N{axis.upper()}'),
                            help=f'N{axis.upper()} points from {axis.upper()}0 to '
                            f'{axis.upper()}1 inclusive (m)')
    parser.add_argument('--poses', type=Path, help='CSV of poses (header x_m,y_m,z_m[,qx,qy,'
                        'qz,qw]) instead of a grid')
    parser.add_argument('--orientation', nargs=4, type=float, metavar=('QX', 'QY', 'QZ', 'QW'),
                        help='platform orientation of the grid (default: '
                        'robot.initial_orientation)')
    parser.add_argument('--method', choices=METHODS, help='cable model (model.method)')
    parser.add_argument('--elements', type=int, help='elements per cable (fem, fem_sag)')
    parser.add_argument('--vary', action='append', default=[], metavar='NAME=V1,V2,...',
                        help='design variants: any parameter of the table, several values '
                        '(arrays as [a, b, c]); repeat for more names; multiplies the grid')
    parser.add_argument('--output', type=Path, required=True, help='folder of the results')
    parser.add_argument('--scheduler', metavar='ADDRESS',
                        help='an existing Dask scheduler, e.g. tcp://10.0.0.5:8786')
    parser.add_argument('--workers', type=int, help='local worker processes (default: the '
                        'cores of this machine; 0: compute in this process without Dask)')
    parser.add_argument('--chunk-size', type=int, default=DEFAULT_CHUNK,
                        help=f'poses per task (default {DEFAULT_CHUNK})')
    parser.add_argument('--retries', type=int, default=2, help='retries of a failing task')
    parser.add_argument('--resume', action='store_true',
                        help='continue the run in --output: compute only unfinished chunks')
    parser.add_argument('--maps-axis', nargs='+', choices='xyz', default=['z'],
                        help='slice the maps across these axes (default z)')
    parser.add_argument('--no-maps', action='store_true', help='write no PNG maps')
    parser.add_argument('--skip-auto', action='store_true',
                        help="leave auto_method/auto_elements empty (auto's choice costs "
                        'about 0.3 s per pose) unless --method auto')
    return parser.parse_args(argv)


class Run:
    """What the arguments describe: parameters, poses, tasks and the run's folder."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.config_path = Path(args.config) if args.config else default_config_path()
        params = read_params_file(self.config_path)
        if args.method:
            params['model.method'] = args.method
        if args.elements is not None:
            params['model.elements_per_cable'] = args.elements
        self.settings = settings_from_params(params)       # checks the base config
        self.params = params
        self.vary = parse_vary(args.vary)
        self.variant_list = variants(self.vary)
        for values in self.variant_list:                   # every variant must be a robot
            try:
                settings_from_params({**params, **values})
            except ConfigError as exc:
                raise WorkspaceError(f'--vary {values}: {exc}') from None
        self.poses, self.shape, self.order, self.grid = self._poses(args)
        if args.workers is not None and args.workers < 0:
            raise WorkspaceError('--workers must be 0 or more')
        if args.retries < 0:
            raise WorkspaceError('--retries must be 0 or more')
        self.tasks = chunk_tasks(params, self.poses, self.order, self.variant_list,
                                 args.chunk_size, auto_columns=not args.skip_auto)
        self.rows = self.poses.shape[0] * len(self.variant_list)
        self.out = args.output
        self.chunk_dir = self.out / 'chunks'

    def _poses(self, args):
        given = [a for a in 'xyz' if getattr(args, a) is not None]
        if args.poses is not None:
            if given:
                raise WorkspaceError('give either --poses or the grid (--x --y --z), not both')
            poses = read_poses_csv(args.poses)
            return poses, None, np.arange(poses.shape[0]), None
        if len(given) < 3:
            missing = [a for a in 'xyz' if a not in given]
            raise WorkspaceError(f'give the grid (--x X0 X1 NX --y ... --z ...; missing '
                                 f'--{missing[0]}) or --poses FILE.csv')
        axes = [axis_values(a, *getattr(args, a)) for a in 'xyz']
        q = unit_quaternion(args.orientation if args.orientation is not None else
                            self._initial_quaternion())
        shape = tuple(a.size for a in axes)
        return grid_poses(*axes, q), shape, serpentine(shape), axes

    def _initial_quaternion(self) -> np.ndarray:
        q = self.params.get('robot.initial_orientation', [0.0, 0.0, 0.0, 1.0])
        return np.asarray(q, dtype=float)

    def fingerprint(self) -> str:
        """What decides the rows: parameters, poses, variants, chunking, auto columns."""
        digest = hashlib.sha256()
        digest.update(json.dumps({'params': _plain(self.params), 'vary': self.vary,
                                  'chunk': self.args.chunk_size,
                                  'auto': not self.args.skip_auto}, sort_keys=True).encode())
        digest.update(np.ascontiguousarray(self.poses).tobytes())
        return digest.hexdigest()

    def metadata(self, argv) -> dict:
        return {'command': shlex.join([PROG, *argv]), 'config_path': str(self.config_path),
                'config': _plain(self.params), 'config_text': _text(self.config_path),
                'vary': self.vary, 'chunk_size': self.args.chunk_size, 'rows': self.rows,
                'grid': None if self.grid is None else
                {a: v.tolist() for a, v in zip('xyz', self.grid)}}

    def chunk_path(self, chunk: int) -> Path:
        return self.chunk_dir / f'chunk-{chunk:06d}.parquet'


def _plain(params: dict) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in params.items()}


def _text(path: Path) -> str:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return ''


# --------------------------------------------------------------------------- the plan on disk

def prepare(run: Run, resume: bool) -> list:
    """The tasks still to compute; writes or checks ``plan.json``."""
    plan_path = run.out / 'plan.json'
    plan = {'version': PLAN_VERSION, 'fingerprint': run.fingerprint(),
            'chunks': len(run.tasks), 'rows': run.rows}
    if plan_path.exists():
        try:
            old = json.loads(plan_path.read_text())
        except (OSError, ValueError):
            raise WorkspaceError(f'{plan_path} is unreadable: choose another --output') \
                from None
        done = sum(1 for t in run.tasks if finished(run, t))
        if not resume:
            raise WorkspaceError(f'{run.out} holds a run already ({done} of '
                                 f'{old.get("chunks", "?")} chunks done): continue it with '
                                 '--resume or choose another --output')
        if old.get('fingerprint') != plan['fingerprint']:
            raise WorkspaceError(f'--resume: {run.out} was started with other arguments (config,'
                                 ' grid or poses, --vary, --method, --elements, --chunk-size '
                                 'or --skip-auto differ): give them as before')
    elif resume:
        raise WorkspaceError(f'--resume: {run.out} holds no run (no plan.json)')
    else:
        run.chunk_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write(plan_path, json.dumps(plan, indent=1).encode())
    run.chunk_dir.mkdir(parents=True, exist_ok=True)
    return [t for t in run.tasks if not finished(run, t)]


def finished(run: Run, task) -> bool:
    """A chunk file with exactly the task's rows and none of them ``failed``."""
    import pyarrow.parquet as pq
    path = run.chunk_path(task.chunk)
    if not path.exists():
        return False
    try:
        table = pq.read_table(path, columns=['pose_id', 'status'])
    except Exception:   # noqa: BLE001 - any unreadable file is recomputed
        return False
    return (table.column('pose_id').to_pylist() == [int(i) for i in task.pose_id]
            and 'failed' not in table.column('status').to_pylist())


def write_chunk(run: Run, task, columns: dict) -> None:
    import pyarrow.parquet as pq
    path = run.chunk_path(task.chunk)
    tmp = path.with_suffix('.tmp')
    pq.write_table(chunk_table(columns, task.variant), tmp)
    os.replace(tmp, path)


def assemble(run: Run, argv) -> tuple[Path, object]:
    """``workspace.parquet`` from the chunk files: every row id exactly once, in order."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    tables = [pq.read_table(run.chunk_path(t.chunk)) for t in run.tasks]
    table = pa.concat_tables(tables)
    table = table.take(pa.compute.sort_indices(table, [('pose_id', 'ascending')]))
    ids = table.column('pose_id').to_numpy()
    if ids.size != run.rows or np.any(ids != np.arange(run.rows)):
        raise WorkspaceError(f'the chunk files hold {ids.size} rows for {run.rows} poses: '
                             'rerun with --resume')
    meta = dict(table.schema.metadata or {})
    meta[b'cdpr_workspace'] = json.dumps(run.metadata(argv)).encode()
    table = table.replace_schema_metadata(meta)
    path = run.out / 'workspace.parquet'
    tmp = path.with_suffix('.tmp')
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path, table


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_suffix(path.suffix + '.tmp')
    tmp.write_bytes(data)
    os.replace(tmp, path)


# --------------------------------------------------------------------------- the engine

def run_tasks(tasks, on_chunk, *, scheduler: str | None = None, workers: int | None = None,
              retries: int = 2, compute=compute_chunk) -> None:
    """Compute ``tasks`` and call ``on_chunk(task, columns)`` as each finishes (in this
    process, in completion order): in this process for ``workers == 0``, else on Dask (a
    LocalCluster of ``workers`` processes on 127.0.0.1, or the cluster at ``scheduler``).
    A task that still fails after ``retries`` gets :func:`failed_columns`."""
    if not scheduler and workers == 0:
        for task in tasks:
            on_chunk(task, compute(task))
        return
    from dask.distributed import Client, LocalCluster, as_completed
    logging.getLogger('distributed').setLevel(logging.ERROR)
    cluster = None
    client = None
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout=f'{CONNECT_TIMEOUT_S}s')
            except (OSError, TimeoutError, ValueError) as exc:
                raise WorkspaceError(f'cannot reach the Dask scheduler at {scheduler}: '
                                     f'{_one_line(exc)}') from None
        else:
            count = workers or default_workers()
            previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # workers ignore Ctrl-C
            try:
                cluster = LocalCluster(n_workers=count, threads_per_worker=1, processes=True,
                                       host='127.0.0.1', dashboard_address='127.0.0.1:0',
                                       silence_logs=logging.CRITICAL)
            finally:
                signal.signal(signal.SIGINT, previous)
            client = Client(cluster)
        by_key = {}
        for task in tasks:
            future = client.submit(compute, task, retries=retries, pure=False,
                                   key=f'cdpr-workspace-chunk-{task.chunk}-{os.urandom(4).hex()}')
            by_key[future.key] = (future, task)
        for future in as_completed([f for f, _ in by_key.values()]):
            task = by_key.pop(future.key)[1]
            columns = chunk_result(future, task, retries)
            future.release()
            on_chunk(task, columns)
    finally:
        if client is not None:
            client.close(timeout=10)
        if cluster is not None:
            cluster.close(timeout=10)


def chunk_result(future, task, retries: int) -> dict:
    """The columns of a finished chunk's Dask future, or :func:`failed_columns` with the
    reason. A result lost with its worker after ``as_completed`` saw it finish is 'lost', not
    failed: ``result()`` waits while the scheduler computes it again elsewhere (its status,
    read at that moment, said neither 'finished' nor 'error', and 3 poses were reported failed
    with 'NoneType: None')."""
    try:
        return future.result()
    except Exception as exc:  # noqa: BLE001 - the task's own error after its retries, or the
        # engine's (KilledWorker, CancelledError)
        return failed_columns(task, f'the engine gave up on this chunk after {retries} '
                              f'retries: {_one_line(exc)}')


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def _one_line(exc) -> str:
    text = str(exc).strip().splitlines()
    return f'{type(exc).__name__}: {text[0]}' if text else type(exc).__name__


# --------------------------------------------------------------------------- main

@interruptible(PROG)
def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    try:
        run = Run(args)
        todo = prepare(run, args.resume)
    except (ConfigError, WorkspaceError) as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 1
    except OSError as exc:
        print(f'{PROG}: error: cannot write {exc.filename or args.output}: {exc.strerror}',
              file=sys.stderr)
        return 1
    from tqdm import tqdm
    todo_rows = sum(t.pose_id.size for t in todo)
    bar = tqdm(total=run.rows, initial=run.rows - todo_rows, unit='pose', desc=PROG,
               disable=None, smoothing=0.1)
    try:
        def on_chunk(task, columns):
            write_chunk(run, task, columns)
            bar.update(len(columns['pose_id']))
        if todo:
            run_tasks(todo, on_chunk, scheduler=args.scheduler, workers=args.workers,
                      retries=args.retries)
        bar.close()
        path, table = assemble(run, argv)
        written = [path]
        from cdpr_dynamics.analysis import workspace_maps
        if not args.no_maps:
            written += workspace_maps.write_maps(table, run, args.maps_axis)
        written.append(workspace_maps.write_summary(table, run))
    except WorkspaceError as exc:
        bar.close()
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 1
    except OSError as exc:
        bar.close()
        print(f'{PROG}: error: cannot write {exc.filename or args.output}: {exc.strerror}',
              file=sys.stderr)
        return 1
    finally:
        bar.close()
    for item in written:
        print(f'wrote {item}')
    statuses = table.column('status').to_pylist()
    counts = ', '.join(f'{s} {statuses.count(s)}' for s in dict.fromkeys(statuses))
    print(f'{run.rows} poses: {counts}')
    if 'failed' in statuses:
        first = table.column('reason').to_pylist()[statuses.index('failed')]
        print(f'{PROG}: error: {statuses.count("failed")} of {run.rows} poses failed in the '
              f'engine ({first}); --resume recomputes them', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
