"""Run ``dynamics_node`` as a child process in an isolated ROS environment.

Used by ``cdpr_demo``, the benchmark and the DDS tests: a ROS domain id of their own (reserved
with a lock file so parallel runs on one machine do not share a domain), localhost-only
discovery, logs in a folder of their own, the venv's ament prefix. ROS-free (no rclpy import).
"""
from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LOCK_DIR = Path(tempfile.gettempdir()) / 'cdpr_dynamics_domains'


class DomainReservation:
    """A ROS domain id held by an exclusive lock on ``LOCK_DIR/<id>.lock`` until released."""

    def __init__(self, domain_id: int, handle):
        self.domain_id = domain_id
        self._handle = handle

    def release(self) -> None:
        if self._handle is not None:
            self._handle.close()   # closing drops the flock
            self._handle = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def reserve_domain_id(low: int = 1, high: int = 140) -> DomainReservation:
    """Lock a free domain id in [low, high], starting from one derived from the pid."""
    LOCK_DIR.mkdir(parents=True, exist_ok=True)
    span = high - low + 1
    start = (os.getpid() * 7919 + time.monotonic_ns() // 1000) % span
    for k in range(span):
        domain = low + (start + k) % span
        handle = open(LOCK_DIR / f'{domain}.lock', 'a+')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        return DomainReservation(domain, handle)
    raise RuntimeError(f'no free ROS domain id in [{low}, {high}]')


def ament_prefix() -> str:
    """AMENT_PREFIX_PATH with this Python's prefix first when it holds an ament index."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    if (Path(sys.prefix) / 'share' / 'ament_index').is_dir() and sys.prefix not in prefixes:
        prefixes.insert(0, sys.prefix)
    return os.pathsep.join(prefixes)


def isolated_env(domain_id: int, log_dir, base: dict | None = None) -> dict:
    """An environment for ROS processes on ``domain_id``, localhost only, logs in ``log_dir``."""
    env = dict(os.environ if base is None else base)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    for name in ('ROS_LOCALHOST_ONLY', 'ROS_STATIC_PEERS'):
        env.pop(name, None)
    Path(log_dir).mkdir(parents=True, exist_ok=True)
    env['ROS_LOG_DIR'] = str(log_dir)
    env['AMENT_PREFIX_PATH'] = ament_prefix()
    env['PYTHONUNBUFFERED'] = '1'
    return env


def apply_env(env: dict) -> None:
    """Make this process use ``env``'s ROS settings (call before ``rclpy.init``)."""
    for name in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_LOG_DIR',
                 'AMENT_PREFIX_PATH'):
        os.environ[name] = env[name]
    for name in ('ROS_LOCALHOST_ONLY', 'ROS_STATIC_PEERS'):
        os.environ.pop(name, None)


def console_script(name: str) -> Path | None:
    """The installed console script ``name`` of this package, or None.

    Looked up as ``ros2 run`` does, in ``<prefix>/lib/cdpr_dynamics`` of the package's ament
    prefix (a colcon workspace, /opt/ros), then beside this Python (a venv's ``bin``), then
    on PATH.
    """
    candidates = []
    try:
        from ament_index_python.packages import get_package_prefix
        candidates.append(Path(get_package_prefix('cdpr_dynamics')) / 'lib' / 'cdpr_dynamics'
                          / name)
    except Exception:  # no ament index for the package: fall through
        pass
    candidates.append(Path(sys.executable).parent / name)
    found = shutil.which(name)
    if found:
        candidates.append(Path(found))
    for path in candidates:
        if path.is_file() and os.access(path, os.X_OK):
            return path
    return None


def node_command() -> list[str]:
    """How to start ``dynamics_node``: its console script (:func:`console_script`), or
    ``python -m cdpr_dynamics.ros.node``."""
    path = console_script('dynamics_node')
    return [str(path)] if path else [sys.executable, '-m', 'cdpr_dynamics.ros.node']


def start_node(params_file, env: dict, parameters: dict | None = None, stdout=None,
               stderr=None, extra_args=()) -> subprocess.Popen:
    """Start ``dynamics_node --ros-args --params-file FILE [-p name:=value ...]``."""
    command = node_command() + ['--ros-args', '--params-file', str(params_file)]
    for name, value in (parameters or {}).items():
        command += ['-p', f'{name}:={value}']
    command += list(extra_args)
    return subprocess.Popen(command, env=env, stdout=stdout, stderr=stderr,
                            start_new_session=True)


def stop_process(proc: subprocess.Popen, timeout_s: float = 10.0) -> int:
    """SIGINT, then SIGTERM, then SIGKILL, each given ``timeout_s``; the exit status."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            break
        try:
            proc.send_signal(sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            continue
    return proc.wait()


def rss_kib(pid: int) -> int:
    """Resident set size (KiB) of a process, from /proc/<pid>/status."""
    with open(f'/proc/{pid}/status', encoding='ascii') as status:
        for line in status:
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    raise RuntimeError(f'no VmRSS for pid {pid}')


def wait_until(condition, timeout_s: float, step=None, interval_s: float = 0.01) -> bool:
    """Call ``step()`` (e.g. spin once) until ``condition()`` holds or the time is up."""
    deadline = time.monotonic() + timeout_s
    while True:
        if condition():
            return True
        if time.monotonic() >= deadline:
            return False
        if step is not None:
            step()
        else:
            time.sleep(interval_s)
