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
relations) by Newton's method with the exact Jacobian a0 M + a1 dM M + dR/dq + a1 dR/dq'
(:meth:`CompressionFreeCables.jacobians`; a line search handles the kinks), to
|r| <= 1e-10 (sum T_i + |F|). Newton starts from the step of R linearised at the last state
and keeps its matrix while the same cables are taut: two evaluations of the forces per step
(one Newton correction) on the paper's load, a Jacobian only where a step needs more.
Measured on the paper's 1500 N, 5 Hz case the error against dt/8 falls 3.5-4.3 times per
halving of dt (9e-5 of the peak at the paper's dt = 1 ms), second order like the linear
Newmark despite the kinks; an undamped free vibration through slack keeps its energy to 2e-3
(test_slack).

The platform's displacement is small in this model (rotations to first order, the chords
moved by G_i q): a step that takes the platform beyond :data:`SMALL_ANGLE_RAD` of rotation, or
a chord beyond it (|G_i q| / l_i, the shortest cable's), raises :class:`DynamicsError` with
that displacement. A load that slackens cables this far flings the platform, and no
small-displacement model answers that.

``cable_damping=False`` keeps C = dM M + dK K linear and slackens on the elastic tension only
(the damper may push): it separates the effect of slack from that of where damping sits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dgesv as gesv

from cdpr_dynamics.dynamics.system import Damping, DynamicsError, PlatformSystem
from cdpr_dynamics.mechanics.robot import skew

NEWTON_ITERATIONS = 50
RESIDUAL_TOL = 1e-10
#: rotation (rad) of the platform or of a chord beyond which the small-displacement model of
#: the module docstring no longer answers (sin and tan then differ from the angle by 0.2-0.3 %)
SMALL_ANGLE_RAD = 0.1


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
        n = len(self.length)
        self._g2 = self.g.reshape(-1, nd)                               # (3 n, nd)
        self._gtg = np.einsum('cia,cib->cab', self.g, self.g).reshape(n, nd * nd)   # G_i^T G_i
        self._rotation = (self.rotation / self.tension[:, None, None]).reshape(n, nd * nd)
        self._eye = np.eye(nd)
        self._both = np.zeros((nd, 2))                                  # (q, q') columns
        self._ones = np.ones(3)
        self._rest = self.tension - self.k_axial * self.length          # T - k L

    def state(self, q: np.ndarray, qdot: np.ndarray, stiffness_factor: float = 0.0):
        """(cable forces P (n,), restoring force R (nd,), tangent K_t = dR/dq (nd, nd)) at
        (q, q').

        ``stiffness_factor`` is dK: the cables' damping inside P (module docstring).
        """
        pull, restoring, parts = self.forces(q, qdot, stiffness_factor)
        return pull, restoring, self.jacobians(parts)[0]

    def forces(self, q: np.ndarray, qdot: np.ndarray, stiffness_factor: float = 0.0):
        """(P (n,), R (nd,), parts): :meth:`state` without the tangent, which
        :meth:`jacobians` makes from ``parts`` where it is needed.

        Written as few numpy calls on (n, 3) arrays (a live prediction steps through it while a
        cable is slack).
        """
        dk = stiffness_factor
        if self.nd == 3:         # a point mass: G_i = I, d_i = q for every cable
            d, d_dot = q, qdot
        else:
            both = self._both
            both[:, 0] = q
            both[:, 1] = qdot
            moved = (self._g2 @ both).reshape(-1, 3, 2)
            d, d_dot = moved[:, :, 0], moved[:, :, 1]
        chord = self.chord - d
        length = np.sqrt((chord * chord) @ self._ones)
        t = chord / length[:, None]
        along = (t * d_dot) @ self._ones if self.nd == 6 else t @ d_dot    # -(stretch rate)
        pull = np.maximum(0.0, self._rest + self.k_axial * (length - dk * along))
        per_length = pull / length
        # P t - dK s w with w = d' - a t, the transverse velocity: t (P + dK s a) - dK s d'
        damper = dk * per_length
        parts = (dk, pull, t, d_dot, length, along, per_length, None, None)
        if self.nd == 3:
            return pull, self.static_force - t.T @ (pull + damper * along) \
                + damper.sum() * qdot, parts
        force = t * (pull + damper * along)[:, None] - damper[:, None] * d_dot
        rot = (pull @ self._rotation).reshape(self.nd, self.nd) + self.load_rotation
        rotated = q + dk * qdot
        restoring = self.static_force - self._g2.T @ force.reshape(-1) + rot @ rotated
        return pull, restoring, parts[:7] + (rot, rotated)

    def jacobians(self, parts) -> tuple[np.ndarray, np.ndarray]:
        """(dR/dq, dR/dq') (nd, nd) of :meth:`forces`' ``parts``, exact (Newton converges
        quadratically through them): per taut cable, with s = P/l', a = t.d', w = d' - a t
        the transverse velocity and N = I - t t^T, the blocks G^T B G of

            B_q = k t t^T + s (1 + dK a / l') N - dK (k - s)/l' (t w^T + w t^T)
                  + dK^2 k / l'^2 w w^T,
            B_v = dK (k t t^T + s N) - dK^2 k / l' w t^T,

        plus, for a rigid platform, the rotational terms' own and through P (zero for a
        slack cable); written with h = G^T t, m = G^T w and G^T N G = G^T G - h h^T.
        """
        dk, pull, t, d_dot, length, along, per_length, rot, rotated = parts
        across = d_dot - along[:, None] * t              # w
        k = np.where(pull > 0.0, self.k_axial, 0.0)
        spread = per_length * (1.0 + dk * along / length)
        cross = dk * (k - per_length) / length
        k_dk_l = dk * k / length
        if rot is None:
            h, m = t, across
            gtg_q, gtg_v = spread.sum() * self._eye, dk * per_length.sum() * self._eye
        else:
            hm = np.matmul(np.stack((t, across), axis=1), self.g)             # (n, 2, nd)
            h, m = hm[:, 0], hm[:, 1]
            nd = self.nd
            gtg_q = (spread @ self._gtg).reshape(nd, nd)
            gtg_v = dk * (per_length @ self._gtg).reshape(nd, nd)
        hq = h * (k - spread)[:, None] - m * cross[:, None]
        mq = m * (dk * k_dk_l / length)[:, None] - h * cross[:, None]
        jq = hq.T @ h + mq.T @ m + gtg_q
        jv = (h * (dk * (k - per_length))[:, None] - m * (dk * k_dk_l)[:, None]).T @ h + gtg_v
        if rot is not None:
            n = len(length)
            turned = (self._rotation.reshape(n, -1, self.nd) @ rotated)   # (n, nd): dR/dP_i
            dpull = m * k_dk_l[:, None] - h * k[:, None]                  # dP_i/dq
            jq = jq + rot + turned.T @ dpull
            jv = jv + dk * rot - dk * turned.T @ (h * k[:, None])
        return jq, jv

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
        # rows (q, v, a) of the state: c_a = wa . (q, v, a), c_v = wv . (q, v, a) (step)
        self._wa = -np.array([self.a0, self.a2, self.a3])
        self._wv = np.array([0.0, 1.0, self.a6]) + self.a7 * self._wa
        self._we = self._wv + np.array([self.a1, -1.0, 0.0])     # v_new - v at q_new = q
        self._offset = np.hstack([self.m * wa + self.linear * wv          # M c_a + C c_v
                                  for wa, wv in zip(self._wa, self._wv)])
        self.scale = float(np.abs(cables.tension).sum())
        self.q, self.v, self.acc = np.zeros(nd), np.zeros(nd), np.zeros(nd)
        self.pull = cables.tension.copy()
        self.iterations = 0
        # R at the state, the matrices of the last Newton step and the cables taut there
        self._restoring, self._jacobians, self._taut = None, None, None

    def start(self, q, v, force) -> None:
        """Set the state (q, v) and the acceleration that balances ``force`` there."""
        self.q = np.array(q, dtype=float)
        self.v = np.array(v, dtype=float)
        self.pull, self._restoring, parts = self.cables.forces(self.q, self.v, self.dk)
        self._jacobians = self._newton_matrices(parts)
        self._taut = self.pull > 0.0
        self.acc = np.linalg.solve(self.m, force - self.linear @ self.v - self._restoring)

    def _residual(self, q_new, offset, v_offset):
        """(r, v, P, R, parts) at q_new: r = a0 M q_new + a1 C q_new + ``offset`` + R with
        v = a1 q_new + ``v_offset`` (the Newmark relations of the step, :meth:`step`)."""
        v_new = self.a1 * q_new + v_offset
        pull, restoring, parts = self.cables.forces(q_new, v_new, self.dk)
        return self.jacobian_constant @ q_new + offset + restoring, v_new, pull, restoring, parts

    def _newton_matrices(self, parts):
        """(dR/dq', J = dr/dq_new = a0 M + a1 C + dR/dq + a1 dR/dq') at :meth:`forces`'
        ``parts``."""
        jq, jv = self.cables.jacobians(parts)
        return jv, self.jacobian_constant + jq + self.a1 * jv

    @staticmethod
    def _newton_step(matrices, r) -> np.ndarray:
        """-J^-1 r (LAPACK's gesv: numpy's wrapper costs several times a 3 x 3 or 6 x 6
        solve)."""
        x, info = gesv(matrices[1], r)[2:]
        if info:
            raise DynamicsError('slack-aware Newmark: singular Newton matrix')
        return -x

    def step(self, force) -> np.ndarray:
        """One step to the load ``force`` (nd,) at its end; returns q (the stepper's own).

        With a_new = a0 q_new + c_a and v_new = a1 q_new + c_v (Newmark) the residual is
        r(q_new) = (a0 M + a1 C) q_new + M c_a + C c_v - F + R(q_new, v_new). Newton starts from
        the step of R linearised at the last state, and reuses the last Newton matrix while
        the same cables are taut (recomputed where a step needs a second Newton iteration):
        most steps converge in two evaluations of the forces and no Jacobian.
        """
        tol = RESIDUAL_TOL * (self.scale + math.sqrt(float(force @ force)))
        q = self.q
        state = np.concatenate((q, self.v, self.acc))
        rows = state.reshape(3, -1)
        c_a, c_v = self._wa @ rows, self._wv @ rows
        offset = self._offset @ state - force
        matrices = self._jacobians
        linear = (self.jacobian_constant @ q + offset + self._restoring
                  + matrices[0] @ (self._we @ rows))
        q_new = q + self._newton_step(matrices, linear)
        r, v_new, pull, restoring, parts = self._residual(q_new, offset, c_v)
        norm = math.sqrt(float(r @ r))
        fresh = False
        for it in range(1, NEWTON_ITERATIONS + 1):
            if norm <= tol:
                break
            if fresh or not np.array_equal(pull > 0.0, self._taut):
                matrices = self._newton_matrices(parts)
                self._taut = pull > 0.0
            fresh = True
            step = self._newton_step(matrices, r)
            for halving in range(40):   # line search: the force has kinks where cables slacken
                trial_q = q_new + 0.5 ** halving * step
                trial = self._residual(trial_q, offset, c_v)
                trial_norm = math.sqrt(float(trial[0] @ trial[0]))
                if trial_norm < norm:
                    break
            q_new, norm = trial_q, trial_norm
            r, v_new, pull, restoring, parts = trial
        else:
            raise DynamicsError(f'slack-aware Newmark: Newton did not converge (residual '
                                f'{norm:.3g} N)')
        self._check_small(q_new)
        self.q, self.v, self.acc = q_new, v_new, self.a0 * q_new + c_a
        self.pull, self.iterations = pull, it
        self._restoring = restoring
        self._jacobians = matrices
        return q_new

    def _check_small(self, q: np.ndarray) -> None:
        """Raise :class:`DynamicsError` where ``q`` leaves the small-displacement model."""
        cables = self.cables
        rotation = math.sqrt(float(q[3:6] @ q[3:6])) if cables.nd == 6 else 0.0
        chord = float((np.linalg.norm(cables.g @ q, axis=1) / cables.length).max())
        if max(rotation, chord) > SMALL_ANGLE_RAD:
            moved = math.sqrt(float(q[:3] @ q[:3]))
            raise DynamicsError(
                f'slack cables let the platform move {moved:.3g} m'
                + (f' and turn {rotation:.3g} rad' if cables.nd == 6 else '')
                + f', beyond the small-displacement model ({SMALL_ANGLE_RAD} rad of a chord or '
                'the platform): the load slackens the cables far more than the model answers')


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
