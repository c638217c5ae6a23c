"""The measured modes table of ``cdpr_calibrate`` : CSV, ``#`` lines comments.

One row per mode: ``pose_id``, the platform frame's pose ``x_m y_m z_m qx qy qz qw`` in
``robot.frame_id``, ``frequency_hz`` and optionally ``std_hz``, ``damping_ratio``,
``damping_ratio_std`` and the mode's direction ``dx dy dz rx ry rz`` (an empty cell: not
known). :class:`ModesTable` holds it as arrays, NaN where a value is not known.
"""
from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass

import numpy as np

POSE_COLUMNS = ('x_m', 'y_m', 'z_m', 'qx', 'qy', 'qz', 'qw')
REQUIRED_COLUMNS = ('pose_id',) + POSE_COLUMNS + ('frequency_hz',)
DIRECTION_COLUMNS = ('dx', 'dy', 'dz', 'rx', 'ry', 'rz')
OPTIONAL_COLUMNS = ('std_hz', 'damping_ratio', 'damping_ratio_std') + DIRECTION_COLUMNS
COLUMNS = REQUIRED_COLUMNS + OPTIONAL_COLUMNS


class TableError(ValueError):
    """A modes table that cannot be read; the message is one line naming the row or column."""


@dataclass(frozen=True)
class ModesTable:
    """Measured modes: per row its pose id, pose (7), frequency and the optional columns."""

    pose_id: np.ndarray            # (m,) int
    pose: np.ndarray               # (m, 7): x y z (m), qx qy qz qw
    frequency_hz: np.ndarray       # (m,)
    std_hz: np.ndarray             # (m,) NaN: not known
    damping_ratio: np.ndarray
    damping_ratio_std: np.ndarray
    direction: np.ndarray          # (m, 6) dx dy dz rx ry rz, NaN: not known

    @property
    def poses(self) -> np.ndarray:
        """The distinct pose ids, in the order they first appear."""
        _, first = np.unique(self.pose_id, return_index=True)
        return self.pose_id[np.sort(first)]

    def rows_of(self, pose_id: int) -> np.ndarray:
        """Row indices of one pose."""
        return np.flatnonzero(self.pose_id == pose_id)

    def subset(self, rows) -> 'ModesTable':
        """The table of some rows."""
        rows = np.asarray(rows, dtype=int)
        return ModesTable(*(getattr(self, f)[rows] for f in self.__dataclass_fields__))


def _number(text: str, row: int, column: str) -> float:
    text = text.strip()
    if not text:
        if column in REQUIRED_COLUMNS:
            raise TableError(f'row {row}: {column} is empty')
        return float('nan')
    try:
        value = float(text)
    except ValueError:
        raise TableError(f'row {row}: {column} = {text[:30]!r} is not a number') from None
    if not np.isfinite(value):
        raise TableError(f'row {row}: {column} is not finite')
    return value


def read_modes_table(path: str | os.PathLike) -> ModesTable:
    """The table of a CSV file; :class:`TableError` with one line on any problem."""
    try:
        with open(path, encoding='utf-8') as stream:
            lines = [line for line in stream if line.strip() and not line.lstrip()
                     .startswith('#')]
    except (OSError, UnicodeDecodeError) as exc:
        raise TableError(f'cannot read modes table {path}: {exc}') from None
    if not lines:
        raise TableError(f'modes table {path} has no header')
    reader = csv.DictReader(io.StringIO(''.join(lines)))
    header = [name.strip() for name in reader.fieldnames or []]
    reader.fieldnames = header
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise TableError(f'modes table {path} lacks column {missing[0]} (needs '
                         f'{", ".join(REQUIRED_COLUMNS)})')
    unknown = [c for c in header if c not in COLUMNS]
    if unknown:
        raise TableError(f'modes table {path} has an unknown column {unknown[0]!r}')
    values = {c: [] for c in COLUMNS}
    for row, record in enumerate(reader, start=1):
        if None in record:
            raise TableError(f'row {row}: more cells than columns')
        for column in COLUMNS:
            values[column].append(_number(record.get(column) or '', row, column))
    if not values['pose_id']:
        raise TableError(f'modes table {path} has no rows')
    array = {c: np.asarray(v, dtype=float) for c, v in values.items()}
    pose_id = array['pose_id']
    if np.any(pose_id != np.round(pose_id)):
        raise TableError('pose_id must be an integer')
    if np.any(array['frequency_hz'] <= 0):
        row = int(np.argmax(array['frequency_hz'] <= 0)) + 1
        raise TableError(f'row {row}: frequency_hz must be positive')
    pose = np.stack([array[c] for c in POSE_COLUMNS], axis=1)
    norm = np.linalg.norm(pose[:, 3:], axis=1)
    if np.any(np.abs(norm - 1.0) > 1e-3):
        row = int(np.argmax(np.abs(norm - 1.0))) + 1
        raise TableError(f'row {row}: the quaternion is not a unit quaternion (norm '
                         f'{norm[row - 1]:.4f})')
    table = ModesTable(pose_id.astype(int), pose, array['frequency_hz'], array['std_hz'],
                       array['damping_ratio'], array['damping_ratio_std'],
                       np.stack([array[c] for c in DIRECTION_COLUMNS], axis=1))
    for pid in table.poses:
        rows = table.rows_of(pid)
        if np.ptp(pose[rows], axis=0).max() > 1e-6:
            raise TableError(f'pose_id {pid} has rows at different poses')
    return table


def write_modes_table(path: str | os.PathLike, table: ModesTable, comments=()) -> None:
    """Write ``table`` as CSV with ``comments`` as ``#`` lines first; unknown cells empty."""
    columns = {'pose_id': table.pose_id, 'frequency_hz': table.frequency_hz,
               'std_hz': table.std_hz, 'damping_ratio': table.damping_ratio,
               'damping_ratio_std': table.damping_ratio_std}
    columns.update({c: table.pose[:, i] for i, c in enumerate(POSE_COLUMNS)})
    columns.update({c: table.direction[:, i] for i, c in enumerate(DIRECTION_COLUMNS)})
    with open(path, 'w', encoding='utf-8', newline='') as stream:
        for line in comments:
            stream.write(f'# {line}\n')
        stream.write(','.join(COLUMNS) + '\n')
        for row in range(table.pose_id.size):
            cells = []
            for column in COLUMNS:
                value = columns[column][row]
                cells.append(str(int(value)) if column == 'pose_id' else
                             '' if not np.isfinite(value) else f'{value:.10g}')
            stream.write(','.join(cells) + '\n')
