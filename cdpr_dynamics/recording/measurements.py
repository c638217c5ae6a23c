"""Measured samples of a recording: a pose or IMU topic as arrays for ``cdpr_calibrate``."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.recording.base import RecordingError
from cdpr_dynamics.recording.reader import read_messages, recording_info
from msg_adapters.samples import IMU_TYPE, POSE_TYPE, imu_row, pose_row, stamp_ns

DEFAULT_TOPIC = '/measured_pose'


@dataclass(frozen=True)
class Samples:
    """A topic's samples: kind ('pose' or 'imu'), times t_s (n,) from the first stamp
    ``origin_ns`` (header stamps; arrival where unstamped), rows (n, 7 or 6), and for an IMU
    the poses of a pose topic interpolated at its times (or None)."""

    topic: str
    kind: str
    t_s: np.ndarray
    rows: np.ndarray
    poses: np.ndarray | None = None
    origin_ns: int = 0


def _series(path, topic: str, type_name: str):
    times, rows = [], []
    convert = pose_row if type_name == POSE_TYPE else imu_row
    for record in read_messages(path, {topic: type_name}):
        stamp = stamp_ns(record.message)
        times.append(stamp if stamp > 0 else record.log_time_ns)
        rows.append(convert(record.message))
    return np.array(times, dtype=np.int64), np.array(rows).reshape(len(rows), -1)


def read_samples(path, topic: str | None = None) -> Samples:
    """The samples of ``topic`` (default: ``/measured_pose``, else the only pose topic, else
    the only IMU topic);
    :class:`RecordingError` with one line when there is none or it has another type."""
    info = recording_info(path)
    types = {name: t.type for name, t in info.topics.items()}
    usable = {name: kind for name, kind in types.items() if kind in (POSE_TYPE, IMU_TYPE)}
    if topic is None and DEFAULT_TOPIC in usable:
        topic = DEFAULT_TOPIC
    if topic is None:
        poses = [n for n, k in usable.items() if k == POSE_TYPE]
        imus = [n for n, k in usable.items() if k == IMU_TYPE]
        choice = poses if len(poses) == 1 else imus if not poses and len(imus) == 1 else None
        if choice is None:
            raise RecordingError(f'{path}: give --topic, one of the pose or IMU topics '
                                 f'{sorted(usable) or "(none in the file)"}')
        topic = choice[0]
    name = topic if topic.startswith('/') else '/' + topic
    if name not in types:
        raise RecordingError(f'{path}: no topic {name}; pose and IMU topics: '
                             f'{sorted(usable) or "none"}')
    if types[name] not in (POSE_TYPE, IMU_TYPE):
        raise RecordingError(f'{path}: topic {name} is {types[name]}, not {POSE_TYPE} or '
                             f'{IMU_TYPE}')
    t_ns, rows = _series(path, name, types[name])
    origin = int(t_ns.min()) if t_ns.size else 0
    t = (t_ns - origin) * 1e-9
    if types[name] == POSE_TYPE:
        return Samples(name, 'pose', t, rows, origin_ns=origin)
    pose_topics = [n for n, k in usable.items() if k == POSE_TYPE]
    poses = None
    if pose_topics:
        pt_ns, prow = _series(path, pose_topics[0], POSE_TYPE)
        pt = (pt_ns - origin) * 1e-9
        if pt.size:
            order = np.argsort(pt)
            poses = np.stack([np.interp(t, pt[order], c) for c in prow[order].T], axis=1)
    return Samples(name, 'imu', t, rows, poses, origin)
