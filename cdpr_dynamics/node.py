"""``dynamics_node``: live vibration prediction of a CDPR beside its controller (SPEC section 5).

    ros2 run cdpr_dynamics dynamics_node --ros-args --params-file config/paper_cdpr.yaml

Subscribes ``pose`` (PoseStamped) and ``wrench`` (WrenchStamped), sensor-data QoS; publishes
``predicted_displacement`` (Vector3Stamped, stamped with the wrench's stamp), ``cable_tensions``
(JointState: position = length m, effort = tension N; transient local, one per accepted pose)
and ``/diagnostics``; serves ``frequency_response`` (rcl_interfaces/srv/GetParameters).

The node only wires ROS to :class:`cdpr_dynamics.live.LivePredictor` (the same core as
``cdpr_replay``) and to :func:`cdpr_dynamics.analysis.frf_arrays`; every message conversion and
content check is in ``msg_adapters``. A bad input is rejected with a reason (diagnostics and a
throttled log line) and the node carries on with its last good state.
"""
from __future__ import annotations

import collections
import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped, WrenchStamped
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rcl_interfaces.srv import GetParameters
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data,
                       qos_profile_services_default)
from sensor_msgs.msg import JointState

from cdpr_dynamics.analysis import (AnalysisError, build_system, damping_for, damping_warnings,
                                    frf_arrays, safe)
from cdpr_dynamics.config import (NODE_PARAMETERS, PARAMETER_BY_NAME, PARAMETERS, ConfigError,
                                  Param, node_options, settings_from_params)
from cdpr_dynamics.dynamics import natural_frequencies
from cdpr_dynamics.live import LivePredictor
from msg_adapters import diagnostics as diag
from msg_adapters.displacement import displacement_message
from msg_adapters.frf_service import ARRAYS, pack_response, parse_request, settings_changes
from msg_adapters.joint_state import tensions_message
from msg_adapters.inputs import NUMERIC_ERRORS, InputHandler, first_line
from msg_adapters.validation import InvalidMessage, s_to_stamp

NODE_NAME = 'cdpr_dynamics'

#: Fixed for the life of the node: the robot itself and what is set up once.
READ_ONLY = {'robot.frame_id', 'robot.anchors', 'robot.attachments', 'robot.initial_position',
             'robot.initial_orientation', 'node.diagnostics_period_s',
             'node.wrench_queue_depth', 'node.service_introspection'}
LOG_PERIOD_S = 1.0
WRENCH_BATCH = 64         # wrenches taken per callback beyond the first
CHANGE_PERIOD_S = 0.1


def _descriptor(param: Param) -> ParameterDescriptor:
    default = param.default
    if isinstance(default, str):
        kind = ParameterType.PARAMETER_STRING
    elif isinstance(default, list):
        kind = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif isinstance(default, int):
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
        if age is not None:
            values['last_rejection_age_s'] = round(age, 3)
        return values


class DynamicsNode(Node):
    """The ``cdpr_dynamics`` node: see the module docstring."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self._flat = self._declare_parameters()
        node_options(self._flat)          # node.* values and choices, as the tools check them
        self.settings = settings_from_params(self._flat)
        self.frame_id = self.settings.robot.frame_id
        self.predictor = LivePredictor(self.settings, self._flat['node.pose_tolerance_m'],
                                       self._flat['node.angle_tolerance_rad'])
        self.revision = 0                      # bumps whenever the model state changes
        self._rebuilds = 0
        self.inputs = InputHandler(self.predictor, self.frame_id,
                                   self._flat['node.quaternion_tolerance'])
        self._pose_stamp = None
        self._rebuild_s = collections.deque(maxlen=512)
        self._compute_s = collections.deque(maxlen=4096)   # check + integrate + message
        self._publish_s = collections.deque(maxlen=4096)   # handing the prediction to DDS
        self._wrench_times = collections.deque(maxlen=8192)
        self._frf_cache = collections.OrderedDict()
        self._frf = {'calls': 0, 'cache_hits': 0, 'failures': 0, 'last_ms': 0.0,
                     'last_error': ''}
        self._modal_warnings: list[str] = []
        self._lowest_hz = float('nan')
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
        self.displacement_pub = self.create_publisher(Vector3Stamped, 'predicted_displacement',
                                                      10)
        self.tensions_pub = self.create_publisher(JointState, 'cable_tensions', latched)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.pose_sub = self.create_subscription(PoseStamped, 'pose', self.on_pose,
                                                 qos_profile_sensor_data)
        self.wrench_sub = self.create_subscription(WrenchStamped, 'wrench', self.on_wrench,
                                                   sensor)
        self.frf_service = self.create_service(GetParameters, 'frequency_response',
                                               self.on_frequency_response)
        self._configure_introspection(self._flat['node.service_introspection'])
        self.add_on_set_parameters_callback(self.on_set_parameters)

        self._diag_dirty = True
        self._diag_last = -np.inf
        self._diag_timer = self.create_timer(CHANGE_PERIOD_S, self.on_diagnostics_timer)
        self._publish_tensions(self.get_clock().now().to_msg())
        update = self.predictor.last_update
        logger.info(f'{update.method} model, {update.dofs} DOFs at '
                    f'{np.round(self.predictor.position_m, 4).tolist()} m in {self.frame_id!r}; '
                    f'waiting for pose and wrench')

    # ---------------------------------------------------------------------- parameters

    def _declare_parameters(self) -> dict:
        flat = {}
        for param in PARAMETERS + NODE_PARAMETERS:
            descriptor = _descriptor(param)
            default = param.default
            if isinstance(default, list) and not default:
                default = Parameter.Type.DOUBLE_ARRAY   # no default: must come from the file
            try:
                value = self.declare_parameter(param.name, default, descriptor).value
            except InvalidParameterTypeException as exc:
                value = self._declare_widened(param, descriptor, exc)
            except InvalidParameterValueException as exc:
                raise ConfigError(f'parameter {param.name}: {first_line(exc)}') from None
            flat[param.name] = param.default if value is None else _plain(value)
        return flat

    def _declare_widened(self, param: Param, descriptor, exc):
        """Take an integer (array) from the file for a double (array): 30 for 30.0, as the
        offline tools do; any other type mismatch is a configuration error."""
        override = getattr(self, '_parameter_overrides', {}).get(param.name)
        widen = {(ParameterType.PARAMETER_DOUBLE, Parameter.Type.INTEGER): float,
                 (ParameterType.PARAMETER_DOUBLE_ARRAY, Parameter.Type.INTEGER_ARRAY):
                 lambda v: [float(x) for x in v]}
        convert = override is not None and widen.get((descriptor.type, override.type_))
        if not convert:
            raise ConfigError(f'parameter {param.name}: {first_line(exc)}') from None
        try:
            return self.declare_parameter(param.name, convert(override.value), descriptor,
                                          ignore_override=True).value
        except InvalidParameterValueException as err:
            raise ConfigError(f'parameter {param.name}: {first_line(err)}') from None

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
        if analysis_changed:
            self._rebuilt(update)
            self._update_modal()
            self._publish_tensions(self._pose_stamp or self.get_clock().now().to_msg())
            self.get_logger().info(
                'parameters ' + ', '.join(f'{p.name}={_plain(p.value)}' for p in params)
                + f': {update.method} model, {update.dofs} DOFs')
        self._diag_dirty = True
        return SetParametersResult(successful=True)

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

    def on_pose(self, msg: PoseStamped) -> None:
        """Move the model to the pose; rebuild only when it moved more than the tolerance."""
        try:
            update = self.inputs.pose(msg)
        except InvalidMessage as exc:
            self._reject(self.pose_health, exc.kind, str(exc))
            return
        self._pose_stamp = msg.header.stamp
        if self.pose_health.accept():
            self._diag_dirty = True
        if update.rebuilt:
            self._rebuilt(update)
        self._publish_tensions(msg.header.stamp)

    def on_wrench(self, msg: WrenchStamped) -> None:
        """Handle the wrench, then those already waiting (bounded): one executor round trip
        costs more than the prediction itself, so a burst is taken in one go."""
        self._handle_wrench(msg)
        for _ in range(WRENCH_BATCH):
            msg = _take(self.wrench_sub)
            if msg is None:
                break
            self._handle_wrench(msg)

    def _handle_wrench(self, msg: WrenchStamped) -> None:
        """Advance the integrator to the wrench's stamp and publish the prediction."""
        start = time.perf_counter()
        try:
            u = self.inputs.wrench(msg)
        except InvalidMessage as exc:
            self._reject(self.wrench_health, exc.kind, str(exc))
            return
        prediction = displacement_message(u, self.frame_id, msg.header.stamp)
        computed = time.perf_counter()
        self.displacement_pub.publish(prediction)
        if self.wrench_health.accept():
            self._diag_dirty = True
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
        self._diag_dirty = True

    def _publish_tensions(self, stamp) -> None:
        eq = self.predictor.eq
        self.tensions_pub.publish(tensions_message(eq.geometry.length_m, eq.tensions.tension_n,
                                                   stamp, self.frame_id))

    def _warm_up(self) -> None:
        """One throw-away wrench so the first real one does not pay first-call costs."""
        self.predictor.wrench_reason(np.zeros(3), np.zeros(3))
        self.predictor.advance(0, np.zeros(3))
        self.predictor.advance(round(self.settings.dt_s * 1e9), np.zeros(3))
        self.predictor.reset_time()
        displacement_message(np.zeros(3), self.frame_id, s_to_stamp(0.0))

    def _update_modal(self) -> None:
        """Lowest natural frequencies and damping warnings: on start and on settings changes."""
        try:
            freqs = safe(natural_frequencies, self.predictor.system, 12)
            self._set_modal(freqs)
        except NUMERIC_ERRORS as exc:
            self._modal_warnings = [f'natural frequencies failed: {first_line(exc)}']

    def _set_modal(self, freqs) -> None:
        freqs = np.asarray(freqs)
        self._lowest_hz = float(freqs[0]) if freqs.size else float('nan')
        damping = damping_for(self.predictor.settings, self.predictor.system)
        self._modal_warnings = damping_warnings(damping, freqs[freqs > 0])

    # ------------------------------------------------------------------------- service

    def on_frequency_response(self, request, response):
        """FRF at the current pose and tensions; overrides for this call; reasons as STRING."""
        start = time.perf_counter()
        parsed = parse_request(request.names)
        self._frf['calls'] += 1
        arrays, error = None, parsed.error
        if not error and any(name in ARRAYS for name in parsed.names):
            key = (self.revision, parsed.key())
            if key in self._frf_cache:
                self._frf_cache.move_to_end(key)
                arrays, error = self._frf_cache[key]
                self._frf['cache_hits'] += 1
            else:
                try:
                    arrays = self._compute_frf(parsed.overrides)
                except NUMERIC_ERRORS as exc:
                    error = f'frequency response failed: {first_line(exc)}'
                except Exception as exc:
                    error = f'frequency response failed: {type(exc).__name__}: {exc}'
                if self._flat['node.frf_cache_size'] > 0:
                    self._frf_cache[key] = (arrays, error)
                    while len(self._frf_cache) > self._flat['node.frf_cache_size']:
                        self._frf_cache.popitem(last=False)
        if error:
            self._frf['failures'] += 1
            self._frf['last_error'] = error
            self.get_logger().warning(error, throttle_duration_sec=LOG_PERIOD_S)
        self._frf['last_ms'] = (time.perf_counter() - start) * 1e3
        self._diag_dirty = True
        return pack_response(parsed.names, arrays, error, response)

    def _compute_frf(self, overrides: dict) -> dict:
        settings = self.predictor.settings
        changes = settings_changes(overrides, settings.frf_force_n)
        n_points = changes.get('n_points', settings.n_points)
        if n_points > self._flat['node.frf_max_points']:
            raise ConfigError(f'n_points={n_points} exceeds node.frf_max_points = '
                              f'{self._flat["node.frf_max_points"]}')
        if changes:
            settings = settings.replace(**changes)
        if 'method' in changes or 'elements_per_cable' in changes:
            system = safe(build_system, settings, self.predictor.eq)
        else:       # the model the node integrates (auto's choice, or the fallback)
            system = self.predictor.system
        if not system.assembly.valid:
            raise AnalysisError(f'method {system.assembly.method} is not valid for this state: '
                                + '; '.join(system.assembly.warnings))
        arrays = safe(frf_arrays, settings, system)
        if not overrides:
            self._set_modal(arrays['natural_frequencies_hz'])
        return arrays

    # --------------------------------------------------------------------- diagnostics

    def on_diagnostics_timer(self) -> None:
        now = time.monotonic()
        if self._diag_dirty or now - self._diag_last >= self._flat['node.diagnostics_period_s']:
            self._diag_dirty = False
            self._diag_last = now
            self.diagnostics_pub.publish(self.diagnostics())

    def diagnostics(self) -> DiagnosticArray:
        """The node's DiagnosticArray: model, pose input, wrench input, frequency_response."""
        hw = self.get_fully_qualified_name()
        name = self.get_name()
        statuses = [self._model_status(name, hw)]
        for title, health, extra in (('pose input', self.pose_health, {}),
                                     ('wrench input', self.wrench_health, self._wrench_stats())):
            level, reason = health.report()
            message = reason or f'{health.accepted} accepted'
            statuses.append(diag.status_message(f'{name}: {title}', level, message,
                                                {**health.values(), **extra}, hw))
        frf_level = diag.WARN if self._frf['last_error'] else diag.OK
        statuses.append(diag.status_message(
            f'{name}: frequency_response', frf_level,
            self._frf['last_error'] or f'{self._frf["calls"]} calls', dict(self._frf), hw))
        self._frf['last_error'] = ''
        return diag.diagnostics_message(statuses, self.get_clock().now().to_msg())

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
            'sag_parameter': np.round(update.sag_parameter, 4).tolist(),
            'rebuilds': self._rebuilds,
        }
        for stage, seconds in update.timings_s.items():
            values[f'last_update_{stage}_ms'] = seconds * 1e3
        if rebuild.size:
            values['update_ms_p50'] = float(np.percentile(rebuild, 50))
            values['update_ms_p99'] = float(np.percentile(rebuild, 99))
        values['warnings'] = warnings or 'none'
        level = diag.WARN if warnings else diag.OK
        message = (f'{update.method}, {update.dofs} DOFs' + (f': {warnings[0]}' if warnings
                                                             else ''))
        return diag.status_message(f'{name}: model', level, message, values, hw)

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


def main(args=None):
    """Run the node until Ctrl-C or SIGTERM; a bad configuration exits 1 with one line."""
    try:
        rclpy.init(args=args)
    except Exception as exc:  # e.g. a parameter file rcl cannot parse
        print(f'dynamics_node: error: {first_line(exc)}', file=sys.stderr)
        return 1
    node = None
    status = 0
    try:
        node = DynamicsNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except NUMERIC_ERRORS as exc:
        print(f'dynamics_node: error: {first_line(exc)}', file=sys.stderr)
        status = 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
