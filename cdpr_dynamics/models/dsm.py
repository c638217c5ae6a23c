"""``dsm``: the exact dynamic stiffness of each taut straight cable, the reference model.

Each cable is a continuous straight member of length L (the current chord, as in ``fem``),
mass mu = gamma/g per unit length, axial stiffness EA and uniform tension T, fixed at its
anchor. Axial and transverse motions decouple exactly as in ``fem``:

    axial        EA u'' = mu u_tt,     wave speed c_a = sqrt(EA/mu)
    transverse   T  v'' = mu v_tt,     wave speed c_t = sqrt(T/mu)   (two directions)

With u(0) = 0 at the anchor and u(L) = U at the platform, the harmonic solution at
lam = omega^2 is u(x) = U sin(kx)/sin(kL), so the end force EA u'(L) gives the exact end
dynamic stiffness

    S_a(lam) = EA k cot(kL) = (EA/L) z cot z,   z^2 = (kL)^2 = lam mu L^2 / EA
    S_t(lam) = T  k cot(kL) = (T/L)  z cot z,   z^2 = lam mu L^2 / T

and the platform feels S_a u u^T + S_t (I - u u^T). ``z cot z`` is even in z, so only z^2
enters and complex lam (Rayleigh damping, see :mod:`cdpr_dynamics.models.base`) needs no
branch choice; z cot z = 1 - z^2/3 - z^4/45 - ... gives the static springs EA/L and T/L at
lam = 0. This is the n -> infinity limit of ``fem`` (element stiffness EA/l and T/l, l = L/n,
consistent mass), whose end stiffness and natural frequencies converge to it as n^-2.

There are no finite matrices (``blocks`` is None): natural frequencies and classified modes
come from Wittrick-Williams counting on the condensed platform dynamic stiffness, with the
cables' fixed-end modes (:meth:`ContinuousCables.fixed_end_mode_count`) as J0
(:mod:`cdpr_dynamics.dynamics.modes`); on an anchor end those are the modes of the span
clamped at the platform and held by the anchor springs (:func:`clamped_roots`).

An anchor end (:class:`cdpr_dynamics.models.base.AnchorEnd`) is a massless spring of compliance
f between the ground and the cable's anchor end, in a direction of its own: with the fixed-
fixed member's end stiffness s and transfer t (t^2 = s^2 + k mu lam, k = EA or T) the end
feels s - t^2 f/(1 + s f) = (s - k mu lam f)/(1 + s f) (:meth:`ContinuousCables.parts`): along
the cable (f = series length / EA) and normal to the pulley plane (f = c / T).

Valid while the cables are taut and their sag negligible; a cable with T <= 0 is flagged
(``valid`` False), its transverse stiffness taken as the T -> 0 limit 0 (T = 0) or the
unstable real value (T/L) z coth z (T < 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from cdpr_dynamics.models.base import (AxialTransverse, CableAssembly, CableSet,
                                       axial_transverse, slack_warnings)

_SERIES_BELOW = 0.25     # |z^2| up to which z cot z is summed as its series (to 2e-16)
_LARGE_IMAG = 30.0       # |Im z| above which cot z uses exp(2iz) (cos, sin would overflow)
# z cot z = 1 - sum_n 2 zeta(2n) (z/pi)^2n = sum_n (-1)^n 4^n B_2n z^2n / (2n)!, n = 0..9
_SERIES = (1.0, -1 / 3, -1 / 45, -2 / 945, -1 / 4725, -2 / 93555, -1382 / 638512875,
           -4 / 18243225, -3617 / 162820783125, -87734 / 38979295480125)


def z_cot_z(z2) -> np.ndarray:
    """``z cot z`` as a function of ``z2 = z^2`` (any shape), stable everywhere.

    |z^2| <= :data:`_SERIES_BELOW` (e.g. every axial wave below a few hundred Hz): its Taylor
    series in z^2 to the 18th power (:data:`_SERIES`, the next term below 2e-16 there), by
    Horner, no transcendental call. Elsewhere real ``z2`` (undamped) in real arithmetic: z /
    tan z (z^2 >= 0) or y coth y = y + 2y / expm1(2y) (z^2 = -y^2 < 0); complex ``z2``
    (damped): z = x + iy (y >= 0) by a real square root and
    cot z = (sin x cos x - i sinh y cosh y) / (sin^2 x + sinh^2 y) (three real transcendental
    calls, no cancellation); for y large
    cot z = i (1 + q)/(q - 1), q = exp(2iz), |q| < e^-60, which never overflows.
    Infinite (a pole) where sin z = 0, z = j pi. Real in, real out.
    """
    z2 = np.asarray(z2)
    small = np.abs(z2) <= _SERIES_BELOW
    if z2.dtype.kind != 'c':
        z2 = z2.astype(float)
    far = _z_cot_z_complex if z2.dtype.kind == 'c' else _z_cot_z_real
    if small.all():
        return _series(z2)
    if not small.any():
        return far(z2)
    out = np.empty_like(z2)
    out[small] = _series(z2[small])
    out[~small] = far(z2[~small])
    return out


def upper_root(z2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y): the square root x + iy of complex ``z2`` with y >= 0, real arithmetic:
    t = sqrt((|z2| + |Re z2|)/2), h = |Im z2| / (2t), x = sign(Im z2) (t or h), y = h or t."""
    a, b = np.ascontiguousarray(z2.real), np.ascontiguousarray(z2.imag)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        norm = a * a
        norm += b * b
        np.sqrt(norm, out=norm)                               # |z2|
        if not np.all(np.isfinite(norm)):                     # |z2| > 1e154: no squares
            norm = np.hypot(a, b)
        pos = a >= 0.0
        norm += np.abs(a, out=a)
        norm *= 0.5
        t = np.sqrt(norm, out=norm)
        h = np.abs(b)
        h *= 0.5
        h /= t
        x = np.where(pos, t, h)
        np.copysign(x, b, out=x)
        return x, np.where(pos, h, t)


def _z_cot_z_real(z2: np.ndarray) -> np.ndarray:
    """:func:`z_cot_z` of real z^2 away from 0 (no series)."""
    root = np.sqrt(np.abs(z2))
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        if np.all(z2 >= 0.0):
            return root / np.tan(root)
        out = np.empty_like(z2)
        pos = z2 >= 0.0
        out[pos] = root[pos] / np.tan(root[pos])
        y = root[~pos]
        out[~pos] = y + 2.0 * y / np.expm1(2.0 * y)
    return out


def _z_cot_z_complex(z2: np.ndarray) -> np.ndarray:
    """:func:`z_cot_z` of complex z^2 away from 0, real arithmetic but for large Im z."""
    return _cot_parts(*upper_root(z2))


def _cot_parts(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """z cot z of z = x + iy (y >= 0): (x sc + y shch + i (y sc - x shch)) / (s^2 + sh^2),
    sc = sin x cos x, sh = sinh y, shch = sinh y cosh y from e = expm1(y) (no cancellation
    near 0); for y > :data:`_LARGE_IMAG` i z (1 + q)/(q - 1), q = exp(2iz)."""
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        s, c = np.sin(x), np.cos(x)
        e = np.expm1(y)
        e_plus = e + 1.0
        sh = e + 2.0
        sh *= e
        sh /= e_plus
        sh *= 0.5                                             # sinh y
        shch = np.reciprocal(e_plus, out=e_plus)
        shch += sh
        shch *= sh                                            # sinh y cosh y
        sc = c
        sc *= s
        den = np.multiply(s, s, out=s)
        den += np.square(sh, out=sh)
        out = np.empty(x.shape, dtype=complex)
        part = x * sc
        part += y * shch
        part /= den
        out.real = part
        part = np.multiply(y, sc, out=part)
        part -= x * shch
        part /= den
        out.imag = part
    large = y > _LARGE_IMAG
    if large.any():
        zl = x[large] + 1j * y[large]
        q = np.exp(2j * zl)
        out[large] = zl * 1j * (1.0 + q) / (q - 1.0)
    return out


def _series(z2, bound: float = _SERIES_BELOW):
    """The Taylor series of z cot z in z^2 (:data:`_SERIES`), Horner, real or complex, for
    |z^2| <= ``bound``: as many terms as that needs (:func:`_series_terms`)."""
    terms = _series_terms(bound)
    out = np.full_like(z2, _SERIES[terms - 1])
    for c in _SERIES[terms - 2::-1]:
        out *= z2
        out += c
    return out


def _series_terms(bound: float) -> int:
    """Terms n = 0..N-1 of :data:`_SERIES` for |z^2| <= ``bound``: the first left out,
    |c_N| bound^N = 2 zeta(2N) (bound/pi^2)^N <= 3.3 (bound/pi^2)^N, below 2.3e-16 (all ten at
    :data:`_SERIES_BELOW`; four for an axial wave at 40 Hz, |z^2| ~ 6e-4)."""
    if not bound > 0.0:
        return 1
    ratio = bound / math.pi ** 2
    if ratio >= 1.0:
        return len(_SERIES)
    return int(min(len(_SERIES), max(1, math.ceil(math.log(2.3e-16 / 3.3) / math.log(ratio)))))


def _taut_waves(lam: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """:func:`z_cot_z` of z^2 = lam ratio for complex ``lam`` (nl,) and ``ratio`` > 0 (...):
    (..., nl). Rows whose largest |z^2| is within :data:`_SERIES_BELOW` (the axial waves) are
    the series throughout, with the terms that largest |z^2| needs; the others use
    z = sqrt(lam) sqrt(ratio), one root per lam, and the series where |z^2| = ratio |lam| is
    within :data:`_SERIES_BELOW`."""
    flat = ratio.ravel()
    largest = np.abs(lam).max(initial=0.0)
    series = flat * largest <= _SERIES_BELOW
    if series.all():
        return _series(lam * ratio[..., None], float(flat.max(initial=0.0) * largest))
    rows = np.flatnonzero(~series)
    x, y = upper_root(lam)
    root = np.sqrt(flat[rows, None])
    far = _cot_parts(root * x, root * y)
    small = flat[rows, None] * np.abs(lam) <= _SERIES_BELOW       # |z^2| = ratio |lam|
    if small.any():
        far[small] = _series((lam * flat[rows, None])[small])
    if rows.size == flat.size:
        return far.reshape(ratio.shape + (lam.size,))
    out = np.empty((flat.size, lam.size), dtype=complex)
    out[rows] = far
    rows = np.flatnonzero(series)
    out[rows] = _series(lam * flat[rows, None], float(flat[rows].max() * largest))
    return out.reshape(ratio.shape + (lam.size,))


@dataclass(frozen=True, eq=False)
class ContinuousCables:
    """The end dynamic stiffness of taut continuous cables, callable on ``lam`` (see module).

    Besides ``__call__(lam) -> (nl, n, 3, 3)`` it counts the cables' own natural frequencies
    with both ends fixed (:meth:`fixed_end_mode_count`), the J0 term of Wittrick-Williams.
    """

    unit: np.ndarray          # (n, 3)
    length_m: np.ndarray      # (n,)
    tension_n: np.ndarray     # (n,)
    ea_n: float
    mass_per_length_kg_m: float
    wave: Callable[[np.ndarray], np.ndarray] = z_cot_z     # z cot z of z^2
    anchor_compliance: np.ndarray | None = None   # (2, n) axial, out-of-plane (m/N); or None
    normal: np.ndarray | None = None               # (n, 3) pulley plane normals; or None

    def axial(self, lam) -> np.ndarray:
        """(nl, n) exact axial end stiffness (EA/L) z cot z, z^2 = lam mu L^2 / EA."""
        return self._waves(lam, np.full(self.length_m.shape, self.ea_n)).T.astype(complex)

    def transverse(self, lam) -> np.ndarray:
        """(nl, n) exact transverse end stiffness (T/L) z cot z, z^2 = lam mu L^2/T; 0 at T = 0."""
        return self._waves(lam, self.tension_n).T.astype(complex)

    def parts(self, lam) -> np.ndarray:
        """(2, n, nl) axial and transverse end stiffness, frequency last (real for real lam):
        the :class:`cdpr_dynamics.models.base.AxialTransverse` of these cables; with an
        anchor end (3, n, nl), the out-of-plane row last (module doc)."""
        stiffness = np.stack([np.full(self.length_m.shape, self.ea_n), self.tension_n])
        fixed = self._waves(lam, stiffness)
        if self.anchor_compliance is None:
            return fixed
        lam = np.ravel(lam)
        f = self.anchor_compliance[..., None]                               # (2, n, 1)
        ends = fixed[[0, 1]]
        load = stiffness[..., None] * self.mass_per_length_kg_m * lam       # k mu lam
        springs = (ends - load * f) / (1.0 + ends * f)
        return np.stack([springs[0], fixed[1], springs[1]])

    def _waves(self, lam, stiffness) -> np.ndarray:
        """(stiffness/L) z cot z, z^2 = lam mu L^2 / stiffness, for ``stiffness`` (..., n) and
        ``lam`` (nl,): (..., n, nl); 0 where the stiffness is 0."""
        lam = np.ravel(lam)
        if lam.dtype.kind != 'c':
            lam = lam.astype(float)
        zero = stiffness == 0.0
        safe = np.where(zero, 1.0, stiffness)
        length = self.length_m
        ratio = self.mass_per_length_kg_m * length ** 2 / safe                # z^2 / lam
        if self.wave is z_cot_z and lam.dtype.kind == 'c' and np.all(ratio > 0.0):
            wave = _taut_waves(lam, ratio)
        else:
            wave = self.wave(lam * ratio[..., None])
        out = (safe / length)[..., None] * wave
        if zero.any():
            out[zero] = 0.0
        return out

    def __call__(self, lam) -> np.ndarray:
        parts = self.parts(lam)
        return axial_transverse(self.unit, parts[0].T, parts[1].T, self.normal,
                                None if self.normal is None else parts[2].T).astype(complex)

    def fixed_end_fundamentals_rad_s(self) -> tuple[np.ndarray, np.ndarray]:
        """(axial, transverse) first fixed-fixed circular frequencies pi c / L of each cable.

        The j-th is j times the first; transverse ones are double (two directions). A cable
        with T <= 0 has no positive transverse fundamental (nan).
        """
        mu = self.mass_per_length_kg_m
        axial = math.pi * np.sqrt(self.ea_n / mu) / self.length_m
        with np.errstate(invalid='ignore'):
            transverse = np.where(self.tension_n > 0.0,
                                  math.pi * np.sqrt(self.tension_n / mu) / self.length_m, np.nan)
        return axial, transverse

    def clamped_kinds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(fundamental pi c / L, beta, k), (3, n) each, of the three directions of each cable
        with the platform end fixed: axial (k = EA), transverse in the pulley plane and
        transverse normal to it (k = T). beta = k f / L is the anchor end's compliance f
        (0: fixed anchor) over the span's own, L / k."""
        axial, transverse = self.fixed_end_fundamentals_rad_s()
        fundamental = np.stack([axial, transverse, transverse])
        k = np.stack([np.full(self.length_m.shape, self.ea_n), self.tension_n, self.tension_n])
        beta = np.zeros_like(fundamental)
        if self.anchor_compliance is not None:
            beta[[0, 2]] = k[[0, 2]] * self.anchor_compliance / self.length_m
        return fundamental, beta, k

    def fixed_end_mode_count(self, omega_rad_s, per_cable: bool = False) -> np.ndarray:
        """J0: how many natural frequencies of the cables, platform end fixed, lie below omega.

        A direction without anchor compliance has j pi c / L (j >= 1); one on an anchor spring
        has the roots z_j of z cot z = -1/beta (:func:`clamped_roots`), one in each
        ((j - 1/2) pi, j pi): x = omega L / (pi c) passes floor(x) of them, and the next one
        where frac(x) > 1/2 and beta z cot z < -1 (Wittrick-Williams on the anchor node: the
        span clamped at both ends, j pi, plus the sign of 1/f + (k/L) z cot z).
        ``omega_rad_s`` (nw,) -> (nw,) int, or (nw, n) per cable.
        """
        omega = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))[:, None, None]
        fundamental, beta, _ = self.clamped_kinds()
        if np.any(~(fundamental > 0.0)):
            raise ValueError('the fixed-end mode count needs every cable taut (T > 0)')
        x = omega / fundamental                                           # (nw, 3, n)
        counts = np.maximum(np.ceil(x) - 1.0, 0.0)
        sprung = beta > 0.0
        if sprung.any():
            whole = np.floor(x)
            z = math.pi * x
            with np.errstate(divide='ignore', invalid='ignore'):
                past = (x - whole > 0.5) & (beta * z / np.tan(z) < -1.0)
            counts = np.where(sprung, whole + past, counts)
        counts = counts.sum(axis=1).astype(int)
        return counts if per_cable else counts.sum(axis=1)


def clamped_roots(j, beta) -> np.ndarray:
    """The j-th root z_j of z cot z = -1/beta (beta > 0), in ((j - 1/2) pi, j pi): the j-th
    mode of a span clamped at one end and on a spring of compliance beta L / k at the other;
    j pi where beta is 0. Bisection on beta z cos z + sin z to round-off, vectorised."""
    j, beta = np.broadcast_arrays(np.asarray(j, dtype=float), np.asarray(beta, dtype=float))
    lo, hi = (j - 0.5) * math.pi, j * math.pi
    sign_lo = np.sign(np.sin(lo))
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        same = np.sign(beta * mid * np.cos(mid) + np.sin(mid)) == sign_lo
        lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
    return np.where(beta > 0.0, 0.5 * (lo + hi), j * math.pi)


def build(cables: CableSet, elements_per_cable: int = 0) -> CableAssembly:
    """Exact continuous taut cables; ``elements_per_cable`` is ignored (recorded as 0)."""
    warnings = slack_warnings(cables.tension_n)
    end = cables.anchor_end
    compliance = normal = None
    if end is not None:
        compliance, normal = np.stack(end.compliance(cables.ea_n, cables.tension_n)), \
            end.plane_normal
    members = ContinuousCables(cables.unit, cables.length_m,
                               np.asarray(cables.tension_n, dtype=float), float(cables.ea_n),
                               cables.mass_per_length_kg_m, anchor_compliance=compliance,
                               normal=normal)
    if not members.mass_per_length_kg_m > 0.0:
        raise ValueError('dsm needs cables with mass (weight_per_length and gravity > 0)')
    return CableAssembly('dsm', 0, members, cables.tension_n[:, None] * cables.unit, None,
                         valid=not warnings, warnings=warnings,
                         decoupled=AxialTransverse(members.unit, members.parts, normal))
