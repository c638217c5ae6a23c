"""Shared fixtures: an isolated ROS environment for subprocesses, a kept-on-failure folder."""
from __future__ import annotations

import itertools
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
TEST_OUTPUT = REPO / 'test_output'
PAPER_CONFIG = REPO / 'config' / 'paper_cdpr.yaml'
_domain_counter = itertools.count()

# A suite started as a background job of a shell without job control (``scripts/test.sh ... &``)
# inherits SIGINT ignored, and so would every child it starts: the Ctrl-C tests would then
# interrupt nothing. Children start as they do from a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def unique_domain_id() -> int:
    """A ROS domain id in 1..232 derived from the pid and a counter (one per call)."""
    return 1 + (os.getpid() * 31 + next(_domain_counter) * 7) % 232


@pytest.fixture
def ros_env(tmp_path) -> dict:
    """Environment for ROS subprocesses of one test.

    A domain id of its own, localhost-only discovery, logs under the test's tmp folder, the
    venv's ament prefix and the repository on PYTHONPATH; RMW_IMPLEMENTATION left as it is.
    """
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(unique_domain_id())
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.pop('ROS_STATIC_PEERS', None)
    log_dir = tmp_path / 'ros_log'
    log_dir.mkdir(exist_ok=True)
    env['ROS_LOG_DIR'] = str(log_dir)
    prefixes = [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    if sys.prefix not in prefixes:   # the venv that holds the ROS wheels
        prefixes.insert(0, sys.prefix)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(prefixes)
    env['PYTHONPATH'] = os.pathsep.join(
        [str(REPO)] + [p for p in env.get('PYTHONPATH', '').split(os.pathsep) if p])
    env['PYTHONUNBUFFERED'] = '1'
    return env


#: fixtures that start ROS processes or DDS participants: a test using one is marked ``ros``
ROS_FIXTURES = ('ros_env', 'procs', 'processes')


def pytest_collection_modifyitems(config, items):
    """Mark ``ros`` every test that uses a fixture of :data:`ROS_FIXTURES` (the stress lane
    runs them; ``scripts/test.sh --quick`` leaves them out)."""
    for item in items:
        if any(name in getattr(item, 'fixturenames', ()) for name in ROS_FIXTURES):
            item.add_marker(pytest.mark.ros)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    setattr(item, f'rep_{report.when}', report)


@pytest.fixture
def ros_context(tmp_path, monkeypatch):
    """An rclpy Context of this test's own, in-process: a reserved domain id, localhost
    discovery, logs under tmp_path, no signal handlers; shut down after the test."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from cdpr_dynamics.ros.process import isolated_env, reserve_domain_id

    with reserve_domain_id(1, 140) as domain:
        for name, value in isolated_env(domain.domain_id, tmp_path / 'log').items():
            if name.startswith(('ROS_', 'AMENT_')):
                monkeypatch.setenv(name, value)
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        try:
            yield context
        finally:
            rclpy.try_shutdown(context=context)


@pytest.fixture
def output_dir(request) -> Path:
    """test_output/<module>/<test>/: for recordings and logs of a test; removed if it passes."""
    module = Path(str(request.node.fspath)).stem
    name = ''.join(c if c.isalnum() or c in '-_.' else '_' for c in request.node.name)
    path = TEST_OUTPUT / module / name
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    yield path
    failed = any(getattr(getattr(request.node, f'rep_{when}', None), 'failed', False)
                 for when in ('setup', 'call'))
    if not failed and not os.environ.get('CDPR_KEEP_TEST_OUTPUT'):
        shutil.rmtree(path, ignore_errors=True)
        for folder in (path.parent, TEST_OUTPUT):   # only if nothing else is kept there
            try:
                folder.rmdir()
            except OSError:
                break


# ----------------------------------------------------------------------------- helpers


def write_config(tmp_path, base: Path = PAPER_CONFIG, **changes) -> Path:
    """``base`` (the paper config) with ``section.name=value`` changes (value None: left
    out), written under ``tmp_path`` keyed ``/**`` as the shipped files are."""
    doc = yaml.safe_load(Path(base).read_text())
    params = doc['/**']['ros__parameters']
    for dotted, value in changes.items():
        section, name = dotted.split('.')
        if value is None:
            params.get(section, {}).pop(name, None)
        else:
            params.setdefault(section, {})[name] = value
    path = tmp_path / 'robot.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def installed(name: str) -> str:
    """Path of this package's installed console script ``name``, however it is installed: in
    ``<prefix>/lib/cdpr_dynamics`` of its ament prefix (colcon workspace, /opt/ros, as
    ``ros2 run`` finds it), beside this Python (a venv) or on PATH."""
    from cdpr_dynamics.ros.process import console_script
    path = console_script(name)
    if path is None:
        raise FileNotFoundError(f'console script {name} not found: is cdpr_dynamics installed '
                                '(scripts/setup.sh, or colcon build + install/setup.bash)?')
    return str(path)


def analyze(*args, env=None) -> subprocess.CompletedProcess:
    """Run the installed ``cdpr_analyze`` (one BLAS thread) with ``args``."""
    return subprocess.run([installed('cdpr_analyze'), *map(str, args)], capture_output=True,
                          text=True, timeout=300,
                          env={**(env or os.environ), 'OMP_NUM_THREADS': '1'})


def wait_until(condition, timeout: float, what: str, period: float = 0.05):
    """Poll ``condition`` until it returns something true (returned) or ``timeout`` s pass."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout} s waiting for {what}')
        time.sleep(period)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (s), from /proc/<pid>/stat."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
