"""Method ``auto``: the cheapest cable model whose estimated error over the band is within
``model.tolerance``; and the yardstick the estimates are checked against.

**Errors.** Over the band [0, f_max] (f_max = ``frf.f_max_hz``) a model has two errors:

* frequency error: the largest relative error of its natural frequencies in the band, modes
  paired in ascending order (the first N of each list, N = the larger number of modes in the
  band); a mode the model does not have counts 100 % (massless models miss every cable mode,
  fem with n elements has only n - 1 per cable and direction), and errors are capped at 100 %;
* FRF error: the largest relative error max_f |A(f) - A_ref(f)| / |A_ref(f)| of the damped
  complex response of the centroid over the FRF sweep (it bounds the error of |A|).

**Estimates** (cheap: closed forms per cable and 3x3/6x6 algebra on the platform DOFs, no
eigen-solution and no reference run; about 10-20 ms for a whole choice):

* the "truth" is a closed-form sag-aware continuous cable (:func:`true_end_stiffness`):
  Irvine's shallow inclined cable (Cable Structures, 1981, ch. 3) at its mean tension, i.e.
  the exact straight-cable dynamic stiffness of ``dsm`` with Irvine's dynamic sag compliance in
  series with the axial one and its coupling to the in-plane normal direction. Its axial
  stiffness is Ernst's (EA + T)/L / (1 + lambda^2/12) statically and vanishes at Irvine's
  symmetric in-plane modes tan(w/2) = w/2 - (4/lambda^2)(w/2)^3 (lambda^2 from
  :func:`models.catenary.sag_parameter`). Against fem_sag n = 256 its end stiffness agrees to
  1e-5 on the paper's robot and to 0.3 % at lambda^2 = 334 (test_selection);
* each model's end stiffness S_i is known in closed form (spring, the FEM chain recursion,
  the catenary stiffness; ``fem_sag`` n: the truth keeping (1 - 1/n^2) of the sag compliance,
  the midpoint rule of n straight elements, plus the straight chain's discretisation error),
  so the platform error dZ = sum_i G_i^T (S_i - S_true,i) G_i is too. The FRF error is the
  first-order change of the centroid's response, |Z_true^-1 dZ A| / |A|, max over the sweep
  (configured Rayleigh damping) for the configured force and unit forces along x, y and z;
  the platform modes' error is |phi^T dZ(w_p) phi| / (2 w_p^2 phi^T M phi) at the spring
  model's modes;
* cable modes in the band: a model without cable DOFs misses them (100 %); fem with n elements
  has the chain's dispersion error sqrt(6(1 - cos t)/(2 + cos t))/t - 1, t = j pi/n, on the
  j-th mode (and misses modes j >= n); straight models add Irvine's shift of the first
  symmetric in-plane mode (100 % once lambda^2 >= 4 pi^2, where it crosses the antisymmetric
  one) or a quarter of the relative tension variation, gamma dz/(4 T), along the cable,
  whichever is larger.

Straight models (spring, fem, dsm) fail where lambda^2 is not small: their axial stiffness is
off by ~lambda^2/12 statically and their symmetric in-plane cable modes by ~4 lambda^2/pi^4, so
at 1 % they need lambda^2 below about 0.1-0.2 (the paper's lower cables, lambda^2 = 0.20, are
at the edge; a 20 N steel cable has lambda^2 ~ 300). No fixed threshold is used: the estimate
itself is compared with the tolerance.

**Choice.** Candidates in order of cost (measured compute time grows with the DOFs; at equal
DOFs straight before sagged): spring, fem n = 1, catenary, catenary_exact (3 or 6 DOFs), then
fem and fem_sag with the smallest n that passes (n up to :data:`MAX_ELEMENTS`). ``dsm`` is not
a candidate: it has no finite matrices, so no time history for the node. When nothing passes,
the candidate with the smallest estimated error is taken and the reason says so.

**Yardstick** (:func:`reference_solution`, :func:`measure_error`): ``dsm`` where the sag is
negligible (estimated effect below a tenth of the tolerance), otherwise ``fem_sag`` at n and 2n
elements, Richardson-extrapolated (its n^-2 error removed).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from cdpr_dynamics import models
from cdpr_dynamics.dynamics import (DENSE_EIGEN_DOFS, Damping, PlatformSystem, frequency_response,
                                    natural_frequencies, platform_system)
from cdpr_dynamics.models.base import CableAssembly, CableSet, axial_transverse
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.models.dsm import natural_frequencies_dsm, z_cot_z

MAX_ELEMENTS = 256          # largest n auto considers (fem_sag n = 256: 6123 DOFs, 8 cables)
MISSED = 1.0                # error of a missed mode (and the cap of every error)
SAG_NEGLIGIBLE = 0.1        # sag negligible for the yardstick below this fraction of tolerance
SAFETY = 1.25               # auto needs SAFETY * estimate <= tolerance (estimate checked in tests)
MASSLESS = ('spring', 'fem', 'catenary', 'catenary_exact')   # in this order at n = 1
STEP = 1.25                 # n grows by this factor while the estimate is above the tolerance


class SelectionError(ValueError):
    """No cable model can describe the scene (e.g. a cable without tension)."""


@dataclass(frozen=True)
class ModelChoice:
    """What ``auto`` chose, why (one line), and its estimated relative error over the band."""

    method: str
    elements_per_cable: int
    reason: str
    estimated_error: float
    estimated_freq_error: float = 0.0
    estimated_frf_error: float = 0.0
    considered: tuple = field(default=(), compare=False)   # (method, n, estimate) in cost order


@dataclass(frozen=True)
class ErrorEstimate:
    """Estimated relative errors of one model over the band, and the main cause."""

    method: str
    elements_per_cable: int
    freq_error: float
    frf_error: float
    cause: str

    @property
    def error(self) -> float:
        return max(self.freq_error, self.frf_error)


def _pct(fraction: float) -> str:
    """A relative error as a percentage with two significant digits ('0.73', '100')."""
    value = 100.0 * float(fraction)
    return f'{value:.2g}' if value < 99.5 else f'{value:.0f}'


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


# --------------------------------------------------------------------------- the scene

@dataclass(frozen=True, eq=False)
class Scene:
    """Per-cable scales of a scene: what decides which model it needs (SI units, Hz)."""

    cables: CableSet
    f_max_hz: float
    sag_parameter: np.ndarray          # Irvine's lambda^2
    mean_tension_n: np.ndarray         # tension at mid-height along the cable
    transverse_hz: np.ndarray          # first fixed-fixed transverse mode sqrt(T/mu)/(2L)
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
    mean = tension - 0.5 * gamma * rise
    lam2 = sag_parameter(cables)
    unit = cables.unit
    normal = -up[None, :] + (unit @ up)[:, None] * unit
    normal_norm = np.linalg.norm(normal, axis=1)
    direction = normal / np.where(normal_norm > 0, normal_norm, 1.0)[:, None]
    return Scene(cables, float(f_max_hz), lam2, mean, np.sqrt(tension / mu) / (2.0 * length),
                 np.sqrt(cables.ea_n / mu) / (2.0 * length), irvine_symmetric_ratio(lam2) - 1.0, gamma * np.abs(rise) / (4.0 * tension),
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
    mean tension T, a = gamma cos(theta) L / T, w^2 = lam mu L^2 / T, s = (tan(w/2)/(w/2) - 1),
    and the axial compliance D = (L/(EA + T)) (1/(z_a cot z_a) + lambda^2 s/w^2), an additional
    tension h = (U + c V)/D with c = a s / 2 gives

        K_xx = 1/D,   K_xy = c/D,   K_yy = (T/L) w cot w + c^2/D,   K_zz = (T/L) w cot w.

    ``sag_scale`` multiplies lambda^2 (and a^2): ``fem_sag`` with n straight elements keeps
    (1 - 1/n^2) of the sag compliance (the midpoint rule of the sag integral). ``elements`` n
    evaluates the sag terms the way a chain of n elements sees them: at w / r(w/n), r the
    chain's frequency ratio (its modes are r times too high, so at a given frequency it
    responds like the continuous cable at a lower one).
    """
    c = sc.cables
    lam = np.asarray(lam, dtype=complex).reshape(-1, 1)
    length, mu, tension = c.length_m, c.mass_per_length_kg_m, sc.mean_tension_n
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
    return out


def _straight_end_stiffness(cables: CableSet, n: int | None, lam) -> np.ndarray:
    """Straight continuous cables (n None, ``dsm``) or the FEM chain of n elements."""
    method = 'dsm' if n is None else 'fem'
    return models.build(method, cables, n or 1).end_stiffness(np.asarray(lam, dtype=complex))


def model_end_stiffness(sc: Scene, method: str, n: int, lam,
                        straight: np.ndarray | None = None) -> np.ndarray:
    """(nl, n, 3, 3) end stiffness of ``method`` as the estimates see it.

    spring, fem, dsm: exact; catenary, catenary_exact: their static 3x3 stiffness; fem_sag:
    the truth with (1 - 1/n^2) of the sag compliance (the n straight elements lose the sag
    inside each) plus the discretisation error of the straight chain of n elements.
    ``straight`` may hold the ``dsm`` end stiffness at ``lam`` (it does not depend on n).
    """
    lam = np.asarray(lam, dtype=complex).reshape(-1)
    if method == 'spring':
        return models.build('spring', sc.cables).end_stiffness(lam)
    if method in ('catenary', 'catenary_exact'):
        stiffness = models.build(method, sc.cables).static_end_stiffness()
        return np.broadcast_to(stiffness, (lam.size,) + stiffness.shape).astype(complex)
    if method == 'fem':
        return _straight_end_stiffness(sc.cables, n, lam)
    if straight is None and method in ('dsm', 'fem_sag'):
        straight = _straight_end_stiffness(sc.cables, None, lam)
    if method == 'dsm':
        return straight
    if method == 'fem_sag':
        return true_end_stiffness(sc, lam, 1.0 - 1.0 / n ** 2, n) + (
            _straight_end_stiffness(sc.cables, n, lam) - straight)
    raise SelectionError(f'no error estimate for method {method!r}')


# --------------------------------------------------------------------------- the estimator

class Estimator:
    """Error estimates of any model for one scene, band and damping (see the module)."""

    def __init__(self, settings, eq, f_max_hz: float | None = None,
                 damping: Damping | None = None):
        self.settings = settings
        self.eq = eq
        f_max = settings.f_max_hz if f_max_hz is None else float(f_max_hz)
        self.scene = scene(eq.cables, f_max)
        self.damping = band_damping(settings, eq) if damping is None else damping
        grid = settings.frequencies_hz
        grid = grid[(grid > 0) & (grid <= f_max)]
        self.omega = 2.0 * math.pi * grid
        self.damped = self.damping.mass_factor > 0 or self.damping.stiffness_factor > 0
        w = self.omega
        self.lam = (w * w - 1j * w * self.damping.mass_factor) / (
            1.0 + 1j * w * self.damping.stiffness_factor)
        truth = CableAssembly('truth', 0, lambda lam: true_end_stiffness(self.scene, lam),
                              eq.cables.tension_n[:, None] * eq.cables.unit, None)
        self.truth_system = platform_system(settings.robot, eq.geometry, truth)
        self._truth_frf = self.truth_system.dynamic_stiffness(self.omega, self.damping) \
            if self.omega.size else None
        self._truth_frf_ends = true_end_stiffness(self.scene, self.lam)
        self._platform_modes()
        self._truth_modes_ends = true_end_stiffness(self.scene, self.mode_omega ** 2)
        self._straight_frf_ends = _straight_end_stiffness(eq.cables, None, self.lam)
        self._straight_modes_ends = _straight_end_stiffness(eq.cables, None,
                                                            self.mode_omega ** 2)

    def _platform_modes(self) -> None:
        """Modes of the spring model on the platform DOFs that lie in (or near) the band."""
        spring = platform_system(self.settings.robot, self.eq.geometry,
                                 models.build('spring', self.eq.cables))
        m = spring.platform_mass
        values, vectors = scipy.linalg.eigh(spring.static_stiffness(), m)
        omega = np.sqrt(np.clip(values, 0.0, None))
        keep = omega <= 2.0 * math.pi * self.scene.f_max_hz * 1.1
        self.mode_omega = omega[keep]
        self.mode_shapes = vectors[:, keep]
        self.mode_mass = np.einsum('ik,ij,jk->k', self.mode_shapes, m, self.mode_shapes)

    def frf_error(self, method: str, n: int) -> float:
        """First-order relative FRF error of the centroid's translation, max over the sweep.

        dA = -Z_true^-1 dZ A_true for the configured force and for unit forces along x, y
        and z (the node sees any direction): max |dA[:3]| / |A_true[:3]|.
        """
        if not self.damped or self._truth_frf is None:
            return 0.0
        ends = model_end_stiffness(self.scene, method, n, self.lam, self._straight_frf_ends)
        scale = 1.0 + 1j * self.omega * self.damping.stiffness_factor
        dz = scale[:, None, None] * self.truth_system.cables_on_platform(ends - self._truth_frf_ends)
        response = self._truth_response                                  # (nf, nd, loads)
        with np.errstate(all='ignore'):
            change = np.linalg.solve(self._truth_frf, dz @ response)
            rel = np.linalg.norm(change[:, :3], axis=1) / np.linalg.norm(response[:, :3], axis=1)
        if not np.all(np.isfinite(rel)):
            return MISSED
        return float(min(rel.max(), MISSED))

    @functools.cached_property
    def _truth_response(self) -> np.ndarray:
        """(nf, nd, 4) truth responses to the configured force and unit forces x, y, z."""
        nd = self.truth_system.platform_dofs
        loads = np.zeros((nd, 4))
        loads[:3, 0] = self.settings.frf_force_n
        loads[:3, 1:] = np.eye(3)
        if not np.any(loads[:, 0]):
            loads[2, 0] = 1.0
        with np.errstate(all='ignore'):
            return np.linalg.solve(self._truth_frf, np.broadcast_to(
                loads.astype(complex), (self.omega.size, nd, 4)))

    def platform_mode_error(self, method: str, n: int) -> float:
        """First-order relative shift of the platform modes in the band (undamped)."""
        if self.mode_omega.size == 0:
            return 0.0
        lam = self.mode_omega ** 2
        ends = model_end_stiffness(self.scene, method, n, lam, self._straight_modes_ends)
        with np.errstate(all='ignore'):
            dz = self.truth_system.cables_on_platform(ends - self._truth_modes_ends).real
            phi = self.mode_shapes
            shift = np.abs(np.einsum('ak,kab,bk->k', phi, dz, phi)) / (
                2.0 * lam * self.mode_mass)
        return float(min(np.max(np.where(np.isfinite(shift), shift, MISSED)), MISSED))

    def cable_mode_error(self, method: str, n: int) -> tuple[float, str]:
        """Estimated error on the cable modes in the band and its cause."""
        sc = self.scene
        jt, ja = sc.transverse_in_band, sc.axial_in_band
        if not np.any(jt) and not np.any(ja):
            return 0.0, ''
        modes = sc.cable_modes_in_band
        if method in ('spring', 'catenary', 'catenary_exact') or (method == 'fem' and n == 1) \
                or (method == 'fem_sag' and n == 1):
            return MISSED, f'no cable DOFs: {modes} cable modes in the band missed'
        error = 0.0
        cause = ''
        if method in ('fem', 'fem_sag'):
            top = int(max(jt.max(), ja.max()))
            if n <= top:
                return MISSED, (f'n = {n} resolves {n - 1} of the {top} modes per cable in '
                                'the band')
            disc = float(max(dispersion_error(np.pi * jt / n).max(),
                             dispersion_error(np.pi * ja / n).max()))
            error, cause = disc, f'cable mode {top} off by {_pct(disc)} % (n = {n})'
        if method in models.STRAIGHT_METHODS:
            with_mode = jt > 0
            sym = np.where(with_mode, np.minimum(sc.symmetric_shift, MISSED), 0.0).max()
            tension = np.where(with_mode, sc.tension_shift, 0.0).max()
            straight = float(max(sym, tension))
            if straight > 0:
                i = int(np.argmax(np.where(with_mode, sc.sag_parameter, -1.0)))
                what = (f'ignores sag (lambda^2 = {sc.sag_parameter[i]:.3g}: symmetric '
                        f'in-plane cable mode off by {_pct(min(sym, MISSED))} %)'
                        if sym >= tension else
                        f'takes the end tension for the whole cable (it varies by '
                        f'{400 * tension:.2g} %)')
                cause = f'{cause} and {what}' if cause else what
                error += straight
        return float(min(error, MISSED)), cause

    def estimate(self, method: str, n: int, full: bool = True) -> ErrorEstimate:
        """:class:`ErrorEstimate` of ``method`` with ``n`` elements per cable.

        With ``full`` False a model that misses cable modes is not looked at further (its
        FRF error is then nan): what :func:`choose_model` needs, at a fraction of the cost.
        """
        n = int(n) if method in ('fem', 'fem_sag') else 1
        cable, cause = self.cable_mode_error(method, n)
        if cable >= MISSED and not full:
            return ErrorEstimate(method, n, MISSED, math.nan, cause)
        platform = self.platform_mode_error(method, n)
        frf = self.frf_error(method, n)
        freq = max(cable, platform)
        if platform > cable:
            cause = f'platform modes off by ~{_pct(platform)} %'
        if frf > freq:
            cause = f'FRF off by ~{_pct(frf)} %'
        return ErrorEstimate(method, n, freq, frf, cause)


# --------------------------------------------------------------------------- the choice

def _cost(method: str, n: int, n_cables: int, platform_dofs: int) -> float:
    """Relative compute cost: the DOFs (time grows with them: build + FRF + modes took 1.4 ms
    at 3 DOFs, 19 ms at 363, 38 ms at 1515 for fem; fem_sag 1.3 times fem at equal DOFs),
    ties broken by kind."""
    dofs = platform_dofs + 3 * n_cables * (n - 1)
    rank = {'spring': 0.0, 'fem': 0.1, 'catenary': 0.2, 'catenary_exact': 0.3}
    if method == 'fem_sag':
        return 1.3 * dofs + 0.4
    return dofs + rank.get(method, 0.0)


def choose_model(settings, eq, f_max_hz: float | None = None,
                 damping: Damping | None = None) -> ModelChoice:
    """The cheapest model whose estimated error over [0, f_max] is within ``model.tolerance``.

    ``f_max_hz`` defaults to ``frf.f_max_hz``; ``damping`` to the configured one
    (:func:`band_damping`: a ``damping.modal_ratio`` is fitted on the spring model's modes).
    A model passes when
    ``SAFETY * estimate <= tolerance``. Raises :class:`SelectionError` (a ValueError) when no
    model describes the scene (a cable without tension).
    """
    est = Estimator(settings, eq, f_max_hz, damping)
    tol = float(settings.tolerance)
    nd = est.truth_system.platform_dofs
    ncab = eq.cables.n_cables

    def cost(e: ErrorEstimate) -> float:
        return _cost(e.method, e.elements_per_cable, ncab, nd)

    def passes(e: ErrorEstimate) -> bool:
        return SAFETY * e.error <= tol

    candidates = [est.estimate(m, 1, full=False) for m in MASSLESS]
    sc = est.scene
    top = int(max(sc.transverse_in_band.max(), sc.axial_in_band.max()))
    start = min(MAX_ELEMENTS,
                max(2, top + 1, math.ceil(top * math.pi / largest_phase(tol / SAFETY))))
    for family in ('fem', 'fem_sag'):
        if family == 'fem':
            limit = est.estimate('dsm', 0)      # fem as n -> inf: sag errors do not shrink
            if not passes(limit):
                candidates.append(ErrorEstimate('fem', MAX_ELEMENTS + 1, limit.freq_error,
                                                limit.frf_error,
                                                f'straight cables: {limit.cause}'))
                continue
        n, failed = start, start - 1
        while True:
            e = est.estimate(family, n)
            candidates.append(e)
            if passes(e) or n >= MAX_ELEMENTS:
                break
            # errors fall as n^-2 once the modes are resolved: aim there, at least STEP n
            aim = n * math.sqrt(SAFETY * e.error / tol) if e.error < MISSED else STEP * n
            failed, n = n, min(MAX_ELEMENTS, max(n + 1, math.ceil(max(aim, STEP * n))))
        while passes(e) and n - failed > 1:        # bisect down to the smallest passing n
            mid = (n + failed) // 2
            trial = est.estimate(family, mid)
            candidates.append(trial)
            if passes(trial):
                n, e = mid, trial
            else:
                failed = mid
    band = f'0-{sc.f_max_hz:g} Hz'
    considered = tuple((c.method, c.elements_per_cable, c.error) for c in candidates)
    found = [c for c in candidates if passes(c)]
    if found:
        best = min(found, key=cost)
        rejected = _rejections([c for c in candidates if not passes(c)
                                and (cost(c) < cost(best) or c.method != best.method)])
        reason = (f'auto: {_label(best)}, the cheapest model estimated within model.tolerance '
                  f'{100 * tol:g} % over {band} ({_pct(best.error)} %: {best.cause})'
                  + (f'; rejected: {rejected}' if rejected else ''))
    else:
        best = min(candidates, key=lambda c: (c.error, cost(c)))
        reason = (f'auto: no model reaches model.tolerance {100 * tol:g} % over {band} with '
                  f'n <= {MAX_ELEMENTS}; {_label(best)} has the smallest estimated error '
                  f'({_pct(best.error)} %: {best.cause})')
    return ModelChoice(best.method, best.elements_per_cable, reason, best.error,
                       best.freq_error, best.frf_error, considered)


def _label(e: ErrorEstimate) -> str:
    return f'{e.method} n={e.elements_per_cable}' if e.method in ('fem', 'fem_sag') \
        else e.method


def _rejections(rejected: list[ErrorEstimate]) -> str:
    """'spring (misses ...), fem n<=12 (...)': the finest rejected candidate of each method."""
    last: dict[str, ErrorEstimate] = {}
    for c in rejected:
        key = c.method if c.method not in ('fem', 'fem_sag') or c.elements_per_cable > 1 \
            else f'{c.method}1'
        if key not in last or c.elements_per_cable > last[key].elements_per_cable:
            last[key] = c
    groups: dict[str, list[str]] = {}
    for c in last.values():
        if c.method in ('fem', 'fem_sag') and c.elements_per_cable > MAX_ELEMENTS:
            name = f'{c.method} (any n)'
        elif c.method in ('fem', 'fem_sag') and c.elements_per_cable > 1:
            name = f'{c.method} n<={c.elements_per_cable}'
        else:
            name = _label(c)
        cause = c.cause if c.error >= MISSED else f'{_pct(c.error)} %: {c.cause}'
        groups.setdefault(cause, []).append(name)
    return '; '.join(f'{", ".join(names)} ({cause})' for cause, names in groups.items())


# --------------------------------------------------------------------------- the yardstick

REFERENCE_DISPERSION = 1e-3   # fem_sag reference: dispersion error at n before extrapolation
REFERENCE_MIN_ELEMENTS = 32
REFERENCE_MAX_ELEMENTS = 512
BEYOND_BAND = 1.5             # reference modes are computed up to this times f_max


@dataclass(frozen=True, eq=False)
class Reference:
    """The solution models are measured against, on the band [0, f_max].

    ``frequencies_hz`` holds every natural frequency up to ``BEYOND_BAND * f_max`` (ascending),
    ``response`` the damped complex FRF of the centroid (nf, 3) on ``frequency_grid_hz``;
    ``uncertainty`` is the estimated relative error of the reference itself.
    """

    label: str
    method: str
    elements_per_cable: int
    f_max_hz: float
    frequencies_hz: np.ndarray
    frequency_grid_hz: np.ndarray
    response: np.ndarray
    damping: Damping
    sag_effect: float             # estimated error of straight exact cables (dsm) on this band
    uncertainty: float

    @property
    def modes_in_band(self) -> int:
        return int(np.sum(self.frequencies_hz <= self.f_max_hz))


@dataclass(frozen=True, eq=False)
class Solution:
    """One model's answer: its system, FRF (nf, 3) complex and lowest natural frequencies."""

    system: PlatformSystem
    response: np.ndarray
    frequencies_hz: np.ndarray


@dataclass(frozen=True)
class Measured:
    """Errors of one model against a :class:`Reference` (relative, capped at 1 = 100 %)."""

    method: str
    elements_per_cable: int
    dofs: int
    freq_error: float
    frf_error: float
    modes_in_band: int            # the reference's
    missed_modes: int             # pairs without a counterpart, or off by 100 % or more
    valid: bool = True
    note: str = ''

    @property
    def error(self) -> float:
        return max(self.freq_error, self.frf_error)


def solve(settings, eq, method: str, n: int, frequency_grid_hz, damping: Damping,
          f_max_hz: float, at_least: int = 0) -> Solution:
    """Build ``method`` (n elements), its FRF on the grid and its modes up to ``f_max_hz``.

    At least ``at_least`` modes (when the model has that many DOFs), and always one beyond
    ``f_max_hz`` when the model has it, so that modes can be paired.
    """
    system = platform_system(settings.robot, eq.geometry, models.build(method, eq.cables, n))
    response = frequency_response(system, frequency_grid_hz, settings.frf_force_n,
                                  damping=damping).response[:, :3]
    if system.assembly.blocks is None:
        freqs = natural_frequencies_dsm(system, None, f_max_hz)
        if freqs.size < at_least + 1:
            freqs = natural_frequencies_dsm(system, at_least + 1)
    else:
        # the sparse eigen-solver of natural_frequencies takes at most dofs - 1 modes
        most = system.dofs if system.dofs <= DENSE_EIGEN_DOFS else system.dofs - 1
        count = min(most, max(at_least, 3) + 8)
        while True:
            freqs = natural_frequencies(system, count)
            if freqs[-1] > f_max_hz or count >= most:
                break
            count = min(most, 2 * count)
    return Solution(system, response, freqs)


def pair_errors(frequencies_hz, reference_hz, f_max_hz: float) -> tuple[float, int]:
    """(max relative error, missed pairs) of modes paired in ascending order (module doc)."""
    model = np.sort(np.asarray(frequencies_hz, dtype=float))
    ref = np.sort(np.asarray(reference_hz, dtype=float))
    count = max(int(np.sum(ref <= f_max_hz)), int(np.sum(model <= f_max_hz)))
    both = min(count, model.size, ref.size)
    errors = np.abs(model[:both] - ref[:both]) / ref[:both]
    missed = count - both + int(np.sum(errors >= MISSED))
    worst = float(errors.max(initial=0.0))
    return (MISSED if missed else min(worst, MISSED)), missed


def frf_error(response, reference_response) -> float:
    """max_f |A(f) - A_ref(f)| / |A_ref(f)| of complex centroid responses (nf, 3)."""
    diff = np.linalg.norm(np.asarray(response) - reference_response, axis=1)
    ref = np.linalg.norm(reference_response, axis=1)
    with np.errstate(all='ignore'):
        rel = diff / ref
    return float(np.max(np.where(np.isfinite(rel), rel, np.inf), initial=0.0))


def band_damping(settings, eq) -> Damping:
    """The configured damping, fitted on the spring model where ``damping.modal_ratio`` > 0."""
    from cdpr_dynamics.analysis import damping_for
    spring = platform_system(settings.robot, eq.geometry, models.build('spring', eq.cables))
    return damping_for(settings, spring)


def reference_elements(sc: Scene, f_hi_hz: float) -> int:
    """Power of two n >= 32 whose dispersion error on the cables' top mode below f_hi is
    below :data:`REFERENCE_DISPERSION` (at most :data:`REFERENCE_MAX_ELEMENTS`)."""
    top = float(np.max(f_hi_hz / sc.transverse_hz))
    t = largest_phase(REFERENCE_DISPERSION)
    n = REFERENCE_MIN_ELEMENTS
    while n < REFERENCE_MAX_ELEMENTS and math.pi * top / n > t:
        n *= 2
    return n


def reference_solution(settings, eq, f_max_hz: float | None = None,
                       damping: Damping | None = None) -> Reference:
    """``dsm`` where sag is negligible at the tolerance, else Richardson-extrapolated fem_sag.

    Negligible: the estimated error of exact straight cables over the band (sag, tension
    varying along the cable) is below ``SAG_NEGLIGIBLE * model.tolerance``.
    """
    f_max = settings.f_max_hz if f_max_hz is None else float(f_max_hz)
    damping = band_damping(settings, eq) if damping is None else damping
    grid = settings.frequencies_hz
    grid = grid[grid <= f_max]
    est = Estimator(settings, eq, f_max, damping)
    sag_effect = est.estimate('dsm', 0).error
    f_hi = BEYOND_BAND * f_max
    if sag_effect <= SAG_NEGLIGIBLE * settings.tolerance:
        sol = solve(settings, eq, 'dsm', 0, grid, damping, f_hi)
        freqs = sol.frequencies_hz
        return Reference('dsm (exact straight cables; sag negligible: estimated '
                         f'{_pct(sag_effect)} %)', 'dsm', 0, f_max, freqs[freqs <= f_hi],
                         grid, sol.response, damping, sag_effect, 1e-9)
    n = reference_elements(est.scene, f_hi)
    dsm = solve(settings, eq, 'dsm', 0, grid[:1], damping, f_hi)
    count = int(np.sum(dsm.frequencies_hz <= f_hi)) + 8
    coarse = solve(settings, eq, 'fem_sag', n, grid, damping, f_hi, count)
    fine = solve(settings, eq, 'fem_sag', 2 * n, grid, damping, f_hi, count)
    if not (coarse.system.assembly.valid and fine.system.assembly.valid):
        raise SelectionError('no sag-aware reference: ' + '; '.join(fine.system.assembly.warnings))
    k = min(coarse.frequencies_hz.size, fine.frequencies_hz.size)
    freqs = (4.0 * fine.frequencies_hz[:k] - coarse.frequencies_hz[:k]) / 3.0
    response = (4.0 * fine.response - coarse.response) / 3.0
    keep = freqs <= f_hi
    in_band = freqs <= f_max
    uncertainty = max(float(np.max(np.abs(fine.frequencies_hz[:k] - freqs)[in_band]
                                   / freqs[in_band], initial=0.0)),
                      frf_error(fine.response, response))
    return Reference(f'fem_sag n={n}/{2 * n} Richardson (sag not negligible: straight cables '
                     f'off by ~{_pct(sag_effect)} %)', 'fem_sag', 2 * n, f_max, freqs[keep],
                     grid, response, damping, sag_effect, uncertainty)


def measure_error(settings, eq, method: str, n: int, reference: Reference,
                  solution: Solution | None = None) -> Measured:
    """Real errors of ``method`` (n elements) against ``reference`` (see the module doc)."""
    if solution is None:
        solution = solve(settings, eq, method, n, reference.frequency_grid_hz,
                         reference.damping, reference.f_max_hz, reference.modes_in_band)
    assembly = solution.system.assembly
    freq, missed = pair_errors(solution.frequencies_hz, reference.frequencies_hz,
                               reference.f_max_hz)
    frf = frf_error(solution.response, reference.response)
    return Measured(method, assembly.elements_per_cable, solution.system.dofs, freq, frf,
                    reference.modes_in_band, missed, assembly.valid,
                    '; '.join(assembly.warnings))


def accuracy_warnings(settings, eq, method: str, n: int,
                      f_max_hz: float | None = None) -> list[str]:
    """Warnings when a configured model is estimated off by more than ``model.tolerance``.

    E.g. fem with too few elements for the cable modes in the band, a massless model that
    misses them, a straight model that ignores sag. Empty for a scene without estimates
    (slack cables: the models' own warnings say why).
    """
    if method == 'auto':
        return []
    try:
        est = Estimator(settings, eq, f_max_hz)
        e = est.estimate(method, n)
    except (SelectionError, np.linalg.LinAlgError):
        return []
    tol = float(settings.tolerance)
    if not e.error > tol:
        return []
    size = f' n={e.elements_per_cable}' if method in ('fem', 'fem_sag') else ''
    return [f'accuracy: {method}{size} is estimated {_pct(e.error)} % off over '
            f'0-{est.scene.f_max_hz:g} Hz (> model.tolerance {100 * tol:g} %): {e.cause}; '
            'model.method auto picks a model that meets it']
