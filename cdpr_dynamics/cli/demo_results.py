"""What ``cdpr_demo`` received and what it says about it: the predictions matched by stamp,
the cable tensions under the load (slack or not), the node's input counts, the FRF along the
load. Plain numpy on what arrived; no ROS here."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Received:
    """What the demo received: ``predictions`` {stamp ns: (receive s, ux, uy, uz)}, ``poses``
    {stamp ns: (x, y, z, qx, qy, qz, qw)} (predicted_pose), ``tensions`` [(stamp s, T...)]."""

    predictions: dict
    poses: dict
    tensions: list


def status_count(status: dict | None, key: str) -> int | None:
    """The integer value ``key`` of a status (:func:`msg_adapters.diagnostics.read_statuses`
    form), or None where the status or the value is missing."""
    try:
        return int(status['values'][key])
    except (TypeError, KeyError, ValueError):
        return None


@dataclass(frozen=True)
class TensionEstimate:
    """Cable tensions under the load, T_i(t) = T_i^static(t) + dT_i(q(t)): the node's
    ``cable_tensions`` in force at each prediction's stamp plus the quasi-static change
    :func:`~cdpr_dynamics.dynamics.system.tension_change` of the predicted platform motion q (the
    model linearised at the initial pose: on the paper robot the 5 cm circle changes dT by up
    to 5.4 %, checked at its far point).
    ``t_s`` (nt,) s from t0, ``static_n`` and ``total_n`` (nt, n) N."""

    t_s: np.ndarray
    static_n: np.ndarray
    total_n: np.ndarray
    tension_min_n: float

    @property
    def lowest(self) -> tuple[float, int, float]:
        """(lowest tension N, its cable, its time s)."""
        k, i = np.unravel_index(np.argmin(self.total_n), self.total_n.shape)
        return float(self.total_n[k, i]), int(i), float(self.t_s[k])

    @property
    def slack(self) -> np.ndarray:
        """(nt, n) True where a cable would carry no tension (T <= 0)."""
        return self.total_n <= 0.0

    def sentence(self) -> str:
        low, cable, at = self.lowest
        slack = self.slack
        if slack.any():
            cables = ', '.join(str(i) for i in np.flatnonzero(slack.any(axis=0)))
            return (f'the load slackens cable(s) {cables}: lowest tension {low:.1f} N (cable '
                    f'{cable} at {at:.2f} s), a cable slack {slack.any(axis=1).mean():.0%} of '
                    'the time (the linear prediction does not hold while a cable is slack)')
        if low < self.tension_min_n:
            return (f'no cable slackens, but cable {cable} dips to {low:.1f} N at {at:.2f} s, '
                    f'below tension.min_n {self.tension_min_n:g} N')
        return f'no cable slackens: lowest tension {low:.1f} N (cable {cable} at {at:.2f} s)'


def _platform_motion(settings, options, got: Received, stamps) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, q (nt, ndof)) of the predictions received: the centroid's translation (the
    reported point's displacement less theta x R r for ``node.output_point_m`` r) and, for a
    rigid platform, the small rotation theta = rotvec(q_pred q_cmd^-1) of ``predicted_pose``."""
    from scipy.spatial.transform import Rotation
    u = np.array([got.predictions[s][1:] for s in stamps]).reshape(-1, 3)
    if settings.robot.point_mass:
        return stamps, u
    keep = np.array([s in got.poses for s in stamps], dtype=bool)
    stamps, u = stamps[keep], u[keep]
    quat = np.array([got.poses[s][3:] for s in stamps]).reshape(-1, 4)
    commanded = Rotation.from_matrix(settings.initial_rotation)
    theta = (Rotation.from_quat(quat) * commanded.inv()).as_rotvec() if quat.size else quat[:, :3]
    arm = settings.initial_rotation @ np.asarray(options['node.output_point_m'], dtype=float)
    return stamps, np.hstack([u - np.cross(theta, arm), theta])


def tension_estimate(settings, options, got: Received, t0_ns: int) -> TensionEstimate | str:
    """:class:`TensionEstimate` of the predictions received, or the reason there is none."""
    from cdpr_dynamics.analysis.pipeline import AnalysisError, build_system, equilibrium
    from cdpr_dynamics.dynamics.system import DynamicsError, tension_change
    stamps = np.array(sorted(got.predictions), dtype=np.int64)
    rows = sorted(got.tensions)
    if not stamps.size or not rows:
        return 'no predictions or no cable_tensions received'
    stamps, q = _platform_motion(settings, options, got, stamps)
    try:
        system = build_system(settings, equilibrium(settings))
    except (AnalysisError, DynamicsError, ValueError) as exc:
        return f'tension estimate unavailable: {exc}'
    rows = np.array(rows)
    k = np.clip(np.searchsorted(rows[:, 0], stamps * 1e-9, side='right') - 1, 0, None)
    static = rows[k, 1:]
    return TensionEstimate((stamps - t0_ns) * 1e-9, static, static + tension_change(system, q),
                           settings.tension_min_n)


def input_sentence(what: str, sent: int, status: dict | None) -> str:
    """'N published, A accepted by the node, R rejected (kinds; last reason)' from the node's
    ``<what> input`` diagnostics."""
    if status is None:
        return f'{what}: {sent} published; the node reported no counts'
    values = status['values']
    accepted, rejected = status_count(status, 'accepted'), status_count(status, 'rejected') or 0
    text = f'{what}: {sent} published, {accepted} accepted by the node, {rejected} rejected'
    if rejected:
        kinds = ', '.join(f'{k[len("rejected_"):]} {v}' for k, v in values.items()
                          if k.startswith('rejected_'))
        text += f' ({kinds}; last: {values.get("last_rejection", "?")})'
    lost = sent - (accepted or 0) - rejected
    if lost > 0:
        text += (f', {lost} not taken by the node (dropped from its queue while it was busy; '
                 f'load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)')
    return text


def along(frf: dict, direction: np.ndarray) -> np.ndarray:
    """|u . d| (..., per frequency) of the FRF's complex translations u_k = A_k e^{i phi_k}
    (k = x, y, z) along the unit vector ``direction`` d."""
    u = sum(d * frf[f'amplitude_{k}_m'] * np.exp(1j * frf[f'phase_{k}_rad'])
            for d, k in zip(direction, 'xyz'))
    return np.abs(u)
