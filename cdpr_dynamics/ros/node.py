"""``dynamics_node``: live vibration prediction of a CDPR beside its controller.

    ros2 run cdpr_dynamics dynamics_node --ros-args --params-file config/paper_cdpr.yaml

Subscribes ``pose`` (PoseStamped) and ``wrench`` (WrenchStamped), sensor-data QoS; publishes
``predicted_displacement`` (Vector3Stamped, stamped with the wrench's stamp) and
``predicted_pose`` (PoseStamped, same stamp) of ``node.output_point_m``, ``cable_tensions``
(JointState: position = length m, effort = tension N; transient local, one per accepted pose)
``cdpr_markers`` (MarkerArray of :mod:`msg_adapters.markers`, transient local: at start and
after rebuilds, the displacement arrow too, at most every diagnostics tick) and ``/diagnostics``;
serves ``frequency_response`` (rcl_interfaces/srv/GetParameters).

This module wires ROS to :class:`cdpr_dynamics.analysis.live.LivePredictor` (the same core as
``cdpr_replay``); the node's other roles are modules of their own: its parameters
(:mod:`~cdpr_dynamics.ros.parameters`), the ``frequency_response`` server
(:mod:`~cdpr_dynamics.ros.frf_server`), ``/diagnostics``
(:mod:`~cdpr_dynamics.ros.diagnostics`), the worker process of the slow analyses
(:mod:`~cdpr_dynamics.ros.worker`), the process with its threads and signals
(:mod:`~cdpr_dynamics.ros.process`), and every use of rclpy beyond its public API
(:mod:`~cdpr_dynamics.ros.rclpy_compat`). Every message conversion and content check is in
``msg_adapters``. A bad input is rejected with a reason (diagnostics and a throttled log line)
and the node carries on with its last good state.

Limits: stamps never latch the node (:mod:`msg_adapters.stamps`, timed against this node's
clock); each wrench costs at most ``node.max_steps_per_wrench`` Newmark steps; the service
refuses oversized requests before any work and queues ``node.frf_queue_depth`` calls; the
limits are read-only; a ``set_parameters`` request applies all or none; user strings are
echoed cut.
"""
from __future__ import annotations

import dataclasses
import functools
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped, WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import MarkerArray

from cdpr_dynamics.analysis.config import ConfigError, node_options, settings_from_params
from cdpr_dynamics.analysis.controller import length_offsets, mode_labels
from cdpr_dynamics.analysis.live import LivePredictor, PoseUpdate
from cdpr_dynamics.analysis.pipeline import damping_for, damping_warnings
from cdpr_dynamics.mechanics.robot import quaternion_to_matrix
from cdpr_dynamics.ros import budget, diagnostics
from cdpr_dynamics.ros.diagnostics import InputHealth, Timings
from cdpr_dynamics.ros.frf_server import FrfServer
from cdpr_dynamics.ros.parameters import IO_SUFFIX, NODE_NAME, changed, declare_parameters, plain
from cdpr_dynamics.ros.rclpy_compat import make_set_parameters_atomic, take_next
from cdpr_dynamics.ros.worker import BackgroundStatics, StaticsRequest, Worker, modes_job
from msg_adapters import diagnostics as diag
from msg_adapters.arrays import shaper_message, table_message
from msg_adapters.displacement import displacement_message, fill_displacement
from msg_adapters.joint_state import length_offsets_message, tensions_message
from msg_adapters.markers import equilibrium_markers, update_arrow
from msg_adapters.pose import fill_pose, pose_message
from msg_adapters.inputs import NUMERIC_ERRORS, InputHandler, first_line
from msg_adapters.stamps import StampPolicy, handle_in_stamp_order
from msg_adapters.validation import (InvalidMessage, clip, clock_ns, ns_to_stamp, s_to_stamp,
                                     stamp_to_ns)

CHANGE_PERIOD_S = 0.1
NAME_CHECK_S = 1.0         # the graph is searched for a namesake this often
NAME_WINDOW_S = 10.0       # a namesake found within this long of the start: this node is
#                            the newcomer (discovery takes seconds on a loaded machine)
NAME_TOPICS = ('/rosout', '/parameter_events')  # a node is counted by its publishers here (every
#                            rclpy and rclcpp node has them unless told otherwise)
OUTPUT_DEPTH = 1000      # predictions kept for a reliable subscriber that lags: 1 s at 1 kHz
#                          (a depth of 10 drops what a subscriber busy for 10 ms has not taken)
MARKERS_PERIOD_S = 0.5    # markers of a new equilibrium at most this often (milliseconds each)
CONTROLLER_PARAMETERS = ('node.shaper', 'node.shaper_modes', 'node.notch_sample_rate_hz',
                         'node.output_point_m')
NOTCH_LABELS = ('b0', 'b1', 'b2', 'a0', 'a1', 'a2')
MODES_PERIOD_S = 0.5      # modes refreshed after rebuilds at most this often (a moving pose
#                           rebuilds at 50 Hz and more; its modes change slowly)
MODES_DUTY = 0.1          # and at most this share of a core: a refresh that took 0.5 s (the
#                           heavy-sag 6-DOF robot at fem_sag 16) waits 5 s for the next
INLINE_MODES_S = 0.002    # modes that took at most this are computed in the pose's callback
#                           (no worker round trip: vibration_modes within ms of the pose)


def nodes_named(node: Node, name: str, namespace: str) -> int:
    """How many live nodes the graph seen by ``node`` holds with this name and namespace: their
    publishers on whichever of NAME_TOPICS has more of them. Not the graph's node list: beside
    busy cores Fast DDS can keep a node that has left in a peer's node list for good (a fresh
    participant no longer lists it), while its endpoints leave the graph with its participant."""
    return max(sum(1 for info in node.get_publishers_info_by_topic(topic)
                   if (info.node_name, info.node_namespace) == (name, namespace))
               for topic in NAME_TOPICS)


def _locked(method):
    """Run a callback under the node's lock: the pose and wrench callbacks (main thread) and
    the parameter, service, guard and timer callbacks (the services thread) share the
    predictor."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self.lock:
            return method(self, *args, **kwargs)
    return wrapper


class DynamicsNode(Node):
    """The ``cdpr_dynamics`` node: see the module docstring."""

    def __init__(self, io_arguments: list | None = None, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        # the pose and wrench path's own node, spun alone (see cdpr_dynamics.ros.process); one
        # lock keeps its callbacks and those of this node (parameters, service, timer) apart
        self.lock = threading.RLock()
        self.io = Node(f'{self.get_name()}{IO_SUFFIX}', namespace=self.get_namespace(),
                       context=self.context, cli_args=io_arguments,
                       use_global_arguments=io_arguments is None,
                       start_parameter_services=False, enable_rosout=False)
        self.flat = declare_parameters(self)
        node_options(self.flat)          # node.* values and choices, as the tools check them
        self.settings = settings_from_params(self.flat)
        self.frame_id = self.settings.robot.frame_id
        self._node_clock = self.get_clock()
        self.predictor = LivePredictor(self.settings, self.flat['node.pose_tolerance_m'],
                                       self.flat['node.angle_tolerance_rad'],
                                       self.flat['node.slack'])
        self.revision = 0                      # bumps whenever the model state changes
        self._rebuilds = 0
        self.predictor.max_steps_per_wrench = self.flat['node.max_steps_per_wrench']
        self.inputs = InputHandler(self.predictor, self.frame_id,
                                   self.flat['node.quaternion_tolerance'],
                                   StampPolicy.from_options(self.flat))
        self._step_warnings: list[str] = []
        self._pose_stamp = None
        self._held_pose = None
        self.timings = Timings()
        self._modal_warnings: list[str] = []
        self._budget_warnings: list[str] = []     # a setting over the node's means
        self._name_warnings: list[str] = []       # a namesake in the graph
        self._shaping_skipped: list[str] = []
        self._logged_warning_kinds = None
        self._lowest_hz = float('nan')
        self._platform_hz = np.zeros(0)     # classified platform modes up to frf.f_max_hz
        self._modal_stale = False           # a rebuild since: refreshed before diagnostics
        self._worker = Worker()             # FRF calls and modes refreshes, off the executor
        self._modes_future = None
        self._modes_asked = -np.inf
        self._modes_period_s = MODES_PERIOD_S
        self._modes_seconds = np.inf        # what the last modes job took
        self._rebuild_stamp_ns = 0          # the pose whose model is in use (0: the initial)
        self._modes_stamp_ns = 0            # the pose whose model the modes job had
        self._controller_outputs = None     # the start's, published once the publishers exist
        # node.rebuild: worker: the statics of moved poses in a process of their own
        self._background = (BackgroundStatics(self._wake)
                            if self.flat['node.rebuild'] == 'worker' else None)
        self._settings_token = 0            # bumps with the analysis settings
        self._parameters_revision = 0       # bumps with every parameter change
        self._modes_parameters = 0          # the parameters_revision the modes job had
        logger = self.get_logger()
        self.pose_health = InputHealth(logger.get_child('pose'), diag.ERROR)
        self.wrench_health = InputHealth(logger.get_child('wrench'), diag.WARN)
        self._update_modal()
        self._warm_up()
        self._check_budget()

        def sensor(depth):
            return QoSProfile(history=qos_profile_sensor_data.history, depth=depth,
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
        self.modes_pub = self.create_publisher(Float64MultiArray, 'vibration_modes', latched)
        self.shaper_pub = self.create_publisher(Float64MultiArray, 'input_shaper', latched)
        self.notch_pub = self.create_publisher(Float64MultiArray, 'notch_filter', latched)
        self.offsets_pub = self.create_publisher(JointState, 'cable_length_offsets', latched)
        self._markers_arrow = None
        self._markers = None
        self._markers_stale = False
        self._markers_built = -np.inf
        self.pose_sub = self.io.create_subscription(
            PoseStamped, 'pose', self.on_pose, sensor(self.flat['node.pose_queue_depth']))
        self.wrench_sub = self.io.create_subscription(
            WrenchStamped, 'wrench', self.on_wrench, sensor(self.flat['node.wrench_queue_depth']))
        subs = (self.pose_sub, self.wrench_sub)
        self._input_takes = [functools.partial(take_next, sub) for sub in subs]
        self._input_handles = (self._handle_pose, self._handle_wrench)
        self._input_budget = sum(sub.qos_profile.depth for sub in subs)
        self.frf = FrfServer(self, self._worker, self._wake, self._own_modes)
        self._worker_guard = self.create_guard_condition(self._on_worker_done)
        self.add_on_set_parameters_callback(self.on_set_parameters)
        make_set_parameters_atomic(self)

        self.diag_dirty = True
        self._diag_last = -np.inf
        self._diag_timer = self.create_timer(CHANGE_PERIOD_S, self.on_diagnostics_timer)
        self._started = time.monotonic()
        self._name_timer = self.create_timer(NAME_CHECK_S, self._check_name)
        self._publish_tensions(self.get_clock().now().to_msg())
        if self._controller_outputs is not None:
            self._publish_controller(self._controller_outputs)
        self._publish_markers(self.predictor.prediction().displacement_m
                              * self.flat['node.marker_scale'], self.predictor.settings,
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

    @_locked
    def on_set_parameters(self, params) -> SetParametersResult:
        """Validate a runtime change as a whole, apply it, or reject it with the reason.

        Parameters not of this package (``use_sim_time``, ...) are left to rclpy."""
        params = [p for p in params if p.name in self.flat]
        if not params:
            return SetParametersResult(successful=True)
        try:
            flat, settings, analysis_changed = changed(self.flat, params)
            if analysis_changed:
                update = self.predictor.set_settings(settings)
                refused = self._over_budget()
                if refused:
                    self.predictor.set_settings(self.settings)
                    raise ConfigError(f'refused: {refused}')
                self._settings_token += 1
        except NUMERIC_ERRORS as exc:
            reason = first_line(exc)
            self.get_logger().warning(f'parameter change rejected: {reason}')
            return SetParametersResult(successful=False, reason=reason)
        except Exception as exc:  # never let a parameter change take the node down
            reason = f'{type(exc).__name__}: {first_line(exc)}'
            self.get_logger().error(f'parameter change rejected: {reason}')
            return SetParametersResult(successful=False, reason=reason)
        self.flat, self.settings = flat, settings
        self._parameters_revision += 1
        self.frf.cache.clear()
        self.predictor.pose_tolerance_m = flat['node.pose_tolerance_m']
        self.predictor.angle_tolerance_rad = flat['node.angle_tolerance_rad']
        self.inputs.quaternion_tolerance = flat['node.quaternion_tolerance']
        self.inputs.policy = StampPolicy.from_options(flat)
        self.predictor.set_slack(flat['node.slack'])
        if any(p.name in CONTROLLER_PARAMETERS for p in params):
            self._modal_stale = True         # vibration_modes, shapers: the next refresh
        if analysis_changed:
            self._budget_warnings = []
            self._rebuilt(update)
            self._publish_tensions(self._pose_stamp or self.get_clock().now().to_msg())
            self.get_logger().info(
                'parameters ' + ', '.join(f'{p.name}={clip(plain(p.value))}' for p in params)
                + f': {update.method} model, {update.dofs} DOFs')
        self.diag_dirty = True
        return SetParametersResult(successful=True)

    def _over_budget(self) -> str:
        """Why one wrench on the model in use costs more than the wrenches' period ('')."""
        period_s, measured = budget.wrench_period_s(self.timings.wrench_times)
        return budget.over_budget(budget.wrench_cost_s(self.predictor, period_s), period_s,
                                  measured)

    def _check_budget(self) -> None:
        """At start: a configuration over the node's means is a model warning (no wrench has
        come yet; a runtime change over them is refused, :meth:`on_set_parameters`)."""
        reason = self._over_budget()
        self._budget_warnings = [f'over budget: {reason}'] if reason else []

    def _check_name(self) -> None:
        """Every NAME_CHECK_S: another node of this name and namespace in the graph is a
        warning (on both nodes, cleared when it leaves); a newcomer (this node found it within
        NAME_WINDOW_S of its start) with ``node.unique_name: refuse`` ends instead."""
        same = nodes_named(self, self.get_name(), self.get_namespace())
        if (same >= 2) == bool(self._name_warnings):
            return
        self.diag_dirty = True
        if same < 2:
            self._name_warnings = []
            self.get_logger().info(f'no other node named {self.get_fully_qualified_name()} '
                                   'any more')
            return
        text = (f'another node named {self.get_fully_qualified_name()} is running: each '
                'input would be predicted twice and set_parameters reach either')
        if (self.flat['node.unique_name'] == 'refuse'
                and time.monotonic() - self._started <= NAME_WINDOW_S):
            raise ConfigError(f'{text} (node.unique_name: refuse)')
        self._name_warnings = [f'name: {text}']
        self.get_logger().warning(text)

    # -------------------------------------------------------------------------- inputs

    def on_pose(self, msg: PoseStamped) -> None:
        """Handle the pose and the inputs waiting behind it (see :meth:`_take_inputs`)."""
        self._take_inputs(msg, None)

    def on_wrench(self, msg: WrenchStamped) -> None:
        """Handle the wrench and the inputs waiting behind it (see :meth:`_take_inputs`)."""
        self._take_inputs(None, msg)

    def _take_inputs(self, pose, wrench) -> None:
        """Handle the message taken and the poses and wrenches already waiting (bounded), in
        stamp order: a node that runs behind still predicts each wrench with the model of the
        last pose stamped at or before it, as the inputs were sent. One round trip through the
        wait set costs more than a prediction, so a burst is taken in one go: up to both
        queues' depth (beyond that the node receives more than it can handle, and the queues
        drop inputs)."""
        handle_in_stamp_order((pose, wrench), self._input_takes, self._input_handles,
                              self._input_budget)

    @_locked
    def _handle_pose(self, msg: PoseStamped) -> None:
        """Move the model to the pose; rebuild only when it moved more than the tolerance."""
        background = self._background is not None
        try:
            update = self.inputs.pose(msg, clock_ns(self._node_clock),
                                      self._hold_pose if background else None)
        except InvalidMessage as exc:
            self._reject(self.pose_health, exc.kind, str(exc))
            return
        self._pose_stamp = ns_to_stamp(self.inputs.last_pose_ns)
        if self.pose_health.accept(self.inputs.late_by_ns):
            self.diag_dirty = True
        if self.inputs.notice:
            self.diag_dirty = self.pose_health.warn('clock', self.inputs.notice)
        if update.rebuilt:
            self._rebuilt(update, self.inputs.last_pose_ns)
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
                self._rebuilt(update, stamp_to_ns(request.stamp))
                self.timings.swap_s.append(time.monotonic() - request.asked_s)
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
        out = self.predictor.prediction(self.flat['node.output_point_m'])
        fill_displacement(self._displacement_msg, out.displacement_m, stamp)
        fill_pose(self._pose_msg, out.position_m, out.quaternion, stamp)
        computed = time.perf_counter()
        self.displacement_pub.publish(self._displacement_msg)
        if self.pose_pub.get_subscription_count():    # serialising it for nobody costs
            self.pose_pub.publish(self._pose_msg)
        if self.wrench_health.accept(self.inputs.late_by_ns):
            self.diag_dirty = True
        if self.inputs.notice:
            self.diag_dirty = self.wrench_health.warn('time', self.inputs.notice)
        now = time.perf_counter()
        self.timings.compute_s.append(computed - start)
        self.timings.publish_s.append(now - computed)
        self.timings.wrench_times.append(now)

    def _reject(self, health: InputHealth, kind: str, reason: str) -> None:
        if health.reject(kind, reason):
            self.diag_dirty = True

    def _rebuilt(self, update, stamp_ns: int | None = None) -> None:
        """After a rebuild (at the pose stamped ``stamp_ns``; None: no pose, a parameter)."""
        if stamp_ns is not None:
            self._rebuild_stamp_ns = stamp_ns
        self.revision += 1
        self._rebuilds += 1
        self.frf.cache.clear()
        if self._modes_future is not None and stamp_ns is None:   # other settings: not wanted
            self._worker.cancel(self._modes_future, 'superseded by a newer model')
        self.timings.rebuild_s.append(sum(update.timings_s.values()))
        self._modal_stale = True
        if stamp_ns is not None and time.monotonic() - self._modes_asked >= self._modes_period_s:
            if self._modes_seconds <= INLINE_MODES_S and self._modes_future is None:
                self._update_modal()        # cheap modes: here, published with the pose's stamp
            else:
                self._refresh_modal()       # at once in the worker
        self.diag_dirty = True
        self._log_model_warnings()
        self._markers_stale = True        # published by the next diagnostics tick

    def _log_model_warnings(self) -> None:
        """Log the model's warnings (sag, accuracy, slack, heavy damping, fallback, time step)
        besides /diagnostics: all of them at start and whenever their set changes, and once
        when the last one clears. A warning's kind is its text before the first ':', so a
        number that moves with the pose does not repeat it."""
        warnings = (list(self.predictor.last_update.warnings) + list(self._modal_warnings)
                    + self._budget_warnings)
        kinds = frozenset(w.split(':', 1)[0] for w in warnings)
        before = self._logged_warning_kinds or frozenset()
        if kinds == before and self._logged_warning_kinds is not None:
            return
        self._logged_warning_kinds = kinds
        logger = self.get_logger()
        for warning in warnings:
            logger.warning(f'model: {warning}')
        if not warnings and before:
            logger.info(f'model: no warnings any more ({", ".join(sorted(before))} cleared)')

    def _publish_tensions(self, stamp) -> None:
        """``cable_tensions`` and ``cable_length_offsets`` of the model in use."""
        predictor = self.predictor
        eq = predictor.eq
        self.tensions_pub.publish(tensions_message(eq.geometry.cable_length_m,
                                                   eq.tensions.tension_n, stamp, self.frame_id))
        self.offsets_pub.publish(length_offsets_message(
            length_offsets(predictor.settings.robot, eq), predictor.stretch_rate_m_s(),
            predictor.cable_force_n(), stamp, self.frame_id))

    def _publish_controller(self, found: dict) -> None:
        """``vibration_modes`` and, with a shaper, ``input_shaper`` and ``notch_filter`` of a
        modes job's answer, stamped (in their layout) with the pose its model belongs to."""
        stamp_ns = found['stamp_ns']
        labels = mode_labels(found['platform_dofs'])
        self.modes_pub.publish(table_message(found['mode_table'], labels, stamp_ns))
        if 'shaper_pairs' in found:
            self.shaper_pub.publish(shaper_message(found['shaper_pairs'], stamp_ns))
            self.notch_pub.publish(table_message(
                found['notches'], NOTCH_LABELS, stamp_ns, 'notch',
                sample_rate_hz=self.flat['node.notch_sample_rate_hz']))

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
        out = self.predictor.prediction(self.flat['node.output_point_m'])
        pose_message(out.position_m, out.quaternion, self.frame_id, s_to_stamp(0.0))

    def _modes_args(self) -> tuple:
        assembly = self.predictor.system.assembly
        controller = {'point_m': tuple(self.flat['node.output_point_m']),
                      'shaper': self.flat['node.shaper'],
                      'shaper_modes': self.flat['node.shaper_modes'],
                      'sample_rate_hz': self.flat['node.notch_sample_rate_hz']}
        return (self.predictor.settings, self.predictor.eq, assembly.method,
                assembly.elements_per_cable, self.predictor.max_steps_per_wrench, controller)

    def _update_modal(self) -> None:
        """Classified modes (the lowest platform mode), damping and time-step warnings of the
        current model, computed here: at start, before the node serves anything, and after a
        pose rebuild where they take at most INLINE_MODES_S."""
        self._modal_stale = False
        self._modes_stamp_ns = self._rebuild_stamp_ns
        self._modes_asked = time.monotonic()
        try:
            found = modes_job(*self._modes_args())
            self._pace_modes(found['seconds'])
            self._apply_modes(found)
        except Exception as exc:  # noqa: BLE001 - as from the worker: reported, kept going
            self._modal_warnings = [f'natural frequencies failed: {first_line(exc)}']

    def _refresh_modal(self) -> None:
        """After a rebuild: the same in the worker process (:meth:`_take_modes` applies it),
        one job at a time; the diagnostics keep the previous model's values meanwhile. A pose
        rebuild asks at once where the pacing allows (else the diagnostics tick does), and a
        job outlived by the pose still answers, stamped with the pose it was asked for."""
        if self._modes_future is not None:
            return
        self._modal_stale = False
        self._modes_stamp_ns = self._rebuild_stamp_ns
        self._modes_parameters = self._parameters_revision
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
        if self._modes_parameters != self._parameters_revision:   # parameters changed since
            self._modal_stale = True
            return
        if found is None:
            self._modal_warnings = [error]
        else:
            self._apply_modes(found)
        self.diag_dirty = True
        self._log_model_warnings()    # damping, time step may have changed

    def _pace_modes(self, seconds: float) -> None:
        """The next refresh waits at least MODES_PERIOD_S and ``seconds`` / MODES_DUTY, so
        that refreshes taking ``seconds`` each use at most MODES_DUTY of a core."""
        self._modes_period_s = max(MODES_PERIOD_S, seconds / MODES_DUTY)
        self._modes_seconds = seconds

    def _apply_modes(self, found: dict) -> None:
        self._platform_hz = found['platform_hz']
        self._step_warnings = found['step_warnings']
        self._set_modal(found['frequency_hz'])
        self._shaping_skipped = list(found.get('skipped', ()))
        if 'mode_table' in found:
            found = dict(found, stamp_ns=self._modes_stamp_ns)
            if hasattr(self, 'modes_pub'):
                self._publish_controller(found)
            else:                                    # at start, before the publishers
                self._controller_outputs = found

    def _set_modal(self, freqs) -> None:
        freqs = np.asarray(freqs)
        self._lowest_hz = float(freqs[0]) if freqs.size else float('nan')
        damping = damping_for(self.predictor.settings, self.predictor.system)
        self._modal_warnings = damping_warnings(damping, freqs[freqs > 0]) + self._step_warnings

    # ------------------------------------------------------------ the worker's answers

    def _wake(self, _future) -> None:
        """From a worker's thread: run :meth:`_on_worker_done` on the executor."""
        try:
            self._worker_guard.trigger()
        except Exception:  # noqa: BLE001 - the node is being destroyed: nothing to answer
            pass

    def _on_worker_done(self) -> None:
        """Take the worker's modes and the background statics if they are in, then send the
        frequency_response answers that are ready."""
        with self.lock:
            self._take_modes()
            if self._background is not None:
                self._take_statics()
        self.frf.answer_ready()

    def _own_modes(self, arrays) -> None:
        """The FRF of the node's own model at its current state (a call without overrides)
        refreshes its natural frequencies and modal warnings."""
        self._platform_hz = np.asarray(arrays['platform_natural_frequencies_hz'])
        self._set_modal(arrays['natural_frequencies_hz'])

    # --------------------------------------------------------------------- diagnostics

    def on_diagnostics_timer(self) -> None:
        """Markers (those of a new equilibrium at most every MARKERS_PERIOD_S: building them
        costs milliseconds, poses come at 50 Hz and more; the arrow every tick) and
        diagnostics when something changed.
        The state is read under the lock; the messages are built and published outside it,
        so the pose and wrench thread waits for neither."""
        now = time.monotonic()
        with self.lock:
            arrow = self.predictor.prediction().displacement_m * self.flat['node.marker_scale']
            rebuilt = self._markers is None or (
                self._markers_stale and now - self._markers_built >= MARKERS_PERIOD_S)
            markers_due = rebuilt or not np.array_equal(arrow, self._markers_arrow)
            if rebuilt:
                self._markers_stale = False
                self._markers_built = now
            state = (self.predictor.settings, self.predictor.eq)
            statuses = None
            if (self.diag_dirty
                    or now - self._diag_last >= self.flat['node.diagnostics_period_s']):
                self.diag_dirty = False
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
        if (self._modes_future is not None
                and self._worker.running_s(self._modes_future) > budget.MODES_BUDGET_S):
            self._worker.cancel(self._modes_future,
                                f'over its time budget of {budget.MODES_BUDGET_S:g} s')
        self.frf.cancel_over_budget(budget.FRF_BUDGET_S)
        extra = {'rebuilds': self._rebuilds, 'rebuild': self.flat['node.rebuild']}
        if self._background is not None:
            extra['poses_superseded'] = self._background.superseded
        extra.update(self.timings.model_values())
        extra.update(self._slack_values())
        modal = {'lowest_hz': self._lowest_hz, 'platform_hz': self._platform_hz,
                 'warnings': self._slack_warnings() + self._modal_warnings
                 + self._shaping_skipped + self._budget_warnings
                 + self._name_warnings}
        return [diagnostics.model_status(name, hw, self.predictor, modal, extra),
                diagnostics.input_status(name, 'pose input', self.pose_health,
                                         {'publishers': self.pose_sub.get_publisher_count()},
                                         hw),
                diagnostics.input_status(name, 'wrench input', self.wrench_health,
                                         {'publishers': self.wrench_sub.get_publisher_count(),
                                          **self.timings.wrench_values()}, hw),
                self.frf.status(name, hw)]

    def _slack_values(self) -> dict:
        predictor = self.predictor
        return {'slack': predictor.slack,
                'slack_cables': ', '.join(map(str, predictor.slack_cables)) or 'none',
                'slack_time_s': round(predictor.slack_time_s, 6)}

    def _slack_warnings(self) -> list[str]:
        """The slack cables at the last wrench, as a warning (empty when all are taut)."""
        predictor = self.predictor
        if not predictor.slack_cables:
            return []
        cables = ', '.join(map(str, predictor.slack_cables))
        if predictor.slack == 'aware':
            return [f'slack: cable(s) {cables} slack, the compression-free model predicts '
                    f'({predictor.slack_time_s:.3f} s slack in total)']
        return [f'slack: cable(s) {cables} would be slack, the linear prediction does not hold '
                f'(node.slack: linear; {predictor.slack_time_s:.3f} s in total)']
