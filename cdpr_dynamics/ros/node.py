"""``dynamics_node``: live vibration prediction of a CDPR beside its controller (SPEC section 5).

    ros2 run cdpr_dynamics dynamics_node --ros-args --params-file config/paper_cdpr.yaml

Subscribes ``pose`` (PoseStamped) and ``wrench`` (WrenchStamped), sensor-data QoS; publishes
``predicted_displacement`` (Vector3Stamped, stamped with the wrench's stamp) and
``predicted_pose`` (PoseStamped, same stamp) of ``node.output_point_m``, ``cable_tensions``
(JointState: position = length m, effort = tension N; transient local, one per accepted pose)
``cdpr_markers`` (MarkerArray of :mod:`msg_adapters.markers`, transient local: at start and
after rebuilds, the displacement arrow too, at most every diagnostics tick) and ``/diagnostics``;
serves ``frequency_response`` (rcl_interfaces/srv/GetParameters).

The node only wires ROS to :class:`cdpr_dynamics.analysis.live.LivePredictor` (the same core as
``cdpr_replay``) and to :func:`cdpr_dynamics.analysis.pipeline.frf_arrays`, which runs in a worker
process (:mod:`cdpr_dynamics.ros.worker`, as do the modes refreshed after rebuilds) so that the
executor keeps serving pose and wrench during a long call; every message conversion and
content check is in ``msg_adapters``. A bad input is rejected with a reason (diagnostics and a
throttled log line) and the node carries on with its last good state.

Hardening (issue 14): stamps never latch the node (:mod:`msg_adapters.stamps`, timed against
this node's clock); each wrench costs at most ``node.max_steps_per_wrench`` Newmark steps; the
service refuses oversized requests before any work and queues ``node.frf_queue_depth`` calls;
the limits are read-only; a ``set_parameters`` request applies all or none; user strings are
echoed cut; SIGINT/SIGTERM end the process with status 0 within ``STOP_DEADLINE_S``
(:class:`Stopper`).
"""
from __future__ import annotations

import _thread
import collections
import contextlib
import dataclasses
import functools
import os
import signal
import socket
import sys
import threading
import time

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped, WrenchStamped
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rcl_interfaces.srv import GetParameters
from rclpy.exceptions import (InvalidParameterTypeException, InvalidParameterValueException,
                              ParameterNotDeclaredException)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data, qos_profile_services_default)
from sensor_msgs.msg import JointState
from visualization_msgs.msg import MarkerArray

from cdpr_dynamics.analysis.pipeline import damping_for, damping_warnings, equilibrium_summary
from cdpr_dynamics.analysis.config import (NODE_PARAMETERS, PARAMETER_BY_NAME, PARAMETERS,
                                           ROS_NODE_PARAMETERS, ConfigError, Param, check_names,
                                           check_params, check_problem_size, check_value,
                                           default_config_path, node_options, read_params_file,
                                           settings_from_params)
from cdpr_dynamics.analysis.live import LivePredictor, PoseUpdate
from cdpr_dynamics.mechanics.robot import quaternion_to_matrix
from cdpr_dynamics.ros.worker import (BackgroundStatics, JobFailed, StaticsRequest, Worker,
                                      modes_job)
from msg_adapters import diagnostics as diag
from msg_adapters.displacement import displacement_message, fill_displacement
from msg_adapters.frf_service import (ARRAYS, pack_response, parse_request, response_size_error,
                                      settings_changes)
from msg_adapters.joint_state import tensions_message
from msg_adapters.markers import equilibrium_markers, update_arrow
from msg_adapters.pose import fill_pose, pose_message
from msg_adapters.inputs import NUMERIC_ERRORS, InputHandler, first_line
from msg_adapters.stamps import StampPolicy
from msg_adapters.validation import (InvalidMessage, clip, clock_ns, ns_to_stamp, s_to_stamp,
                                     stamp_to_ns)

NODE_NAME = 'cdpr_dynamics'
IO_SUFFIX = '_io'         # the companion node of pose and wrench: '<name>_io', same namespace

#: Fixed for the life of the node: the robot itself and what is set up once.
READ_ONLY = {'robot.frame_id', 'robot.anchors', 'robot.attachments', 'robot.initial_position',
             'robot.initial_orientation', 'node.diagnostics_period_s',
             'node.wrench_queue_depth', 'node.service_introspection',
             # limits protect the node: a client must not raise them at runtime
             'node.frf_max_points', 'node.frf_max_values', 'node.frf_queue_depth',
             'node.frf_cache_size', 'node.max_steps_per_wrench', 'node.rebuild'}
LOG_PERIOD_S = 1.0
WRENCH_BATCH = 64         # wrenches taken per callback beyond the first
CHANGE_PERIOD_S = 0.1
STOP_DEADLINE_S = 0.8     # after SIGINT/SIGTERM the process ends within this, cleanly or not
LOOP_WAIT_S = 0.1         # the pose and wrench loop returns to Python at least this often
OUTPUT_DEPTH = 1000      # predictions kept for a reliable subscriber that lags: 1 s at 1 kHz
#                          (a depth of 10 drops what a subscriber busy for 10 ms has not taken)
SWITCH_INTERVAL_S = 0.0005   # the GIL changes hands at least this often (Python's default,
#                              5 ms, would let the services thread hold a wrench that long)
MARKERS_PERIOD_S = 0.5    # markers of a new equilibrium at most this often (milliseconds each)
MODES_PERIOD_S = 0.5      # modes refreshed after rebuilds at most this often (a moving pose
#                           rebuilds at 50 Hz and more; its modes change slowly)
MODES_DUTY = 0.1          # and at most this share of a core: a refresh that took 0.5 s (the
#                           heavy-sag 6-DOF robot at fem_sag 16) waits 5 s for the next


def _locked(method):
    """Run a callback under the node's lock: the pose and wrench callbacks (main thread) and
    the parameter, service, guard and timer callbacks (the services thread) share the
    predictor."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)
    return wrapper


def _descriptor(param: Param) -> ParameterDescriptor:
    value_type = param.value_type
    if value_type is str:
        kind = ParameterType.PARAMETER_STRING
    elif value_type is list:
        kind = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif value_type is int:
        kind = ParameterType.PARAMETER_INTEGER
    else:
        kind = ParameterType.PARAMETER_DOUBLE
    descriptor = ParameterDescriptor(name=param.name, type=kind, description=param.description,
                                     read_only=param.name in READ_ONLY)
    if param.choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(param.choices)
    elif param.length:
        descriptor.additional_constraints = f'{param.length} values'
    elif param.length == 0:
        descriptor.additional_constraints = '3 values per cable'
    if param.low is not None and kind == ParameterType.PARAMETER_INTEGER:
        descriptor.integer_range = [IntegerRange(from_value=int(param.low),
                                                 to_value=int(param.high), step=0)]
    elif param.low is not None and kind == ParameterType.PARAMETER_DOUBLE:
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(param.low), to_value=float(param.high), step=0.0)]
    return descriptor


class InputHealth:
    """Counters and the last rejection of one input; the worst level since the last report."""

    def __init__(self, logger, bad_level: int):
        self.logger = logger
        self.bad_level = bad_level
        self.accepted = 0
        self.rejected = collections.Counter()
        self.last_reason = ''
        self.last_reason_time = 0.0
        self.level = diag.OK           # of the latest input
        self.worst = diag.OK           # since the last report
        self.worst_reason = ''
        self._logged: dict[str, float] = {}
        self._suppressed = collections.Counter()
        self._children = {}
        self.notes = collections.Counter()
        self.last_note = ''

    def accept(self) -> bool:
        """Count a good input; True when the level changed."""
        self.accepted += 1
        changed = self.level != diag.OK
        self.level = diag.OK
        return changed

    def reject(self, kind: str, reason: str) -> bool:
        """Count a rejection, log it (at most once a second per kind); True when it is news."""
        now = time.monotonic()
        self.rejected[kind] += 1
        news = self.level != self.bad_level or reason != self.last_reason
        self.last_reason, self.last_reason_time = reason, now
        self.level = self.bad_level
        if self.worst < self.bad_level:
            self.worst, self.worst_reason = self.bad_level, reason
        if now - self._logged.get(kind, -np.inf) >= LOG_PERIOD_S:
            more = self._suppressed.pop(kind, 0)
            text = reason + (f' ({more} more since the last log)' if more else '')
            if kind not in self._children:
                self._children[kind] = self.logger.get_child(kind)
            logger = self._children[kind]
            # throttled above (once a second per kind, counting what was held back)
            if self.bad_level >= diag.ERROR:
                logger.error(text)
            else:
                logger.warning(text)
            self._logged[kind] = now
        else:
            self._suppressed[kind] += 1
        return news

    def warn(self, kind: str, text: str) -> bool:
        """An accepted input that is worth a warning (a clock jump, a skipped interval): log it
        (throttled as rejections are), count it and raise this report to WARN; True (news)."""
        self.notes[kind] += 1
        self.last_note = text
        if self.worst < diag.WARN:
            self.worst, self.worst_reason = diag.WARN, text
        now = time.monotonic()
        key = 'note_' + kind
        if now - self._logged.get(key, -np.inf) >= LOG_PERIOD_S:
            more = self._suppressed.pop(key, 0)
            self.logger.warning(text + (f' ({more} more since the last log)' if more else ''))
            self._logged[key] = now
        else:
            self._suppressed[key] += 1
        return True

    def report(self):
        """(level, reason) for this report: the worst since the last one; then reset."""
        level, reason = max(self.level, self.worst), self.worst_reason or (
            self.last_reason if self.level else '')
        self.worst, self.worst_reason = diag.OK, ''
        return level, reason

    def values(self) -> dict:
        age = time.monotonic() - self.last_reason_time if self.last_reason else None
        values = {'accepted': self.accepted, 'rejected': sum(self.rejected.values())}
        values.update({f'rejected_{k}': v for k, v in sorted(self.rejected.items())})
        values['last_rejection'] = self.last_reason or 'none'
        if self.notes:
            values['warnings'] = sum(self.notes.values())
            values['last_warning'] = self.last_note
        if age is not None:
            values['last_rejection_age_s'] = round(age, 3)
        return values


class DynamicsNode(Node):
    """The ``cdpr_dynamics`` node: see the module docstring."""

    def __init__(self, io_arguments: list | None = None, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        # the pose and wrench path's own node, spun alone (see :func:`main`); one lock keeps
        # its callbacks and those of this node (parameters, service, timer) apart
        self._lock = threading.RLock()
        self.io = Node(f'{self.get_name()}{IO_SUFFIX}', namespace=self.get_namespace(),
                       context=self.context, cli_args=io_arguments,
                       use_global_arguments=io_arguments is None,
                       start_parameter_services=False, enable_rosout=False)
        self._flat = self._declare_parameters()
        node_options(self._flat)          # node.* values and choices, as the tools check them
        self.settings = settings_from_params(self._flat)
        self.frame_id = self.settings.robot.frame_id
        self._node_clock = self.get_clock()
        self.predictor = LivePredictor(self.settings, self._flat['node.pose_tolerance_m'],
                                       self._flat['node.angle_tolerance_rad'])
        self.revision = 0                      # bumps whenever the model state changes
        self._rebuilds = 0
        self.predictor.max_steps_per_wrench = self._flat['node.max_steps_per_wrench']
        self.inputs = InputHandler(self.predictor, self.frame_id,
                                   self._flat['node.quaternion_tolerance'],
                                   StampPolicy.from_options(self._flat))
        self._step_warnings: list[str] = []
        self._pose_stamp = None
        self._rebuild_s = collections.deque(maxlen=512)
        self._compute_s = collections.deque(maxlen=4096)   # check + integrate + message
        self._publish_s = collections.deque(maxlen=4096)   # handing the prediction to DDS
        self._wrench_times = collections.deque(maxlen=8192)
        self._frf_cache = collections.OrderedDict()
        self._frf = {'calls': 0, 'answered': 0, 'waiting': 0, 'cache_hits': 0, 'failures': 0,
                     'last_ms': 0.0, 'last_error': ''}
        self._modal_warnings: list[str] = []
        self._lowest_hz = float('nan')
        self._platform_hz = np.zeros(0)     # classified platform modes up to frf.f_max_hz
        self._modal_stale = False           # a rebuild since: refreshed before diagnostics
        self._worker = Worker()             # FRF calls and modes refreshes, off the executor
        self._frf_pending = collections.deque()    # _PendingCall in request order
        self._inflight = {}                 # cache key -> the worker's future
        self._modes_future = None
        self._modes_revision = -1
        self._modes_asked = -np.inf
        self._modes_period_s = MODES_PERIOD_S
        # node.rebuild: worker: the statics of moved poses in a process of their own
        self._background = (BackgroundStatics(self._wake)
                            if self._flat['node.rebuild'] == 'worker' else None)
        self._settings_token = 0            # bumps with the analysis settings
        self._swap_s = collections.deque(maxlen=512)   # pose arrival -> its model in use
        logger = self.get_logger()
        self.pose_health = InputHealth(logger.get_child('pose'), diag.ERROR)
        self.wrench_health = InputHealth(logger.get_child('wrench'), diag.WARN)
        self._update_modal()
        self._warm_up()

        sensor = QoSProfile(history=qos_profile_sensor_data.history,
                            depth=self._flat['node.wrench_queue_depth'],
                            reliability=qos_profile_sensor_data.reliability,
                            durability=qos_profile_sensor_data.durability)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.displacement_pub = self.io.create_publisher(Vector3Stamped,
                                                         'predicted_displacement', OUTPUT_DEPTH)
        self.pose_pub = self.io.create_publisher(PoseStamped, 'predicted_pose', OUTPUT_DEPTH)
        # one message per output topic, filled per wrench (publish serialises it at once)
        self._displacement_msg = displacement_message(np.zeros(3), self.frame_id, s_to_stamp(0.0))
        self._pose_msg = pose_message(np.zeros(3), (0.0, 0.0, 0.0, 1.0), self.frame_id)
        self.tensions_pub = self.create_publisher(JointState, 'cable_tensions', latched)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.markers_pub = self.create_publisher(MarkerArray, 'cdpr_markers', latched)
        self._markers_arrow = None
        self._markers = None
        self._markers_stale = False
        self._markers_built = -np.inf
        self.pose_sub = self.io.create_subscription(PoseStamped, 'pose', self.on_pose,
                                                    qos_profile_sensor_data)
        self.wrench_sub = self.io.create_subscription(WrenchStamped, 'wrench', self.on_wrench,
                                                      sensor)
        # calls wait in a queue of node.frf_queue_depth (rclpy's default holds 10 and DDS drops
        # the oldest beyond it without a word): each waiting call is answered in turn
        service_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                                 depth=self._flat['node.frf_queue_depth'],
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.VOLATILE)
        self.frf_service = self.create_service(GetParameters, 'frequency_response',
                                               self.on_frequency_response,
                                               qos_profile=service_qos)
        self.frf_service.send_response = self._send_frf_response
        self._worker_guard = self.create_guard_condition(self._answer_ready)
        self._configure_introspection(self._flat['node.service_introspection'])
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self._make_set_parameters_atomic()

        self._diag_dirty = True
        self._diag_last = -np.inf
        self._diag_timer = self.create_timer(CHANGE_PERIOD_S, self.on_diagnostics_timer)
        self._publish_tensions(self.get_clock().now().to_msg())
        self._publish_markers(self.predictor.prediction().displacement_m
                              * self._flat['node.marker_scale'], self.predictor.settings,
                              self.predictor.eq)
        update = self.predictor.last_update
        logger.info(f'{update.method} model, {update.dofs} DOFs at '
                    f'{np.round(self.predictor.position_m, 4).tolist()} m in '
                    f'{clip(repr(self.frame_id))}; waiting for pose and wrench')
        self._log_model_warnings()

    def destroy_node(self):
        """Stop the worker processes, then the pose and wrench node and this one."""
        self._worker.close()
        if self._background is not None:
            self._background.close()
        self.io.destroy_node()
        return super().destroy_node()

    # ---------------------------------------------------------------------- parameters

    def _declare_parameters(self) -> dict:
        """Declare the table's parameters; their values (flat, dotted) as the tools read them.

        Strict as the tools (SPEC section 3): a name given to this node (params file or
        ``-p``; rclpy keeps them in ``_parameter_overrides``) that is not in the table is a
        :class:`ConfigError` naming the closest one; parameters without a default are
        declared by type only and left out of the result when not given, so
        :func:`settings_from_params` names the missing one."""
        check_names(getattr(self, '_parameter_overrides', {}))
        type_only = {float: Parameter.Type.DOUBLE, int: Parameter.Type.INTEGER,
                     str: Parameter.Type.STRING, list: Parameter.Type.DOUBLE_ARRAY}
        flat = {}
        for param in PARAMETERS + NODE_PARAMETERS:
            descriptor = _descriptor(param)
            default = param.default
            if default is None or (isinstance(default, list) and not default):
                default = type_only[param.value_type]   # no default: must come from the file
            try:
                value = self.declare_parameter(param.name, default, descriptor).value
            except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
                value = self._declare_widened(param, descriptor, exc)
            if value is not None:
                flat[param.name] = _plain(value)
            elif param.default is not None:
                flat[param.name] = param.default
        return flat

    def _declare_widened(self, param: Param, descriptor, exc):
        """A value ROS refuses (another type: 30 for 30.0, '2.01e10'; out of range) converted
        and checked as the offline tools do (:func:`check_value`): declared with the converted
        value, or the tools' one-line reason; never rclpy's multi-line text."""
        override = getattr(self, '_parameter_overrides', {}).get(param.name)
        if override is None:
            raise ConfigError(f'parameter {param.name}: {first_line(exc)}') from None
        value = check_value(param.name, _plain(override.value))
        value = value.tolist() if isinstance(value, np.ndarray) else value
        try:
            return self.declare_parameter(param.name, value, descriptor,
                                          ignore_override=True).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as err:
            raise ConfigError(f'parameter {param.name}: {first_line(err)}') from None

    @_locked
    def on_set_parameters(self, params) -> SetParametersResult:
        """Validate a runtime change as a whole, apply it, or reject it with the reason.

        Parameters not of this package (``use_sim_time``, ...) are left to rclpy."""
        ours = [p for p in params if p.name in self._flat]
        if not ours:
            return SetParametersResult(successful=True)
        params = ours
        flat = dict(self._flat)
        flat.update({p.name: _plain(p.value) for p in params})
        analysis_changed = any(p.name in PARAMETER_BY_NAME for p in params)
        try:
            settings = settings_from_params(flat)
            node_options(flat)
            if analysis_changed:
                update = self.predictor.set_settings(settings)
                self._settings_token += 1
        except NUMERIC_ERRORS as exc:
            reason = first_line(exc)
            self.get_logger().warning(f'parameter change rejected: {reason}')
            return SetParametersResult(successful=False, reason=reason)
        except Exception as exc:  # never let a parameter change take the node down
            reason = f'{type(exc).__name__}: {first_line(exc)}'
            self.get_logger().error(f'parameter change rejected: {reason}')
            return SetParametersResult(successful=False, reason=reason)
        self._flat, self.settings = flat, settings
        self._frf_cache.clear()
        self.predictor.pose_tolerance_m = flat['node.pose_tolerance_m']
        self.predictor.angle_tolerance_rad = flat['node.angle_tolerance_rad']
        self.inputs.quaternion_tolerance = flat['node.quaternion_tolerance']
        self.inputs.policy = StampPolicy.from_options(flat)
        if analysis_changed:
            self._rebuilt(update)
            self._publish_tensions(self._pose_stamp or self.get_clock().now().to_msg())
            self.get_logger().info(
                'parameters ' + ', '.join(f'{p.name}={clip(_plain(p.value))}' for p in params)
                + f': {update.method} model, {update.dofs} DOFs')
        self._diag_dirty = True
        return SetParametersResult(successful=True)

    def _make_set_parameters_atomic(self) -> None:
        """Serve ``set_parameters`` all or none: rclpy applies the parameters of one request
        one by one (a 20-parameter request with one bad value applied 19, with 19 rebuilds);
        here the request goes through :meth:`on_set_parameters` once, every result is that
        one's (same reason), and the model is rebuilt at most once."""
        for service in self.services:
            if service.srv_name.endswith('/set_parameters'):
                service.callback = self._on_set_parameters_service

    def _on_set_parameters_service(self, request, response):
        params = [Parameter.from_parameter_msg(p) for p in request.parameters]
        try:
            result = self.set_parameters_atomically(params)
        except ParameterNotDeclaredException as exc:
            result = SetParametersResult(successful=False, reason=clip(str(exc), 500))
        response.results = [result] * len(params)
        return response

    def _configure_introspection(self, mode: str) -> None:
        try:
            from rclpy.service_introspection import ServiceIntrospectionState
        except ImportError:  # older rclpy: no service introspection
            return
        state = {'off': ServiceIntrospectionState.OFF,
                 'metadata': ServiceIntrospectionState.METADATA,
                 'contents': ServiceIntrospectionState.CONTENTS}[mode]
        self.frf_service.configure_introspection(self.get_clock(), qos_profile_services_default,
                                                 state)

    # -------------------------------------------------------------------------- inputs

    @_locked
    def on_pose(self, msg: PoseStamped) -> None:
        """Move the model to the pose; rebuild only when it moved more than the tolerance."""
        background = self._background is not None
        try:
            update = self.inputs.pose(msg, clock_ns(self._node_clock),
                                      self._hold_pose if background else None)
        except InvalidMessage as exc:
            self._reject(self.pose_health, exc.kind, str(exc))
            return
        self._pose_stamp = ns_to_stamp(self.inputs.last_pose_ns)
        if self.pose_health.accept():
            self._diag_dirty = True
        if self.inputs.notice:
            self._diag_dirty = self.pose_health.warn('clock', self.inputs.notice)
        if update.rebuilt:
            self._rebuilt(update)
        if not background or not self._queue_pose(*self._held_pose):
            self._publish_tensions(self._pose_stamp)   # else with its model (_take_statics)

    def _hold_pose(self, position_m, quaternion) -> PoseUpdate:
        """``node.rebuild: worker``: the pose's update for the input checks: keep the pose for
        :meth:`_queue_pose`, the model stays as it is."""
        self._held_pose = (np.asarray(position_m, dtype=float), quaternion_to_matrix(quaternion))
        update = self.predictor.last_update
        return PoseUpdate(False, update.method, update.dofs, sag_parameter=update.sag_parameter)

    def _queue_pose(self, position_m, rotation) -> bool:
        """Give a moved pose to the background statics (latest wins; True); the current
        model keeps predicting until :meth:`_take_statics` swaps the pose's model in. False
        where the model in use is already at the pose."""
        if not (self._background.busy or self.predictor.moved(position_m, rotation)):
            return False
        self._background.request(StaticsRequest(
            position_m, rotation, self.predictor.settings, self._settings_token,
            self._pose_stamp, time.monotonic()))
        return True

    def _take_statics(self) -> None:
        """Swap in the model of the pose the background statics solved (its tensions
        published), or report why the pose was rejected; then the next waiting pose."""
        taken = self._background.take()
        if taken is None:
            return
        request, result = taken
        if request.token != self._settings_token:         # settings changed: solve it again
            if self._background.pending is None:
                self._background.pending = request
        elif isinstance(result, Exception):
            self._reject(self.pose_health, 'state', f'pose rejected: {first_line(result)}')
        else:
            try:
                update = self.predictor.apply(result)
            except NUMERIC_ERRORS as exc:
                self._reject(self.pose_health, 'state', f'pose rejected: {first_line(exc)}')
            except Exception as exc:  # noqa: BLE001 - a bug must not stop the node (as inline)
                self._reject(self.pose_health, 'internal',
                             f'{type(exc).__name__}: {clip(exc)}')
            else:
                self._rebuilt(update)
                self._swap_s.append(time.monotonic() - request.asked_s)
                self._publish_tensions(request.stamp)
        self._background.submit_pending(self._next_statics)

    def _next_statics(self, request: StaticsRequest) -> StaticsRequest | None:
        """The waiting pose as the background statics should solve it next (with the current
        settings), or None where the model in use is already there (its tensions are then
        published with the pose's stamp, as for a pose that did not move)."""
        if request.token != self._settings_token:
            return dataclasses.replace(request, settings=self.predictor.settings,
                                       token=self._settings_token)
        if self.predictor.moved(request.position_m, request.rotation):
            return request
        self._publish_tensions(request.stamp)
        return None

    def on_wrench(self, msg: WrenchStamped) -> None:
        """Handle the wrench, then those already waiting (bounded): one executor round trip
        costs more than the prediction itself, so a burst is taken in one go."""
        self._handle_wrench(msg)
        for _ in range(WRENCH_BATCH):
            msg = _take(self.wrench_sub)
            if msg is None:
                break
            self._handle_wrench(msg)

    @_locked
    def _handle_wrench(self, msg: WrenchStamped) -> None:
        """Advance the integrator to the wrench's stamp and publish the prediction."""
        start = time.perf_counter()
        try:
            self.inputs.wrench(msg, clock_ns(self._node_clock))
        except InvalidMessage as exc:
            self._reject(self.wrench_health, exc.kind, str(exc))
            return
        stamp = msg.header.stamp if self.inputs.last_wrench_ns == stamp_to_ns(msg.header.stamp) \
            else ns_to_stamp(self.inputs.last_wrench_ns)     # an unstamped one: its arrival
        out = self.predictor.prediction(self._flat['node.output_point_m'])
        fill_displacement(self._displacement_msg, out.displacement_m, stamp)
        fill_pose(self._pose_msg, out.position_m, out.quaternion, stamp)
        computed = time.perf_counter()
        self.displacement_pub.publish(self._displacement_msg)
        if self.pose_pub.get_subscription_count():    # serialising it for nobody costs
            self.pose_pub.publish(self._pose_msg)
        if self.wrench_health.accept():
            self._diag_dirty = True
        if self.inputs.notice:
            self._diag_dirty = self.wrench_health.warn('time', self.inputs.notice)
        now = time.perf_counter()
        self._compute_s.append(computed - start)
        self._publish_s.append(now - computed)
        self._wrench_times.append(now)

    def _reject(self, health: InputHealth, kind: str, reason: str) -> None:
        if health.reject(kind, reason):
            self._diag_dirty = True

    def _rebuilt(self, update) -> None:
        self.revision += 1
        self._rebuilds += 1
        self._frf_cache.clear()
        self._rebuild_s.append(sum(update.timings_s.values()))
        self._modal_stale = True
        self._diag_dirty = True
        self._log_model_warnings()
        self._markers_stale = True        # published by the next diagnostics tick

    def _log_model_warnings(self) -> None:
        """Log the model's warnings (sag, accuracy, slack, heavy damping, fallback, time step)
        besides /diagnostics: all of them at start and whenever their set changes, and once
        when the last one clears. A warning's kind is its text before the first ':', so a
        number that moves with the pose does not repeat it."""
        warnings = list(self.predictor.last_update.warnings) + list(self._modal_warnings)
        kinds = frozenset(w.split(':', 1)[0] for w in warnings)
        before = getattr(self, '_logged_warning_kinds', frozenset())
        if kinds == before and hasattr(self, '_logged_warning_kinds'):
            return
        self._logged_warning_kinds = kinds
        logger = self.get_logger()
        for warning in warnings:
            logger.warning(f'model: {warning}')
        if not warnings and before:
            logger.info(f'model: no warnings any more ({", ".join(sorted(before))} cleared)')

    def _publish_tensions(self, stamp) -> None:
        eq = self.predictor.eq
        self.tensions_pub.publish(tensions_message(eq.geometry.length_m, eq.tensions.tension_n,
                                                   stamp, self.frame_id))

    def _publish_markers(self, arrow, settings, eq, rebuilt: bool = True) -> None:
        """``cdpr_markers`` of the equilibrium ``eq`` (rebuilt) or only its arrow moved to
        ``arrow``, the predicted displacement of the centroid times ``node.marker_scale``."""
        self._markers_arrow = arrow
        stamp = self.get_clock().now().to_msg()
        if rebuilt or self._markers is None:
            self._markers = equilibrium_markers(settings, eq, arrow, 1.0, stamp)
        else:
            update_arrow(self._markers, arrow, 1.0, stamp)
        self.markers_pub.publish(self._markers)

    def _warm_up(self) -> None:
        """One throw-away wrench so the first real one does not pay first-call costs."""
        self.predictor.wrench_reason(np.zeros(3), np.zeros(3))
        self.predictor.advance(0, np.zeros(3))
        self.predictor.advance(round(self.settings.dt_s * 1e9), np.zeros(3))
        self.predictor.reset_time()
        displacement_message(np.zeros(3), self.frame_id, s_to_stamp(0.0))
        out = self.predictor.prediction(self._flat['node.output_point_m'])
        pose_message(out.position_m, out.quaternion, self.frame_id, s_to_stamp(0.0))

    def _modes_args(self) -> tuple:
        assembly = self.predictor.system.assembly
        return (self.predictor.settings, self.predictor.eq, assembly.method,
                assembly.elements_per_cable, self.predictor.max_steps_per_wrench)

    def _update_modal(self) -> None:
        """Classified modes (the lowest platform mode), damping and time-step warnings of the
        current model, computed here: at start, before the node serves anything."""
        self._modal_stale = False
        try:
            found = modes_job(*self._modes_args())
            self._pace_modes(found['seconds'])
            self._apply_modes(found)
        except NUMERIC_ERRORS as exc:
            self._modal_warnings = [f'natural frequencies failed: {first_line(exc)}']

    def _refresh_modal(self) -> None:
        """After a rebuild: the same in the worker process (:meth:`_take_modes` applies it),
        one job at a time; the diagnostics keep the previous model's values meanwhile."""
        if self._modes_future is not None:
            return
        self._modal_stale = False
        self._modes_revision = self.revision
        self._modes_asked = time.monotonic()
        self._modes_future = self._worker.submit('modes', *self._modes_args())
        self._modes_future.add_done_callback(self._wake)

    def _take_modes(self) -> None:
        future = self._modes_future
        if future is None or not future.done():
            return
        self._modes_future = None
        try:
            found, error = future.result(), ''
            self._pace_modes(found['seconds'])
        except Exception as exc:  # noqa: BLE001 - JobFailed, WorkerError: reported, kept going
            found, error = None, f'natural frequencies failed: {first_line(exc)}'
        if self._modes_revision != self.revision:      # rebuilt since: ask again
            self._modal_stale = True
            return
        if found is None:
            self._modal_warnings = [error]
        else:
            self._apply_modes(found)
        self._diag_dirty = True
        self._log_model_warnings()    # damping, time step may have changed

    def _pace_modes(self, seconds: float) -> None:
        """The next refresh waits at least MODES_PERIOD_S and ``seconds`` / MODES_DUTY, so
        that refreshes taking ``seconds`` each use at most MODES_DUTY of a core."""
        self._modes_period_s = max(MODES_PERIOD_S, seconds / MODES_DUTY)

    def _apply_modes(self, found: dict) -> None:
        self._platform_hz = found['platform_hz']
        self._step_warnings = found['step_warnings']
        self._set_modal(found['frequency_hz'])

    def _set_modal(self, freqs) -> None:
        freqs = np.asarray(freqs)
        self._lowest_hz = float(freqs[0]) if freqs.size else float('nan')
        damping = damping_for(self.predictor.settings, self.predictor.system)
        self._modal_warnings = damping_warnings(damping, freqs[freqs > 0]) + self._step_warnings

    # ------------------------------------------------------------------------- service

    def on_frequency_response(self, request, response):
        """FRF at the current pose and tensions; overrides for this call; reasons as STRING.

        Refusals and cached results are answered at once; anything to compute goes to the
        worker process (:mod:`cdpr_dynamics.ros.worker`) while the executor keeps serving pose and
        wrench: the callback returns a :class:`_PendingCall` and the answer is sent when the
        worker is done (:meth:`_answer_ready`). Answers leave in request order: a call that
        could be answered at once waits behind the calls before it."""
        call = _PendingCall(parse_request(request.names), response, time.perf_counter())
        with self._lock:
            answer_now = self._take_call(call)
        if answer_now:
            return self._answer(call)     # outside the lock: a large reply takes milliseconds
        return call       # its header arrives in _send_frf_response; answered in order

    def _take_call(self, call) -> bool:
        """Look the call up in the cache or give it to the worker; True where it can be
        answered at once (nothing waits before it and its result is known)."""
        self._frf['calls'] += 1
        parsed = call.parsed
        error = parsed.error or self._frf_limits(parsed)  # refused before any work
        if not error and any(name in ARRAYS for name in parsed.names):
            key = (self.revision, parsed.key())
            if key in self._frf_cache:
                self._frf_cache.move_to_end(key)
                call.result = self._frf_cache[key]
                self._frf['cache_hits'] += 1
            elif len(self._frf_pending) >= self._flat['node.frf_queue_depth']:
                call.result = (None, f'frequency response busy: {len(self._frf_pending)} calls '
                                     'waiting (node.frf_queue_depth); call again later')
            else:
                call.key = key
                try:
                    call.future = (self._inflight.get(key)
                                   or self._submit_frf(parsed.overrides, key))
                except NUMERIC_ERRORS as exc:     # overrides the settings refuse
                    call.result = (None, f'frequency response failed: {first_line(exc)}')
        else:
            call.result = (None, error)
        if call.result is not None and not self._frf_pending:
            return True
        self._frf_pending.append(call)
        return False

    def _submit_frf(self, overrides: dict, key):
        """Queue the FRF of this call at the current state on the worker (a future)."""
        settings = self.predictor.settings
        changes = settings_changes(overrides, settings.frf_force_n, settings.frf_moment_nm)
        if changes:
            settings = settings.replace(**changes)
        if 'method' in changes or 'elements_per_cable' in changes:
            method, elements = settings.method, settings.elements_per_cable
        else:       # the model the node integrates (auto's choice, or the fallback)
            assembly = self.predictor.system.assembly
            method, elements = assembly.method, assembly.elements_per_cable
        future = self._worker.submit('frf', settings, self.predictor.eq, method, elements)
        self._inflight[key] = future
        future.add_done_callback(self._wake)
        return future

    def _wake(self, _future) -> None:
        """From the worker's thread: run :meth:`_answer_ready` on the executor."""
        try:
            self._worker_guard.trigger()
        except Exception:  # noqa: BLE001 - the node is being destroyed: nothing to answer
            pass

    def _send_frf_response(self, response, header) -> None:
        """The service's ``send_response`` (the executor calls it with the callback's return
        value): a :class:`_PendingCall` keeps the header for its answer later."""
        if isinstance(response, _PendingCall):
            response.header = header
            self._answer_ready()
            return
        type(self.frf_service).send_response(self.frf_service, response, header)

    def _answer_ready(self) -> None:
        """Send the waiting answers whose results are in, oldest first (request order), and
        take the worker's modes if they are in; the replies are packed and sent outside the
        lock (a 20000-point reply takes milliseconds)."""
        ready = []
        with self._lock:
            self._take_modes()
            if self._background is not None:
                self._take_statics()
            while self._frf_pending:
                call = self._frf_pending[0]
                if call.header is None or (call.result is None and not call.future.done()):
                    break
                self._frf_pending.popleft()
                if call.result is None:
                    call.result = self._frf_result(call)
                ready.append(call)
        for call in ready:
            message = self._answer(call)
            try:
                type(self.frf_service).send_response(self.frf_service, message, call.header)
            except Exception as exc:  # noqa: BLE001 - the client left or the node is stopping
                self.get_logger().warning(f'frequency_response answer not sent: {exc}',
                                          throttle_duration_sec=LOG_PERIOD_S)

    def _frf_result(self, call) -> tuple:
        """(arrays, error) of a finished worker job, cached by state; the node's own model's
        natural frequencies (no overrides) refresh its modal warnings."""
        self._inflight.pop(call.key, None)
        try:
            arrays, error = call.future.result(), ''
        except JobFailed as exc:
            arrays, error = None, f'frequency response failed: {exc}'
        except Exception as exc:  # noqa: BLE001 - WorkerError: the process died
            arrays, error = None, f'frequency response failed: {type(exc).__name__}: {exc}'
        if self._flat['node.frf_cache_size'] > 0:
            self._frf_cache[call.key] = (arrays, error)
            while len(self._frf_cache) > self._flat['node.frf_cache_size']:
                self._frf_cache.popitem(last=False)
        if arrays is not None and not call.parsed.overrides and call.key[0] == self.revision:
            self._platform_hz = np.asarray(arrays['platform_natural_frequencies_hz'])
            self._set_modal(arrays['natural_frequencies_hz'])
        return arrays, error

    def _answer(self, call) -> GetParameters.Response:
        arrays, error = call.result
        if error:
            self._frf['failures'] += 1
            self._frf['last_error'] = error
            self.get_logger().warning(error, throttle_duration_sec=LOG_PERIOD_S)
        self._frf['last_ms'] = (time.perf_counter() - call.start) * 1e3
        self._frf['answered'] += 1
        self._frf['waiting'] = len(self._frf_pending)
        self._diag_dirty = True
        return pack_response(call.parsed.names, arrays, error, call.response)

    def _frf_limits(self, parsed) -> str:
        """Why a request is refused before any work ('' if it is not): more points than
        ``node.frf_max_points``, a reply over ``node.frf_max_values``, a model over the
        problem-size limit (:func:`cdpr_dynamics.analysis.config.check_problem_size`)."""
        settings = self.predictor.settings
        n_points = parsed.overrides.get('n_points', settings.n_points)
        if n_points > self._flat['node.frf_max_points']:
            return (f'n_points={n_points} exceeds node.frf_max_points = '
                    f'{self._flat["node.frf_max_points"]}')
        error = response_size_error(parsed.names, n_points, self._flat['node.frf_max_values'])
        if not error and ('method' in parsed.overrides
                          or 'elements_per_cable' in parsed.overrides):
            try:
                check_problem_size(settings, parsed.overrides.get('method'),
                                   parsed.overrides.get('elements_per_cable'))
            except ConfigError as exc:
                error = f'frequency response refused: {first_line(exc)}'
        return error

    # --------------------------------------------------------------------- diagnostics

    def on_diagnostics_timer(self) -> None:
        """Markers (those of a new equilibrium at most every MARKERS_PERIOD_S: building them
        costs milliseconds, poses come at 50 Hz and more; the arrow every tick) and
        diagnostics when something changed.
        The state is read under the lock; the messages are built and published outside it,
        so the pose and wrench thread waits for neither."""
        now = time.monotonic()
        with self._lock:
            arrow = self.predictor.prediction().displacement_m * self._flat['node.marker_scale']
            rebuilt = self._markers is None or (
                self._markers_stale and now - self._markers_built >= MARKERS_PERIOD_S)
            markers_due = rebuilt or not np.array_equal(arrow, self._markers_arrow)
            if rebuilt:
                self._markers_stale = False
                self._markers_built = now
            state = (self.predictor.settings, self.predictor.eq)
            statuses = None
            if (self._diag_dirty
                    or now - self._diag_last >= self._flat['node.diagnostics_period_s']):
                self._diag_dirty = False
                self._diag_last = now
                statuses = self._statuses()
        if markers_due:
            self._publish_markers(arrow, *state, rebuilt=rebuilt)
        if statuses is not None:
            self.diagnostics_pub.publish(diag.diagnostics_message(
                [diag.status_message(*status) for status in statuses],
                self.get_clock().now().to_msg()))

    def _statuses(self) -> list[tuple]:
        """The diagnostics statuses (name, level, message, values, hardware id): model, pose
        input, wrench input, frequency_response."""
        hw = self.get_fully_qualified_name()
        name = self.get_name()
        if self._modal_stale and time.monotonic() - self._modes_asked >= self._modes_period_s:
            self._refresh_modal()
        statuses = [self._model_status(name, hw)]
        for title, health, extra in (('pose input', self.pose_health, {}),
                                     ('wrench input', self.wrench_health, self._wrench_stats())):
            level, reason = health.report()
            message = reason or f'{health.accepted} accepted'
            statuses.append((f'{name}: {title}', level, message, {**health.values(), **extra},
                             hw))
        frf_level = diag.WARN if self._frf['last_error'] else diag.OK
        statuses.append((f'{name}: frequency_response', frf_level,
                         self._frf['last_error'] or f'{self._frf["calls"]} calls',
                         dict(self._frf), hw))
        self._frf['last_error'] = ''
        return statuses

    def _model_status(self, name: str, hw: str):
        p = self.predictor
        update = p.last_update
        warnings = list(update.warnings) + self._modal_warnings
        rebuild = np.array(self._rebuild_s) * 1e3
        values = {
            'method': update.method, 'configured_method': p.settings.method,
            'elements_per_cable': p.settings.elements_per_cable, 'dofs': update.dofs,
            'position_m': np.round(p.position_m, 5).tolist(),
            'qp_status': p.eq.tensions.status, 'qp_iterations': p.eq.tensions.iterations,
            'tension_min_n': float(p.eq.tensions.tension_n.min()),
            'tension_max_n': float(p.eq.tensions.tension_n.max()),
            'lowest_natural_frequency_hz': self._lowest_hz,
            'lowest_platform_mode_hz': (float(self._platform_hz[0]) if self._platform_hz.size
                                        else float('nan')),
            'platform_modes_hz': np.round(self._platform_hz, 4).tolist(),
            'sag_parameter': np.round(update.sag_parameter, 4).tolist(),
            **_equilibrium_values(p.settings, p.eq),
            'rebuilds': self._rebuilds,
            'rebuild': self._flat['node.rebuild'],
        }
        if self._background is not None:
            values['poses_superseded'] = self._background.superseded
            if self._swap_s:
                swap = np.array(self._swap_s) * 1e3
                values['swap_ms_p50'] = float(np.percentile(swap, 50))
                values['swap_ms_max'] = float(swap.max())
        for stage, seconds in update.timings_s.items():
            values[f'last_update_{stage}_ms'] = seconds * 1e3
        if rebuild.size:
            values['update_ms_p50'] = float(np.percentile(rebuild, 50))
            values['update_ms_p99'] = float(np.percentile(rebuild, 99))
        values['warnings'] = warnings or 'none'
        level = diag.WARN if warnings else diag.OK
        message = (f'{update.method}, {update.dofs} DOFs' + (f': {warnings[0]}' if warnings
                                                             else ''))
        return f'{name}: model', level, message, values, hw

    def _wrench_stats(self) -> dict:
        values = {}
        for key, samples in (('compute', self._compute_s), ('publish', self._publish_s)):
            if samples:
                ms = np.array(samples) * 1e3
                values[f'{key}_ms_p50'] = float(np.percentile(ms, 50))
                values[f'{key}_ms_p99'] = float(np.percentile(ms, 99))
        times = np.array(self._wrench_times)
        recent = times[times > time.perf_counter() - 1.0]
        values['rate_hz'] = float(recent.size)
        return values


class _PendingCall:
    """A frequency_response call until it is answered: the parsed request, its response
    object, when it came, its cache key and worker future (or its result), its header."""

    def __init__(self, parsed, response, start: float):
        self.parsed, self.response, self.start = parsed, response, start
        self.key = None
        self.future = None
        self.result = None       # (arrays, error) once known
        self.header = None


def _equilibrium_values(settings, eq) -> dict:
    """Diagnostics of the static state: statics kind, residual, iterations, per-cable end force
    (N, 3 values per cable) and unstretched length (m)."""
    summary = equilibrium_summary(settings, eq)
    return {'statics': summary['statics'],
            'equilibrium_residual_n': summary['residual_n'],
            'equilibrium_residual_nm': summary['residual_nm'],
            'equilibrium_relative_residual': summary['relative_residual'],
            'statics_iterations': summary['iterations'],
            'end_force_n': np.round(eq.end_force_n, 4).ravel().tolist(),
            'unstretched_length_m': np.round(eq.unstretched_length_m, 6).tolist()}


def _take(subscription):
    """The next message waiting on ``subscription``, or None (rclpy's executor does the same
    through the same handle); any failure just ends the batch."""
    try:
        with subscription.handle:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
    except Exception:  # destroyed or an rclpy without this handle API: back to the executor
        return None
    return None if taken is None else taken[0]


def _plain(value):
    """A parameter value as plain Python (array.array -> list)."""
    if hasattr(value, 'tolist') and not isinstance(value, (str, bytes)):
        return value.tolist()
    return list(value) if isinstance(value, (list, tuple)) else value


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
an error. The table (names, units, defaults, ranges) is in README.md, section Configuration,
and in cdpr_dynamics/analysis/config.py (PARAMETERS); on a running node: ros2 param describe
/cdpr_dynamics NAME. Ctrl-C or SIGTERM stops it; a bad configuration exits 1 with one line.
"""


def _ros_override(rule: str) -> str:
    """A ``-p NAME:=VALUE`` rule checked as the tools check a config (name, value) and written
    with the parameter's ROS type (``frf.n_points:=400.0`` -> ``400``, ``robot.mass_kg:=40`` ->
    ``40.0``): rcl silently drops some overrides whose type differs from the params file's."""
    name, sep, text = rule.partition(':=')
    if not sep or name in ROS_NODE_PARAMETERS or name.startswith('qos_overrides.'):
        return rule                      # rcl's own rules (and its one-line error)
    check_names([name])
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        raise ConfigError(f'-p {rule[:80]}: the value is not YAML') from None
    value = check_value(name, value)
    if isinstance(value, np.ndarray):
        return f'{name}:=[{", ".join(repr(float(x)) for x in value)}]'
    if isinstance(value, float):
        return f'{name}:={value!r}'
    return rule if isinstance(value, str) else f'{name}:={value}'


def _check_command_line(argv) -> tuple[bool, list]:
    """(help asked, the arguments for rclpy). For ``-h``/``--help``: (True, argv). Otherwise
    every ``--params-file`` is read strictly, as the tools read a config (size, UTF-8,
    aliases, depth, duplicates, the node key for this node's name and namespace, names and
    values), and every ``-p`` rule checked and typed (:func:`_ros_override`), so a bad
    configuration gets the tools' one line before rcl parses it (:class:`ConfigError`).
    Arguments outside ``--ros-args`` are refused."""
    user, files, name, namespace, ros = [], [], NODE_NAME, '/', False
    out = list(argv[:1])
    args = iter(argv[1:])
    for arg in args:
        out.append(arg)
        if arg == '--ros-args':
            ros = True
        elif not ros or arg == '--':
            ros = False
            if arg != '--':
                user.append(arg)
        elif arg == '--params-file':
            files.append(next(args, None))
            out.append(files[-1])
        elif arg in ('-p', '--param'):
            rule = next(args, None)
            out.append(rule if rule is None else _ros_override(rule))
        elif arg in ('-r', '--remap'):
            out.append(next(args, ''))
            node, key, value = _split_rule(out[-1])
            if node in ('', NODE_NAME) and key == '__ns':
                namespace = value
            elif node in ('', NODE_NAME) and key in ('__node', '__name'):
                name = value
        elif arg in ('-e', '--enclave', '--log-level', '--log-file-name', '--log-config-file'):
            out.append(next(args, None))
    if '-h' in user or '--help' in user:
        return True, list(argv)
    if user:
        raise ConfigError(f'unknown argument {user[0][:60]!r} (see dynamics_node --help)')
    for path in files:
        if path is None:
            raise ConfigError('--params-file needs a file name')
        check_params(read_params_file(path, name, namespace))
    return False, [a for a in out if a is not None]


def main(args=None):
    """Run the node until Ctrl-C or SIGTERM; a bad configuration exits 1 with one line."""
    try:
        help_asked, args = _check_command_line(sys.argv if args is None else args)
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
    try:   # rclpy's own signal handlers would shut the context down under a running callback
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # e.g. a parameter file rcl cannot parse
        print(f'dynamics_node: error: {first_line(exc)}', file=sys.stderr)
        return 1
    stopper = Stopper()
    node = None
    status = 0
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    services = SingleThreadedExecutor()
    failed: list[BaseException] = []
    thread = None
    try:
        node = DynamicsNode(io_arguments=_io_arguments(args))
        services.add_node(node)
        thread = threading.Thread(target=_serve, args=(services, failed), name='cdpr_services',
                                  daemon=True)
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
        if failed and not stopper.signalled:
            print(f'dynamics_node: error: {first_line(failed[0])}', file=sys.stderr)
            status = 1
        stopper.stopping(status)
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
    if stopper.signalled:
        # stopped by a signal: nothing is left to do, and the interpreter's own finalisation
        # (seconds under load, with the default signal dispositions back) is skipped
        stopper.exit(status)
    return status


class InputLoop:
    """The pose and wrench path's own loop (the main thread): one rcl wait set over the io
    node's ``subscriptions``, made once and refilled each turn, then each ready one's message
    taken and handed to its callback.

    rclpy's SingleThreadedExecutor does the same through a wait set made anew on every turn
    from every entity of the node, with tasks and callback groups: 222 against 72 us per turn
    here (two subscriptions, nothing ready), which at 1 kHz wrenches is 15 % of a core and
    part of each wrench's latency. :meth:`spin` returns to Python at least every
    ``LOOP_WAIT_S`` (a signal is handled there) and ends when the context shuts down or
    ``stop()`` says so (checked every turn); an exception from a callback ends it (as the
    executor's ``spin`` does). ``AttributeError`` from the constructor: this rclpy lacks the
    wait set API (use the executor).

    ``stop`` is how a signal ends the loop even where its :class:`Stopped` is lost: raised in
    Python code that a pybind11 call runs (a message's conversion inside ``take_message``) it
    comes out as that call's RuntimeError ("Unable to convert call argument"), which a batch's
    ``_take`` ends the batch on. Under a 2 kHz wrench stream 10 of 30 SIGTERMs went that way
    and the loop kept predicting until the watchdog (0.8 s; 1.8 and 3.8 s where the watchdog
    thread waited that long for the GIL).
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
                    if pointer in ready:
                        taken = handle.take_message(msg_type, raw)
                        if taken is not None:
                            callback(taken[0])


def _serve(executor, failed: list) -> None:
    """The services thread: parameters, frequency_response, the worker's answers, the
    diagnostics timer. A callback that raises ends the node as one in the main thread would
    (``failed`` keeps the error for :func:`main`)."""
    try:
        executor.spin()
    except ExternalShutdownException:
        pass
    except Exception as exc:  # noqa: BLE001 - reported by main with one line, status 1
        failed.append(exc)
        _thread.interrupt_main()


def _io_arguments(argv) -> list:
    """ROS arguments for the companion pose and wrench node: the remap rules of ``argv`` that
    concern it (global ones but a node rename, and those addressed to this node's name,
    without the name), in the same namespace; no parameters (it declares none)."""
    rules, args = [], iter(argv[1:])
    for arg in args:
        if arg in ('-r', '--remap'):
            rules.append(_split_rule(next(args, '')))
    name = next((value for node, key, value in reversed(rules)
                 if node in ('', NODE_NAME) and key in ('__node', '__name')), NODE_NAME)
    out = []
    for node, key, value in rules:
        if key not in ('__node', '__name') and node in ('', NODE_NAME, name):
            out += ['-r', f'{key}:={value}']
    return ['--ros-args'] + out if out else []


def _split_rule(rule: str) -> tuple[str, str, str]:
    """A remap rule ``[node:]key:=value`` as (node or '', key, value)."""
    target, _, value = rule.partition(':=')
    node, _, key = target.rpartition(':')
    return node, key, value


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

    def stopping(self, status: int = 0) -> None:
        """The shutdown is under way: every later signal is ignored, and the watchdog ends the
        process with ``status`` if the shutdown takes longer than ``STOP_DEADLINE_S``."""
        self._status = status
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

    def _watchdog(self):
        try:
            self._read.recv(1)
        except OSError:
            return
        if not self._finished.wait(STOP_DEADLINE_S):
            self.exit(self._status)


if __name__ == '__main__':
    sys.exit(main())
