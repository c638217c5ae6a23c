"""The elastic catenary (Irvine, Cable Structures, 1981): ``catenary`` and ``catenary_exact``.

One cable: unstrained length ``L0`` (m), weight ``gamma`` per unstrained length (N/m), axial
stiffness ``EA`` (N), ``e`` the unit "up" (``-g/|g|``). End A is the anchor, end B the platform
attachment, ``l = r_B - r_A`` (m); ``F`` (N) is the force applied at B on the cable. With
``V = F.e``, ``H_vec = F - V e``, ``a0 = V``, ``a1 = V - gamma L0``, ``T_B = |F|``,
``T_A = sqrt(H^2 + a1^2)``, the end position and the flexibility (m/N) are

    l = L0/EA (F - gamma L0/2 e) + q H_vec + s e,                                    (Eq. 25)
    C = dl/dF = L0/EA I + q (I - e e^T) + L0 p/(T_A T_B) (H^2 e e^T - H_vec H_vec^T)
                - s/(T_A T_B) (H_vec e^T + e H_vec^T),                               (Eq. 29)

with ``p``, ``q``, ``s`` in forms finite at H = 0 and gamma = 0; the stiffness the platform
feels is ``K = C^-1`` (N/m). ``catenary`` is the paper's method (L0 = chord, F along the chord,
the corrected C); ``catenary_exact`` solves L0 and F by Newton so the cable closes on the chord.
The solves work in each cable's vertical plane. The derivation, the signs against the paper's
Section IV and its misprints: doc/theory.md, section "The elastic catenary".
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from cdpr_dynamics.models.base import (row_norm, CableAssembly, CableSet, anchor_series,
                                       axial_transverse, massless_assembly)


# --------------------------------------------------------------------------- closed forms

_all = np.logical_and.reduce            # ndarray.all without its wrapper (on arrays)


def _every(flags) -> bool:
    """Whether every entry of a bool array is True: Python's all() over its list, ~10x
    cheaper than the ufunc reduction on the few entries of a robot's cables."""
    return all(flags.ravel().tolist())


def _some(flags) -> bool:
    """Whether any entry of a bool array is True (as :func:`_every`)."""
    return any(flags.ravel().tolist())


def _asinhc(x):
    """asinh(x)/x for x >= 0 (numpy's asinh keeps full relative precision near 0: the quotient
    equals the series 1 - x^2/6 + 3 x^4/40 there to 1e-16; x = 0 gives 1)."""
    x = np.maximum(x, 1e-300)
    return np.arcsinh(x) / x


class _Parts(NamedTuple):
    """Intermediate quantities of the closed forms (see the module docstring)."""

    v: np.ndarray         # F.e
    h_vec: np.ndarray     # F - V e (in a cable's plane: its signed horizontal component f_h)
    h2: np.ndarray        # H^2
    t_b: np.ndarray       # tension at B (|F|)
    t_a: np.ndarray       # tension at A
    p: np.ndarray
    q: np.ndarray
    s: np.ndarray
    min_tension: np.ndarray
    a1: np.ndarray        # V - gamma L0, the vertical component of the tension vector at A


def _closed_forms(v, h_vec, h2, length, gamma) -> _Parts:
    """:class:`_Parts` from V = F.e, H_vec (or f_h) and H^2 = |H_vec|^2 (module docstring).

    The caller ignores numpy's floating-point warnings (trial states past slack give inf/nan)."""
    a1 = v - gamma * length
    t_b = np.sqrt(h2 + v * v)
    t_a = np.sqrt(h2 + a1 * a1)
    same = v * a1 > 0.0
    taut = _every(same)                 # no low point in any cable: one branch (same numbers)
    total = v + a1
    p = total / (v * t_a + a1 * t_b)
    if not taut:
        p = np.where(same, p, (h2 + t_a * t_b - v * a1) / ((t_a + t_b) * h2))
    s = length * total / (t_a + t_b)
    lp = length * p
    q = lp * _asinhc(gamma * lp)
    # lowest tension: at an end, or H where the tangent is horizontal inside the cable
    min_tension = np.minimum(t_a, t_b)
    if not taut:
        min_tension = np.where(same, min_tension, np.sqrt(h2))
    return _Parts(v, h_vec, h2, t_b, t_a, p, q, s, min_tension, a1)


def _parts(force, length, gamma, up) -> _Parts:
    force = np.asarray(force, dtype=float)
    length = np.asarray(length, dtype=float)
    up = np.asarray(up, dtype=float)
    v = force @ up if up.ndim == 1 else np.einsum('...i,...i->...', force, up)
    h_vec = force - v[..., None] * up
    h2 = np.einsum('...i,...i->...', h_vec, h_vec)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        return _closed_forms(v, h_vec, h2, length, gamma)


def _flexibility_terms(r: _Parts, length, ea):
    """(L0/EA + q, L0 p/(T_A T_B), s/(T_A T_B)): C = (L0/EA + q) I + (L0 p H^2/(T_A T_B) - q)
    e e^T - L0 p/(T_A T_B) H_vec H_vec^T - s/(T_A T_B) (H_vec e^T + e H_vec^T) (Eq. 29)."""
    tt = r.t_a * r.t_b
    return length / ea + r.q, length * r.p / tt, r.s / tt


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
    c_nn, k, m = _flexibility_terms(r, length, ea)
    ee = up[..., :, None] * up[..., None, :]
    hh = r.h_vec[..., :, None] * r.h_vec[..., None, :]
    he = r.h_vec[..., :, None] * up[..., None, :]
    c = c_nn[..., None, None] * np.eye(3) + (k * r.h2 - r.q)[..., None, None] * ee
    return c - k[..., None, None] * hh - m[..., None, None] * (he + np.swapaxes(he, -1, -2))


def tensions(force, unstrained_length, gamma, up):
    """(tension at B, tension at A, lowest tension along the cable), each shape (...)."""
    r = _parts(force, unstrained_length, gamma, up)
    return r.t_b, r.t_a, r.min_tension


def up_and_weight(cables: CableSet) -> tuple[np.ndarray, float]:
    """Unit up vector and the effective weight per length (0 without gravity)."""
    g = np.asarray(cables.gravity_m_s2, dtype=float).ravel()
    norm = math.sqrt(g.dot(g))          # np.linalg.norm's own arithmetic, without its wrapper
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
    cos_theta = row_norm(horizontal) / length
    t = np.asarray(cables.tension_n, dtype=float)
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = gamma * length * cos_theta / t
        sag_ratio = ratio / 8.0
        lam2 = ratio ** 2 * cables.ea_n / (t * (1.0 + 8.0 * sag_ratio ** 2))
    out = lam2 if t.min() > 0.0 else np.where(t > 0, lam2, np.inf)
    out.setflags(write=False)
    return out


# --------------------------------------------------------------------------- the cable planes

class _Planes(NamedTuple):
    """The vertical plane of each cable's chord (module docstring, "In the plane"), per pose.

    ``horizontal`` (n, 3) the unit h, ``span_h``/``span_v`` (n,) l = -chord as l_h h + l_v e,
    ``tol_scale`` max(L, 1) (m) of the closure tests, ``cos_h``, ``cos_v`` l/|l| in the plane
    and ``sin2`` 1 - cos_v^2 (the parabola start of :func:`solve`); ``doubled`` the same with
    the spans and lengths repeated (2n,), for :func:`_residual` of two starts per cable in one
    pass."""

    up: np.ndarray
    gamma: float
    ea: float
    length: np.ndarray
    unit: np.ndarray
    horizontal: np.ndarray
    span_h: np.ndarray
    span_v: np.ndarray
    tol_scale: np.ndarray
    cos_h: np.ndarray
    cos_v: np.ndarray
    sin2: np.ndarray
    doubled: '_Planes | None' = None     # span_h, span_v, length repeated: two starts at once


#: {(chord bytes, chord shape, gravity bytes, EA, gamma): _Planes}: the last ``_PLANES_KEPT``
_PLANES: dict = {}
_PLANES_KEPT = 4


def _planes(cables: CableSet) -> _Planes:
    """:class:`_Planes` of ``cables``, kept for the last few chords (a pose's statics and
    model ask for the same chords at many tensions; keyed by the arrays' bytes, i.e. by value,
    so never stale: a chord changed in place is a new key)."""
    chord = np.asarray(cables.chord_m, dtype=float)
    gravity = np.asarray(cables.gravity_m_s2, dtype=float)
    key = (chord.tobytes(), chord.shape, gravity.tobytes(), float(cables.ea_n),
           float(cables.weight_per_length_n_per_m))
    planes = _PLANES.get(key)
    if planes is None:
        planes = _PLANES[key] = _make_planes(cables, chord)
        while len(_PLANES) > _PLANES_KEPT:            # the oldest first (insertion order)
            _PLANES.pop(next(iter(_PLANES)), None)
    return planes


def _make_planes(cables: CableSet, chord: np.ndarray) -> _Planes:
    up, gamma = up_and_weight(cables)
    length = row_norm(chord)
    span_v = -(chord @ up)
    horizontal = -chord - span_v[:, None] * up
    span_h = row_norm(horizontal)
    level = span_h > 1e-12 * length         # else a vertical chord: any horizontal h will do
    if _every(level):
        horizontal = horizontal / span_h[:, None]
    else:
        axis = np.eye(3)[int(np.argmin(np.abs(up)))]
        axis = axis - (axis @ up) * up
        horizontal = np.where(level[:, None], horizontal / np.where(level, span_h, 1.0)[:, None],
                              axis / np.linalg.norm(axis))
        span_h = np.where(level, span_h, 0.0)
    cos_v = span_v / length
    twice = np.concatenate([[span_h, span_v, length]] * 2, axis=1)
    planes = _Planes(up, gamma, float(cables.ea_n), length, chord / length[:, None], horizontal,
                     span_h, span_v, np.maximum(length, 1.0), span_h / length, cos_v,
                     1.0 - cos_v * cos_v)
    for array in (*planes, twice):       # shared through the cache: read-only
        if isinstance(array, np.ndarray):
            array.flags.writeable = False
    return planes._replace(doubled=planes._replace(span_h=twice[0], span_v=twice[1],
                                                   length=twice[2]))


def _in_plane(force, planes: _Planes):
    """(f_h, f_v) of forces (n, 3) in their cables' planes (their normal part dropped)."""
    return np.add.reduce(force * planes.horizontal, axis=1), force @ planes.up


def _lift(f_h, f_v, planes: _Planes):
    """Vectors (n, 3) f_h h + f_v e from their components in the cables' planes."""
    return f_h[:, None] * planes.horizontal + f_v[:, None] * planes.up


def _plane_stiffness(f_h, f_v, l0, planes: _Planes, r: _Parts) -> np.ndarray:
    """K = C^-1 (n, 3, 3) of in-plane catenaries: C is block diagonal in (h, e; n) with
    c_hh = c_nn - k f_h^2, c_he = -m f_h, c_ee = L0/EA + k f_h^2, c_nn = L0/EA + q
    (:func:`_flexibility_terms`), inverted in closed form (symmetric by construction)."""
    c_nn, k, m = _flexibility_terms(r, l0, planes.ea)
    kh2 = k * r.h2
    c_hh, c_ee, c_he = c_nn - kh2, l0 / planes.ea + kh2, -m * f_h
    inv_det = 1.0 / (c_hh * c_ee - c_he * c_he)
    k_nn = 1.0 / c_nn
    h, up = planes.horizontal, planes.up
    he = h[:, :, None] * up                                 # h e^T, then + e h^T below
    return (k_nn[:, None, None] * np.eye(3)
            + (c_ee * inv_det - k_nn)[:, None, None] * (h[:, :, None] * h[:, None, :])
            + (c_hh * inv_det - k_nn)[:, None, None] * (up[:, None] * up)
            - (c_he * inv_det)[:, None, None] * (he + he.transpose(0, 2, 1)))


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


def _residual(x, planes: _Planes, t_inv, scale):
    """(residual (3, n) of the closure (h, e) and of |F| = T, the :class:`_Parts` of it) at
    x = (f_h, f_v, L0) (3, n); ``t_inv`` 1/T, ``scale`` the tension row's scale (m)."""
    f_h, f_v, l0 = x
    r = _closed_forms(f_v, f_h, f_h * f_h, l0, planes.gamma)
    elastic = l0 / planes.ea
    return np.array([(elastic + r.q) * f_h - planes.span_h,
                     elastic * (f_v - (0.5 * planes.gamma) * l0) + r.s - planes.span_v,
                     scale * (r.t_b * t_inv - 1.0)]), r


def _column_norm(res):
    return np.sqrt(np.add.reduce(res * res, axis=0))


def _adjugate_solve(x, planes: _Planes, r: _Parts, rhs_h, rhs_v):
    """det(C) and adj(C) [g, rhs] (2, 2, n) in the plane: g = dl/dL0 = (1/EA + 1/T_A)(F - gamma
    L0 e) (the tension vector at A), C = [c_hh c_he; c_he c_ee] the in-plane flexibility
    (module docstring), so that C^-1 g = out[:, 0]/det and C^-1 rhs = out[:, 1]/det (rhs_h,
    rhs_v arrays (n,))."""
    f_h, l0 = x[0], x[2]
    elastic = l0 / planes.ea
    tt = r.t_a * r.t_b                      # _flexibility_terms, L0/EA once
    k, m = l0 * r.p / tt, r.s / tt
    kh2 = k * r.h2
    c_hh, c_ee, c_he = elastic + r.q - kh2, elastic + kh2, -m * f_h
    g = 1.0 / planes.ea + 1.0 / r.t_a
    b = np.array([[g * f_h, rhs_h], [g * r.a1, rhs_v]])        # a1 = f_v - gamma L0
    adj = np.array([c_ee * b[0] - c_he * b[1], c_hh * b[1] - c_he * b[0]])
    return c_hh * c_ee - c_he * c_he, adj


def _newton_step(x, res, planes: _Planes, row_scale, r: _Parts) -> np.ndarray:
    """Newton step (3, n) of (f_h, f_v, L0) for ``res``: [C g; d^T 0] step = -res with C the
    in-plane flexibility, g = dl/dL0, d = row_scale F/|F| (the 4x4 system of the module
    docstring without its normal row, which is zero in the plane), by block elimination with
    u = C^-1 res_l, w = C^-1 g: dL0 = (res_T - d.u)/(d.w), dF = -u - w dL0."""
    det, adj = _adjugate_solve(x, planes, r, res[0], res[1])        # adj[:, 0] = det w, ...
    d_adj = (row_scale / r.t_b) * (x[0] * adj[0] + x[1] * adj[1])   # (d.w, d.u) det
    dl0 = (res[2] * det - d_adj[1]) / d_adj[0]
    return np.concatenate([-(adj[:, 1] + adj[:, 0] * dl0) / det, dl0[None]])


#: a solution of :func:`solve` is accepted at this residual (closure over max(L, 1), tension
#: relative)
ACCEPT_TOLERANCE = 1e-9


def solve(cables: CableSet, max_iterations: int = 60,
          min_tension_ratio: float = 1e-6, start: CatenaryState | None = None,
          max_halvings: int = 30, tolerance: float = 1e-13) -> CatenaryState:
    """Newton on (F, L0) per cable: the end closes on the chord and |F| = T_i.

    Starts from the taut parabola (L0 = L/(1 + T/EA) and F with |F| = T such that the mean
    tension vector F - gamma L0 e/2 lies along the chord, its first-order closure: F = c l/|l|
    + gamma L0/2 e, c = -g cos + sqrt(T^2 - g^2 sin^2), g = gamma L0/2, cos = e.l/|l|; used
    where g < T/4, else the straight cable F = -T u), or from ``start`` (a nearby solution,
    e.g. of the previous pose or tension: its end-force direction in this chord's plane and
    L0, the force rescaled to |F| = T_i) where that cable was valid and its start is closer;
    damped by step halving. Newton works in each cable's plane (module docstring: F = f_h h +
    f_v e, three unknowns f_h, f_v, L0 and three equations, closed-form steps) and stops at a
    residual of ``tolerance`` max(L, 1) (the end closure in m, the tension scaled by L); a
    solution is accepted (valid) at a closure below ``ACCEPT_TOLERANCE`` max(L, 1) and a
    relative tension error below ``ACCEPT_TOLERANCE``, so on chords of at least
    ``tolerance``/``ACCEPT_TOLERANCE`` (0.1 m at 1e-10) a ``tolerance`` up to 1e-10 changes no
    verdict, only the last digits of F and L0 (a shorter chord can stop within ``tolerance``
    with its tension row, scaled by L, short of acceptance).
    A cable is invalid when T_i <= 0, when Newton does not converge (no catenary with that end
    tension spans the chord) or when the tension somewhere along it is below
    ``min_tension_ratio`` times T_i (slack: it cannot hold its own weight). ``max_iterations``
    and ``max_halvings`` (of each Newton step) bound the work, e.g. for cheap existence probes.
    """
    return _solve(cables, max_iterations, min_tension_ratio, start, max_halvings, tolerance)[0]


def solve_with_sensitivity(cables: CableSet, start: CatenaryState | None = None,
                           warm_only: bool = False
                           ) -> tuple[CatenaryState, np.ndarray, np.ndarray]:
    """(:func:`solve` (default tolerances), then its :func:`tension_sensitivity`): the
    sensitivity from the solve's own last evaluation at the solution (its in-plane (f_h, f_v,
    L0) and closed forms) instead of the lifted forces projected back into the planes: the
    same numbers to rounding, without a second evaluation (the sag statics' SQP asks for both
    at every accepted iterate).

    ``warm_only``: where every live cable's ``start`` is valid, Newton starts from it alone,
    without the parabola beside it (for a first-order prediction of the solution, as the SQP's
    trial steps give, the better start: the same solution to rounding); where that leaves any
    cable invalid, the general solve decides (the same verdicts and reasons)."""
    if warm_only and start is not None:
        out = _solve(cables, 60, 1e-6, start, 30, 1e-13, True)
        if out is not None and _every(out[0].valid):
            return (out[0], *_sensitivity(out[1], out[2], out[3], out[0].valid))
    state, x, parts, planes = _solve(cables, 60, 1e-6, start, 30, 1e-13)
    return (state, *_sensitivity(x, parts, planes, state.valid))


def _parabola_start(t_safe, planes: _Planes) -> np.ndarray:
    """x = (f_h, f_v, L0) (3, n) of :func:`solve`'s taut parabola start (its docstring), the
    straight cable where g >= T/4; the caller ignores floating-point warnings."""
    cos_h, cos_v = planes.cos_h, planes.cos_v                          # l/|l| in the plane
    x = np.array([t_safe * cos_h, t_safe * cos_v, planes.length / (1.0 + t_safe / planes.ea)])
    if planes.gamma > 0.0:
        g = 0.5 * planes.gamma * x[2]
        disc = t_safe * t_safe - g * g * planes.sin2
        taut = (g < 0.25 * t_safe) & (disc > 0.0)
        if _every(taut):
            c = -g * cos_v + np.sqrt(disc)
            x[0], x[1] = c * cos_h, c * cos_v + g
        else:
            c = -g * cos_v + np.sqrt(np.where(taut, disc, 1.0))
            x[:2] = np.where(taut, [c * cos_h, c * cos_v + g], x[:2])
    return x


def _warm_start(start: CatenaryState, planes: _Planes, t_safe):
    """(f_h, f_v, L0) of a nearby solution: its end force in this chord's plane rescaled to
    |F| = T, its L0."""
    f_h, f_v = _in_plane(np.asarray(start.force_n, dtype=float), planes)
    rescale = t_safe / np.sqrt(f_h * f_h + f_v * f_v)
    return f_h * rescale, f_v * rescale, start.unstrained_length_m


def _solve(cables, max_iterations, min_tension_ratio, start, max_halvings, tolerance,
           warm_only=False):
    """:func:`solve`, returning (state, x = (f_h, f_v, L0) (3, n) before the invalid cables'
    stand-ins, the :class:`_Parts` of x, the planes); ``warm_only``
    (:func:`solve_with_sensitivity`): from ``start`` alone, None where a live cable's start is
    not valid."""
    planes = _planes(cables)
    gamma, length = planes.gamma, planes.length
    tension = np.asarray(cables.tension_n, dtype=float)
    n = length.size
    live = tension > 0
    t_safe = tension if _every(live) else np.where(live, tension, 1.0)
    t_inv = 1.0 / t_safe
    with np.errstate(all='ignore'):       # trial states past slack give inf/nan: rejected
        if warm_only:
            if not _every(start.valid | ~live):
                return None
            x = np.array(_warm_start(start, planes, t_safe))
            res, parts = _residual(x, planes, t_inv, length)
            norm = _column_norm(res)
        elif start is None:
            x = _parabola_start(t_safe, planes)
            res, parts = _residual(x, planes, t_inv, length)
            norm = _column_norm(res)
        else:   # per cable the better start: the nearby solution or the parabola
            both = np.concatenate([_parabola_start(t_safe, planes),
                                   _warm_start(start, planes, t_safe)], axis=1)
            twice = planes.doubled
            res, parts = _residual(both, twice, np.concatenate([t_inv, t_inv]),
                                   twice.length)                 # both starts in one pass
            norm = _column_norm(res)
            warm = start.valid & live & (norm[n:] < norm[:n])
            if _every(warm):
                x, res, norm = both[:, n:], res[:, n:], norm[n:]
                parts = _Parts(*(field[n:] for field in parts))
            elif _some(warm):    # (the parts again at x: the ufuncs' last bits depend on
                x = np.where(warm, both[:, n:], both[:, :n])     # the array's length)
                res = np.where(warm, res[:, n:], res[:, :n])
                norm = np.where(warm, norm[n:], norm[:n])
                parts = None
            else:
                x, res, norm = both[:, :n], res[:, :n], norm[:n]
                parts = _Parts(*(field[:n] for field in parts))
        tol = tolerance * planes.tol_scale
        x, res, iterations, parts = _newton(x, res, norm, tol, live, planes, t_inv, length,
                                            max_iterations, max_halvings, parts)
        if parts is None:
            parts = _residual(x, planes, t_inv, length)[1]
        t_a, t_min = parts.t_a, parts.min_tension
        residual = np.sqrt(res[0] * res[0] + res[1] * res[1])
        finite = np.isfinite(residual)
        if not _every(finite):
            residual = np.where(finite, residual, np.inf)
        tension_error = np.abs(res[2]) / length
        converged = live & (residual <= ACCEPT_TOLERANCE * planes.tol_scale) & (
            tension_error <= ACCEPT_TOLERANCE)
        taut = t_min > min_tension_ratio * t_safe
    valid = converged & taut
    l0 = x[2]
    reasons = []
    all_valid = _every(valid)
    for i in (range(n) if not all_valid else ()):
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
    force = _lift(x[0], x[1], planes)
    if not all_valid:
        force = np.where(valid[:, None], force, -np.maximum(tension, 0.0)[:, None] * planes.unit)
        l0 = np.where(valid, l0, length)
        t_a = np.where(valid, t_a, np.maximum(tension, 0.0))
        t_min = np.where(valid, t_min, np.minimum(tension, 0.0))
    return (CatenaryState(force, l0, t_a, t_min, residual, iterations, valid, tuple(reasons)),
            x, parts, planes)


def _jacobian(force, l0, ea, gamma, up, row_scale, parts: _Parts | None = None
              ) -> np.ndarray:
    """(n, 4, 4) derivative of (end position, row_scale |F|) with respect to (F, L0), in 3D.

    d l = C dF + (1/EA + 1/T_A) (F - gamma L0 e) dL0 (C of :func:`flexibility`; F - gamma L0 e
    is the tension vector at A) and d|F| = F.dF/|F|; ``parts`` those of (F, L0) if known.
    The reference of the in-plane steps (:func:`_newton_step`, :func:`tension_sensitivity`).
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
    :func:`_jacobian`; in the cable's plane with w = C^-1 dl/dL0 and d = F/|F|:
    dL0/dT = -1/(d.w), dF/dT = w/(d.w)). The force on the platform changes by -dF/dT per
    newton of end tension: along the end tangent by 1, plus a turn of the tangent as the sag
    changes. Finite only for valid cables away from the fold where T stops falling as L0
    grows (NaN elsewhere).
    """
    planes = _planes(cables)
    f_h, f_v = _in_plane(np.asarray(state.force_n, dtype=float), planes)
    x = (f_h, f_v, np.asarray(state.unstrained_length_m, dtype=float))
    with np.errstate(all='ignore'):
        r = _closed_forms(f_v, f_h, f_h * f_h, x[2], planes.gamma)
    return _sensitivity(x, r, planes, state.valid)


def _sensitivity(x, r: _Parts, planes: _Planes, valid) -> tuple[np.ndarray, np.ndarray]:
    """:func:`tension_sensitivity` at x = (f_h, f_v, L0) with its :class:`_Parts` ``r``, NaN
    where not ``valid`` or not finite."""
    f_h, f_v = x[0], x[1]
    with np.errstate(all='ignore'):
        det, adj = _adjugate_solve(x, planes, r, f_h, f_v)          # rhs unused here
        w = adj[:, 0]                                                 # det C^-1 g
        d_w = (f_h * w[0] + f_v * w[1]) / r.t_b                       # det (d.w)
        out = np.concatenate([w / d_w, (-det / d_w)[None]])
    finite = np.isfinite(out)
    if not (_every(finite) and _every(valid)):
        out = np.where(valid & _all(finite, axis=0), out, np.nan)
    return _lift(out[0], out[1], planes), out[2]


def _newton(x, res, norm, tol, live, planes: _Planes, t_inv, scale, max_iterations,
            max_halvings=30, parts=None):
    """Damped Newton iterations of :func:`solve` on x = (f_h, f_v, L0) (3, n), vectorised over
    cables; the caller ignores floating-point warnings.

    ``parts``: the :class:`_Parts` of the starting x or None; returned likewise for the final
    state (None where it is not known: the caller computes them), so that one evaluation per
    iteration serves the residual, the next step and the final tensions."""
    iterations = 0
    row_scale = scale * t_inv
    for iterations in range(1, max_iterations + 1):
        todo = live & (norm > tol)
        if not _some(todo):
            break
        if parts is None:
            parts = _residual(x, planes, t_inv, scale)[1]
        step = _newton_step(x, res, planes, row_scale, parts)
        ok = todo & _all(np.isfinite(step), axis=0)
        if not _every(ok):
            step = np.where(ok, step, 0.0)
        trial = x + step                    # the full step first
        positive = trial[2] > 0
        if not _every(positive):
            trial[2] = np.where(positive, trial[2], x[2])   # evaluated at the old L0
        trial_r, trial_p = _residual(trial, planes, t_inv, scale)
        trial_n = _column_norm(trial_r)
        good = ok & positive & np.isfinite(trial_n) & ((trial_n < norm) | (trial_n <= tol))
        if _every(good | ~ok):
            # all at the full step: cables without a step (step 0) sit where they were
            if not _some(good):
                break
            x, res, parts, norm = trial, trial_r, trial_p, trial_n
            continue
        # else halve the steps of the cables that did not improve, one halving at a time
        new_x = np.where(good, trial, x)
        new_res = np.where(good, trial_r, res)
        improve = good
        alpha = np.where(improve, 1.0, 0.5)
        for _ in range(1, max_halvings):
            trial = x + alpha * step
            positive = trial[2] > 0
            if not _every(positive):
                trial[2] = np.where(positive, trial[2], x[2])
            trial_r = _residual(trial, planes, t_inv, scale)[0]
            trial_n = _column_norm(trial_r)
            good = ok & ~improve & positive & np.isfinite(trial_n) & (
                (trial_n < norm) | (trial_n <= tol))
            new_x = np.where(good, trial, new_x)
            new_res = np.where(good, trial_r, new_res)
            improve |= good
            if _every(improve | ~ok):
                break
            alpha = np.where(improve, alpha, 0.5 * alpha)
        if not _some(improve):
            break
        x, res, parts = new_x, new_res, None
        norm = _column_norm(res)
    return x, res, iterations, parts


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


def _stiffness(f_h, f_v, l0, cables, ok, parts: _Parts | None = None) -> np.ndarray:
    """K = C^-1 where ``ok`` (:func:`_plane_stiffness` of the in-plane end forces f_h, f_v),
    the placeholder spring elsewhere; ``parts`` of (f_h, f_v, l0) where the caller has them."""
    planes = _planes(cables)
    with np.errstate(all='ignore'):
        if parts is None:
            parts = _closed_forms(f_v, f_h, f_h * f_h, l0, planes.gamma)
        stiffness = _plane_stiffness(f_h, f_v, l0, planes, parts)
    if _every(ok):
        return stiffness
    return np.where(ok[:, None, None], stiffness, _placeholder(cables))


#: Newton tolerance of the paper catenary's existence test (:func:`solve`: same verdicts)
EXISTENCE_TOLERANCE = 1e-10
#: end tension over the weight of a chord's length above which :func:`exists` needs no solve
EXPLICIT_EXISTENCE_RATIO = 2.0


def exists(cables: CableSet) -> np.ndarray:
    """(n,) bool: whether a taut elastic catenary with end tension T_i spans each chord, the
    verdict of :func:`solve` at ``EXISTENCE_TOLERANCE`` (the paper catenary's test), decided
    without the Newton solve where it is foregone.

    Explicit test: T_i >= 2 gamma L_i (the cable's weight over its chord at most half its end
    tension) and L_i >= EXISTENCE_TOLERANCE/ACCEPT_TOLERANCE = 0.1 m. Such a catenary exists
    (the least end tension at which one spans a chord, :func:`cdpr_dynamics.mechanics.statics.
    lowest_tension`, is at most ~1.05 gamma L, for chords ~60 degrees steep with the platform
    end on top; gamma L for a vertical one hanging from it; ~0.75 gamma L for a level one),
    stays taut (its tension is above T_i - gamma L0 > 0 at the ends and H > 0 at a low point)
    and the solve's taut parabola start (used where gamma L0/2 < T/4, here always) is
    first-order exact in gamma L/T: Newton converges in a few steps (at most 4 iterations)
    (``test/test_catenary_kernels.py`` compares the verdicts over random chords, inclinations,
    tensions and EA, and checks the bound on the least tension). The length bound keeps the
    solve's stopping test (``EXISTENCE_TOLERANCE`` max(L, 1) on the tension row scaled by L)
    within its acceptance test (``ACCEPT_TOLERANCE`` relative): shorter chords can stop just
    short of acceptance, a verdict only the solve gives. Where any cable fails the test all
    are solved (one vectorised solve costs the same for one cable or all); weightless cables
    exist for T > 0.
    """
    planes = _planes(cables)
    tension = np.asarray(cables.tension_n, dtype=float)
    if planes.gamma == 0.0:
        return tension > 0
    length = planes.length
    sure = (tension >= EXPLICIT_EXISTENCE_RATIO * planes.gamma * length) & (
        length >= EXISTENCE_TOLERANCE / ACCEPT_TOLERANCE)
    return sure if _every(sure) else solve(cables, tolerance=EXISTENCE_TOLERANCE).valid


def build(cables: CableSet, elements_per_cable: int = 1) -> CableAssembly:
    """``catenary``: the paper's modified method, L0 = chord, F = T_i along the chord.

    ``elements_per_cable`` is ignored (massless, one node). Invalid (placeholder spring
    stiffness, a warning) where T_i <= 0 or the tension along the cable would reach zero.
    """
    planes = _planes(cables)
    gamma = planes.gamma
    tension = np.asarray(cables.tension_n, dtype=float)
    length = planes.length
    f_h, f_v, parts = _paper_catenary(cables)     # T_i <= 0 (clamped to 0 there): invalid
    t_min = parts.min_tension
    spans = exists(cables)
    ok = (tension > 0) & (t_min > 1e-6 * np.abs(tension)) & spans
    valid = bool(ok.all())
    warnings = []
    for i in () if valid else np.flatnonzero(~ok):
        if not tension[i] > 0:
            warnings.append(f'cable {i} is slack (T = {tension[i]:.3g} N <= 0)')
        elif not spans[i]:
            warnings.append(f'cable {i}: no taut elastic catenary with end tension '
                            f'{tension[i]:.3g} N spans its chord of {length[i]:.4g} m (cable '
                            f'weight {gamma * length[i]:.3g} N): the paper\'s catenary assumes '
                            'one that cannot exist')
        else:
            warnings.append(f'cable {i} is slack: tension {tension[i]:.3g} N at the platform '
                            f'cannot hold the {gamma * length[i]:.3g} N cable hanging below it')
    stiffness = anchor_series(_stiffness(f_h, f_v, length, cables, ok, parts), cables)
    return massless_assembly('catenary', stiffness,
                             tension[:, None] * planes.unit, valid, warnings)


def paper_misclosure(cables: CableSet) -> np.ndarray:
    """(n,) m: how far the paper's assumed catenary (L0 = chord, end force T_i along the chord)
    ends from the anchor, |l(F, L0) - l_chord| of Eq. 25 (in the cables' planes: the closure
    rows of :func:`_residual`); 0 for weightless cables up to the elastic stretch T L/EA that
    L0 = chord leaves out."""
    planes = _planes(cables)
    f_h, f_v, r = _paper_catenary(cables)
    elastic = planes.length / planes.ea
    with np.errstate(all='ignore'):
        miss_h = (elastic + r.q) * f_h - planes.span_h              # as _residual's rows
        miss_v = elastic * (f_v - (0.5 * planes.gamma) * planes.length) + r.s - planes.span_v
    return np.sqrt(miss_h * miss_h + miss_v * miss_v)


@functools.lru_cache(maxsize=8)
def _paper_catenary(cables: CableSet):
    """(f_h, f_v, :class:`_Parts`) of the paper's assumed catenaries (L0 = chord, end force
    max(T_i, 0) along the chord, in the cables' planes), kept for the last few CableSets
    (immutable): the model (:func:`build`) and its misclosure warning ask for the same."""
    planes = _planes(cables)
    tension = np.maximum(np.asarray(cables.tension_n, dtype=float), 0.0)
    length = planes.length
    f_h, f_v = tension * planes.span_h / length, tension * planes.span_v / length   # -T u
    with np.errstate(all='ignore'):
        parts = _closed_forms(f_v, f_h, f_h * f_h, length, planes.gamma)
    return f_h, f_v, parts


def state_of(cables: CableSet) -> CatenaryState:
    """The catenaries of ``cables``: those the statics solved (``cables.sag_state``), or solved
    here at ``cables.tension_n``."""
    return cables.sag_state if cables.sag_state is not None else solve(cables)


def build_exact(cables: CableSet, elements_per_cable: int = 1) -> CableAssembly:
    """``catenary_exact``: Newton-consistent L0 and end force per cable (see :func:`solve`)."""
    state = state_of(cables)
    f_h, f_v = _in_plane(state.force_n, _planes(cables))
    stiffness = anchor_series(
        _stiffness(f_h, f_v, state.unstrained_length_m, cables, state.valid), cables)
    return massless_assembly('catenary_exact', stiffness, -state.force_n,
                             bool(np.all(state.valid)), state.reasons)
