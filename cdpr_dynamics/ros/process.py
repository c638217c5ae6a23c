"""The node's process: ``dynamics_node``'s ``main`` (command line, the two threads, signals and
the stop watchdog), and how tools and tests start it as a child in an isolated ROS environment.

The node runs in two threads: the main thread takes pose and wrench alone
(:class:`~cdpr_dynamics.ros.rclpy_compat.InputLoop`), a services thread runs an executor for
parameters, ``frequency_response``, the worker's answers and the diagnostics timer. SIGINT and
SIGTERM end the process with status 0 within ``STOP_DEADLINE_S`` (:class:`Stopper`); a bad
configuration exits 1 with one line (within ``FAILURE_DEADLINE_S`` once it runs: time to leave
the ROS graph cleanly).

Children (``cdpr_demo``, the benchmark, the DDS tests) get a ROS domain id of their own
(reserved with a lock file so parallel runs on one machine do not share a domain),
localhost-only discovery, logs in a folder of their own, the venv's ament prefix.

Importing this module does not import rclpy (tools that start a node need not pay for it).
"""
from __future__ import annotations

import _thread
import fcntl
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

LOCK_DIR = Path(tempfile.gettempdir()) / 'cdpr_dynamics_domains'
STOP_DEADLINE_S = 0.8     # after SIGINT/SIGTERM the process ends within this, cleanly or not
FAILURE_DEADLINE_S = 5.0  # ... after an error of its own (nobody waits on it): time to leave
#                           the graph cleanly, as peers otherwise list it until its DDS lease
#                           runs out (20 s)
SWITCH_INTERVAL_S = 0.0005   # the GIL changes hands at least this often (Python's default,
#                              5 ms, would let the services thread hold a wrench that long)


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
    ``python -m cdpr_dynamics.ros.process``."""
    path = console_script('dynamics_node')
    return [str(path)] if path else [sys.executable, '-m', 'cdpr_dynamics.ros.process']


_STARTED: list = []      # children started by start_child, for stop_started


def start_child(command, **popen_kwargs) -> subprocess.Popen:
    """``subprocess.Popen(command, start_new_session=True, **popen_kwargs)``, kept for
    :func:`stop_started`. A child in a session of its own does not get a terminal's Ctrl-C:
    its parent must stop it. A SIGINT during the start (in the main thread) is held back until
    the child is recorded, so it cannot leave it running unrecorded; then it is handled as it
    would have been. It is held back by a handler, not by blocking the signal: a blocked
    signal mask is inherited across exec, and a child started with SIGINT blocked would ignore
    :func:`stop_process`'s SIGINT (it then waits for its SIGTERM)."""
    held = []
    previous = None     # None: not held back (another thread, or a handler not set from Python)
    if (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is not None):
        previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(frame))
    try:
        proc = subprocess.Popen(command, start_new_session=True, **popen_kwargs)
        _STARTED[:] = [p for p in _STARTED if p.poll() is None] + [proc]
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
            if held:
                _deliver_sigint(previous, held[0])
    return proc


def _deliver_sigint(handler, frame) -> None:
    """Handle a SIGINT held back by :func:`start_child` as ``handler`` (what
    :func:`signal.signal` returned) would have."""
    if callable(handler):
        handler(signal.SIGINT, frame)
    elif handler == signal.SIG_DFL:
        os.kill(os.getpid(), signal.SIGINT)
    # SIG_IGN: nothing to do


def stop_started(timeout_s: float = 10.0) -> None:
    """Stop every child of :func:`start_child` still running (:func:`stop_process`)."""
    while _STARTED:
        stop_process(_STARTED.pop(), timeout_s)


def start_node(params_file, env: dict, parameters: dict | None = None, stdout=None,
               stderr=None, extra_args=()) -> subprocess.Popen:
    """Start ``dynamics_node --ros-args --params-file FILE [-p name:=value ...]`` in a session
    of its own (:func:`start_child`)."""
    command = node_command() + ['--ros-args', '--params-file', str(params_file)]
    for name, value in (parameters or {}).items():
        command += ['-p', f'{name}:={value}']
    command += list(extra_args)
    return start_child(command, env=env, stdout=stdout, stderr=stderr)


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


# ------------------------------------------------------------- the node's own process

USAGE = """\
usage: dynamics_node [-h] --ros-args --params-file ROBOT.yaml [-p NAME:=VALUE ...]
                     [-r pose:=TOPIC] [-r wrench:=TOPIC] [-r __ns:=/NAMESPACE]

Live vibration prediction of a cable-driven parallel robot: ROS 2 node 'cdpr_dynamics'
(subscribes pose and wrench; publishes predicted_displacement, cable_tensions and
/diagnostics; serves frequency_response).

  ros2 run cdpr_dynamics dynamics_node --ros-args --params-file {config}

The params file describes the robot (anchors, mass, cables, tension limits: no defaults) and
may set the numerical settings (model, damping, frf, newmark, node: documented defaults). Key
its section '/**:' (any namespace) or 'cdpr_dynamics:'. A name not in the parameter table is
an error. The table (names, units, defaults, ranges) is in doc/configuration.md (the docs
site's Configuration page) and in cdpr_dynamics/analysis/config.py (PARAMETERS); on a running
node: ros2 param describe /cdpr_dynamics NAME. Ctrl-C or SIGTERM stops it; a bad
configuration exits 1 with one line.
"""


def main(args=None):
    """Run the node until Ctrl-C or SIGTERM; a bad configuration exits 1 with one line.

    The signal handlers come first, before the heavy imports: a signal at any moment after the
    start ends the process with status 0."""
    stopper = Stopper()
    try:
        status = _run(stopper, sys.argv if args is None else args)
    except Stopped:
        status = 0
    if stopper.signalled:
        # stopped by a signal: nothing is left to do, and the interpreter's own finalisation
        # (seconds under load, with the default signal dispositions back) is skipped
        stopper.exit(status)
    return status


def _run(stopper, argv) -> int:
    from cdpr_dynamics.analysis.config import ConfigError, default_config_path
    from cdpr_dynamics.ros.parameters import check_command_line, io_arguments
    from msg_adapters.inputs import first_line
    try:
        help_asked, args = check_command_line(argv)
        if help_asked:
            try:
                config = default_config_path()
            except ConfigError:
                config = 'config/paper_cdpr.yaml'
            print(USAGE.format(config=config), end='')
            return 0
    except ConfigError as exc:
        print(f'dynamics_node: error: {first_line(exc)}', file=sys.stderr)
        return 1
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from cdpr_dynamics.ros.node import DynamicsNode
    from cdpr_dynamics.ros.rclpy_compat import InputLoop
    try:   # rclpy's own signal handlers would shut the context down under a running callback
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # e.g. a parameter file rcl cannot parse
        print(f'dynamics_node: error: {first_line(exc)}', file=sys.stderr)
        return 1
    node = None
    status = 0
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    services = SingleThreadedExecutor()
    failed: list[BaseException] = []
    thread = None
    try:
        node = DynamicsNode(io_arguments=io_arguments(args))
        services.add_node(node)
        thread = threading.Thread(target=_serve, args=(services, failed, stopper),
                                  name='cdpr_services', daemon=True)
        thread.start()
        try:                                  # the pose and wrench path, alone
            lean = InputLoop(node.context, (node.pose_sub, node.wrench_sub),
                             stop=lambda: stopper.signalled)
        except AttributeError:                # an rclpy without the wait set API
            lean = SingleThreadedExecutor()
            lean.add_node(node.io)
        lean.spin()
    except (Stopped, KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # noqa: BLE001 - one line, status 1 (a signal that lands inside
        failed.append(exc)    # a pybind11 call comes out as its RuntimeError: a stop, below)
    finally:
        if failed and (stopper.failed or not stopper.signalled):
            print(f'dynamics_node: error: {first_line(failed[0])}', file=sys.stderr)
            status = 1
        stopper.stopping(status, FAILURE_DEADLINE_S if status else STOP_DEADLINE_S)
        try:
            services.shutdown(timeout_sec=0.2)
            if thread is not None:
                thread.join(0.2)
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
        except Exception:  # noqa: BLE001 - stopping anyway; a half-torn callback may object
            pass
        stopper.done()
    return status


def _serve(executor, failed: list, stopper) -> None:
    """The services thread: parameters, frequency_response, the worker's answers, the
    diagnostics timer. A callback that raises ends the node as one in the main thread would
    (``failed`` keeps the error for :func:`main`)."""
    from rclpy.executors import ExternalShutdownException
    try:
        executor.spin()
    except ExternalShutdownException:
        pass
    except Exception as exc:  # noqa: BLE001 - reported by main with one line, status 1
        failed.append(exc)
        stopper.failed = True      # the main thread's Stopped comes from this, not a signal
        _thread.interrupt_main()


class Stopped(BaseException):
    """Raised in the main thread by the first SIGINT or SIGTERM: it unwinds whatever runs (a
    burst of wrenches, a long frequency_response call) straight to :func:`main`. A
    BaseException, so the callbacks' ``except Exception`` guards let it through."""


class Stopper:
    """Clean shutdown on SIGINT and SIGTERM, at any moment, within ``STOP_DEADLINE_S``.

    The first signal raises :class:`Stopped` in the main thread (Python runs signal handlers
    there, between bytecodes); later ones are ignored (``ros2 launch`` sends two SIGINTs
    close together). A watchdog thread, woken by :func:`signal.set_wakeup_fd` the moment a
    signal arrives (even while the main thread is inside a long C call), ends the process
    with status 0 if the orderly shutdown has not finished by the deadline.
    """

    def __init__(self):
        self._signal = None
        self._finished = threading.Event()
        self._read, self._write = socket.socketpair()
        self._write.setblocking(False)
        signal.set_wakeup_fd(self._write.fileno(), warn_on_full_buffer=False)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        threading.Thread(target=self._watchdog, name='stop_watchdog', daemon=True).start()

    def _on_signal(self, signum, frame):
        if self._signal is None:
            self._signal = signum
            raise Stopped(signum)

    @property
    def signalled(self) -> bool:
        return bool(self._signal)

    def stopping(self, status: int = 0, deadline_s: float = STOP_DEADLINE_S) -> None:
        """The shutdown is under way: every later signal is ignored, and the watchdog ends the
        process with ``status`` if the shutdown takes longer than ``deadline_s``."""
        self._status = status
        self._deadline_s = deadline_s
        if self._signal is None:
            self._signal = 0
        try:
            self._write.send(b'\0')       # arm the watchdog (a signal has armed it already)
        except OSError:
            pass

    def done(self) -> None:
        self._finished.set()

    def exit(self, status: int) -> None:
        """End the process now with ``status`` (streams flushed)."""
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001
                pass
        os._exit(status)

    _status = 0
    _deadline_s = STOP_DEADLINE_S
    failed = False      # stopping because the services thread failed (status 1)

    def _watchdog(self):
        try:
            self._read.recv(1)
        except OSError:
            return
        if not self._finished.wait(self._deadline_s):
            self.exit(self._status)


if __name__ == '__main__':
    sys.exit(main())
