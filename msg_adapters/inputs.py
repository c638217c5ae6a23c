"""The node's input handling without ROS: pose and wrench messages in, library calls out.

``dynamics_node`` and ``cdpr_replay`` both accept inputs through :class:`InputHandler`, so a
replay rejects exactly what the node rejects and predicts exactly what it predicts.
"""
from __future__ import annotations

import numpy as np

from cdpr_dynamics.analysis.pipeline import AnalysisError
from cdpr_dynamics.analysis.config import ConfigError
from cdpr_dynamics.dynamics.system import DynamicsError
from cdpr_dynamics.analysis.live import LivePredictor, PoseUpdate
from cdpr_dynamics.mechanics.robot import quaternion_to_matrix
from msg_adapters.pose import check_pose, pose_fields
from msg_adapters.stamps import StampClock, StampPolicy
from msg_adapters.validation import InvalidMessage, clip
from msg_adapters.wrench import check_wrench, wrench_fields

#: Failures of the numerics on a state: the input is rejected, the last good state kept.
NUMERIC_ERRORS = (AnalysisError, ConfigError, DynamicsError, ValueError, np.linalg.LinAlgError)


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name if it has none)."""
    text = str(exc).strip()
    return clip(text.splitlines()[0], 2000) if text else type(exc).__name__


def _late_by(stamp, other_ns: int | None, at_equal: bool) -> int | None:
    """How far ``stamp`` lies behind the other input's last stamp ``other_ns`` where it came
    out of stamp order with it (``at_equal``: equal stamps too), else None."""
    if other_ns is None or stamp.jumped:
        return None
    behind = other_ns - stamp.ns
    return behind if behind > 0 or (at_equal and behind == 0) else None


class InputHandler:
    """Pose and wrench messages through the same checks and calls as ``dynamics_node``.

    :meth:`pose` and :meth:`wrench` return the result, or raise
    :class:`~msg_adapters.validation.InvalidMessage` (``kind`` and one-line reason) where the
    input is rejected and the last good state kept: the adapters' checks (not finite, not a
    unit quaternion, another frame), the stamp policy (:mod:`msg_adapters.stamps`: unstamped,
    ahead of the node's clock ``now_ns``, out of order), a pose the model cannot use
    (``state``: outside the workspace, infeasible tensions, crossing cables), a wrench the
    cables cannot hold (``infeasible``), and (``internal``) anything unexpected.

    After an accepted input, :attr:`notice` holds a warning worth telling ('' if none): the
    sender's clock jumped back (the stream restarted at the new stamp), or the integrator
    skipped part of a long interval (``node.max_steps_per_wrench``). :attr:`last_wrench_ns`
    is the time the last wrench was taken at (its arrival time for an unstamped one).
    After an accepted pose or wrench (one at a time: :meth:`wrench_run` leaves it as it was),
    :attr:`late_by_ns` is None, or how far its stamp lies behind the last one of the other
    input where it came out of stamp order with it: a pose taken after a wrench stamped at or
    after it (0 at equal stamps; that wrench had the previous pose), a wrench taken after a
    pose stamped after it (it has the newer pose). A replay in stamp order gives those
    wrenches the other pose.
    """

    def __init__(self, predictor: LivePredictor, frame_id: str, quaternion_tolerance: float,
                 policy: StampPolicy = StampPolicy()):
        self.predictor = predictor
        self.frame_id = frame_id
        self.quaternion_tolerance = quaternion_tolerance
        self.pose_clock = StampClock('pose', policy)
        self.wrench_clock = StampClock('wrench', policy)
        self.notice = ''
        self.late_by_ns: int | None = None

    @property
    def policy(self) -> StampPolicy:
        return self.wrench_clock.policy

    @policy.setter
    def policy(self, policy: StampPolicy) -> None:
        self.pose_clock.policy = self.wrench_clock.policy = policy

    @property
    def last_pose_ns(self) -> int | None:
        return self.pose_clock.last_ns

    @property
    def last_wrench_ns(self) -> int | None:
        return self.wrench_clock.last_ns

    def pose(self, msg, now_ns: int | None = None, move=None) -> PoseUpdate:
        """Move the model to the pose; rebuilds only when it moved more than the tolerance.
        ``move(position_m, quaternion=...)``: what moves it (default the predictor's
        ``update_pose``; the node's background rebuild queues it instead)."""
        return self.pose_values(*pose_fields(msg), now_ns, move)

    def pose_values(self, stamp_ns: int, frame_id: str, values: tuple,
                    now_ns: int | None = None, move=None) -> PoseUpdate:
        """:meth:`pose` of a pose's fields (:func:`~msg_adapters.pose.pose_fields`)."""
        self.notice = ''
        try:
            pose = check_pose(stamp_ns, frame_id, values, self.frame_id,
                              self.quaternion_tolerance)
            stamp = self.pose_clock.check(pose.stamp_ns, now_ns)
            update = (move or self.predictor.update_pose)(pose.position_m,
                                                          quaternion=pose.quaternion)
        except InvalidMessage:
            raise
        except NUMERIC_ERRORS as exc:
            raise InvalidMessage(f'pose rejected: {first_line(exc)}', 'state') from None
        except Exception as exc:  # noqa: BLE001 - a bug must not stop the node: report it
            raise InvalidMessage(f'{type(exc).__name__}: {clip(exc)}', 'internal') from None
        self.pose_clock.accept(stamp)
        self.notice = stamp.note
        self.late_by_ns = _late_by(stamp, self.wrench_clock.last_ns, at_equal=True)
        return update

    def pose_still(self, stamp_ns: int, frame_id: str, values: tuple) -> bool:
        """Whether :meth:`pose_values` of this pose leaves the model as it is: a pose it
        rejects, or one within the tolerances of the current pose (no rebuild)."""
        try:
            pose = check_pose(stamp_ns, frame_id, values, self.frame_id,
                              self.quaternion_tolerance)
        except InvalidMessage:
            return True
        return not self.predictor.moved(np.asarray(pose.position_m, dtype=float),
                                        quaternion_to_matrix(pose.quaternion))

    def wrench(self, msg, now_ns: int | None = None) -> np.ndarray:
        """Advance the integrator to the wrench's time; the displacement (3,) m there."""
        return self.wrench_values(*wrench_fields(msg), now_ns)

    def wrench_values(self, stamp_ns: int, frame_id: str, values: tuple,
                      now_ns: int | None = None) -> np.ndarray:
        """:meth:`wrench` of a wrench's fields (:func:`~msg_adapters.wrench.wrench_fields`)."""
        self.notice = ''
        try:
            wrench = check_wrench(stamp_ns, frame_id, values, self.frame_id)
            stamp = self.wrench_clock.check(wrench.stamp_ns, now_ns)
            reason = self.predictor.wrench_reason(wrench.force_n, wrench.moment_nm)
            if reason:
                raise InvalidMessage(reason, 'infeasible')
            if stamp.jumped:
                self.predictor.rebase_time()
            u = self.predictor.advance(stamp.ns, wrench.force_n, wrench.moment_nm)
        except InvalidMessage:
            raise
        except NUMERIC_ERRORS as exc:
            raise InvalidMessage(f'wrench rejected: {first_line(exc)}', 'state') from None
        except Exception as exc:  # noqa: BLE001
            raise InvalidMessage(f'{type(exc).__name__}: {clip(exc)}', 'internal') from None
        self.wrench_clock.accept(stamp)
        self.late_by_ns = _late_by(stamp, self.pose_clock.last_ns, at_equal=False)
        note, skipped = stamp.note, self.predictor.notice
        self.notice = f'{note}; {skipped}' if note and skipped else note or skipped
        return u

    def wrench_run(self, stamps_ns: np.ndarray, frame_id: str,
                   values: np.ndarray) -> tuple[int, np.ndarray]:
        """:meth:`wrench_values` of the first k of a run of wrenches in one frame (stamps (m,)
        ns, values (m, 6)), without a node clock, at once: (k, the platform states (k, nd)
        after each, :meth:`LivePredictor.advance_run`'s). They are the leading wrenches that
        :meth:`wrench_values` would accept without a word (finite, in the robot's frame,
        stamped, in order, well inside the feasible set) and the predictor can take in one
        loop; k < m leaves the next one to :meth:`wrench_values`, which then accepts or
        rejects it as it would any other (and the run goes on after it)."""
        empty = np.empty((0, self.predictor.system.platform_dofs))
        if frame_id != self.frame_id or not len(stamps_ns):
            return 0, empty
        last = self.wrench_clock.last_ns
        force, moment = values[:, :3], values[:, 3:6]
        plain = (np.isfinite(values).all(axis=1) & (stamps_ns != 0)
                 & (stamps_ns >= np.maximum.accumulate(stamps_ns))
                 & self.predictor.wrenches_clear(force, moment))
        if last is not None:
            plain &= stamps_ns >= last
        count = len(stamps_ns) if plain.all() else int(plain.argmin())
        count, q = self.predictor.advance_run(stamps_ns[:count], force, moment)
        if count:
            self.notice = ''
            self.wrench_clock.last_ns = int(stamps_ns[count - 1])
        return count, q if count else empty
