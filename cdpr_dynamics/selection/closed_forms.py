"""Closed forms behind ``auto``'s error estimates: per-cable scales, continuous cables, chains.

* :func:`scene`: what decides which model a scene needs, per cable (Irvine's lambda^2, the
  wave tension, first transverse and axial modes, the sag direction);
* :func:`wave_tension`: the uniform tension of a string with the cable's transit time of
  transverse waves along its catenary (where its string modes lie);
* :func:`dispersion_error`: a consistent-mass FEM chain of n elements on the j-th fixed-fixed
  string mode, sqrt(6(1 - cos t)/(2 + cos t))/t - 1 at t = j pi / n;
* :func:`irvine_symmetric_ratio`: Irvine's first symmetric in-plane mode of a sagged cable;
* :func:`true_end_stiffness`: the closed-form sag-aware dynamic end stiffness of a continuous
  shallow inclined cable (Irvine, Cable Structures, 1981, ch. 3) at its :func:`wave_tension`, i.e.
  the exact straight-cable dynamic stiffness of ``dsm`` with Irvine's dynamic sag compliance
  in series with the axial one and its coupling to the in-plane normal direction. Its axial
  stiffness is Ernst's (EA + T)/L / (1 + lambda^2/12) statically and vanishes at Irvine's
  symmetric in-plane modes tan(w/2) = w/2 - (4/lambda^2)(w/2)^3. Against fem_sag n = 256 it
  agrees to 1e-5 on the paper's robot and to 0.3 % at lambda^2 = 334 (test_selection);
* :func:`model_end_stiffness`: each model's end stiffness as the estimates see it (spring, the
  FEM chain recursion, the catenary stiffness; ``fem_sag`` n: the truth keeping (1 - 1/n^2)
  of the sag compliance, the midpoint rule of n straight elements, plus the straight chain's
  discretisation error).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics import models
from cdpr_dynamics.models.base import CableSet, anchor_series, axial_transverse
from cdpr_dynamics.models.catenary import sag_parameter, up_and_weight
from cdpr_dynamics.models.dsm import z_cot_z


class SelectionError(ValueError):
    """No cable model can describe the scene (e.g. a cable without tension)."""


# --------------------------------------------------------------------------- closed forms

def dispersion_error(t) -> np.ndarray:
    """Relative error sqrt(6(1 - cos t)/(2 + cos t))/t - 1 of a consistent-mass FEM chain on a
    fixed-fixed string mode of phase t = j pi / n per element (t^2/24 for small t)."""
    t = np.asarray(t, dtype=float)
    return np.sqrt(chain_frequency_ratio_squared(t * t).real) - 1.0


def largest_phase(tolerance: float) -> float:
    """The largest t in (0, pi] with :func:`dispersion_error` (t) <= ``tolerance``."""
    if dispersion_error(math.pi) <= tolerance:
        return math.pi
    lo, hi = 0.0, math.pi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if dispersion_error(mid) <= tolerance else (lo, mid)
    return lo


def irvine_symmetric_ratio(lam2) -> np.ndarray:
    """First symmetric in-plane frequency of a sagged cable over the taut string's (pi).

    Root w of tan(w/2) = w/2 - (4/lambda^2)(w/2)^3 in (pi, 3pi) (Irvine 1981, Eq. 3.59),
    divided by pi: 1 at lambda^2 = 0, 2 at lambda^2 = 4 pi^2, 2.86 as lambda^2 -> inf.
    """
    lam2 = np.atleast_1d(np.asarray(lam2, dtype=float))
    lo = np.full(lam2.shape, 0.5 * math.pi)
    hi = np.full(lam2.shape, 1.5 * math.pi)
    with np.errstate(divide='ignore', invalid='ignore'):
        for _ in range(64):                 # h(x) = tan x - x + 4 x^3/lambda^2 increases
            x = 0.5 * (lo + hi)
            h = np.tan(x) - x + np.where(lam2 > 0, 4.0 * x ** 3 / lam2, np.inf)
            h = np.where(lam2 == np.inf, np.tan(x) - x, h)
            lo, hi = np.where(h < 0, x, lo), np.where(h < 0, hi, x)
    return np.where(lam2 > 0, (lo + hi) / math.pi, 1.0)


def _sag_compliance(w2: np.ndarray) -> np.ndarray:
    """(tan(w/2)/(w/2) - 1)/w^2 as a function of w^2 (complex), 1/12 + w^2/120 near 0."""
    w2 = np.asarray(w2, dtype=complex)
    w = np.sqrt(w2)
    w = np.where(w.imag < 0, -w, w)
    small = np.abs(w) < 1e-2
    x = np.where(small, 1.0, 0.5 * w)
    with np.errstate(all='ignore'):
        direct = (np.tan(x) / x - 1.0) / np.where(small, 1.0, w2)
    return np.where(small, 1.0 / 12.0 + w2 / 120.0, direct)


_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(24)


def wave_tension(cables: CableSet) -> np.ndarray:
    """(n,) the uniform tension T_w whose taut string over the chord L has the cable's transit
    time of transverse waves, t = integral of sqrt(mu / T(s)) ds along it: T_w = mu (L / t)^2.

    The string modes of a cable whose tension varies along it lie near j / (2 t) (WKB), not
    at the end tension's. Along the elastic catenary of sag-consistent statics
    (``cables.sag_state``) the tension is |F_B - gamma s up| at the unstrained arc length s
    from the platform end (F_B the force on the cable there): with H its part normal to up
    and x = F_B . up - gamma s, t = sqrt(mu)/gamma * integral of (H^2 + x^2)^(-1/4) dx,
    taken as sqrt(mu H)/gamma * integral of sqrt(cosh u) du over x = H sinh u (smooth where a
    heavily sagged cable hangs through a low point of tension H). Without a valid catenary
    (chord statics), the tension varies linearly with height along the chord:
    t = 2 L sqrt(mu) / (sqrt(T_A) + sqrt(T_B)).
    """
    tension = np.asarray(cables.tension_n, dtype=float)
    up, gamma = up_and_weight(cables)
    if gamma == 0.0:
        return tension
    length = cables.length_m
    anchor = tension + gamma * (np.asarray(cables.chord_m) @ up)   # T_A = T_B - gamma rise
    with np.errstate(invalid='ignore'):
        out = (0.5 * (np.sqrt(np.maximum(anchor, 0.0)) + np.sqrt(tension))) ** 2
    state = cables.sag_state
    if state is None:
        return out
    force = np.asarray(state.force_n, dtype=float)
    vertical = force @ up
    horizontal = np.maximum(np.linalg.norm(force - vertical[:, None] * up, axis=1),
                            1e-12 * tension)
    top = np.arcsinh(vertical / horizontal)
    bottom = np.arcsinh((vertical - gamma * state.unstrained_length_m) / horizontal)
    u = 0.5 * (top + bottom)[:, None] + 0.5 * (top - bottom)[:, None] * _NODES
    integral = 0.5 * (top - bottom) * (np.sqrt(np.cosh(u)) @ _WEIGHTS)
    transit = np.sqrt(cables.mass_per_length_kg_m * horizontal) / gamma * integral
    wave = cables.mass_per_length_kg_m * (length / transit) ** 2
    return np.where(np.asarray(state.valid) & np.isfinite(wave), wave, out)


# --------------------------------------------------------------------------- the scene

@dataclass(frozen=True, eq=False)
class Scene:
    """Per-cable scales of a scene: what decides which model it needs (SI units, Hz)."""

    cables: CableSet
    f_max_hz: float
    sag_parameter: np.ndarray          # Irvine's lambda^2
    wave_tension_n: np.ndarray         # :func:`wave_tension`: the string of the same transit time
    transverse_hz: np.ndarray          # first fixed-fixed transverse mode sqrt(T_w/mu)/(2L)
    axial_hz: np.ndarray               # first fixed-fixed axial mode sqrt(EA/mu)/(2L)
    symmetric_shift: np.ndarray        # Irvine's first symmetric in-plane mode / pi - 1
    tension_shift: np.ndarray          # gamma |dz| / (4 T): straight models' transverse error
    sag_direction: np.ndarray          # (n, 3) unit: gravity's part normal to the chord
    normal_weight_n_per_m: np.ndarray  # gamma cos(theta): weight per length normal to the chord

    @property
    def transverse_in_band(self) -> np.ndarray:
        """Highest transverse mode index j with j f_t <= f_max, per cable."""
        return np.floor(self.f_max_hz / self.transverse_hz + 1e-12).astype(int)

    @property
    def axial_in_band(self) -> np.ndarray:
        return np.floor(self.f_max_hz / self.axial_hz + 1e-12).astype(int)

    @property
    def cable_modes_in_band(self) -> int:
        """How many fixed-fixed cable modes lie in the band (two directions transverse)."""
        return int(2 * self.transverse_in_band.sum() + self.axial_in_band.sum())


def scene(cables: CableSet, f_max_hz: float) -> Scene:
    """The :class:`Scene` of ``cables`` for the band [0, ``f_max_hz``]."""
    tension = np.asarray(cables.tension_n, dtype=float)
    if np.any(~(tension > 0)):
        i = int(np.argmin(tension))
        raise SelectionError(f'cable {i} carries no tension (T = {tension[i]:.3g} N): no cable '
                             'model describes a slack cable')
    mu = cables.mass_per_length_kg_m
    if not mu > 0:
        raise SelectionError('cables without mass: the error estimates need gamma > 0')
    length = cables.length_m
    g = np.asarray(cables.gravity_m_s2, dtype=float)
    up = -g / np.linalg.norm(g) if np.any(g) else np.array([0.0, 0.0, 1.0])
    rise = -np.asarray(cables.chord_m) @ up          # platform end above the anchor: > 0
    gamma = cables.weight_per_length_n_per_m
    lowest = tension - gamma * np.maximum(rise, 0.0)
    if np.any(~(lowest > 0)):
        i = int(np.argmin(lowest))
        raise SelectionError(f'cable {i} cannot hold its own weight: {tension[i]:.3g} N at the '
                             f'platform, {gamma * rise[i]:.3g} N of cable below it')
    wave = wave_tension(cables)
    lam2 = sag_parameter(cables)
    unit = cables.unit
    normal = -up[None, :] + (unit @ up)[:, None] * unit
    normal_norm = np.linalg.norm(normal, axis=1)
    direction = normal / np.where(normal_norm > 0, normal_norm, 1.0)[:, None]
    return Scene(cables, float(f_max_hz), lam2, wave, np.sqrt(wave / mu) / (2.0 * length),
                 np.sqrt(cables.ea_n / mu) / (2.0 * length), irvine_symmetric_ratio(lam2) - 1.0,
                 gamma * np.abs(rise) / (4.0 * tension),
                 direction, gamma * normal_norm)


# --------------------------------------------------------------------------- end stiffnesses

def chain_frequency_ratio_squared(t2) -> np.ndarray:
    """r(t)^2 = 6 (1 - cos t) / ((2 + cos t) t^2) as a function of t^2 (complex): the square
    of a consistent-mass chain's frequency over the string's at phase t per element."""
    t2 = np.asarray(t2, dtype=complex)
    t = np.sqrt(t2)
    small = np.abs(t) < 1e-3
    safe = np.where(small, 1.0, t)
    with np.errstate(all='ignore'):
        exact = 6.0 * (1.0 - np.cos(safe)) / ((2.0 + np.cos(safe)) * safe * safe)
    return np.where(small, 1.0 + t2 / 12.0, exact)


def true_end_stiffness(sc: Scene, lam, sag_scale: float = 1.0,
                       elements: int | None = None) -> np.ndarray:
    """(nl, n, 3, 3) closed-form sag-aware dynamic end stiffness of continuous cables.

    Shallow inclined cables (Irvine 1981, ch. 3) in the frame e_x (anchor -> platform end
    along the chord), e_y (gravity's part normal to the chord, the sag direction): with the
    wave tension T (:func:`wave_tension`), a = gamma cos(theta) L / T, w^2 = lam mu L^2 / T,
    s = (tan(w/2)/(w/2) - 1), and the axial compliance D = (L/(EA + T)) (1/(z_a cot z_a) +
    lambda^2 s/w^2), an additional tension h = (U + c V)/D with c = a s / 2 gives

        K_xx = 1/D,   K_xy = c/D,   K_yy = (T/L) w cot w + c^2/D,   K_zz = (T/L) w cot w.

    ``sag_scale`` multiplies lambda^2 (and a^2): ``fem_sag`` with n straight elements keeps
    (1 - 1/n^2) of the sag compliance (the midpoint rule of the sag integral). ``elements`` n
    evaluates the sag terms the way a chain of n elements sees them: at w / r(w/n), r the
    chain's frequency ratio (its modes are r times too high, so at a given frequency it
    responds like the continuous cable at a lower one).
    """
    c = sc.cables
    lam = np.asarray(lam, dtype=complex).reshape(-1, 1)
    length, mu, tension = c.length_m, c.mass_per_length_kg_m, sc.wave_tension_n
    axial_wave = z_cot_z(lam * (mu * length ** 2 / c.ea_n))
    w2 = lam * (mu * length ** 2 / tension)
    w2_sag = w2 if elements is None else w2 / chain_frequency_ratio_squared(w2 / elements ** 2)
    sag = _sag_compliance(w2_sag)
    lam2 = sag_scale * sc.sag_parameter * (c.tension_n / tension) ** 3
    a = math.sqrt(sag_scale) * sc.normal_weight_n_per_m * length / tension
    with np.errstate(all='ignore'):
        compliance = (length / (c.ea_n + c.tension_n)) * (1.0 / axial_wave + lam2 * sag)
        coupling = 0.5 * a * w2_sag * sag
        axial = 1.0 / compliance
        transverse = (tension / length) * z_cot_z(w2)
        out = axial_transverse(c.unit, axial, transverse)
        ex, ey = -c.unit, sc.sag_direction
        xy = ex[:, :, None] * ey[:, None, :]
        out += (coupling * axial)[..., None, None] * (xy + np.swapaxes(xy, -1, -2))
        out += (coupling * coupling * axial)[..., None, None] * (ey[:, :, None] * ey[:, None, :])
    return anchor_series(out, c, lam.ravel())


def straight_end_stiffness(cables: CableSet, n: int | None, lam) -> np.ndarray:
    """(nl, n, 3, 3) end stiffness of straight continuous cables (n None, ``dsm``) or of the
    FEM chain of n elements, at ``lam`` = w^2 (complex with damping)."""
    method = 'dsm' if n is None else 'fem'
    return models.build(method, cables, n or 1).end_stiffness(np.asarray(lam, dtype=complex))


def model_end_stiffness(sc: Scene, method: str, n: int, lam,
                        straight: np.ndarray | None = None,
                        sag_error: np.ndarray | None = None) -> np.ndarray:
    """(nl, n, 3, 3) end stiffness of ``method`` as the estimates see it.

    spring, fem, dsm: exact; catenary, catenary_exact: their static 3x3 stiffness; fem_sag:
    the truth, plus the discretisation error of the straight chain of n elements, plus the
    error of the sag the n straight elements lose: ``sag_error`` / n^2 where given (n^2 times
    that error at ``lam``, measured on fem_sag itself by the estimator), else the closed form
    (the truth with (1 - 1/n^2) of the sag compliance, exact statically but off by a factor
    0.3-5 in its dynamic part). ``straight`` may hold the ``dsm`` end stiffness at ``lam``
    (it does not depend on n).
    """
    lam = np.asarray(lam, dtype=complex).reshape(-1)
    if method == 'spring':
        return models.build('spring', sc.cables).end_stiffness(lam)
    if method in ('catenary', 'catenary_exact'):
        stiffness = models.build(method, sc.cables).static_end_stiffness()
        return np.broadcast_to(stiffness, (lam.size,) + stiffness.shape).astype(complex)
    if method == 'fem':
        return straight_end_stiffness(sc.cables, n, lam)
    if straight is None and method in ('dsm', 'fem_sag'):
        straight = straight_end_stiffness(sc.cables, None, lam)
    if method == 'dsm':
        return straight
    if method == 'fem_sag':
        chain = straight_end_stiffness(sc.cables, n, lam) - straight
        if sag_error is not None:
            return true_end_stiffness(sc, lam) + sag_error / n ** 2 + chain
        return true_end_stiffness(sc, lam, 1.0 - 1.0 / n ** 2, n) + chain
    raise SelectionError(f'no error estimate for method {method!r}')
