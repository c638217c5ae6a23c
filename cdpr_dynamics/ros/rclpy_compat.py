"""Every use of rclpy beyond its public API, in one place, each with why it is needed.

1. :class:`InputLoop` waits on the pose and wrench subscriptions through rclpy's own rcl wait
   set (``rclpy.impl.implementation_singleton``) and takes messages through the subscription's
   handle (:func:`take_next`). The public :class:`~rclpy.executors.SingleThreadedExecutor`
   builds a new wait set from every entity of the node on every turn, with tasks and callback
   groups: about three times the cost of a turn here, which at 1 kHz wrenches is a sizeable
   share of a core and of each wrench's latency. Where the wait-set API is missing the node
   falls back to the executor (:class:`InputLoop` raises ``AttributeError``).
2. :func:`defer_replies` replaces a service's ``send_response`` so that a callback can return a
   placeholder and the reply is sent later (:func:`send_reply`), when the worker process has
   computed it. Jazzy's public way, an ``async`` service callback awaiting a future, keeps the
   executor busy-waiting while the coroutine is suspended (every turn yields the in-progress
   task again without waiting: ros2/rclpy#1405, fixed by ros2/rclpy#1469 after Jazzy), which
   would take a core for the length of every frequency_response call.
3. :func:`make_set_parameters_atomic` swaps the callback of the node's ``set_parameters``
   service: rclpy applies the parameters of one request one by one (a request with one bad
   value of twenty applies nineteen, with nineteen rebuilds); through
   ``set_parameters_atomically`` the request is validated and applied as a whole.
4. :func:`parameter_overrides` reads the names and values given to the node (params file,
   ``-p``) before they are declared (rclpy keeps them in the private ``_parameter_overrides``):
   a name not in the parameter table is refused as the tools refuse it, and a value of another
   type is converted as the tools convert it.
"""
from __future__ import annotations

import contextlib

from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.parameter import Parameter

from msg_adapters.validation import clip

LOOP_WAIT_S = 0.1         # the pose and wrench loop returns to Python at least this often


def take_next(subscription):
    """The next message waiting on ``subscription``, or None (rclpy's executor does the same
    through the same handle); any failure just ends the batch."""
    try:
        with subscription.handle:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
    except Exception:  # destroyed or an rclpy without this handle API: back to the executor
        return None
    return None if taken is None else taken[0]


class InputLoop:
    """The pose and wrench path's own loop (the main thread): one rcl wait set over the io
    node's ``subscriptions``, made once and refilled each turn, then each ready one's message
    taken and handed to its callback.

    :meth:`spin` returns to Python at least every ``LOOP_WAIT_S`` (a signal is handled there)
    and ends when the context shuts down or ``stop()`` says so (checked every turn); an
    exception from a callback ends it (as the executor's ``spin`` does). A turn whose wait
    timed out tries to take from each subscription all the same, so that a wake-up the
    middleware lost leaves no message waiting for the next one. ``AttributeError``
    from the constructor: this rclpy lacks the wait set API (use the executor).

    ``stop`` is how a signal ends the loop even where the exception its handler raises is
    lost: raised in Python code that a pybind11 call runs (a message's conversion inside
    ``take_message``) it comes out as that call's RuntimeError ("Unable to convert call
    argument"), which :func:`take_next` ends a batch on.
    """

    def __init__(self, context, subscriptions, stop=lambda: False):
        from rclpy.impl.implementation_singleton import rclpy_implementation
        self._context = context
        self._subscriptions = tuple(subscriptions)
        self._stop = stop
        with context.handle:
            self._wait_set = rclpy_implementation.WaitSet(len(self._subscriptions), 0, 0, 0, 0,
                                                          0, context.handle)

    def spin(self) -> None:
        timeout_ns = round(LOOP_WAIT_S * 1e9)
        with contextlib.ExitStack() as held:        # none destroyed while the loop waits
            held.enter_context(self._context.handle)
            turn = [(sub.handle, sub.handle.pointer, sub.msg_type, sub.raw, sub.callback)
                    for sub in self._subscriptions]
            for handle, *_ in turn:
                held.enter_context(handle)
            wait_set = self._wait_set
            stop = self._stop
            while self._context.ok() and not stop():
                wait_set.clear_entities()
                for entry in turn:
                    wait_set.add_subscription(entry[0])
                wait_set.wait(timeout_ns)
                ready = wait_set.get_ready_entities('subscription')
                for handle, pointer, msg_type, raw, callback in turn:
                    if pointer in ready or not ready:   # a turn that timed out tries each
                        taken = handle.take_message(msg_type, raw)
                        if taken is not None:
                            callback(taken[0])


def defer_replies(service, placeholder_type, on_deferred) -> None:
    """Let ``service``'s callback answer later: when it returns an instance of
    ``placeholder_type`` (instead of a response), the executor's ``send_response(placeholder,
    header)`` calls ``on_deferred(placeholder, header)``, and the reply is sent afterwards by
    :func:`send_reply` with that header. Any other return value is sent as usual."""
    def send_response(response, header):
        if isinstance(response, placeholder_type):
            on_deferred(response, header)
        else:
            send_reply(service, response, header)
    service.send_response = send_response


def send_reply(service, response, header) -> None:
    """Send ``response`` to the request of ``header`` (the service class's own method, past
    :func:`defer_replies`' replacement)."""
    type(service).send_response(service, response, header)


def make_set_parameters_atomic(node) -> None:
    """Serve ``node``'s ``set_parameters`` all or none: the whole request goes through
    ``set_parameters_atomically`` (so the node's on-set-parameters callback sees it once), and
    every result is that one's (same reason)."""
    def on_request(request, response):
        params = [Parameter.from_parameter_msg(p) for p in request.parameters]
        try:
            result = node.set_parameters_atomically(params)
        except ParameterNotDeclaredException as exc:
            result = SetParametersResult(successful=False, reason=clip(str(exc), 500))
        response.results = [result] * len(params)
        return response

    for service in node.services:
        if service.srv_name.endswith('/set_parameters'):
            service.callback = on_request


def parameter_overrides(node) -> dict:
    """The parameters given to ``node`` (name -> :class:`Parameter`), declared or not."""
    return getattr(node, '_parameter_overrides', {})
