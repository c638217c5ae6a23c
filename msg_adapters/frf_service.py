"""The ``frequency_response`` service (rcl_interfaces/srv/GetParameters).

Request ``names``: the arrays wanted (:data:`ARRAYS`) mixed with ``key=value`` overrides of the
sweep for this call (:data:`OVERRIDES`). Response ``values``: one ParameterValue per name that
is not an override, in request order: DOUBLE_ARRAY with the array, or STRING with the reason
where the name is unknown or the computation failed.

Server side: :func:`parse_request`, :func:`response_size_error`, :func:`settings_changes`,
:func:`pack_response`. Bounded replies: a name asked for again is answered once (later entries
get a STRING saying which entry holds it), a request of more than :data:`MAX_NAMES` names or
whose reply would exceed ``node.frf_max_values`` doubles (distinct arrays x points) is refused
before any work, with the numbers; names echoed in reasons are cut to 80 characters.
Client side: :func:`request_message`, :func:`unpack_response`, :func:`wait_for_frequency_response`
(until a round trip has been made) and the blocking helper :func:`call_frequency_response`,
which returns numpy arrays, sends again a call whose reply did not come, and raises with the
reason.
"""
from __future__ import annotations

import array
import math
import threading
import time
import weakref
from dataclasses import dataclass, field

import numpy as np
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters

from cdpr_dynamics.analysis.pipeline import FRF_ARRAYS, MODE_ARRAYS, ROTATION_ARRAYS
from msg_adapters.validation import clip

SERVICE = 'frequency_response'
ARRAYS = FRF_ARRAYS
#: arrays some models cannot have (rotations of a point mass, classified modes of dsm): the
#: client helper's default request leaves them out of its result instead of failing
OPTIONAL_ARRAYS = ROTATION_ARRAYS + MODE_ARRAYS
#: override key -> type of its value; force_* / moment_* set one component of frf.force_n /
#: frf.moment_nm.
OVERRIDES = {'method': str, 'elements_per_cable': int, 'f_min_hz': float, 'f_max_hz': float,
             'n_points': int, 'force_x_n': float, 'force_y_n': float, 'force_z_n': float,
             'moment_x_nm': float, 'moment_y_nm': float, 'moment_z_nm': float}
_LOADS = (('frf_force_n', ('force_x_n', 'force_y_n', 'force_z_n')),
          ('frf_moment_nm', ('moment_x_nm', 'moment_y_nm', 'moment_z_nm')))


#: most names (arrays and overrides) one request may hold
MAX_NAMES = 100


class FrequencyResponseError(RuntimeError):
    """The service could not be reached or answered with a reason; ``str(exc)`` says which."""


@dataclass
class FrfRequest:
    """A parsed request: array names in order, overrides, and the first override error."""

    names: list[str] = field(default_factory=list)
    overrides: dict = field(default_factory=dict)
    error: str = ''

    def key(self) -> tuple:
        """Hashable identity of the overrides (for caching results)."""
        return tuple(sorted(self.overrides.items()))


def _parse_value(key: str, text: str):
    kind = OVERRIDES[key]
    text = text.strip()
    if kind is str:
        if not text:
            raise ValueError(f'override {key} has an empty value')
        return text
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f'override {key}={clip(repr(text))} is not a number') from None
    if not math.isfinite(value):
        raise ValueError(f'override {key}={text} is not finite')
    if kind is int:
        if not value.is_integer():
            raise ValueError(f'override {key}={text} is not an integer')
        return int(value)
    return value


def parse_request(names) -> FrfRequest:
    """Split request names into array names and ``key=value`` overrides (checked for type)."""
    request = FrfRequest()
    for entry in names:
        if '=' not in entry:
            request.names.append(entry)
            continue
        key, text = (part.strip() for part in entry.split('=', 1))
        if key not in OVERRIDES:
            request.error = request.error or (f'unknown override {clip(repr(key))}; known: '
                                              f'{", ".join(OVERRIDES)}')
            continue
        try:
            request.overrides[key] = _parse_value(key, text)
        except ValueError as exc:
            request.error = request.error or str(exc)
    return request


def response_size_error(names, n_points: int, max_values: int) -> str:
    """Why the reply to ``names`` at ``n_points`` would be too large, or ''.

    At most :data:`MAX_NAMES` names; distinct array names x ``n_points`` at most ``max_values``
    (an estimate: ``natural_frequencies_hz`` holds the modes up to ``f_max_hz``, at least
    12, not ``n_points``)."""
    names = list(names)
    if len(names) > MAX_NAMES:
        return (f'request has {len(names)} names, more than the {MAX_NAMES} one call may ask '
                f'for')
    arrays = [n for n in dict.fromkeys(names) if n in ARRAYS]
    values = len(arrays) * int(n_points)
    if values > max_values:
        return (f'reply too large: {len(arrays)} arrays x {n_points} points = {values} values, '
                f'over node.frf_max_values = {max_values}; ask for fewer arrays or points')
    return ''


def settings_changes(overrides: dict, frf_force_n, frf_moment_nm=(0.0, 0.0, 0.0)) -> dict:
    """Keyword arguments of ``Settings.replace`` for the overrides of one call."""
    loads = [k for _, keys in _LOADS for k in keys]
    changes = {k: v for k, v in overrides.items() if k not in loads}
    for (field_name, keys), base in zip(_LOADS, (frf_force_n, frf_moment_nm)):
        if any(k in overrides for k in keys):
            value = np.array(base, dtype=float)
            for axis, key in enumerate(keys):
                value[axis] = overrides.get(key, value[axis])
            changes[field_name] = value
    return changes


def double_array_value(values) -> ParameterValue:
    """ParameterValue of type DOUBLE_ARRAY (fast path through ``array.array``)."""
    data = array.array('d')
    data.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=data)


def string_value(text: str) -> ParameterValue:
    """ParameterValue of type STRING."""
    return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=text)


def pack_response(names, arrays: dict | None, error: str = '',
                  response: GetParameters.Response | None = None) -> GetParameters.Response:
    """One value per array name: the array, or a STRING with ``error`` or 'unknown ...';
    a name asked for again gets a STRING naming the entry that holds it (answered once)."""
    response = response or GetParameters.Response()
    values = []
    first: dict[str, int] = {}
    for index, name in enumerate(names):
        if name in first:
            values.append(string_value(f'duplicate of entry {first[name]} ({clip(name)}): '
                                       f'answered once'))
            continue
        first[name] = index
        if name not in ARRAYS:
            values.append(string_value(f'unknown array {clip(repr(name))}; known: '
                                       f'{", ".join(ARRAYS)}; overrides: '
                                       f'{", ".join(k + "=..." for k in OVERRIDES)}'))
        elif error or arrays is None:
            values.append(string_value(error or 'not computed'))
        elif isinstance(arrays[name], str):     # an array this model cannot have: why
            values.append(string_value(arrays[name]))
        else:
            values.append(double_array_value(arrays[name]))
    response.values = values
    return response


def request_message(names=None, overrides: dict | None = None) -> GetParameters.Request:
    """A request for ``names`` (default: every array) with ``key=value`` overrides."""
    names = list(ARRAYS if names is None else names)
    for key, value in (overrides or {}).items():
        names.append(f'{key}={value!r}' if isinstance(value, float) else f'{key}={value}')
    return GetParameters.Request(names=names)


def unpack_response(request: GetParameters.Request, response: GetParameters.Response):
    """``(arrays, reasons)``: name -> float64 array, name -> reason string."""
    names = [n for n in request.names if '=' not in n]
    if len(response.values) != len(names):
        raise FrequencyResponseError(f'frequency_response returned {len(response.values)} '
                                     f'values for {len(names)} names')
    arrays, reasons = {}, {}
    for name, value in zip(names, response.values):
        if name in arrays or name in reasons:
            continue                 # a name asked for again: answered at its first entry
        if value.type == ParameterType.PARAMETER_DOUBLE_ARRAY:
            arrays[name] = np.array(value.double_array_value, dtype=float)
        elif value.type == ParameterType.PARAMETER_STRING:
            reasons[name] = value.string_value
        else:
            reasons[name] = f'unexpected parameter type {value.type}'
    return arrays, reasons


_CLIENTS: 'weakref.WeakKeyDictionary' = weakref.WeakKeyDictionary()
PING_FIRST_S = 0.25     # the first wait for the reply to an empty request (then doubled)
CALL_FIRST_S = 2.0      # the first wait for the reply to a call before it is sent again
REPLY_DEPTH = 1000      # replies a client's reader holds before DDS drops the oldest untaken
#                         one: every client of the service receives every client's replies
#                         (the rmw filters its own out afterwards), so rclpy's default of 10
#                         loses a client's reply behind ten of other clients' on a busy machine


class _Client:
    """A node's client of one service and whether a round trip has been made through it."""

    def __init__(self, node, service: str):
        self.client = node.create_client(GetParameters, service, qos_profile=reply_qos())
        self.matched = False      # wait_for_service: this client's endpoints matched a server's
        self.ready = False


def reply_qos():
    """The QoS of this module's clients: rclpy's services default with a reply reader deep
    enough (:data:`REPLY_DEPTH`) for the replies that concurrent clients receive at once."""
    from rclpy.qos import QoSProfile, qos_profile_services_default
    return QoSProfile(history=qos_profile_services_default.history, depth=REPLY_DEPTH,
                      reliability=qos_profile_services_default.reliability,
                      durability=qos_profile_services_default.durability)


def _client(node, service: str) -> _Client:
    clients = _CLIENTS.setdefault(node, {})
    if service not in clients:
        clients[service] = _Client(node, service)
    return clients[service]


def frequency_response_client(node, service: str = SERVICE):
    """The rclpy client of ``service`` that this module's helpers use for ``node`` (made once):
    a reply reaches the client whose round trip :func:`wait_for_frequency_response` made."""
    return _client(node, service).client


def _wait(node, future, seconds: float, spin: bool) -> bool:
    """Wait up to ``seconds`` for ``future`` (spinning ``node`` here, or not); done?"""
    if spin:
        import rclpy
        rclpy.spin_until_future_complete(node, future, executor=node.executor,
                                         timeout_sec=seconds)
    else:
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        done.wait(seconds)
    return future.done()


def _call(node, client, request, deadline: float, first_s: float, spin: bool):
    """The future of ``request`` answered before ``deadline`` (monotonic), or None. A call
    whose reply has not come within its wait (``first_s``, then doubled) is sent again: a
    reply lost in transport is not waited for until the deadline, and the server answers
    equal calls at one state once (its cache, or the computation already under way)."""
    wait_s = first_s
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        future = client.call_async(request)
        if _wait(node, future, min(wait_s, remaining), spin):
            return future
        client.remove_pending_request(future)
        wait_s *= 2


def wait_for_frequency_response(node, timeout_s: float = 10.0, service: str = SERVICE,
                                spin: bool = True) -> bool:
    """Wait until ``service`` answers ``node``; True when it did within ``timeout_s``.

    ``wait_for_service`` says that this client's request writer and reply reader have matched
    the server's; the server's reply writer may not have matched this client's reply reader
    yet, and a reply sent before it has is dropped (Fast DDS waits 100 ms for the match, less
    than discovery takes on a busy machine). So an empty request (answered at once, without
    work) is sent, and sent again, until its reply comes: the round trip proves the match.
    Done once per node and service (:func:`call_frequency_response` calls it)."""
    entry = _client(node, service)
    if entry.ready:
        return True
    deadline = time.monotonic() + timeout_s
    entry.matched = entry.matched or entry.client.wait_for_service(timeout_sec=timeout_s)
    if not entry.matched:
        return False
    ping = _call(node, entry.client, GetParameters.Request(names=[]), deadline, PING_FIRST_S,
                 spin)
    entry.ready = ping is not None
    return entry.ready


def call_frequency_response(node, names=None, overrides: dict | None = None,
                            timeout_s: float = 10.0, service: str = SERVICE,
                            spin: bool = True) -> dict[str, np.ndarray]:
    """Call the service and return ``{name: array}``; raise FrequencyResponseError on errors.

    ``names``: arrays wanted (default all of :data:`ARRAYS`); ``overrides``: e.g.
    ``{'method': 'spring', 'n_points': 100}``. ``spin=True`` spins ``node`` here until the
    answer arrives (a plain script); ``spin=False`` only waits, for a node that an executor
    spins in another thread. Never call it from a callback of the executor spinning ``node``.
    The first call waits until the service can answer (:func:`wait_for_frequency_response`);
    a call whose reply does not come within ``CALL_FIRST_S`` (then twice, four times that) is
    sent again, within ``timeout_s`` in all.
    """
    deadline = time.monotonic() + timeout_s
    if not wait_for_frequency_response(node, timeout_s, service, spin):
        raise FrequencyResponseError(
            f'service {service} not available after {timeout_s:g} s: '
            + ('it matched this client but answered no empty request'
               if _client(node, service).matched else 'no server matched this client'))
    request = request_message(names, overrides)
    future = _call(node, _client(node, service).client, request, deadline, CALL_FIRST_S,
                   spin)
    if future is None:
        raise FrequencyResponseError(f'service {service} did not answer within {timeout_s:g} s')
    if future.exception() is not None:
        raise FrequencyResponseError(f'service {service} failed: {future.exception()}')
    arrays, reasons = unpack_response(request, future.result())
    if names is None:       # the default request: arrays this model cannot have are left out
        reasons = {k: v for k, v in reasons.items() if k not in OPTIONAL_ARRAYS}
    if reasons:
        raise FrequencyResponseError('; '.join(f'{k}: {v}' for k, v in reasons.items())
                                     if len(set(reasons.values())) > 1
                                     else next(iter(reasons.values())))
    return arrays
