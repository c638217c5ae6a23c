"""A worker process for the node's slow analyses, so they never hold the executor that
serves pose and wrench (no rclpy: the child never joins the ROS graph).

The live node answers ``frequency_response`` calls and refreshes its classified modes after
rebuilds; either can take from milliseconds (fem 16) to seconds (a 20000-point fem_sag 64
sweep). With ``node.rebuild: worker`` a second worker computes the statics of each new pose
(:class:`BackgroundStatics`: the sag-consistent equilibrium costs milliseconds per pose). A
thread would hold the GIL for most of that time (the analyses are partly Python), so they run
in a child process (``spawn``: nothing of the parent's DDS threads is inherited),
started with the worker (in the background) and kept. Jobs are pickled plain data
(:class:`Settings`, :class:`Equilibrium`, the model's method and size), run one at a time in
submission order, and their results come back as :class:`concurrent.futures.Future` s
resolved by a pump thread of the parent (which blocks in ``recv`` and so holds no GIL while
the child works).

A child that dies (killed, out of memory) fails the jobs it had with :class:`WorkerError` and
is started again for the next one. :meth:`Worker.cancel` drops a queued job or kills the child
of the running one (:class:`JobCancelled`): the node cancels a modes job that a newer model
supersedes and any job over its time budget, so no call waits behind a stale job. The child
ignores SIGINT (a terminal's Ctrl-C goes to the whole process group: the parent decides) and
ends with its parent (PR_SET_PDEATHSIG on Linux, else at the end of its pipe).
"""
from __future__ import annotations

import concurrent.futures
import ctypes
import multiprocessing
import os
import queue
import signal
import threading
import time
import dataclasses

JOIN_S = 0.5        # how long :meth:`Worker.close` waits for the child before killing it
NICE = 10           # where SCHED_IDLE is not had: the child's nice above its parent's


class WorkerError(RuntimeError):
    """The worker process ended before it answered."""


def frf_job(settings, eq, method: str, elements: int):
    """(arrays, error) of a frequency_response call: :func:`analysis.frf_arrays` of ``method``
    with ``elements`` per cable at the state ``eq``; error '' or the reason (one line)."""
    from cdpr_dynamics.analysis.pipeline import AnalysisError, build_system, frf_arrays
    system = build_system(settings, eq, method, elements)
    if not system.assembly.valid:
        raise AnalysisError(f'method {system.assembly.method} is not valid for this state: '
                            + '; '.join(system.assembly.warnings))
    return frf_arrays(settings, system)


def modes_job(settings, eq, method: str, elements: int, max_steps: int,
              controller: dict | None = None) -> dict:
    """What the node reports of its model's modes: every natural frequency up to
    ``frf.f_max_hz`` (at least 12), the platform ones, the time-step warnings, and the
    seconds it took (the node spaces its refreshes by it). ``controller`` (``point_m``,
    ``shaper``, ``shaper_modes``, ``sample_rate_hz``) adds the ``vibration_modes`` table
    (``mode_table``) and, unless the shaper is ``none``, the
    shaper's impulses (``shaper_pairs``), the ``notches`` and why modes were ``skipped``
    (:mod:`cdpr_dynamics.analysis.controller`)."""
    from cdpr_dynamics.analysis.pipeline import build_system, damping_for, system_modes
    from cdpr_dynamics.analysis.live import time_step_warnings
    start = time.perf_counter()
    system = build_system(settings, eq, method, elements)
    found = system_modes(settings, system)
    positive = found.frequency_hz[found.frequency_hz > 0]
    lowest = float(positive[0]) if positive.size else float('nan')
    out = {'frequency_hz': found.frequency_hz, 'platform_hz': found.platform_hz,
           'step_warnings': time_step_warnings(settings, system, lowest, max_steps)}
    if controller is not None:
        from cdpr_dynamics.analysis.controller import controller_shaping, mode_table
        damping = damping_for(settings, system)
        out['mode_table'] = mode_table(system, found, damping, settings.f_max_hz,
                                       controller['point_m'])
        out['platform_dofs'] = system.platform_dofs
        if controller['shaper'] != 'none':
            shaping = controller_shaping(found, damping, controller['shaper'],
                                         controller['shaper_modes'],
                                         controller['sample_rate_hz'])
            out['shaper_pairs'] = (() if shaping.shaper is None
                                   else shaping.shaper.pairs())
            out['notches'] = shaping.notches
            out['skipped'] = shaping.skipped
    out['seconds'] = time.perf_counter() - start
    return out


_STATICS = {}    # in the child: (settings token, LivePredictor) of the statics job


def statics_job(token, settings, position_m, rotation):
    """:meth:`LivePredictor.statics` of the pose on a predictor kept in the child per settings
    ``token`` (a new token: a new predictor), whose warm starts follow the poses it is given."""
    from cdpr_dynamics.analysis.live import LivePredictor
    if _STATICS.get('token') != token:
        _STATICS.clear()
        _STATICS.update(token=token, predictor=LivePredictor(settings))
    predictor = _STATICS['predictor']
    statics = predictor.statics(position_m, rotation)
    # the next pose starts from here
    predictor.eq = statics.eq if statics.model_eq is None else statics.model_eq
    # the SQP's warm QP stays here: the parent has no use for it, and it would triple the
    # time the answer takes to pickle and unpickle (3.6 of 4.2 ms for heavy_sag_6dof)
    sag = None if statics.model_eq is None else statics.model_eq.sag
    if sag is not None and sag.step_qp is not None:
        model_eq = dataclasses.replace(statics.model_eq,
                                       sag=dataclasses.replace(sag, step_qp=None))
        statics = dataclasses.replace(statics, model_eq=model_eq)
    return statics


JOBS = {'frf': frf_job, 'modes': modes_job, 'statics': statics_job}


def _die_with_parent() -> None:
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):      # not Linux: the closed pipe ends the loop instead
        pass


def _yield_to_parent() -> None:
    """Run every thread of the child under ``SCHED_IDLE`` (Linux): it gets a core only where
    no normal task wants it, and a waking one (the node's wrench path) preempts it at once. A
    nice value only shares the cores by weight, so a waking wrench waited behind the analysis
    on a 2-core machine. Each thread is set: numpy's BLAS threads start when the child imports
    it, before this runs. Where SCHED_IDLE is not available (not Linux, not permitted) the
    threads run at ``nice`` +:data:`NICE`."""
    try:
        threads = [int(tid) for tid in os.listdir('/proc/self/task')]
    except OSError:
        threads = [0]                       # the calling thread
    for tid in threads:
        try:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        except (OSError, AttributeError):
            try:
                os.setpriority(os.PRIO_PROCESS, tid,
                               min(19, os.getpriority(os.PRIO_PROCESS, tid) + NICE))
            except (OSError, AttributeError):   # not permitted or not POSIX: same priority
                pass


def _serve(conn) -> None:
    """The child's loop: (name, args) in, (True, result) or (False, message) out."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    _yield_to_parent()
    from msg_adapters.inputs import NUMERIC_ERRORS, first_line
    while True:
        try:
            name, args = conn.recv()
        except (EOFError, OSError, KeyboardInterrupt):
            return
        try:
            reply = (True, JOBS[name](*args))
        except NUMERIC_ERRORS as exc:
            reply = (False, first_line(exc))
        except Exception as exc:  # noqa: BLE001 - any failure is the job's answer, not the end
            reply = (False, f'{type(exc).__name__}: {first_line(exc)}')
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return


class JobCancelled(WorkerError):
    """A job cancelled before it answered (superseded, or over its time budget)."""


class Worker:
    """One child process serving :data:`JOBS` in order (see the module docstring)."""

    def __init__(self):
        self._context = multiprocessing.get_context('spawn')
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._process = None
        self._conn = None
        self._closed = False
        self._lock = threading.Lock()
        self._running = None            # the future of the job the child is computing
        self._running_since = 0.0
        self._cancelled = ''            # why the running job's child was killed
        self._thread = threading.Thread(target=self._pump, name='cdpr_worker', daemon=True)
        self._thread.start()

    def submit(self, name: str, *args) -> concurrent.futures.Future:
        """Queue job ``name`` (a key of :data:`JOBS`) with ``args``; its future resolves to
        the job's result, or raises :class:`JobFailed` (the job's one-line reason) or
        :class:`WorkerError`."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        if self._closed:
            future.set_exception(WorkerError('the worker is closed'))
        else:
            self._jobs.put((future, name, args))
        return future

    def running_s(self, future) -> float:
        """Seconds the child has been computing ``future``'s job (0 if it is not)."""
        with self._lock:
            return time.monotonic() - self._running_since if self._running is future else 0.0

    def cancel(self, future, reason: str) -> bool:
        """Cancel ``future``'s job: a queued one is dropped (the future cancelled), the running
        one ends with its child, killed (the next job starts another) and its future raises
        :class:`JobCancelled` with ``reason``. False where the job is done already."""
        if future.cancel():
            return True
        with self._lock:
            if self._running is not future or self._process is None:
                return False
            self._cancelled = reason
            self._process.kill()
        return True

    def close(self) -> None:
        """Stop the child (at once: a running job is abandoned) and the pump thread."""
        self._closed = True
        self._jobs.put(None)
        process = self._process
        if process is not None and process.is_alive():
            process.terminate()
            process.join(JOIN_S)
            if process.is_alive():
                process.kill()
        self._thread.join(JOIN_S)

    def _start(self) -> None:
        parent, child = self._context.Pipe()
        self._process = self._context.Process(target=_serve, args=(child,),
                                              name='cdpr_dynamics_worker', daemon=True)
        self._process.start()
        child.close()
        self._conn = parent

    def _pump(self) -> None:
        try:      # at once, so the first job does not wait for Python to start and import
            self._start()
        except Exception:  # noqa: BLE001 - tried again (and reported) with the first job
            self._process = None
        while True:
            job = self._jobs.get()
            if job is None or self._closed:
                if job is not None:
                    job[0].set_exception(WorkerError('the worker is closed'))
                return
            future, name, args = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                if self._process is None or not self._process.is_alive():
                    self._start()
                with self._lock:
                    self._running, self._running_since = future, time.monotonic()
                self._conn.send((name, args))
                ok, value = self._conn.recv()
            except (EOFError, OSError) as exc:
                with self._lock:
                    process, self._process = self._process, None
                    cancelled, self._cancelled, self._running = self._cancelled, '', None
                if cancelled:
                    if process is not None:
                        process.join(JOIN_S)
                    future.set_exception(JobCancelled(cancelled))
                    continue
                code = None if process is None else process.exitcode
                future.set_exception(WorkerError(
                    'the analysis process ended before it answered'
                    + (f' (exit code {code})' if code is not None else f' ({exc})')))
                continue
            except Exception as exc:  # noqa: BLE001 - e.g. arguments that do not pickle
                with self._lock:
                    self._running, self._cancelled = None, ''
                future.set_exception(WorkerError(f'{type(exc).__name__}: {exc}'))
                continue
            with self._lock:       # answered (a cancel that came too late killed an idle child)
                self._running, self._cancelled = None, ''
            if ok:
                future.set_result(value)
            else:
                future.set_exception(JobFailed(value))


class JobFailed(RuntimeError):
    """A job raised in the worker; the message is its one-line reason."""


@dataclasses.dataclass(frozen=True, eq=False)
class StaticsRequest:
    """A pose for :class:`BackgroundStatics`: position (3,) m, rotation (3, 3), the settings
    and their token, the pose's stamp (kept for the caller) and when it was asked (monotonic s)."""

    position_m: object
    rotation: object
    settings: object
    token: int
    stamp: object = None
    asked_s: float = 0.0


class BackgroundStatics:
    """The first half of the node's pose updates (:meth:`LivePredictor.statics`) in a worker
    process of their own (``node.rebuild: worker``), so the pose and wrench thread only swaps
    the answer in (:meth:`LivePredictor.apply`) while the old model keeps predicting.

    One pose at a time: a pose that comes while one is computed waits, and a newer one replaces
    it (latest wins; :attr:`superseded` counts those replaced). ``wake`` is called from the
    worker's thread when an answer is in; :meth:`take` then returns it.
    """

    def __init__(self, wake):
        self._worker = Worker()
        self._wake = wake
        self._future = None
        self._running: StaticsRequest | None = None
        self.pending: StaticsRequest | None = None
        self.superseded = 0

    @property
    def busy(self) -> bool:
        """Whether a pose is being computed."""
        return self._future is not None

    def request(self, request: StaticsRequest) -> None:
        """Compute this pose now, or next (replacing a waiting one) while one is computed."""
        if self._future is None:
            self._submit(request)
            return
        if self.pending is not None:
            self.superseded += 1
        self.pending = request

    def take(self):
        """(request, :class:`PoseStatics` or the exception the job raised) of the finished pose,
        or None while it is computed or when nothing was asked."""
        future = self._future
        if future is None or not future.done():
            return None
        request, self._future, self._running = self._running, None, None
        try:
            return request, future.result()
        except Exception as exc:  # noqa: BLE001 - JobFailed, WorkerError: the caller reports it
            return request, exc

    def submit_pending(self, choose) -> None:
        """Give the waiting pose to the worker as ``choose(request)`` returns it (e.g. with new
        settings), or drop it where that is None (e.g. the model in use is already there)."""
        request, self.pending = self.pending, None
        if request is not None and self._future is None:
            request = choose(request)
            if request is not None:
                self._submit(request)

    def close(self) -> None:
        self._worker.close()

    def _submit(self, request: StaticsRequest) -> None:
        self._running = request
        self._future = self._worker.submit('statics', request.token, request.settings,
                                           request.position_m, request.rotation)
        self._future.add_done_callback(self._wake)
