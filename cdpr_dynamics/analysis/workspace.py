"""Vibration and feasibility over a set of poses: the per-pose work of ``cdpr_workspace``.

Pure library (no ROS, no Dask): the engine (:mod:`cdpr_dynamics.cli.workspace`) sends each
worker a :class:`ChunkTask` and gets back its rows from :func:`compute_chunk`.

**One pose, one row** (:func:`pose_row`), by the calls ``cdpr_analyze`` makes: the chord
statics :func:`~cdpr_dynamics.analysis.pipeline.equilibrium`, ``auto``'s
:func:`~cdpr_dynamics.selection.auto.choose_model`, the statics the model needs
(:func:`~cdpr_dynamics.analysis.pipeline.equilibrium_for`),
:func:`~cdpr_dynamics.analysis.pipeline.build_system`,
the configured damping and :func:`~cdpr_dynamics.dynamics.system.frequency_response` over the
``frf.*`` sweep, the modes classified by :func:`cdpr_dynamics.dynamics.modes.modes`. Columns
(doc/tools/cdpr_workspace.md):

* ``tensions_n`` (N, at the model's statics) and ``tension_margin_n``: how much more load
  the cables could hold with tensions in [T_min, T_max], the smallest slack of the
  wrench-feasible set's facets around the required wrench
  (:meth:`cdpr_dynamics.mechanics.feasibility.WrenchSet.margin` at the chord structure matrix: the
  largest extra force, N, the platform takes in its worst direction; unit facet normals of
  the 6-D wrench space for a rigid platform); negative outside the feasible set (how far).
  (The least-norm distribution sits on T_min at most poses, so its own distance from the
  box is 0 nearly everywhere and maps nothing.) An underactuated robot's tensions are
  determined: its margin is the least distance of a tension from the box, at the equilibrium;
* ``structure_matrix_condition`` sigma_max / sigma_min of W^T (inf where rank deficient);
* ``max_sag_parameter``: the largest Irvine lambda^2 over the cables at the model's statics;
* ``lowest_platform_hz``, ``platform_modes_hz``: modes of kind ``platform`` in [0, f_max] and
  among the 12 lowest (NaN / empty where there is none; massless models: all platform modes;
  ``dsm``, without finite mode shapes: not classified, NaN); ``first_cable_mode_hz`` the
  lowest mode of kind ``cable`` (NaN for massless models);
* ``peak_receptance_m_per_n`` = max_f |A(f)| / |F0|, A the centroid's translation amplitude
  (m) of the FRF of ``frf.force_n`` F0 with the configured damping (m/N);
* ``min_stiffness_n_per_m``: the smallest eigenvalue of the translational static stiffness at
  the centroid, ((K^-1)_tt)^-1 (rotations free for a rigid platform; N/m);
* ``auto_method``, ``auto_elements``: what ``model.method = auto`` picks at this pose;
* ``method``, ``elements_per_cable``: the model the row was computed with;
* ``compute_s``: the wall time of the row;
* ``equilibrium_distance_m``, ``equilibrium_angle_rad``: how far the equilibrium analysed lies
  from the pose (an underactuated robot settles where its cable lengths hold it; 0 for a
  robot whose cables hold every pose).

**Status** (never an exception, never a missing row): ``ok``; ``outside`` (no such pose: not
finite, or an attachment on its anchor), ``rank_deficient``, ``crossing``, ``infeasible`` (no
tension distribution in the box, chord or sag-consistent; an underactuated robot's slack
cable), ``unstable`` (an underactuated robot's equilibrium that gravity and the cables do not
hold), ``method_invalid`` (the model refuses the
state: slack, no catenary spanning the chord, ``auto`` finding no model), ``error`` (any other
failure of the library at that pose, its exception's first line); ``failed`` is the
engine's (a task that kept failing: a worker lost, an environment without the package).
``reason`` is the one-line message of the library (empty for ``ok``; warnings are not
repeated per row).

**Chunks**: :func:`chunk_tasks` cuts the poses of each design variant into runs of neighbours
(a serpentine walk through the grid); a worker builds the settings and the tension QP once per
chunk and warm-starts the QP, the sag statics and the eigen-solver size along it.
"""
from __future__ import annotations

import itertools
import json
import math
import time
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.analysis.pipeline import (AnalysisError, Equilibrium, build_system, damping_for,
                                             equilibrium, equilibrium_for, new_tension_solver,
                                             safe, structure_rank)
from cdpr_dynamics.analysis.config import Settings, check_names, check_value, settings_from_params
from cdpr_dynamics.dynamics.system import frequency_response
from cdpr_dynamics.mechanics.feasibility import WrenchSet
from cdpr_dynamics.mechanics.underactuated import is_underactuated
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.dynamics.modes import modes
from cdpr_dynamics.mechanics.robot import (GeometryError, geometry, quaternion_to_matrix,
                                           required_wrench)
from cdpr_dynamics.selection.auto import choose_model

STATUSES = ('ok', 'outside', 'rank_deficient', 'crossing', 'infeasible', 'unstable',
            'method_invalid', 'error', 'failed')
#: The doc/tools/cdpr_workspace.md columns, then what the row was computed with.
COLUMNS = ('x_m', 'y_m', 'z_m', 'qx', 'qy', 'qz', 'qw', 'status', 'reason', 'tensions_n',
           'tension_margin_n', 'structure_matrix_condition', 'max_sag_parameter',
           'lowest_platform_hz', 'platform_modes_hz', 'first_cable_mode_hz',
           'peak_receptance_m_per_n', 'min_stiffness_n_per_m', 'auto_method', 'auto_elements',
           'compute_s', 'method', 'elements_per_cable', 'equilibrium_distance_m',
           'equilibrium_angle_rad')
LIST_COLUMNS = ('tensions_n', 'platform_modes_hz')
TEXT_COLUMNS = ('status', 'reason', 'auto_method', 'method')
INT_COLUMNS = ('auto_elements', 'elements_per_cable')
DEFAULT_CHUNK = 16

#: equilibrium()'s refusals by the words of their one-line messages, first match wins.
_STATICS_KINDS = (('outside', ('zero length', 'not finite')),
                  ('rank_deficient', ('structure matrix has rank',)),
                  ('crossing', (' cross',)),
                  ('infeasible', ('infeasible tension', 'sag-consistent', 'is slack')),
                  ('unstable', ('unstable',)))


class WorkspaceError(ValueError):
    """Arguments that describe no workspace run; the message is one line."""


def statics_status(message: str) -> str:
    """The status of a pose whose statics :func:`equilibrium` refused with ``message``."""
    for kind, words in _STATICS_KINDS:
        if any(word in message for word in words):
            return kind
    return 'error'
    return 'error'


# --------------------------------------------------------------------------- poses

def axis_values(name: str, start: float, stop: float, count) -> np.ndarray:
    """``count`` points from ``start`` to ``stop`` inclusive; refuses an empty or inverted
    range (one point needs start == stop)."""
    if not (math.isfinite(start) and math.isfinite(stop)):
        raise WorkspaceError(f'--{name}: the range must be finite')
    if float(count) != int(count) or int(count) < 1:
        raise WorkspaceError(f'--{name}: the number of points must be a positive integer, '
                             f'got {count}')
    count = int(count)
    if stop < start:
        raise WorkspaceError(f'--{name}: the range is inverted ({start:g} > {stop:g})')
    if count == 1 and stop != start:
        raise WorkspaceError(f'--{name}: one point needs equal ends (got {start:g} .. '
                             f'{stop:g}); give 2 or more points')
    if count > 1 and stop == start:
        raise WorkspaceError(f'--{name}: {count} points over an empty range ({start:g} .. '
                             f'{stop:g}); give 1 point or a wider range')
    return np.linspace(start, stop, count)


def grid_poses(x: np.ndarray, y: np.ndarray, z: np.ndarray, quaternion) -> np.ndarray:
    """(nx ny nz, 7) poses x y z qx qy qz qw, x slowest and z fastest (the table's order)."""
    q = unit_quaternion(quaternion)
    px, py, pz = np.meshgrid(x, y, z, indexing='ij')
    points = np.stack([px.ravel(), py.ravel(), pz.ravel()], axis=1)
    return np.hstack([points, np.broadcast_to(q, (points.shape[0], 4))])


def unit_quaternion(quaternion) -> np.ndarray:
    """(qx, qy, qz, qw) normalised; refuses one that is not finite or far from unit length."""
    q = np.asarray(quaternion, dtype=float).reshape(4)
    norm = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or abs(norm - 1.0) > 1e-3:
        raise WorkspaceError(f'orientation {q.tolist()} is not a unit quaternion (qx qy qz qw)')
    return q / norm


def serpentine(shape: tuple[int, int, int]) -> np.ndarray:
    """Grid indices (x slowest, z fastest) in a walk where consecutive poses are neighbours:
    z runs up and down, y back and forth."""
    nx, ny, nz = shape
    order = []
    for i in range(nx):
        ys = range(ny) if i % 2 == 0 else range(ny - 1, -1, -1)
        for step, j in enumerate(ys):
            zs = range(nz) if (i * ny + step) % 2 == 0 else range(nz - 1, -1, -1)
            order.extend((i * ny + j) * nz + k for k in zs)
    return np.asarray(order, dtype=int)


def read_poses_csv(path) -> np.ndarray:
    """(n, 7) poses from a CSV with a header naming x_m, y_m, z_m (m) and optionally qx, qy,
    qz, qw (identity where absent)."""
    import csv
    try:
        with open(path, newline='') as stream:
            reader = csv.DictReader(stream)
            fields = [f.strip() for f in (reader.fieldnames or [])]
            rows = [{(k or '').strip(): v for k, v in row.items()} for row in reader]
    except (OSError, UnicodeDecodeError) as exc:
        raise WorkspaceError(f'cannot read --poses {path}: {getattr(exc, "strerror", exc)}') \
            from None
    missing = [c for c in ('x_m', 'y_m', 'z_m') if c not in fields]
    if missing:
        raise WorkspaceError(f'--poses {path}: no column {missing[0]} (the header needs x_m, '
                             f'y_m, z_m and optionally qx, qy, qz, qw)')
    if not rows:
        raise WorkspaceError(f'--poses {path} has no poses')
    names = ('x_m', 'y_m', 'z_m', 'qx', 'qy', 'qz', 'qw')
    default = {'qx': '0', 'qy': '0', 'qz': '0', 'qw': '1'}
    out = np.empty((len(rows), 7))
    for i, row in enumerate(rows):
        try:
            out[i] = [float(row.get(c) or default.get(c, 'nan')) for c in names]
        except ValueError:
            raise WorkspaceError(f'--poses {path}: row {i + 2} is not numeric') from None
        if not np.all(np.isfinite(out[i])):
            raise WorkspaceError(f'--poses {path}: row {i + 2} is not finite')
        out[i, 3:] = unit_quaternion(out[i, 3:])
    return out


# --------------------------------------------------------------------------- variants

def parse_vary(texts) -> dict[str, list]:
    """``['cable.area_m2=5e-5,1e-4', ...]`` -> {name: [values]}, each value checked and
    converted as the parameter's (an array parameter takes [a, b, c] per value)."""
    import yaml
    vary: dict[str, list] = {}
    for text in texts or ():
        name, sep, values = str(text).partition('=')
        name = name.strip()
        if not sep or not name or not values.strip():
            raise WorkspaceError(f'--vary {text!r}: write NAME=V1,V2,...')
        try:
            check_names([name])
        except ValueError as exc:
            raise WorkspaceError(f'--vary: {exc}') from None
        if name in vary:
            raise WorkspaceError(f'--vary {name} is given twice')
        try:
            parsed = yaml.safe_load('[' + values + ']')
        except yaml.YAMLError:
            raise WorkspaceError(f'--vary {text!r}: values are not a comma-separated list') \
                from None
        if not isinstance(parsed, list) or not parsed:
            raise WorkspaceError(f'--vary {text!r}: write NAME=V1,V2,...')
        checked = []
        for value in parsed:
            try:
                value = check_value(name, value)
            except ValueError as exc:
                raise WorkspaceError(f'--vary: {exc}') from None
            checked.append(value.tolist() if isinstance(value, np.ndarray) else value)
        if len({json.dumps(v) for v in checked}) != len(checked):
            raise WorkspaceError(f'--vary {name}: give distinct values')
        vary[name] = checked
    return vary


def variants(vary: dict[str, list]) -> list[dict]:
    """Every combination of the varied values, the first name slowest ([{}] without any)."""
    names = list(vary)
    return [dict(zip(names, combo)) for combo in itertools.product(*(vary[n] for n in names))]


# --------------------------------------------------------------------------- chunks

@dataclass(frozen=True, eq=False)
class ChunkTask:
    """One task: poses (k, 7) with their row ids, all of one design variant."""

    chunk: int
    params: dict                 # flat parameters of the variant (the config plus its values)
    variant: dict                # the varied names and this variant's values
    pose_id: np.ndarray          # (k,) row ids in the final table
    poses: np.ndarray            # (k, 7)
    auto_columns: bool = True


def chunk_tasks(params: dict, poses: np.ndarray, order: np.ndarray, variant_list: list[dict],
                chunk_size: int = DEFAULT_CHUNK, auto_columns: bool = True) -> list[ChunkTask]:
    """The run's tasks: per variant v, the poses in ``order`` cut into runs of ``chunk_size``;
    row id = v * n_poses + pose index."""
    if chunk_size < 1:
        raise WorkspaceError('--chunk-size must be at least 1')
    n = poses.shape[0]
    tasks = []
    for v, values in enumerate(variant_list):
        for start in range(0, n, chunk_size):
            index = order[start:start + chunk_size]
            tasks.append(ChunkTask(len(tasks), {**params, **values}, dict(values),
                                   v * n + index, poses[index], auto_columns))
    return tasks


def compute_chunk(task: ChunkTask) -> dict[str, list]:
    """The rows of one chunk as columns {name: list} (plus ``pose_id``): the settings and
    the tension QP built once, the QP, the sag statics and the eigen-solver size warm-started
    from the previous pose of the chunk."""
    settings = settings_from_params(task.params)
    solver = new_tension_solver(settings)
    rows, previous, hint = [], None, 0
    for pose in task.poses:
        row, eq, count = pose_row(settings, pose, solver, previous, hint, task.auto_columns)
        rows.append(row)
        previous = eq if eq is not None else previous
        hint = count or hint
    columns = {name: [row[name] for row in rows] for name in COLUMNS}
    columns['pose_id'] = [int(i) for i in task.pose_id]
    return columns


def failed_columns(task: ChunkTask, reason: str) -> dict[str, list]:
    """The rows of a chunk the engine could not compute: status ``failed`` with ``reason``."""
    rows = [blank_row(pose, 'failed', reason) for pose in task.poses]
    columns = {name: [row[name] for row in rows] for name in COLUMNS}
    columns['pose_id'] = [int(i) for i in task.pose_id]
    return columns


def blank_row(pose, status: str = 'ok', reason: str = '') -> dict:
    """A row with the pose and no results (NaN, empty lists, None)."""
    row = {name: math.nan for name in COLUMNS}
    row.update(zip(('x_m', 'y_m', 'z_m', 'qx', 'qy', 'qz', 'qw'), map(float, pose)))
    row.update(status=status, reason=reason, tensions_n=[], platform_modes_hz=[],
               auto_method=None, auto_elements=None, method=None, elements_per_cable=None,
               compute_s=0.0)
    return row


# --------------------------------------------------------------------------- one pose

def pose_row(settings: Settings, pose, solver=None, previous: Equilibrium | None = None,
             hint: int = 0, auto_columns: bool = True) -> tuple[dict, Equilibrium | None, int]:
    """(row, the statics to warm-start the next pose from or None, the number of modes
    computed) at ``pose`` (x y z qx qy qz qw); never raises for a state the library refuses.
    """
    begin = time.perf_counter()
    row = blank_row(pose)
    eq, count = None, 0
    try:
        eq, count = _fill(row, settings, np.asarray(pose, dtype=float), solver, previous,
                          hint, auto_columns)
    except _Refused as exc:
        row.update(status=exc.status, reason=exc.reason)
    except Exception as exc:    # noqa: BLE001 - a library failure of one pose is its row's
        text = str(exc).strip().splitlines()
        row.update(status='error', reason=f'{type(exc).__name__}: {text[0]}' if text else
                   type(exc).__name__)
    row['compute_s'] = time.perf_counter() - begin
    return row, eq, count


class _Refused(Exception):
    def __init__(self, status: str, reason: str):
        super().__init__(reason)
        self.status, self.reason = status, reason.splitlines()[0] if reason else status


def _fill(row, settings, pose, solver, previous, hint, auto_columns):
    position, rotation = pose[:3], quaternion_to_matrix(pose[3:])
    try:
        geo = geometry(settings.robot, position, rotation)
        row['structure_matrix_condition'] = structure_rank(geo.structure_matrix)[1]
    except GeometryError as exc:
        raise _Refused('outside', str(exc)) from None
    wrench = required_wrench(settings.robot, settings.external_force_n,
                             settings.external_moment_nm, rotation)
    if not is_underactuated(settings.robot):
        row['tension_margin_n'] = WrenchSet(geo.structure_matrix, settings.tension_min_n,
                                            settings.tension_max_n, wrench).margin(np.zeros(3))
    try:
        chord = equilibrium(settings, position, rotation, solver=solver)
    except AnalysisError as exc:
        raise _Refused(statics_status(str(exc)), str(exc)) from None
    held = chord.balance
    row['equilibrium_distance_m'] = 0.0 if held is None else held.distance_m
    row['equilibrium_angle_rad'] = 0.0 if held is None else held.angle_rad
    if held is not None and held.moved:         # the row describes the equilibrium
        row['structure_matrix_condition'] = structure_rank(held.geometry.structure_matrix)[1]
    if is_underactuated(settings.robot):
        tension = chord.tensions.tension_n
        row['tension_margin_n'] = float(min(np.min(tension - settings.tension_min_n),
                                            np.min(settings.tension_max_n - tension)))
    row['tensions_n'] = chord.tensions.tension_n.tolist()
    method, elements = settings.method, settings.elements_per_cable
    if auto_columns or method == 'auto':
        try:
            choice = safe(choose_model, settings, chord)
            row['auto_method'], row['auto_elements'] = choice.method, \
                int(choice.elements_per_cable)
        except AnalysisError as exc:
            if method == 'auto':
                raise _Refused('method_invalid', f'auto: {exc}') from None
        if method == 'auto':
            method, elements = choice.method, choice.elements_per_cable
    row['method'], row['elements_per_cable'] = method, int(elements)
    start = previous if previous is not None and previous.statics == 'sag' else None
    try:
        eq = equilibrium_for(settings, chord, method, start)
    except AnalysisError as exc:
        raise _Refused(statics_status(str(exc)), str(exc)) from None
    tension = eq.tensions.tension_n
    row['tensions_n'] = tension.tolist()
    row['max_sag_parameter'] = float(np.max(sag_parameter(eq.cables)))
    try:
        system = build_system(settings, eq, method, elements)
    except AnalysisError as exc:
        raise _Refused('method_invalid', str(exc)) from None
    if not system.assembly.valid:
        raise _Refused('method_invalid', f'method {system.assembly.method} fails for this '
                       f'scene: ' + '; '.join(system.assembly.warnings))
    try:
        count = _dynamics(row, settings, system, hint)
    except AnalysisError as exc:
        raise _Refused('error', str(exc)) from None
    return eq, count


def _dynamics(row, settings, system, hint) -> int:
    """Modes, FRF peak and static stiffness of ``system`` into ``row``; the mode count."""
    damping = damping_for(settings, system)
    response = safe(frequency_response, system, settings.frequencies_hz, settings.frf_force_n,
                    damping=damping)
    force = float(np.linalg.norm(settings.frf_force_n))
    amplitude = np.linalg.norm(response.amplitude_m, axis=1)
    row['peak_receptance_m_per_n'] = float(amplitude.max() / force) if force > 0 else math.nan
    row['min_stiffness_n_per_m'] = translational_stiffness(system.static_stiffness())
    count = 0
    if system.assembly.blocks is not None:
        found = safe(modes, system, settings.f_max_hz, hint=hint)
        count = found.frequency_hz.size
        platform = found.platform_hz
        row['platform_modes_hz'] = platform.tolist()
        row['lowest_platform_hz'] = float(platform[0]) if platform.size else math.nan
        cable = found.cable_hz
        row['first_cable_mode_hz'] = float(cable[0]) if cable.size else math.nan
    return count


def translational_stiffness(stiffness: np.ndarray) -> float:
    """Smallest eigenvalue (N/m) of the stiffness a force at the centroid feels,
    ((K^-1)_tt)^-1 (rotations free); 0 where K is singular."""
    try:
        compliance = np.linalg.inv(stiffness)[:3, :3]
        return float(np.linalg.eigvalsh(np.linalg.inv(0.5 * (compliance + compliance.T)))[0])
    except np.linalg.LinAlgError:
        return 0.0


# --------------------------------------------------------------------------- the table

def table_schema():
    """The pyarrow schema of ``workspace.parquet`` (without the varied columns)."""
    import pyarrow as pa
    types = {name: pa.float64() for name in COLUMNS}
    types.update({name: pa.string() for name in TEXT_COLUMNS})
    types.update({name: pa.int64() for name in INT_COLUMNS})
    types.update({name: pa.list_(pa.float64()) for name in LIST_COLUMNS})
    return pa.schema([pa.field('pose_id', pa.int64())]
                     + [pa.field(name, types[name]) for name in COLUMNS])


def chunk_table(columns: dict[str, list], variant: dict):
    """A pyarrow table of one chunk's columns, a column per varied name (its value as text
    for arrays and strings, else float)."""
    import pyarrow as pa
    table = pa.Table.from_pydict({k: columns[k] for k in ['pose_id', *COLUMNS]},
                                 schema=table_schema())
    for name, value in variant.items():
        table = table.append_column(name, pa.array([value_cell(value)] * table.num_rows))
    return table


def value_cell(value):
    """A varied value as a table cell: float for numbers, text otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return json.dumps(value) if not isinstance(value, str) else value
    return float(value)
