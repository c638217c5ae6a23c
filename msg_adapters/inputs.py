"""The node's input handling without ROS: pose and wrench messages in, library calls out.

``dynamics_node`` and ``cdpr_replay`` both accept inputs through :class:`InputHandler`, so a
replay rejects exactly what the node rejects and predicts exactly what it predicts.
"""
from __future__ import annotations

import numpy as np

from cdpr_dynamics.analysis import AnalysisError
from cdpr_dynamics.config import ConfigError
from cdpr_dynamics.dynamics import DynamicsError
from cdpr_dynamics.live import LivePredictor, PoseUpdate
from msg_adapters.pose import read_pose
from msg_adapters.validation import InvalidMessage
from msg_adapters.wrench import read_wrench

#: Failures of the numerics on a state: the input is rejected, the last good state kept.
NUMERIC_ERRORS = (AnalysisError, ConfigError, DynamicsError, ValueError, np.linalg.LinAlgError)


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name if it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


class InputHandler:
    """Pose and wrench messages through the same checks and calls as ``dynamics_node``.

    :meth:`pose` and :meth:`wrench` return the result, or raise
    :class:`~msg_adapters.validation.InvalidMessage` (``kind`` and one-line reason) where the
    input is rejected and the last good state kept: the adapters' checks (not finite, not a
    unit quaternion, another frame, out of order), a pose the model cannot use (``state``:
    outside the workspace, infeasible tensions, crossing cables), a wrench the cables cannot
    hold (``infeasible``), and (``internal``) anything unexpected.
    """

    def __init__(self, predictor: LivePredictor, frame_id: str, quaternion_tolerance: float):
        self.predictor = predictor
        self.frame_id = frame_id
        self.quaternion_tolerance = quaternion_tolerance
        self.last_pose_ns: int | None = None
        self.last_wrench_ns: int | None = None

    def pose(self, msg) -> PoseUpdate:
        """Move the model to the pose; rebuilds only when it moved more than the tolerance."""
        try:
            pose = read_pose(msg, self.frame_id, self.quaternion_tolerance, self.last_pose_ns)
            update = self.predictor.update_pose(pose.position_m, quaternion=pose.quaternion)
        except InvalidMessage:
            raise
        except NUMERIC_ERRORS as exc:
            raise InvalidMessage(f'pose rejected: {first_line(exc)}', 'state') from None
        except Exception as exc:  # noqa: BLE001 - a bug must not stop the node: report it
            raise InvalidMessage(f'{type(exc).__name__}: {exc}', 'internal') from None
        self.last_pose_ns = pose.stamp_ns
        return update

    def wrench(self, msg) -> np.ndarray:
        """Advance the integrator to the wrench's stamp; the displacement (3,) m there."""
        try:
            wrench = read_wrench(msg, self.frame_id, self.last_wrench_ns)
            reason = self.predictor.wrench_reason(wrench.force_n, wrench.moment_nm)
            if reason:
                raise InvalidMessage(reason, 'infeasible')
            u = self.predictor.advance(wrench.stamp_ns, wrench.force_n, wrench.moment_nm)
        except InvalidMessage:
            raise
        except NUMERIC_ERRORS as exc:
            raise InvalidMessage(f'wrench rejected: {first_line(exc)}', 'state') from None
        except Exception as exc:  # noqa: BLE001
            raise InvalidMessage(f'{type(exc).__name__}: {exc}', 'internal') from None
        self.last_wrench_ns = wrench.stamp_ns
        return u
