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

There are no finite matrices (``blocks`` is None): natural frequencies come from the roots of
det Z(omega) of the condensed platform dynamic stiffness, found by the Wittrick-Williams
algorithm in :func:`natural_frequencies_dsm`.

Valid while the cables are taut and their sag negligible; a cable with T <= 0 is flagged
(``valid`` False), its transverse stiffness taken as the T -> 0 limit 0 (T = 0) or the
unstable real value (T/L) z coth z (T < 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cdpr_dynamics.models.base import (CableAssembly, CableSet, axial_transverse,
                                       slack_warnings)

_SERIES_BELOW = 1e-3     # |z| below which z cot z is summed as its series
_LARGE_IMAG = 30.0       # |Im z| above which cot z uses exp(2iz) (cos, sin would overflow)


def z_cot_z(z2) -> np.ndarray:
    """``z cot z`` as a function of ``z2 = z^2`` (complex, any shape), stable everywhere.

    Series 1 - z^2/3 - z^4/45 - 2 z^6/945 near 0; cos/sin elsewhere; for |Im z| large
    cot z = i (1 + q)/(q - 1), q = exp(2iz), |q| < e^-60, which never overflows.
    Infinite (a pole) where sin z = 0, z = j pi.
    """
    z2 = np.asarray(z2, dtype=complex)
    z = np.sqrt(z2)
    z = np.where(z.imag < 0.0, -z, z)        # z cot z is even: take Im z >= 0
    out = np.empty_like(z)
    small = np.abs(z) < _SERIES_BELOW
    large = ~small & (z.imag > _LARGE_IMAG)
    mid = ~small & ~large
    zs = z2[small]
    out[small] = 1.0 - zs / 3.0 - zs * zs / 45.0 - 2.0 * zs ** 3 / 945.0
    zm = z[mid]
    with np.errstate(divide='ignore', invalid='ignore'):
        out[mid] = zm * np.cos(zm) / np.sin(zm)
    zl = z[large]
    q = np.exp(2j * zl)
    out[large] = zl * 1j * (1.0 + q) / (q - 1.0)
    return out


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

    def axial(self, lam) -> np.ndarray:
        """(nl, n) exact axial end stiffness (EA/L) z cot z, z^2 = lam mu L^2 / EA."""
        lam = np.asarray(lam, dtype=complex).reshape(-1, 1)
        length = self.length_m
        return (self.ea_n / length) * z_cot_z(lam * (self.mass_per_length_kg_m * length ** 2
                                                     / self.ea_n))

    def transverse(self, lam) -> np.ndarray:
        """(nl, n) exact transverse end stiffness (T/L) z cot z, z^2 = lam mu L^2/T; 0 at T = 0."""
        lam = np.asarray(lam, dtype=complex).reshape(-1, 1)
        length, tension = self.length_m, self.tension_n
        zero = tension == 0.0
        safe = np.where(zero, 1.0, tension)
        value = (safe / length) * z_cot_z(lam * (self.mass_per_length_kg_m * length ** 2 / safe))
        return np.where(zero, 0.0, value)

    def __call__(self, lam) -> np.ndarray:
        return axial_transverse(self.unit, self.axial(lam), self.transverse(lam))

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

    def fixed_end_mode_count(self, omega_rad_s) -> np.ndarray:
        """J0: how many natural frequencies of the cables, both ends fixed, lie below omega.

        Cable i contributes #{j >= 1 : j w_a < omega} + 2 #{j >= 1 : j w_t < omega}.
        ``omega_rad_s`` (nw,) -> (nw,) int.
        """
        omega = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))[:, None]
        axial, transverse = self.fixed_end_fundamentals_rad_s()
        if np.any(~(transverse > 0.0)):
            raise ValueError('the fixed-end mode count needs every cable taut (T > 0)')

        def below(fundamental):
            return np.maximum(np.ceil(omega / fundamental) - 1.0, 0.0)

        return (below(axial) + 2.0 * below(transverse)).sum(axis=1).astype(int)


def build(cables: CableSet, elements_per_cable: int = 0) -> CableAssembly:
    """Exact continuous taut cables; ``elements_per_cable`` is ignored (recorded as 0)."""
    warnings = slack_warnings(cables.tension_n)
    members = ContinuousCables(cables.unit, cables.length_m,
                               np.asarray(cables.tension_n, dtype=float), float(cables.ea_n),
                               cables.mass_per_length_kg_m)
    if not members.mass_per_length_kg_m > 0.0:
        raise ValueError('dsm needs cables with mass (weight_per_length and gravity > 0)')
    return CableAssembly('dsm', 0, members, cables.tension_n[:, None] * cables.unit, None,
                         valid=not warnings, warnings=warnings)


# --------------------------------------------------------------------------- Wittrick-Williams

def mode_count(system, omega_rad_s) -> np.ndarray:
    """Wittrick-Williams J(omega): the number of natural frequencies below each omega.

    J = J0 + s{Z(omega)}, J0 the cables' fixed-end modes below omega and s{Z} the number of
    negative eigenvalues of the real symmetric undamped condensed dynamic stiffness.
    """
    omega = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    z = system.dynamic_stiffness(omega).real
    z = 0.5 * (z + np.swapaxes(z, -1, -2))
    scale = np.abs(z).max(axis=(1, 2), keepdims=True)
    z = z / np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
    negative = (np.linalg.eigvalsh(z) < 0.0).sum(axis=1)
    return system.assembly.end_stiffness.fixed_end_mode_count(omega) + negative


def natural_frequencies_dsm(system, count: int | None = 12, f_max_hz: float | None = None,
                            tol_hz: float = 1e-9) -> np.ndarray:
    """Natural frequencies (Hz, ascending) of a ``dsm`` system by Wittrick-Williams bisection.

    Without ``f_max_hz``: the ``count`` lowest. With ``f_max_hz``: every natural frequency
    below it (at most the ``count`` lowest of them unless ``count`` is None). Each is bracketed
    by bisection on the mode count J(omega) (:func:`mode_count`) to within ``tol_hz``, so none
    is missed or doubled, repeated ones (equal cables) appear with their multiplicity, and
    modes of the cables that do not move the platform are included. A system with negative
    stiffness (unstable) gives 0 Hz for those modes, as :func:`natural_frequencies` does.

    Raises :class:`cdpr_dynamics.dynamics.DynamicsError` for a model that cannot count its
    cables' fixed-end modes (not ``dsm``) or a cable with T <= 0 (the count is infinite).
    """
    from cdpr_dynamics.dynamics import DynamicsError

    members = system.assembly.end_stiffness
    if not hasattr(members, 'fixed_end_mode_count'):
        raise DynamicsError(f'method {system.assembly.method} has neither finite matrices nor '
                            'a fixed-end mode count: no natural frequencies')
    if np.any(~(np.asarray(members.tension_n) > 0.0)):
        raise DynamicsError('dsm natural frequencies need every cable taut (T > 0): '
                            + '; '.join(system.assembly.warnings))
    if not tol_hz > 0.0:
        raise ValueError('tol_hz must be positive')
    two_pi = 2.0 * math.pi
    if f_max_hz is not None:
        hi_w = two_pi * float(f_max_hz)
        total = int(mode_count(system, hi_w)[0]) if hi_w > 0 else 0
        targets = total if count is None else min(int(count), total)
    else:
        if count is None:
            raise ValueError('give count or f_max_hz')
        targets = int(count)
        hi_w = two_pi
        while mode_count(system, hi_w)[0] < targets:
            hi_w *= 2.0
            if hi_w > two_pi * 1e12:
                raise DynamicsError('mode count does not grow: no natural frequencies found')
    if targets <= 0:
        return np.zeros(0)
    index = np.arange(1, targets + 1)              # find w_k = inf{w : J(w) >= k}
    lo = np.zeros(targets)
    hi = np.full(targets, hi_w)
    tol_w = two_pi * tol_hz
    for _ in range(200):
        if np.all(hi - lo <= np.maximum(tol_w, 4.0 * np.finfo(float).eps * hi)):
            break
        mid = 0.5 * (lo + hi)
        enough = mode_count(system, mid) >= index
        hi = np.where(enough, mid, hi)
        lo = np.where(enough, lo, mid)
    return 0.5 * (lo + hi) / two_pi
