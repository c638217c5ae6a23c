"""What ``cdpr_demo`` received and what it says about it: the predictions matched by stamp,
the cable tensions under the load (slack or not), the node's input counts, the FRF along the
load. Plain numpy on what arrived; no ROS here."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.mechanics.tensions import below_text


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
    """Cable tensions under the load: ``static_n`` (nt, n) N of the pose in force and
    ``total_n`` (nt, n) N the linear prediction's cable forces (:class:`SlackComparison`) at
    ``t_s`` (nt,) s from t0."""

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
            return (f'no cable slackens, but cable {cable} dips to '
                    f'{below_text(low, self.tension_min_n)} N at {at:.2f} s, '
                    f'below tension.min_n {self.tension_min_n:g} N')
        return f'no cable slackens: lowest tension {low:.1f} N (cable {cable} at {at:.2f} s)'


#: What a late pose or wrench (the node's ``late`` count) means, the most it lay behind as {}.
LATE = {'poses': 'taken after a wrench stamped at or after it (up to {:.3g} ms; that wrench had '
                 'the previous pose)',
        'wrenches': 'taken after a pose stamped after it (up to {:.3g} ms; they had the newer '
                    'pose)'}


def input_sentence(what: str, sent: int, status: dict | None) -> str:
    """'N published, A accepted by the node, R rejected (kinds; last reason)', those it took
    out of stamp order with the other input and those it never took, from the node's
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
    late = status_count(status, 'late')
    if late:
        text += f', {late} {LATE[what]}'.format(float(values['late_max_ms']))
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


@dataclass(frozen=True)
class SlackComparison:
    """The demo's inputs fed through the node's own predictor twice, ``node.slack`` aware and
    linear (:class:`~cdpr_dynamics.analysis.live.LivePredictor`, the same function as the node
    and ``cdpr_replay``): per wrench ``t_s`` (nt,) s from t0, ``stamps`` (nt,) ns, centroid
    displacements ``u_aware`` / ``u_linear`` (nt, 3) m, predicted cable forces
    ``force_aware`` / ``force_linear`` (nt, n) N (with the cables' dampers; 0 while slack for
    the aware one) and the ``static_n`` (nt, n) tensions of the pose in force."""

    t_s: np.ndarray
    stamps: np.ndarray
    u_aware: np.ndarray
    u_linear: np.ndarray
    force_aware: np.ndarray
    force_linear: np.ndarray
    static_n: np.ndarray

    @property
    def slack(self) -> np.ndarray:
        """(nt,) True where the aware prediction has a slack cable."""
        return ~(self.force_aware > 0.0).all(axis=1)

    def taut_amplitude_n(self, amplitude_n: float) -> float | None:
        """The largest load amplitude (N) whose linear cable forces stay above zero at every
        wrench of this run (the load scales the dynamic part T - T_static linearly), or None
        where the load never lowers a tension."""
        drop = self.static_n - self.force_linear
        lowered = drop > 0.0
        if amplitude_n == 0.0 or not lowered.any():
            return None
        return float(amplitude_n * np.min(self.static_n[lowered] / drop[lowered]))

    def sentence(self) -> str:
        """What the slack-aware prediction changed, in one line."""
        peak_aware = float(np.abs(self.u_aware).max())
        peak_linear = float(np.abs(self.u_linear).max())
        slack = self.slack
        if not slack.any():
            return (f'no cable slackens: the slack-aware and linear predictions agree (peak |u| '
                    f'{peak_aware * 1e3:.3f} mm)')
        cables = ', '.join(str(i) for i in np.flatnonzero((self.force_aware <= 0).any(axis=0)))
        return (f'cable(s) {cables} slack {slack.mean():.0%} of the time: slack-aware peak '
                f'|u| {peak_aware * 1e3:.3f} mm (linear {peak_linear * 1e3:.3f} mm, its lowest '
                f'cable force {self.force_linear.min():.1f} N)')


def slack_comparison(settings, options, plan, t0_ns: int, wrenches: int,
                     poses: int) -> SlackComparison:
    """:class:`SlackComparison` of the ``wrenches`` and ``poses`` the controller sent (its
    stamps and values, poses first at equal stamps, as it publishes them), those the node
    refuses left out as it leaves them out (a pose without equilibrium, a wrench the cables
    cannot hold)."""
    from cdpr_dynamics.analysis.live import LivePredictor
    from cdpr_dynamics.analysis.pipeline import AnalysisError
    from cdpr_dynamics.cli.demo_plan import stamps_ns
    args = plan.args
    w_stamps = stamps_ns(t0_ns, wrenches, args.wrench_rate)
    p_stamps = stamps_ns(t0_ns, poses, args.pose_rate)
    forces, moments = plan.load.at((w_stamps - t0_ns) * 1e-9)
    predictors = [LivePredictor(settings, options['node.pose_tolerance_m'],
                                options['node.angle_tolerance_rad'], slack)
                  for slack in ('aware', 'linear')]
    n = predictors[0].eq.geometry.length_m.size
    u = np.zeros((2, wrenches, 3))
    force = np.zeros((2, wrenches, n))
    static = np.zeros((wrenches, n))
    accepted = np.zeros(wrenches, dtype=bool)
    k = 0
    for i, stamp in enumerate(w_stamps):
        while k < poses and p_stamps[k] <= stamp:
            position = plan.position((p_stamps[k] - t0_ns) * 1e-9)
            try:
                for predictor in predictors:
                    predictor.update_pose(position, plan.quaternion)
            except AnalysisError:
                pass                               # the node keeps its last good pose too
            k += 1
        if predictors[0].wrench_reason(forces[i], moments[i]):
            continue
        accepted[i] = True
        for j, predictor in enumerate(predictors):
            u[j, i] = predictor.advance(int(stamp), forces[i], moments[i])
            force[j, i] = predictor.cable_force_n()
        static[i] = predictors[0].eq.tensions.tension_n
    return SlackComparison((w_stamps[accepted] - t0_ns) * 1e-9, w_stamps[accepted],
                           u[0, accepted], u[1, accepted], force[0, accepted],
                           force[1, accepted], static[accepted])
