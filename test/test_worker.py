"""The node's worker process (cdpr_dynamics.worker) and the prediction's quaternion.

The worker's answers are checked against the same functions called in this process; its
failures (a job that raises, a child that is killed) against the messages they must give.
"""
from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdpr_dynamics.analysis import build_system, equilibrium, equilibrium_for, frf_arrays, \
    system_modes
from cdpr_dynamics.config import load_settings
from cdpr_dynamics.live import rotated_quaternion
from cdpr_dynamics.worker import JobFailed, Worker, WorkerError

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
