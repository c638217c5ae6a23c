"""std_msgs/Float64MultiArray <-> tables (rows x labelled columns) of the controller topics.

``vibration_modes``: a (k, c) table, layout dims ``[mode;pose_stamp_ns=S, k, k c]`` and
``[<comma-separated column labels>, c, c]``: S is the stamp (ns) of the pose whose model the
modes belong to (0: the initial pose). ``input_shaper``: one dim ``[t0,a0,t1,a1,..., 2 m, 2 m]``
of the m impulses. ``notch_filter``: a (m', 6) table of b0 b1 b2 a0 a1 a2 per notch, labelled
like ``vibration_modes`` (with ``sample_rate_hz=F`` after the stamp).
"""
from __future__ import annotations

import numpy as np
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

STAMP_KEY = 'pose_stamp_ns'


def table_message(rows, labels, stamp_ns: int = 0, row_label: str = 'mode',
                  **keys) -> Float64MultiArray:
    """A row-major table with its column ``labels`` and the pose stamp (ns) in the layout."""
    rows = np.asarray(rows, dtype=float).reshape(-1, len(labels))
    head = ';'.join([row_label, f'{STAMP_KEY}={int(stamp_ns)}']
                    + [f'{k}={v!r}' for k, v in keys.items()])
    msg = Float64MultiArray()
    k, c = rows.shape
    msg.layout.dim = [MultiArrayDimension(label=head, size=k, stride=k * c),
                      MultiArrayDimension(label=','.join(labels), size=c, stride=c)]
    msg.data = rows.ravel().tolist()
    return msg


def read_table(msg: Float64MultiArray) -> tuple[np.ndarray, tuple[str, ...], dict]:
    """(rows (k, c), column labels, the head's keys: ``pose_stamp_ns`` as int, others as
    float) of a :func:`table_message`."""
    head, columns = msg.layout.dim[0], msg.layout.dim[1]
    labels = tuple(columns.label.split(','))
    keys = {}
    for item in head.label.split(';')[1:]:
        key, value = item.split('=', 1)
        keys[key] = int(value) if key == STAMP_KEY else float(value)
    rows = np.asarray(msg.data, dtype=float).reshape(head.size, columns.size)
    return rows, labels, keys


def shaper_message(pairs, stamp_ns: int = 0) -> Float64MultiArray:
    """The impulses t0, a0, t1, a1, ... (s, 1) as one labelled dimension."""
    pairs = np.asarray(pairs, dtype=float).ravel()
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=f't0,a0,t1,a1,...;{STAMP_KEY}={int(stamp_ns)}',
                                          size=pairs.size, stride=pairs.size)]
    msg.data = pairs.tolist()
    return msg


def read_shaper(msg: Float64MultiArray) -> tuple[np.ndarray, np.ndarray]:
    """(times s, amplitudes) of an ``input_shaper`` message."""
    data = np.asarray(msg.data, dtype=float)
    return data[0::2], data[1::2]
