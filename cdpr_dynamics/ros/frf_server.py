"""The node's ``frequency_response`` service: limits, a queue, a cache, replies in order.

A request is refused before any work when it asks for more than the node's limits
(``node.frf_max_points``, ``node.frf_max_values``, the problem-size limit); a request equal to
an earlier one at the same model state is answered from the cache (``node.frf_cache_size``)
or joins the computation already under way; anything else goes to the worker process
(:mod:`cdpr_dynamics.ros.worker`), at most ``node.frf_queue_depth`` calls waiting, while the
node keeps serving pose and wrench. Replies leave in request order: a call that could be
answered at once waits behind the calls before it.
"""
from __future__ import annotations

import collections
import time

from rcl_interfaces.srv import GetParameters
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_services_default)

from cdpr_dynamics.analysis.config import ConfigError, check_problem_size
from cdpr_dynamics.ros.diagnostics import LOG_PERIOD_S
from cdpr_dynamics.ros.rclpy_compat import defer_replies, send_reply
from cdpr_dynamics.ros.worker import JobFailed
from msg_adapters import diagnostics as diag
from msg_adapters.frf_service import (ARRAYS, pack_response, parse_request, response_size_error,
                                      settings_changes)
from msg_adapters.inputs import NUMERIC_ERRORS, first_line

SERVICE_NAME = 'frequency_response'


class PendingCall:
    """A frequency_response call until it is answered: the parsed request, its response
    object, when it came, its cache key and worker future (or its result), its header."""

    def __init__(self, parsed, response, start: float):
        self.parsed, self.response, self.start = parsed, response, start
        self.key = None
        self.future = None
        self.result = None       # (arrays, error) once known
        self.header = None


class FrfServer:
    """``frequency_response`` of ``node`` (a :class:`~cdpr_dynamics.ros.node.DynamicsNode`:
    its lock, predictor, model revision, flat parameters, worker and logger).

    ``wake`` is called (from the worker's thread) when a job is done; the node then calls
    :meth:`answer_ready` on its executor. ``own_modes(arrays)`` receives the FRF arrays of a
    call without overrides at the current state (the node's own natural frequencies)."""

    def __init__(self, node, worker, wake, own_modes):
        self._node = node
        self._worker = worker
        self._wake = wake
        self._own_modes = own_modes
        self.cache = collections.OrderedDict()
        self.stats = {'calls': 0, 'answered': 0, 'waiting': 0, 'cache_hits': 0, 'failures': 0,
                      'last_ms': 0.0, 'last_error': ''}
        self._pending = collections.deque()    # PendingCall in request order
        self._inflight = {}                    # cache key -> the worker's future
        # calls wait in a queue of node.frf_queue_depth (rclpy's default holds 10 and DDS drops
        # the oldest beyond it without a word): each waiting call is answered in turn
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                         depth=node.flat['node.frf_queue_depth'],
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        self.service = node.create_service(GetParameters, SERVICE_NAME, self.on_request,
                                           qos_profile=qos)
        defer_replies(self.service, PendingCall, self._deferred)
        self._configure_introspection(node.flat['node.service_introspection'])

    def _configure_introspection(self, mode: str) -> None:
        try:
            from rclpy.service_introspection import ServiceIntrospectionState
        except ImportError:  # older rclpy: no service introspection
            return
        state = {'off': ServiceIntrospectionState.OFF,
                 'metadata': ServiceIntrospectionState.METADATA,
                 'contents': ServiceIntrospectionState.CONTENTS}[mode]
        self.service.configure_introspection(self._node.get_clock(),
                                             qos_profile_services_default, state)

    @property
    def busy(self) -> bool:
        """Calls are waiting for the worker."""
        return bool(self._pending)

    def on_request(self, request, response):
        """FRF at the current pose and tensions; overrides for this call; reasons as STRING.

        Refusals and cached results are answered at once; anything to compute returns a
        :class:`PendingCall`, answered when the worker is done (:meth:`answer_ready`)."""
        call = PendingCall(parse_request(request.names), response, time.perf_counter())
        with self._node.lock:
            answer_now = self._take_call(call)
        if answer_now:
            return self._answer(call)     # outside the lock: a large reply takes milliseconds
        return call       # its header arrives in _deferred; answered in order

    def _take_call(self, call) -> bool:
        """Look the call up in the cache or give it to the worker; True where it can be
        answered at once (nothing waits before it and its result is known)."""
        self.stats['calls'] += 1
        parsed = call.parsed
        flat = self._node.flat
        error = parsed.error or self._limits(parsed)  # refused before any work
        if not error and any(name in ARRAYS for name in parsed.names):
            key = (self._node.revision, parsed.key())
            if key in self.cache:
                self.cache.move_to_end(key)
                call.result = self.cache[key]
                self.stats['cache_hits'] += 1
            elif len(self._pending) >= flat['node.frf_queue_depth']:
                call.result = (None, f'frequency response busy: {len(self._pending)} calls '
                                     'waiting (node.frf_queue_depth); call again later')
            else:
                call.key = key
                try:
                    call.future = self._inflight.get(key) or self._submit(parsed.overrides, key)
                except NUMERIC_ERRORS as exc:     # overrides the settings refuse
                    call.result = (None, f'frequency response failed: {first_line(exc)}')
        else:
            call.result = (None, error)
        if call.result is not None and not self._pending:
            return True
        self._pending.append(call)
        return False

    def _submit(self, overrides: dict, key):
        """Queue the FRF of this call at the current state on the worker (a future)."""
        predictor = self._node.predictor
        settings = predictor.settings
        changes = settings_changes(overrides, settings.frf_force_n, settings.frf_moment_nm)
        if changes:
            settings = settings.replace(**changes)
        if 'method' in changes or 'elements_per_cable' in changes:
            method, elements = settings.method, settings.elements_per_cable
        else:       # the model the node integrates (auto's choice, or the fallback)
            assembly = predictor.system.assembly
            method, elements = assembly.method, assembly.elements_per_cable
        future = self._worker.submit('frf', settings, predictor.eq, method, elements)
        self._inflight[key] = future
        future.add_done_callback(self._wake)
        return future

    def cancel_over_budget(self, budget_s: float) -> None:
        """Cancel the worker's job of a waiting call that has run longer than ``budget_s``
        (its callers are answered with the reason)."""
        for call in self._pending:
            if (call.future is not None and not call.future.done()
                    and self._worker.running_s(call.future) > budget_s):
                self._worker.cancel(call.future, f'over its time budget of {budget_s:g} s')

    def _deferred(self, call: PendingCall, header) -> None:
        """The executor's reply to a :class:`PendingCall`: keep its header for the answer."""
        call.header = header
        self.answer_ready()

    def answer_ready(self) -> None:
        """Send the waiting answers whose results are in, oldest first (request order); the
        replies are packed and sent outside the lock (a 20000-point reply takes
        milliseconds)."""
        ready = []
        with self._node.lock:
            while self._pending:
                call = self._pending[0]
                if call.header is None or (call.result is None and not call.future.done()):
                    break
                self._pending.popleft()
                if call.result is None:
                    call.result = self._result(call)
                ready.append(call)
        for call in ready:
            message = self._answer(call)
            try:
                send_reply(self.service, message, call.header)
            except Exception as exc:  # noqa: BLE001 - the client left or the node is stopping
                self._node.get_logger().warning(f'frequency_response answer not sent: {exc}',
                                                throttle_duration_sec=LOG_PERIOD_S)

    def _result(self, call) -> tuple:
        """(arrays, error) of a finished worker job, cached by state."""
        self._inflight.pop(call.key, None)
        try:
            arrays, error = call.future.result(), ''
        except JobFailed as exc:
            arrays, error = None, f'frequency response failed: {exc}'
        except Exception as exc:  # noqa: BLE001 - WorkerError: the process died
            arrays, error = None, f'frequency response failed: {type(exc).__name__}: {exc}'
        size = self._node.flat['node.frf_cache_size']
        if size > 0:
            self.cache[call.key] = (arrays, error)
            while len(self.cache) > size:
                self.cache.popitem(last=False)
        if (arrays is not None and not call.parsed.overrides
                and call.key[0] == self._node.revision):
            self._own_modes(arrays)
        return arrays, error

    def _answer(self, call) -> GetParameters.Response:
        arrays, error = call.result
        if error:
            self.stats['failures'] += 1
            self.stats['last_error'] = error
            self._node.get_logger().warning(error, throttle_duration_sec=LOG_PERIOD_S)
        self.stats['last_ms'] = (time.perf_counter() - call.start) * 1e3
        self.stats['answered'] += 1
        self.stats['waiting'] = len(self._pending)
        self._node.diag_dirty = True
        return pack_response(call.parsed.names, arrays, error, call.response)

    def _limits(self, parsed) -> str:
        """Why a request is refused before any work ('' if it is not): more points than
        ``node.frf_max_points``, a reply over ``node.frf_max_values``, a model over the
        problem-size limit (:func:`cdpr_dynamics.analysis.config.check_problem_size`)."""
        settings = self._node.predictor.settings
        flat = self._node.flat
        n_points = parsed.overrides.get('n_points', settings.n_points)
        if n_points > flat['node.frf_max_points']:
            return (f'n_points={n_points} exceeds node.frf_max_points = '
                    f'{flat["node.frf_max_points"]}')
        error = response_size_error(parsed.names, n_points, flat['node.frf_max_values'])
        if not error and ('method' in parsed.overrides
                          or 'elements_per_cable' in parsed.overrides):
            try:
                check_problem_size(settings, parsed.overrides.get('method'),
                                   parsed.overrides.get('elements_per_cable'))
            except ConfigError as exc:
                error = f'frequency response refused: {first_line(exc)}'
        return error

    def status(self, name: str, hw: str) -> tuple:
        """This report's status of the service (its last error, once)."""
        level = diag.WARN if self.stats['last_error'] else diag.OK
        status = (f'{name}: {SERVICE_NAME}', level,
                  self.stats['last_error'] or f'{self.stats["calls"]} calls',
                  dict(self.stats), hw)
        self.stats['last_error'] = ''
        return status
