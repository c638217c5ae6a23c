"""Slack-aware time history: a cable carries no compression.

The linear models let a cable's tension T_i + dT_i go negative, i.e. push on the platform. Here
each cable is a compression-free elastic string from its anchor to its attachment. With the
attachment moved by d_i = G_i q (q the platform DOFs, small rotations) the cable's chord is
l_i - d_i, its length l_i' = |l_i - d_i| and its tension and force on the platform

    tau_i = max(0, T_i + k_i (l_i' - L_i)),        F_i = tau_i (l_i - d_i) / l_i',

with k_i = u_i^T K_i u_i the axial static end stiffness of the configured model (EA/L for
spring and fem, the sag-softened one for the catenary models). Linearised at q = 0 this is the
``spring`` stiffness k_i u u^T + T_i/L_i (I - u u^T): while every cable is taut the response is
the linear one (up to the geometric non-linearity, |d|/L ~ 1e-3 here); a slack cable has
neither elastic nor geometric stiffness and re-engages as soon as it is longer than
L_i - T_i/k_i. Only models without cable DOFs qualify (the platform's mass matrix is the
model's: the cables' own mass enters for fem and fem_sag with n = 1).

Damping is the configured Rayleigh damping, C = dM M + dK K in the linear models. Its
stiffness part is the cables' own (Kelvin-Voigt) damping, so it belongs inside the cable force:
a cable cannot push through its damper either. The cable force along the chord is

    P_i = max(0, T_i + k_i (l_i' - L_i) + dK k_i dl_i'/dt),

plus the transverse damping -dK (P_i/l_i') (I - t t^T) dd_i/dt that goes with the geometric
stiffness; a cable is slack while P_i = 0, and it then neither stiffens nor damps. The
platform obeys M q'' + dM M q' + R(q, q') = F(t), R = sum_i G_i^T (T_i u_i - F_i) (zero at the
static equilibrium the tensions balance; for a rigid platform plus each cable's rotational
geometric term scaled by P_i/T_i). Linearised about rest this is exactly the linear model with
C = dM M + dK K. Without damping R is the gradient of V(q) = sum_i [(tau_i^2 - T_i^2)/(2 k_i) +
T_i u_i . d_i] (point mass), so a free response keeps E = v^T M v / 2 + V(q).

Time stepping is Newmark (the configured alpha, beta) made consistent for the non-linear
force: each step solves its residual M a + dM M v + R(q, v) - F = 0 (v and a from the Newmark
relations) by Newton's method with the tangent (a0 + a1 dM) M + (1 + a1 dK) K_t(q) (terms of
second order in the displacement left out; a line search handles the kinks), to
|r| <= 1e-10 (sum T_i + |F|), two to four iterations per step. Measured on the paper's
1500 N, 5 Hz case the error against dt/8 falls 3.5-4.3 times per halving of dt (9e-5 of the
peak at the paper's dt = 1 ms), second order like the linear Newmark despite the kinks; an
undamped free vibration through slack keeps its energy to 2e-3 (test_slack).

``cable_damping=False`` keeps C = dM M + dK K linear and slackens on the elastic tension only
(the damper may push): it separates the effect of slack from that of where damping sits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.dynamics.system import Damping, DynamicsError, PlatformSystem
from cdpr_dynamics.mechanics.robot import skew

NEWTON_ITERATIONS = 50
RESIDUAL_TOL = 1e-10


@dataclass(frozen=True, eq=False)
class SlackHistory:
    """Slack-aware response: ``t_s`` (nt,), platform DOFs ``u``, ``v``, ``a`` (nt, ndof),
    cable tensions ``tension_n`` (nt, ncab) (0 while slack), Newton iterations per step."""

    t_s: np.ndarray
    u: np.ndarray
    v: np.ndarray
    a: np.ndarray
    tension_n: np.ndarray
    iterations: np.ndarray

    @property
    def u_m(self) -> np.ndarray:
        """(nt, 3) displacement of the centroid (m)."""
        return self.u[:, :3]

    @property
    def slack(self) -> np.ndarray:
        """(nt, ncab) True where a cable carries no tension."""
        return ~(self.tension_n > 0.0)

    def slack_intervals(self, cable: int) -> list[tuple[float, float]]:
        """[(start, end)] times (s) during which ``cable`` is slack (end inclusive)."""
        return intervals(self.t_s, self.slack[:, cable])


def intervals(t_s, flags) -> list[tuple[float, float]]:
    """[(start, end)] times (s) of the runs of True in ``flags`` (nt,), end inclusive."""
    flags = np.asarray(flags, dtype=bool).astype(int)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags, [0]])))
    return [(float(t_s[s]), float(t_s[e - 1])) for s, e in zip(edges[::2], edges[1::2])]


class CompressionFreeCables:
    """Forces, tangent and potential of compression-free cables on the platform DOFs.

    Built from a :class:`PlatformSystem` without cable DOFs (see the module docstring).
    """

    def __init__(self, system: PlatformSystem):
        assembly = system.assembly
        if assembly.blocks is None or assembly.interior_dofs:
            raise DynamicsError(
                f'a slack-aware time history needs a model without cable DOFs (spring, '
                f'catenary, catenary_exact, fem or fem_sag with n = 1), not '
                f'{assembly.method} n={assembly.elements_per_cable}')
        if not assembly.valid:
            raise DynamicsError('slack-aware time history of an invalid model: '
                                + '; '.join(assembly.warnings))
        geo = system.geometry
        self.g = geo.attachment_map()                                  # (n, 3, nd)
        self.chord = np.asarray(geo.chord_m, dtype=float)              # attachment -> anchor
        self.length = np.asarray(geo.length_m, dtype=float)
        self.unit = np.asarray(geo.unit, dtype=float)
        self.tension = np.linalg.norm(assembly.end_force_n, axis=1)
        if np.any(~(self.tension > 0.0)):
            raise DynamicsError('a slack-aware time history starts from taut cables (T > 0)')
        k_end = assembly.static_end_stiffness()
        self.k_axial = np.einsum('ci,cij,cj->c', self.unit, k_end, self.unit)
        nd = system.platform_dofs
        self.nd = nd
        self.mass = system.matrices()[1].toarray()
        self.rotation = np.zeros((len(self.length), nd, nd))          # per cable, at T_i
        if nd == 6:
            f0 = self.tension[:, None] * self.unit
            k_rot = -np.einsum('cij,cjk->cik', skew(f0), skew(geo.lever_m))
            self.rotation[:, 3:, 3:] = 0.5 * (k_rot + np.swapaxes(k_rot, 1, 2))
        self.load_rotation = system.load_stiffness    # gravity's moment: slack or not
        self.static_force = np.einsum('cia,ci->a', self.g, self.tension[:, None] * self.unit)
        self._g2 = self.g.reshape(-1, nd)                               # (3 n, nd)
        self._gtg = np.einsum('cia,cib->cab', self.g, self.g)           # G_i^T G_i
        self._eye = np.eye(nd)

    def state(self, q: np.ndarray, qdot: np.ndarray, stiffness_factor: float = 0.0):
        """(cable forces P (n,), restoring force R (nd,), tangent K_t (nd, nd)) at (q, q').

        ``stiffness_factor`` is dK: the cables' damping inside P (module docstring). Written
        as few numpy calls on (n, 3) arrays (a live prediction steps through it while a cable
        is slack): G_i^T K_i G_i with K_i = w_i t t^T + s_i I is w_i h_i h_i^T + s_i G_i^T G_i,
        h_i = G_i^T t_i.
        """
        point = self.nd == 3          # a point mass: G_i = I, d_i = q for every cable
        if point:
            d, d_dot = q, qdot
        else:
            n = self.length.shape[0]
            d = (self._g2 @ q).reshape(n, 3)
            d_dot = (self._g2 @ qdot).reshape(n, 3)
        chord = self.chord - d
        length = np.sqrt((chord * chord).sum(axis=1))
        t = chord / length[:, None]
        along = (t * d_dot).sum(axis=1)                        # -(stretch rate)
        pull = np.maximum(0.0, self.tension + self.k_axial * (
            length - self.length - stiffness_factor * along))
        per_length = pull / length
        force = pull[:, None] * t - (stiffness_factor * per_length)[:, None] \
            * (d_dot - along[:, None] * t)
        axial = np.where(pull > 0.0, self.k_axial, 0.0) - per_length
        if point:
            restoring = self.static_force - force.sum(axis=0)
            tangent = (t.T * axial) @ t + per_length.sum() * self._eye
            return pull, restoring, tangent
        restoring = self.static_force - self._g2.T @ force.reshape(-1)
        h = np.matmul(t[:, None, :], self.g)[:, 0, :]                         # (n, nd)
        rot = np.tensordot(pull / self.tension, self.rotation, 1) + self.load_rotation
        restoring += rot @ (q + stiffness_factor * qdot)
        tangent = (h.T * axial) @ h + np.tensordot(per_length, self._gtg, 1) + rot
        return pull, restoring, tangent

    def potential(self, q: np.ndarray) -> float:
        """V(q) with grad V = R(q) (exact without the rigid platform's rotational term)."""
        d = np.einsum('cia,a->ci', self.g, q)
        length = np.linalg.norm(self.chord - d, axis=1)
        tau = np.maximum(0.0, self.tension + self.k_axial * (length - self.length))
        return float(np.sum((tau ** 2 - self.tension ** 2) / (2.0 * self.k_axial)
                            + self.tension * np.einsum('ci,ci->c', self.unit, d)))


class SlackStepper:
    """Newmark steps of the compression-free platform (the module docstring's scheme).

    State ``q``, ``v``, ``acc`` (nd,) of the platform DOFs, ``pull`` (n,) the cable forces at
    the last step. :meth:`step` advances one ``dt_s`` to the load ``force`` (nd,) at the step's
    end; both :func:`slack_time_history` and the live predictor step through it, so an offline
    history and a replay give the same numbers.
    """

    def __init__(self, system: PlatformSystem, damping: Damping, dt_s: float = 1e-3,
                 alpha: float = 0.5, beta: float = 0.25, cable_damping: bool = True):
        if not (dt_s > 0 and alpha >= 0.5 and beta >= alpha / 2.0):
            raise DynamicsError(f'slack-aware Newmark needs dt > 0 and the unconditionally '
                                f'stable alpha >= 1/2, beta >= alpha/2 (got alpha = {alpha}, '
                                f'beta = {beta})')
        self.cables = cables = CompressionFreeCables(system)
        nd = cables.nd
        self.m = cables.mass
        self.dt_s = dt_s
        dt = dt_s
        self.a0, self.a1 = 1.0 / (beta * dt * dt), alpha / (beta * dt)
        self.a2, self.a3 = 1.0 / (beta * dt), 1.0 / (2.0 * beta) - 1.0
        self.a6, self.a7 = dt * (1.0 - alpha), alpha * dt
        dm, dk = damping.mass_factor, damping.stiffness_factor
        self.linear = dm * self.m                        # the damping outside the cables
        if not cable_damping:
            self.linear = self.linear + dk * cables.state(np.zeros(nd), np.zeros(nd))[2]
            dk = 0.0
        self.dk = dk
        self.jacobian_constant = self.a0 * self.m + self.a1 * self.linear
        self.scale = float(np.abs(cables.tension).sum())
        self.q, self.v, self.acc = np.zeros(nd), np.zeros(nd), np.zeros(nd)
        self.pull = cables.tension.copy()
        self.iterations = 0

    def start(self, q, v, force) -> None:
        """Set the state (q, v) and the acceleration that balances ``force`` there."""
        self.q = np.array(q, dtype=float)
        self.v = np.array(v, dtype=float)
        self.pull, restoring, _ = self.cables.state(self.q, self.v, self.dk)
        self.acc = np.linalg.solve(self.m, force - self.linear @ self.v - restoring)

    def _residual(self, q_new, force):
        acc_new = self.a0 * (q_new - self.q) - self.a2 * self.v - self.a3 * self.acc
        v_new = self.v + self.a6 * self.acc + self.a7 * acc_new
        pull, restoring, tangent = self.cables.state(q_new, v_new, self.dk)
        r = self.m @ acc_new + self.linear @ v_new + restoring - force
        return r, acc_new, v_new, pull, tangent

    def step(self, force) -> np.ndarray:
        """One step to the load ``force`` (nd,) at its end; returns q (the stepper's own)."""
        dt = self.dt_s
        tol = RESIDUAL_TOL * (self.scale + math.sqrt(float(force @ force)))
        q_new = self.q + dt * self.v + 0.5 * dt * dt * self.acc          # predictor
        r, acc_new, v_new, pull, tangent = self._residual(q_new, force)
        norm = math.sqrt(float(r @ r))
        for it in range(1, NEWTON_ITERATIONS + 1):
            if norm <= tol:
                break
            jacobian = self.jacobian_constant + (1.0 + self.a1 * self.dk) * tangent
            step = np.linalg.solve(jacobian, -r)
            for halving in range(40):   # line search: the force has kinks where cables slacken
                trial_q = q_new + 0.5 ** halving * step
                trial = self._residual(trial_q, force)
                trial_norm = math.sqrt(float(trial[0] @ trial[0]))
                if trial_norm < norm:
                    break
            q_new, norm = trial_q, trial_norm
            r, acc_new, v_new, pull, tangent = trial
        else:
            raise DynamicsError(f'slack-aware Newmark: Newton did not converge (residual '
                                f'{norm:.3g} N)')
        self.q, self.v, self.acc, self.pull, self.iterations = q_new, v_new, acc_new, pull, it
        return q_new


def slack_time_history(system: PlatformSystem, force_n, excitation_hz: float,
                       duration_s: float, damping: Damping, dt_s: float = 1e-3,
                       alpha: float = 0.5, beta: float = 0.25, progress=None,
                       initial_velocity=None, load=None,
                       cable_damping: bool = True) -> SlackHistory:
    """Slack-aware response from rest to ``force_n sin(2 pi f t)`` (see the module docstring).

    ``cable_damping`` False keeps the damping linear, C = dM M + dK K at rest, acting whether
    cables are slack or not, and slackens a cable on its elastic tension alone.
    ``load(t) -> (nd,)`` replaces the harmonic force when given; ``initial_velocity`` (nd,)
    starts the platform moving (free-vibration checks). Raises :class:`DynamicsError` for a
    model with cable DOFs, an unstable Newmark setting or a step Newton cannot converge.
    """
    stepper = SlackStepper(system, damping, dt_s, alpha, beta, cable_damping)
    nd = stepper.cables.nd
    steps = int(round(duration_s / dt_s))
    t = np.arange(steps + 1) * dt_s
    if load is None:
        amplitude = np.zeros(nd)
        amplitude[:3] = force_n
        w = 2.0 * math.pi * excitation_hz

        def load(time_s):
            return amplitude * math.sin(w * time_s)
    stepper.start(np.zeros(nd), np.zeros(nd) if initial_velocity is None else initial_velocity,
                  load(0.0))
    u_out = np.zeros((steps + 1, nd))
    v_out = np.zeros((steps + 1, nd))
    a_out = np.zeros((steps + 1, nd))
    tension = np.zeros((steps + 1, len(stepper.pull)))
    iterations = np.zeros(steps + 1, dtype=int)
    v_out[0], a_out[0], tension[0] = stepper.v, stepper.acc, stepper.pull
    for i in (progress or iter)(range(1, steps + 1)):
        try:
            stepper.step(load(t[i]))
        except DynamicsError as exc:
            raise DynamicsError(f'{exc} at t = {t[i]:.4g} s') from None
        u_out[i], v_out[i], a_out[i] = stepper.q, stepper.v, stepper.acc
        tension[i], iterations[i] = stepper.pull, stepper.iterations
    return SlackHistory(t, u_out, v_out, a_out, tension, iterations)


def peak_displacement(u_m: np.ndarray, axis: int = 2) -> float:
    """max |u| along ``axis`` (m)."""
    return float(np.max(np.abs(np.asarray(u_m)[:, axis]), initial=0.0))


def platform_only_method(method: str) -> str:
    """The model without cable DOFs that stands for ``method`` in a slack-aware history
    (always built with n = 1).

    spring, catenary, catenary_exact: themselves; fem: fem n = 1 (the cables' mass lumped
    consistently on the platform); dsm: fem n = 1; fem_sag: catenary_exact (the static
    stiffness fem_sag converges to, sag included).
    """
    return {'dsm': 'fem', 'fem_sag': 'catenary_exact'}.get(method, method)
