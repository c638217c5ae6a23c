"""The node's worker process (cdpr_dynamics.ros.worker) and the prediction's quaternion.

The worker's answers are checked against the same functions called in this process; its
failures (a job that raises, a child that is killed) against the messages they must give.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdpr_dynamics.analysis.pipeline import (build_system, equilibrium, equilibrium_for,
                                             frf_arrays, system_modes)
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.live import LivePredictor, rotated_quaternion
from cdpr_dynamics.ros.worker import (NICE, BackgroundStatics, JobFailed, StaticsRequest, Worker,
                                      WorkerError)

pytestmark = pytest.mark.ros   # nodes, DDS, worker processes, signals

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 120.0


@pytest.fixture(scope='module')
def worker():
    w = Worker()
    yield w
    w.close()


def test_frf_job_equals_the_library(worker):
    settings = load_settings(REPO / 'config' / 'heavy_sag_6dof.yaml').replace(n_points=60)
    eq = equilibrium_for(settings, equilibrium(settings), 'fem_sag')
    got = worker.submit('frf', settings, eq, 'fem_sag', 8).result(TIMEOUT_S)
    expected = frf_arrays(settings, build_system(settings, eq, 'fem_sag', 8))
    assert set(got) == set(expected)
    for name, value in expected.items():
        if isinstance(value, str):
            assert got[name] == value
        else:
            np.testing.assert_array_equal(got[name], value, err_msg=name)


def test_modes_job_equals_the_library(worker):
    settings = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
    eq = equilibrium(settings)
    got = worker.submit('modes', settings, eq, 'fem', 4, 1000).result(TIMEOUT_S)
    found = system_modes(settings, build_system(settings, eq, 'fem', 4))
    np.testing.assert_allclose(got['frequency_hz'], found.frequency_hz, rtol=1e-12)
    np.testing.assert_allclose(got['platform_hz'], found.platform_hz, rtol=1e-12)
    assert isinstance(got['step_warnings'], list)


def test_a_failing_job_gives_its_reason_and_the_worker_carries_on(worker):
    settings = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
    eq = equilibrium(settings)
    with pytest.raises(JobFailed, match='fem needs at least one element per cable'):
        worker.submit('frf', settings, eq, 'fem', -1).result(TIMEOUT_S)
    with pytest.raises(JobFailed, match='KeyError'):
        worker.submit('no_such_job').result(TIMEOUT_S)
    assert worker.submit('frf', settings.replace(n_points=5), eq, 'spring', 1).result(
        TIMEOUT_S)['frequency_hz'].size == 5


def test_the_worker_runs_below_the_node(worker):
    """The child yields the cores to its parent's wrench path: every thread of it (numpy's BLAS
    threads too) runs under SCHED_IDLE, and the node's threads do not."""
    with pytest.raises(JobFailed):          # any answer: the child is up and serving
        worker.submit('no_such_job').result(TIMEOUT_S)
    threads = [int(tid) for tid in os.listdir(f'/proc/{worker._process.pid}/task')]
    assert [os.sched_getscheduler(tid) for tid in threads] == [os.SCHED_IDLE] * len(threads)
    assert os.sched_getscheduler(0) != os.SCHED_IDLE


def test_without_sched_idle_the_worker_runs_niced():
    """Where SCHED_IDLE is refused, each thread of the child gets nice NICE above its own."""
    code = ('import os, threading\n'
            'def refuse(*args):\n'
            '    raise PermissionError("not permitted")\n'
            'os.sched_setscheduler = refuse\n'
            'gate = threading.Event()\n'
            'other = threading.Thread(target=gate.wait)\n'
            'other.start()\n'
            'from cdpr_dynamics.ros.worker import _yield_to_parent\n'
            'before = os.getpriority(os.PRIO_PROCESS, other.native_id)\n'
            '_yield_to_parent()\n'
            'print(before, os.getpriority(os.PRIO_PROCESS, 0),\n'
            '      os.getpriority(os.PRIO_PROCESS, other.native_id), os.sched_getscheduler(0))\n'
            'gate.set()\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=TIMEOUT_S, env={**os.environ, 'PYTHONPATH': str(REPO)})
    assert out.returncode == 0, out.stderr
    before, main_nice, other_nice, policy = map(int, out.stdout.split())
    assert main_nice == other_nice == min(19, before + NICE)
    assert policy == os.SCHED_OTHER


def test_a_killed_worker_fails_its_job_and_is_started_again():
    settings = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
    eq = equilibrium(settings)
    worker = Worker()
    try:
        worker.submit('frf', settings.replace(n_points=5), eq, 'spring', 1).result(TIMEOUT_S)
        first = worker._process.pid
        big = worker.submit('frf', settings.replace(n_points=200000), eq, 'fem', 64)
        os.kill(first, signal.SIGKILL)
        with pytest.raises(WorkerError, match='ended before it answered'):
            big.result(TIMEOUT_S)
        again = worker.submit('frf', settings.replace(n_points=5), eq, 'spring', 1)
        assert again.result(TIMEOUT_S)['frequency_hz'].size == 5
        assert worker._process.pid != first
    finally:
        worker.close()
    assert not worker._process.is_alive()
    with pytest.raises(WorkerError, match='closed'):
        worker.submit('frf').result(TIMEOUT_S)


def test_statics_in_the_worker_give_the_inline_update(worker):
    """node.rebuild: worker: the heavy-sag 6-DOF robot's poses solved in the child (its own
    predictor, warm-started pose to pose) and applied here give the state of an inline
    update_pose along the same poses: tensions, sag-consistent end forces, the model's
    matrices, the wrenches the cables can hold. A new settings token starts a new predictor
    in the child."""
    settings = load_settings(REPO / 'config' / 'heavy_sag_6dof.yaml').replace(
        method='fem_sag', elements_per_cable=4)
    inline, swapped = LivePredictor(settings), LivePredictor(settings)
    rotation = Rotation.from_euler('z', 0.02).as_matrix()
    for token, step_m in ((1, 0.01), (1, 0.02), (2, 0.03)):
        position = settings.initial_position_m + [step_m, -step_m, 0.5 * step_m]
        statics = worker.submit('statics', token, settings, position, rotation).result(TIMEOUT_S)
        update = swapped.apply(statics)
        expected = inline.update_pose(position, rotation=rotation)
        assert update.rebuilt and update.method == expected.method == 'fem_sag'
        assert update.warnings == expected.warnings
        np.testing.assert_allclose(swapped.eq.tensions.tension_n,
                                   inline.eq.tensions.tension_n, rtol=1e-9)
        np.testing.assert_allclose(swapped.eq.end_force_n, inline.eq.end_force_n, rtol=1e-9,
                                   atol=1e-9)
        k_swapped, _ = swapped.system.matrices(dense=True)
        k_inline, _ = inline.system.matrices(dense=True)
        np.testing.assert_allclose(k_swapped, k_inline, rtol=1e-8, atol=1e-6)
        for force_n in ([0.0, 0.0, 50.0], [30.0, -20.0, -100.0], [0.0, 0.0, -1e4]):
            assert swapped.wrench_reason(force_n) == inline.wrench_reason(force_n)
            assert swapped.wrench_set.margin(force_n) == pytest.approx(
                inline.wrench_set.margin(force_n), rel=1e-9, abs=1e-9)
    assert inline.wrench_reason([0.0, 0.0, -1e4])     # the last one is out of reach


def test_a_refused_pose_fails_its_statics_job(worker):
    settings = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
    future = worker.submit('statics', 7, settings, np.array([0.0, 0.0, 3.0]), np.eye(3))
    with pytest.raises(JobFailed, match='infeasible tension distribution'):
        future.result(TIMEOUT_S)


def test_background_statics_keep_only_the_latest_pose():
    """While one pose is solved, newer ones replace the waiting one (counted); the waiting
    pose goes next as ``choose`` returns it, or is dropped."""
    settings = load_settings(REPO / 'config' / 'paper_cdpr.yaml').replace(method='fem_sag')
    woken = threading.Semaphore(0)       # released by each answer's wake-up
    background = BackgroundStatics(lambda _future: woken.release())
    try:
        poses = [settings.initial_position_m + [0.01 * k, 0.0, 0.0] for k in range(4)]
        for k, position in enumerate(poses):
            background.request(StaticsRequest(position, np.eye(3), settings, 1, stamp=k))
        assert background.busy and background.superseded == 2
        assert background.pending.stamp == 3
        first = _taken(background, woken)
        assert first[0].stamp == 0
        np.testing.assert_allclose(first[1].position_m, poses[0])
        background.submit_pending(lambda request: request)       # pose 3 next
        last = _taken(background, woken)
        assert last[0].stamp == 3
        background.request(StaticsRequest(poses[1], np.eye(3), settings, 1, stamp=4))
        background.request(StaticsRequest(poses[2], np.eye(3), settings, 1, stamp=5))
        _taken(background, woken)
        background.submit_pending(lambda request: None)          # already there: dropped
        assert not background.busy and background.pending is None
    finally:
        background.close()


def _taken(background, woken):
    """Wait for the background statics' wake-up, then take the answer."""
    assert woken.acquire(timeout=TIMEOUT_S)
    taken = background.take()
    assert taken is not None and not isinstance(taken[1], Exception), taken
    return taken


def test_quaternions_agree_with_scipy():
    """live.rotated_quaternion (scalar arithmetic, per prediction) against scipy's Rotation,
    sign included, on random rotations, the identity, half turns and tiny or large theta."""
    rng = np.random.default_rng(7)
    rotations = list(Rotation.random(200, random_state=3).as_matrix())
    rotations += [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
                  np.diag([-1.0, -1.0, 1.0])]
    for k, rotation in enumerate(rotations):
        theta = rng.normal(size=3) * 10.0 ** rng.uniform(-12, 0.5) if k % 4 else np.zeros(3)
        expected = Rotation.from_matrix(rotation)
        if np.any(theta):
            expected = Rotation.from_rotvec(theta) * expected
        np.testing.assert_allclose(rotated_quaternion(rotation, theta), expected.as_quat(),
                                   atol=2e-15, rtol=0)


def test_cancel_kills_the_running_job_and_drops_a_queued_one_then_serves_the_next(worker):
    """A running job cancelled ends with JobCancelled and its reason (its child killed); a
    queued one is dropped without running; the next job is served by a new child."""
    from cdpr_dynamics.ros.worker import JobCancelled
    settings = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
    eq = equilibrium(settings)
    long = settings.replace(n_points=20000)         # fem_sag 400: seconds of work
    running = worker.submit('frf', long, eq, 'fem_sag', 400)
    queued = worker.submit('frf', long, eq, 'fem_sag', 400)
    deadline = time.monotonic() + TIMEOUT_S
    while worker.running_s(running) == 0.0:
        assert time.monotonic() < deadline, 'the first job never started'
        time.sleep(0.01)
    assert worker.running_s(queued) == 0.0
    assert worker.cancel(queued, 'superseded')
    assert worker.cancel(running, 'over its time budget of 1 s')
    with pytest.raises(JobCancelled, match='over its time budget of 1 s'):
        running.result(TIMEOUT_S)
    assert queued.cancelled()
    got = worker.submit('modes', settings, eq, 'fem', 4, 1000).result(TIMEOUT_S)
    found = system_modes(settings, build_system(settings, eq, 'fem', 4))
    np.testing.assert_allclose(got['frequency_hz'], found.frequency_hz, rtol=1e-12)
    assert not worker.cancel(running, 'again')        # done: nothing to cancel
