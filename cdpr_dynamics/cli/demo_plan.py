"""The scripted controller of ``cdpr_demo``: its load, its path, its stamps, its process.

The load is the config's ``frf.force_n`` and (rigid platform) ``frf.moment_nm`` as a harmonic
wrench W(t) = W0 sin(2 pi f t), ``--amplitude-n`` rescaling it to a force of that magnitude; the
path a slow circle through the initial position; the stamps t0 + k T in integer nanoseconds.
:func:`controller_main` is the second process the demo starts (``cdpr_demo --controller``): it
takes its first stamp only once its publishers see the subscribers it was told to expect.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.analysis.config import (
    ConfigError, node_options, read_params_file, settings_from_params)

#: after the controller's publishers see every subscriber, the subscribers' side of the match
#: (discovery is symmetric but not simultaneous) is given this long before the first stamp
START_MARGIN_S = 0.25


class DemoError(RuntimeError):
    """A demo that cannot go on; the message is one line."""


def read_config(path):
    """(settings, node options) of a params file; ConfigError -> DemoError (one line)."""
    try:
        flat = read_params_file(path)
        return settings_from_params(flat), node_options(flat)
    except ConfigError as exc:
        raise DemoError(str(exc)) from None


@dataclass(frozen=True)
class Load:
    """The harmonic wrench W(t) = (F0, M0) sin(2 pi f t): ``force_n`` F0 (3,) N, ``moment_nm``
    M0 (3,) N m about the centroid, ``excitation_hz`` f (Hz); ``axis`` the force's direction
    where F0 = 0 (the config's, before ``--amplitude-n 0``)."""

    force_n: np.ndarray
    moment_nm: np.ndarray
    excitation_hz: float
    axis: tuple = (0.0, 0.0, 1.0)

    @property
    def amplitude_n(self) -> float:
        """|F0| (N)."""
        return float(np.linalg.norm(self.force_n))

    @property
    def direction(self) -> np.ndarray:
        """F0 / |F0| (``axis`` where F0 = 0)."""
        norm = self.amplitude_n
        return self.force_n / norm if norm > 0 else np.asarray(self.axis, dtype=float)

    def at(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """(force (..., 3) N, moment (..., 3) N m) at times ``t_s`` (s)."""
        s = np.sin(2 * np.pi * self.excitation_hz * np.asarray(t_s, dtype=float))[..., None]
        return s * self.force_n, s * self.moment_nm


def demo_load(settings, amplitude_n: float | None, excitation_hz: float) -> Load:
    """The config's ``frf.force_n`` and (rigid platform) ``frf.moment_nm``; ``amplitude_n``
    (N, >= 0) rescales both so that |F0| = amplitude_n, keeping the direction."""
    force = np.asarray(settings.frf_force_n, dtype=float)
    moment = (np.zeros(3) if settings.robot.point_mass
              else np.asarray(settings.frf_moment_nm, dtype=float))
    if amplitude_n is not None:
        norm = float(np.linalg.norm(force))
        if norm == 0.0:
            raise DemoError('--amplitude-n sets the size of frf.force_n, which is zero in this '
                            'config: give frf.force_n a direction')
        axis = tuple(force / norm)
        force, moment = force * (amplitude_n / norm), moment * (amplitude_n / norm)
        return Load(force, moment, excitation_hz, axis)
    return Load(force, moment, excitation_hz)


def _quaternion(settings) -> np.ndarray:
    """The config's initial orientation as (qx, qy, qz, qw)."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(settings.initial_rotation).as_quat()


class Trajectory:
    """The scripted controller's plan: a circle through the start point at the initial
    orientation, and the harmonic load."""

    def __init__(self, settings, args):
        self.centre = settings.initial_position_m
        self.quaternion = _quaternion(settings)
        self.load = demo_load(settings, args.amplitude_n, args.excitation_hz)
        self.args = args

    def position(self, t: float) -> np.ndarray:
        omega = 2 * np.pi / self.args.duration
        r = self.args.radius
        return self.centre + r * np.array([np.cos(omega * t) - 1.0, np.sin(omega * t), 0.0])

    def amplitude_limit_n(self, settings, poses: int = 16) -> float | None:
        """The largest |F0| (N) along the load's direction (its moment scaled with it) that
        the node's wrench set (:func:`~cdpr_dynamics.analysis.live.wrench_set_at`, the tension box)
        holds with both signs at ``poses`` points of the circle: the least
        :meth:`~cdpr_dynamics.mechanics.feasibility.WrenchSet.symmetric_limit` over them; 0 where a
        pose itself has no feasible tensions, None for a load without force."""
        from cdpr_dynamics.analysis.pipeline import AnalysisError, equilibrium
        from cdpr_dynamics.analysis.live import wrench_set_at
        amplitude = self.load.amplitude_n
        if amplitude == 0.0:
            return None
        limits = []
        for t in np.linspace(0.0, self.args.duration, poses, endpoint=False):
            try:
                eq = equilibrium(settings, self.position(t), settings.initial_rotation,
                                 method=settings.method)
            except AnalysisError:
                return 0.0
            limits.append(wrench_set_at(settings, eq).symmetric_limit(self.load.force_n,
                                                                      self.load.moment_nm))
        return amplitude * min(limits)


def period_ns(rate_hz: float) -> int:
    """The controller's message period (integer ns)."""
    return int(round(1e9 / rate_hz))


def stamps_ns(t0_ns: int, count: int, rate_hz: float) -> np.ndarray:
    """Stamps (ns) of the controller's first ``count`` messages at ``rate_hz``:
    t0 + k T, T = round(1e9 / rate) ns."""
    return t0_ns + period_ns(rate_hz) * np.arange(count, dtype=np.int64)


def controller_main(args) -> int:
    """The controller process: waits until its publishers see ``args.subscribers`` subscribers
    each (the node, the recorder), prints a JSON line with its ``t0_ns`` and those counts, then
    publishes poses and wrenches paced by the wall clock and prints a JSON line of what it sent.
    """
    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    from msg_adapters.pose import pose_message
    from msg_adapters.validation import ns_to_stamp
    from msg_adapters.wrench import wrench_message

    settings, _ = read_config(args.config)
    plan = Trajectory(settings, args)
    frame = settings.robot.frame_id
    rclpy.init()
    node = Node('cdpr_demo_controller')
    pose_pub = node.create_publisher(PoseStamped, 'pose', qos_profile_sensor_data)
    wrench_pub = node.create_publisher(WrenchStamped, 'wrench', qos_profile_sensor_data)
    deadline = time.monotonic() + args.timeout
    while min(pose_pub.get_subscription_count(),
              wrench_pub.get_subscription_count()) < args.subscribers:
        if time.monotonic() > deadline:
            print(f'after {args.timeout:g} s pose has '
                  f'{pose_pub.get_subscription_count()} and wrench '
                  f'{wrench_pub.get_subscription_count()} of the {args.subscribers} subscribers '
                  'expected (dynamics_node and the recorder)', file=sys.stderr)
            return 1
        rclpy.spin_once(node, timeout_sec=0.02)
    matched = {'pose': pose_pub.get_subscription_count(),
               'wrench': wrench_pub.get_subscription_count()}
    t0_ns = time.time_ns() + int(START_MARGIN_S * 1e9)
    print(json.dumps({'t0_ns': t0_ns, 'matched': matched}), flush=True)
    n_w = int(round(args.duration * args.wrench_rate))
    n_p = int(round(args.duration * args.pose_rate))
    w_stamps = stamps_ns(t0_ns, n_w, args.wrench_rate)
    p_stamps = stamps_ns(t0_ns, n_p, args.pose_rate)
    forces, moments = plan.load.at((w_stamps - t0_ns) * 1e-9)
    sent_w = sent_p = 0
    first = None
    late = np.zeros(n_w)
    while sent_w < n_w:
        now = time.time_ns()
        # what is due, in stamp order (a pose before the wrench of its stamp), also when this
        # process runs behind: a pose published before older wrenches would reach the node
        # first, and it would predict them with the pose stamped after them
        while sent_p < n_p and p_stamps[sent_p] <= min(now, w_stamps[sent_w]):
            pose_pub.publish(pose_message(plan.position((p_stamps[sent_p] - t0_ns) * 1e-9),
                                          plan.quaternion, frame,
                                          ns_to_stamp(int(p_stamps[sent_p]))))
            sent_p += 1
        while (sent_w < n_w and w_stamps[sent_w] <= now
               and (sent_p == n_p or w_stamps[sent_w] < p_stamps[sent_p])):
            if first is None:
                first = {'pose': pose_pub.get_subscription_count(),
                         'wrench': wrench_pub.get_subscription_count()}
            wrench_pub.publish(wrench_message(forces[sent_w], moments[sent_w], frame,
                                              ns_to_stamp(int(w_stamps[sent_w]))))
            late[sent_w] = (time.time_ns() - w_stamps[sent_w]) * 1e-6
            sent_w += 1
        due = min(w_stamps[sent_w] if sent_w < n_w else np.inf,
                  p_stamps[sent_p] if sent_p < n_p else np.inf)
        if due < np.inf:
            time.sleep(max(0.0, (due - time.time_ns()) * 1e-9))
    node.destroy_node()
    rclpy.try_shutdown()
    print(json.dumps({'wrenches': sent_w, 'poses': sent_p, 'subscribers_at_first_wrench': first,
                      'publish_delay_ms_p50': float(np.percentile(late, 50)),
                      'publish_delay_ms_p99': float(np.percentile(late, 99))}), flush=True)
    return 0
