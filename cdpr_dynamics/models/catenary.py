"""The elastic catenary (Irvine, Cable Structures, 1981): ``catenary`` and ``catenary_exact``.

Convention. One cable, unstrained length ``L0``, weight ``gamma`` per unstrained length (N/m),
axial stiffness ``EA``, gravity along ``-e`` (``e = -g/|g|`` the unit "up", any direction). End A
is the reference (fixed) end, end B the other one; ``l = r_B - r_A``. ``F`` is the force applied
AT B ON the cable (it pulls B away from A for a taut cable) and ``sigma`` the unstrained arc length
measured from B. Equilibrium of the piece [0, sigma] gives the tension vector

    T(sigma) t(sigma) = F - gamma sigma e,        T(sigma) = |F - gamma sigma e|,

with ``t`` the unit tangent pointing towards B, and with dp/dsigma = 1 + T/EA

    l = F L0/EA - gamma L0^2/(2 EA) e + integral_0^L0 (F - gamma sigma e)/T(sigma) d sigma.

Write ``V = F.e``, ``H_vec = F - V e`` (H = |H_vec|), ``a0 = V``, ``a1 = V - gamma L0`` (the
vertical components at B and A), ``T_B = |F|``, ``T_A = sqrt(H^2 + a1^2)``. The integral gives
``H_vec (asinh(a0/H) - asinh(a1/H))/gamma + e (T_B - T_A)/gamma``; in a form finite at H = 0
(a hanging vertical cable) and at gamma = 0 (a weightless cable):

    sinh(asinh(a0/H) - asinh(a1/H)) = (a0 T_A - a1 T_B)/H^2 = gamma L0 p,
        p = (a0 + a1)/(a0 T_A + a1 T_B)                       if a0 a1 > 0 (no low point),
        p = (H^2 + T_A T_B - a0 a1)/((T_A + T_B) H^2)         otherwise (needs H > 0),
    q = L0 p asinh(gamma L0 p)/(gamma L0 p),      s = L0 (a0 + a1)/(T_A + T_B) = (T_B - T_A)/gamma,

    l = L0/EA (F - gamma L0/2 e) + q H_vec + s e.                                     (Eq. 25)

Both forms of ``p`` are sums of same-signed terms where they are used (no cancellation). The
flexibility is ``dl/dF = L0/EA I + integral (I - t t^T)/T d sigma``, in closed form

    C = L0/EA I + q (I - e e^T) + L0 p/(T_A T_B) (H^2 e e^T - H_vec H_vec^T)
        - s/(T_A T_B) (H_vec e^T + e H_vec^T),                                     (Eq. 29)

symmetric and positive definite wherever the tension is positive along the whole cable.

Signs. Here A is the anchor and B the platform attachment: ``l = -chord`` and F is minus the
force the cable exerts on the platform. Moving the attachment by dx changes l by dx and the
force on the platform by -dF = -C^-1 dx, so the stiffness the platform feels is ``K = C^-1``,
positive definite for a taut cable. Seen from the other end (A <-> B, l -> -l,
F -> gamma L0 e - F) C is unchanged: the cable has one 3x3 stiffness K, and its 6x6 two-end
stiffness is [K -K; -K K].

Paper Section IV uses the force F_p = gamma L0 e - F at its node I = A, so its flexibility
dl/dF_p is -C (negative definite) and its tangent matrix [-K K; K -K] of Eq. 33 is the same
[K -K; -K K] in this sign. Its Eq. 25a should read l_x = -F1 L0/EA - (F1/gamma)
ln[(T_j + gamma L0 - F3)/(T_i - F3)], and T_i - F3 loses all digits (0/0 in Eq. 29) when node I
is the upper end of a vertical cable: the forms above do not. The paper's misprints (checked in
``test/test_catenary.py``): Eq. 24a lacks "= 0"; Eqs. 25a-b close the first log too early and
print F0 for F3; Eq. 29b f23 has the wrong sign (it is (F2/gamma)(1/T_j - 1/T_i), like f13);
Eq. 29d has F6/T_i for F6/T_j; Eq. 30b defines T_j, not T_i. The logs of Eqs. 29a/29c are right
(natural log) once Eq. 25a is corrected, and Eq. 33 is right in the sign of Eq. 29.

Models (both massless: the platform end is the only node, like ``spring``):

* ``catenary``: the paper's modified analytical method, L0 = chord length and F = T_i along the
  chord (no Newton iteration); K = C^-1 with the corrected C. As gamma -> 0 it tends to
  EA/L u u^T + T/L EA/(EA + T) (I - u u^T): ``spring`` with the transverse term scaled by
  EA/(EA + T), because the unstrained length is taken as the chord.
* ``catenary_exact``: L0 and F solved by Newton so that the end position closes on the chord
  exactly and |F| = T_i; K = C^-1 at the solution, end force along the end tangent. As
  gamma -> 0 it tends to (EA + T)/L u u^T + T/L (I - u u^T).

Irvine's sag parameter per cable is :func:`sag_parameter`.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from cdpr_dynamics.models.base import (CableAssembly, CableSet, axial_transverse,
                                       massless_assembly)


# --------------------------------------------------------------------------- closed forms

def _asinhc(x):
    """asinh(x)/x for x >= 0 (numpy's asinh keeps full relative precision near 0: the quotient
    equals the series 1 - x^2/6 + 3 x^4/40 there to 1e-16; x = 0 gives 1)."""
    x = np.maximum(x, 1e-300)
    return np.arcsinh(x) / x


class _Parts(NamedTuple):
    """Intermediate quantities of the closed forms (see the module docstring)."""

    v: np.ndarray         # F.e
    h_vec: np.ndarray     # F - V e
    h2: np.ndarray        # H^2
    t_b: np.ndarray       # tension at B (|F|)
    t_a: np.ndarray       # tension at A
    p: np.ndarray
    q: np.ndarray
    s: np.ndarray
    min_tension: np.ndarray


def _parts(force, length, gamma, up) -> _Parts:
    force = np.asarray(force, dtype=float)
    length = np.asarray(length, dtype=float)
    up = np.asarray(up, dtype=float)
    v = force @ up if up.ndim == 1 else np.einsum('...i,...i->...', force, up)
    h_vec = force - v[..., None] * up
    h2 = np.einsum('...i,...i->...', h_vec, h_vec)
    a0, a1 = v, v - gamma * length
    t_b = np.sqrt(h2 + a0 * a0)
    t_a = np.sqrt(h2 + a1 * a1)
    same = a0 * a1 > 0.0
    taut = bool(np.all(same))           # no low point in any cable: one branch (same numbers)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        p = (a0 + a1) / (a0 * t_a + a1 * t_b)
        if not taut:
            p = np.where(same, p, (h2 + t_a * t_b - a0 * a1) / ((t_a + t_b) * h2))
        s = length * (a0 + a1) / (t_a + t_b)
        q = length * p * _asinhc(gamma * length * p)
    # lowest tension: at an end, or H where the tangent is horizontal inside the cable
    min_tension = np.minimum(t_a, t_b)
    if not taut:
        min_tension = np.where(same, min_tension, np.sqrt(h2))
    return _Parts(v, h_vec, h2, t_b, t_a, p, q, s, min_tension)


def end_position(force, unstrained_length, ea, gamma, up, parts: _Parts | None = None
                 ) -> np.ndarray:
    """Position of end B relative to end A (Eq. 25 corrected), shape (..., 3).

    ``force`` (..., 3) is the force applied at B on the cable, ``unstrained_length`` (...) the
    unstrained length (or the unstrained arc length from B for a point inside the cable),
    ``ea`` (N), ``gamma`` (N per unstrained metre), ``up`` the unit vector against gravity;
    ``parts``: :func:`_parts` of the same arguments where the caller has them already.
    """
    up = np.asarray(up, dtype=float)
    length = np.asarray(unstrained_length, dtype=float)
    r = _parts(force, length, gamma, up) if parts is None else parts
    force = np.asarray(force, dtype=float)
    elastic = (length / ea)[..., None] * (force - (0.5 * gamma * length)[..., None] * up)
    return elastic + r.q[..., None] * r.h_vec + r.s[..., None] * up


def flexibility(force, unstrained_length, ea, gamma, up, parts: _Parts | None = None
                ) -> np.ndarray:
    """dl/dF of :func:`end_position` (Eq. 29 corrected), symmetric (..., 3, 3) in m/N.

    ``parts``: :func:`_parts` of the same arguments where the caller has them already."""
    up = np.asarray(up, dtype=float)
    length = np.asarray(unstrained_length, dtype=float)
    r = _parts(force, length, gamma, up) if parts is None else parts
    ee = up[..., :, None] * up[..., None, :]
    hh = r.h_vec[..., :, None] * r.h_vec[..., None, :]
    he = r.h_vec[..., :, None] * up[..., None, :]
    tt = r.t_a * r.t_b
    c = (length / ea)[..., None, None] * np.eye(3) + r.q[..., None, None] * (np.eye(3) - ee)
    c = c + (length * r.p / tt)[..., None, None] * (r.h2[..., None, None] * ee - hh)
    return c - (r.s / tt)[..., None, None] * (he + np.swapaxes(he, -1, -2))


def tensions(force, unstrained_length, gamma, up):
    """(tension at B, tension at A, lowest tension along the cable), each shape (...)."""
    r = _parts(force, unstrained_length, gamma, up)
    return r.t_b, r.t_a, r.min_tension


def up_and_weight(cables: CableSet) -> tuple[np.ndarray, float]:
    """Unit up vector and the effective weight per length (0 without gravity)."""
    g = np.asarray(cables.gravity_m_s2, dtype=float)
    norm = float(np.linalg.norm(g))
    if norm == 0.0:
        return np.array([0.0, 0.0, 1.0]), 0.0
    return -g / norm, float(cables.weight_per_length_n_per_m)


@functools.lru_cache(maxsize=8)
def sag_parameter(cables: CableSet) -> np.ndarray:
    """Irvine's sag parameter lambda^2 of every cable, (n,), dimensionless, read-only (kept
    for the last few CableSets, which are immutable: a pose update asks twice).

    lambda^2 = (gamma L cos(theta)/H)^2 L/(H L_e/EA), L_e = L (1 + 8 (d/L)^2), d = gamma L^2
    cos(theta)/(8 H), with L the chord, theta its inclination to the horizontal and H the tension
    component along the chord (Irvine's inclined cable; the horizontal tension for a level one),
    here the tension at the platform end. inf for a cable without tension; 0 for a vertical one.
    Straight models lose accuracy as lambda^2 approaches 4 pi^2 (where the first symmetric
    in-plane mode of the cable crosses the antisymmetric one).
    """
    up, gamma = up_and_weight(cables)
    length = cables.length_m
    chord = np.asarray(cables.chord_m, dtype=float)
    horizontal = chord - (chord @ up)[:, None] * up
    cos_theta = np.linalg.norm(horizontal, axis=1) / length
    t = np.asarray(cables.tension_n, dtype=float)
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = gamma * length * cos_theta / t
        sag_ratio = ratio / 8.0
        lam2 = ratio ** 2 * cables.ea_n / (t * (1.0 + 8.0 * sag_ratio ** 2))
    out = np.where(t > 0, lam2, np.inf)
    out.setflags(write=False)
    return out


# --------------------------------------------------------------------------- the exact solve

class CatenaryState(NamedTuple):
    """The elastic catenary of each cable, platform end B, anchor A (all stacked over cables).

    ``force_n`` is the force applied at the platform end ON the cable (minus the force on the
    platform); ``residual_m`` the closing error of the end position; ``valid`` marks cables
    whose solution exists and stays taut (``reasons`` say why not).
    """

    force_n: np.ndarray
    unstrained_length_m: np.ndarray
    anchor_tension_n: np.ndarray
    min_tension_n: np.ndarray
    residual_m: np.ndarray
    iterations: int
    valid: np.ndarray
    reasons: tuple[str, ...]


def _row_norm(x: np.ndarray) -> np.ndarray:
    """|x| along the last axis: numpy's norm (the same operations, the same numbers) without
    its argument handling, half the cost on a few cables."""
    return np.sqrt(np.add.reduce(x * x, axis=-1))


def _residual(force, length, target, tension, ea, gamma, up, scale):
    """(residual (n, 4) of the closure and of |F| = T, the :func:`_parts` it was made of)."""
    parts = _parts(force, length, gamma, up)
    pos = end_position(force, length, ea, gamma, up, parts) - target
    t = _row_norm(force)
    return np.concatenate([pos, (scale * (t / tension - 1.0))[:, None]], axis=1), parts


def solve(cables: CableSet, max_iterations: int = 60,
          min_tension_ratio: float = 1e-6, start: CatenaryState | None = None,
          max_halvings: int = 30, tolerance: float = 1e-13) -> CatenaryState:
    """Newton on (F, L0) per cable: the end closes on the chord and |F| = T_i.

    Starts from the taut parabola (L0 = L/(1 + T/EA) and F with |F| = T such that the mean
    tension vector F - gamma L0 e/2 lies along the chord, its first-order closure: F = c l/|l|
    + gamma L0/2 e, c = -g cos + sqrt(T^2 - g^2 sin^2), g = gamma L0/2, cos = e.l/|l|; used
    where g < T/4, else the straight cable F = -T u), or from ``start`` (a nearby solution,
    e.g. of the previous pose or tension: its end-force direction and L0, the force rescaled
    to |F| = T_i) where that cable was valid; damped by step halving. Newton stops at a
    residual of ``tolerance`` max(L, 1) (the end closure in m, the tension scaled by L); a
    solution is accepted (valid) below 1e-9 max(L, 1), so a ``tolerance`` up to 1e-10 changes
    no verdict, only the last digits of F and L0.
    A cable is invalid when T_i <= 0, when Newton does not converge (no catenary with that end
    tension spans the chord) or when the tension somewhere along it is below
    ``min_tension_ratio`` times T_i (slack: it cannot hold its own weight). ``max_iterations``
    and ``max_halvings`` (of each Newton step) bound the work, e.g. for cheap existence probes.
    """
    up, gamma = up_and_weight(cables)
    ea = float(cables.ea_n)
    chord = np.asarray(cables.chord_m, dtype=float)
    length = cables.length_m
    unit = chord / length[:, None]
    target = -chord
    tension = np.asarray(cables.tension_n, dtype=float)
    n = chord.shape[0]
    live = tension > 0
    t_safe = np.where(live, tension, 1.0)
    scale = length
    force = -t_safe[:, None] * unit
    l0 = length / (1.0 + t_safe / ea)
    if gamma > 0.0:
        g = 0.5 * gamma * l0
        cos = -(unit @ up)                                  # e . l/|l|, l = -chord
        disc = t_safe * t_safe - g * g * (1.0 - cos * cos)
        taut = (g < 0.25 * t_safe) & (disc > 0.0)
        c = -g * cos + np.sqrt(np.where(taut, disc, 1.0))
        force = np.where(taut[:, None], -c[:, None] * unit + g[:, None] * up, force)
    res, parts = _residual(force, l0, target, t_safe, ea, gamma, up, scale)
    norm = _row_norm(res)
    if start is not None:   # per cable the better start: the nearby solution or the parabola
        direction = start.force_n / _row_norm(start.force_n)[:, None]
        near_f = t_safe[:, None] * direction
        near_l = start.unstrained_length_m
        with np.errstate(all='ignore'):
            near_r, near_p = _residual(near_f, near_l, target, t_safe, ea, gamma, up, scale)
            near_n = _row_norm(near_r)
        warm = start.valid & live & (near_n < norm)
        if warm.all():
            force, l0, res, norm, parts = near_f, near_l, near_r, near_n, near_p
        elif warm.any():
            force = np.where(warm[:, None], near_f, force)
            l0 = np.where(warm, near_l, l0)
            res = np.where(warm[:, None], near_r, res)
            norm = np.where(warm, near_n, norm)
            parts = None
    tol = tolerance * np.maximum(length, 1.0)
    with np.errstate(all='ignore'):       # trial states past slack give inf/nan: rejected
        force, l0, res, iterations, parts = _newton(force, l0, res, norm, tol, live, target,
                                                    t_safe, ea, gamma, up, scale,
                                                    max_iterations, max_halvings, parts)
        if parts is None:
            parts = _parts(force, l0, gamma, up)
        t_a, t_min = parts.t_a, parts.min_tension
    residual = _row_norm(res[:, :3])
    residual = np.where(np.isfinite(residual), residual, np.inf)
    tension_error = np.abs(res[:, 3]) / scale
    converged = live & (residual <= 1e-9 * np.maximum(length, 1.0)) & (tension_error <= 1e-9)
    taut = t_min > min_tension_ratio * t_safe
    valid = converged & taut
    reasons = []
    for i in (range(n) if not valid.all() else ()):
        if not live[i]:
            reasons.append(f'cable {i} is slack (T = {tension[i]:.3g} N <= 0)')
        elif not converged[i]:
            reasons.append(f'cable {i}: no taut elastic catenary with end tension '
                           f'{tension[i]:.3g} N spans its chord of {length[i]:.4g} m (cable '
                           f'weight {gamma * length[i]:.3g} N): too slack to hold itself')
        elif not taut[i]:
            reasons.append(f'cable {i} is slack: with end tension {tension[i]:.3g} N its '
                           f'tension falls to {t_min[i]:.3g} N along the cable (weight '
                           f'{gamma * l0[i]:.3g} N)')
    force = np.where(valid[:, None], force, -np.maximum(tension, 0.0)[:, None] * unit)
    l0 = np.where(valid, l0, length)
    return CatenaryState(force, l0, np.where(valid, t_a, np.maximum(tension, 0.0)),
                         np.where(valid, t_min, np.minimum(tension, 0.0)), residual, iterations,
                         valid, tuple(reasons))


def _jacobian(force, l0, ea, gamma, up, row_scale, parts: _Parts | None = None
              ) -> np.ndarray:
    """(n, 4, 4) derivative of (end position, row_scale |F|) with respect to (F, L0).

    d l = C dF + (1/EA + 1/T_A) (F - gamma L0 e) dL0 (C of :func:`flexibility`; F - gamma L0 e
    is the tension vector at A) and d|F| = F.dF/|F|; ``parts`` those of (F, L0) if known.
    """
    r = _parts(force, l0, gamma, up) if parts is None else parts
    jac = np.zeros(force.shape[:-1] + (4, 4))
    jac[..., :3, :3] = flexibility(force, l0, ea, gamma, up, r)
    tangent_a = force - (gamma * l0)[..., None] * up            # d l / d L0 (tension at A)
    jac[..., :3, 3] = tangent_a * (1.0 / ea + 1.0 / r.t_a)[..., None]
    jac[..., 3, :3] = (row_scale / r.t_b)[..., None] * force
    return jac


def tension_sensitivity(state: CatenaryState, cables: CableSet) -> tuple[np.ndarray, np.ndarray]:
    """(dF/dT (n, 3), dL0/dT (n,)): how each solved catenary changes with its end tension.

    The chord is held: C dF + (dl/dL0) dL0 = 0 and F.dF/|F| = dT (the 4x4 system of
    :func:`_jacobian`). The force on the platform changes by -dF/dT per newton of end tension:
    along the end tangent by 1, plus a turn of the tangent as the sag changes. Finite only for
    valid cables away from the fold where T stops falling as L0 grows (NaN elsewhere).
    """
    up, gamma = up_and_weight(cables)
    n = state.force_n.shape[0]
    jac = _jacobian(state.force_n, state.unstrained_length_m, float(cables.ea_n), gamma, up,
                    np.ones(n))
    rhs = np.zeros((n, 4))
    rhs[:, 3] = 1.0
    out = np.full((n, 4), np.nan)
    ok = state.valid & np.all(np.isfinite(jac), axis=(1, 2))
    ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], jac, np.eye(4)))) > 0.0
    if np.any(ok):
        out[ok] = np.linalg.solve(jac[ok], rhs[ok][..., None])[..., 0]
    return out[:, :3], out[:, 3]


def _newton(force, l0, res, norm, tol, live, target, t_safe, ea, gamma, up, scale,
            max_iterations, max_halvings=30, parts=None):
    """Damped Newton iterations of :func:`solve` (vectorised over cables).

    ``parts``: :func:`_parts` of the starting (F, L0) or None; returned likewise for the final
    state (None where it is not known: the caller computes them), so that one evaluation per
    iteration serves the residual, the next Jacobian and the final tensions."""
    n = force.shape[0]
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        todo = live & (norm > tol)
        if not np.any(todo):
            break
        if parts is None:
            parts = _parts(force, l0, gamma, up)
        jac = _jacobian(force, l0, ea, gamma, up, scale / t_safe, parts)
        ok = todo & np.all(np.isfinite(jac), axis=(1, 2))
        step = np.zeros((n, 4))
        for i in ([ok] if np.any(ok) else []):
            try:
                step[i] = np.linalg.solve(jac[i], -res[i][..., None])[..., 0]
            except np.linalg.LinAlgError:   # one singular cable: solve them one by one
                for k in np.flatnonzero(i):
                    try:
                        step[k] = np.linalg.solve(jac[k], -res[k])
                    except np.linalg.LinAlgError:
                        ok[k] = False
        alpha = np.ones(n)
        new_force, new_l0, new_res = force, l0, res
        improve = np.zeros(n, dtype=bool)
        whole = None      # the parts of the first full step where every cable takes it
        for halving in range(max_halvings):
            trial_f = force + alpha[:, None] * step[:, :3]
            trial_l = l0 + alpha * step[:, 3]
            trial_r, trial_p = _residual(trial_f, np.where(trial_l > 0, trial_l, l0), target,
                                         t_safe, ea, gamma, up, scale)
            trial_n = _row_norm(trial_r)
            good = ok & ~improve & (trial_l > 0) & np.isfinite(trial_n) & (
                (trial_n < norm) | (trial_n <= tol))
            new_force = np.where(good[:, None], trial_f, new_force)
            new_l0 = np.where(good, trial_l, new_l0)
            new_res = np.where(good[:, None], trial_r, new_res)
            improve |= good
            if np.all(improve | ~ok):
                # all at the first trial: cables without a step (step 0) sit where they were
                whole = trial_p if halving == 0 else None
                break
            alpha = np.where(improve, alpha, 0.5 * alpha)
        if not np.any(improve):
            break
        force, l0, res, parts = new_force, new_l0, new_res, whole
        norm = _row_norm(res)
    return force, l0, res, iterations, parts


# --------------------------------------------------------------------------- models

def placeholder_tension(cables: CableSet) -> np.ndarray:
    """Tension standing in for cables a model cannot represent: max(T, gamma L, 1e-9 EA) > 0."""
    _, gamma = up_and_weight(cables)
    return np.maximum(np.maximum(cables.tension_n, gamma * cables.length_m), 1e-9 * cables.ea_n)


def _placeholder(cables: CableSet) -> np.ndarray:
    """Finite straight-spring stiffness standing in for cables the model cannot represent."""
    length = cables.length_m
    return axial_transverse(cables.unit, cables.ea_n / length,
                            placeholder_tension(cables) / length)


def _stiffness(force, l0, cables, ok, parts: _Parts | None = None) -> np.ndarray:
    """K = C^-1 (symmetrised) where ``ok``, the placeholder spring elsewhere; ``parts`` of
    (force, l0) where the caller has them."""
    up, gamma = up_and_weight(cables)
    if ok.all():
        stiffness = np.linalg.inv(flexibility(force, l0, cables.ea_n, gamma, up, parts))
        return 0.5 * (stiffness + np.swapaxes(stiffness, -1, -2))
    stiffness = _placeholder(cables)
    if np.any(ok):
        flex = flexibility(force[ok], l0[ok], cables.ea_n, gamma, up)
        stiffness[ok] = np.linalg.inv(flex)
        stiffness[ok] = 0.5 * (stiffness[ok] + np.swapaxes(stiffness[ok], -1, -2))
    return stiffness


#: Newton tolerance of the paper catenary's existence test (:func:`solve`: same verdicts)
EXISTENCE_TOLERANCE = 1e-10


def build(cables: CableSet, elements_per_cable: int = 1) -> CableAssembly:
    """``catenary``: the paper's modified method, L0 = chord, F = T_i along the chord.

    ``elements_per_cable`` is ignored (massless, one node). Invalid (placeholder spring
    stiffness, a warning) where T_i <= 0 or the tension along the cable would reach zero.
    """
    up, gamma = up_and_weight(cables)
    tension = np.asarray(cables.tension_n, dtype=float)
    length = cables.length_m
    force = -tension[:, None] * cables.unit
    parts = _parts(force, length, gamma, up)
    t_min = parts.min_tension
    exists = solve(cables, tolerance=EXISTENCE_TOLERANCE).valid if gamma > 0 else tension > 0
    ok = (tension > 0) & (t_min > 1e-6 * np.abs(tension)) & exists
    warnings = []
    for i in np.flatnonzero(~ok):
        if not tension[i] > 0:
            warnings.append(f'cable {i} is slack (T = {tension[i]:.3g} N <= 0)')
        elif not exists[i]:
            warnings.append(f'cable {i}: no taut elastic catenary with end tension '
                            f'{tension[i]:.3g} N spans its chord of {length[i]:.4g} m (cable '
                            f'weight {gamma * length[i]:.3g} N): the paper\'s catenary assumes '
                            'one that cannot exist')
        else:
            warnings.append(f'cable {i} is slack: tension {tension[i]:.3g} N at the platform '
                            f'cannot hold the {gamma * length[i]:.3g} N cable hanging below it')
    return massless_assembly('catenary', _stiffness(force, length, cables, ok, parts),
                             tension[:, None] * cables.unit, bool(np.all(ok)), warnings)


def paper_misclosure(cables: CableSet) -> np.ndarray:
    """(n,) m: how far the paper's assumed catenary (L0 = chord, end force T_i along the chord)
    ends from the anchor, |l(F, L0) - l_chord| of Eq. 25; 0 for weightless cables up to the
    elastic stretch T L/EA that L0 = chord leaves out."""
    up, gamma = up_and_weight(cables)
    tension = np.maximum(np.asarray(cables.tension_n, dtype=float), 0.0)
    force = -tension[:, None] * cables.unit
    with np.errstate(all='ignore'):
        end = end_position(force, cables.length_m, float(cables.ea_n), gamma, up)
    return np.linalg.norm(end + np.asarray(cables.chord_m), axis=1)


def state_of(cables: CableSet) -> CatenaryState:
    """The catenaries of ``cables``: those the statics solved (``cables.sag_state``), or solved
    here at ``cables.tension_n``."""
    return cables.sag_state if cables.sag_state is not None else solve(cables)


def build_exact(cables: CableSet, elements_per_cable: int = 1) -> CableAssembly:
    """``catenary_exact``: Newton-consistent L0 and end force per cable (see :func:`solve`)."""
    state = state_of(cables)
    stiffness = _stiffness(state.force_n, state.unstrained_length_m, cables, state.valid)
    return massless_assembly('catenary_exact', stiffness, -state.force_n,
                             bool(np.all(state.valid)), state.reasons)
