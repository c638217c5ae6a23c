"""``auto``'s error estimates: how far each cable model is off over the band, without solving it.

**Errors.** Over the band [0, f_max] (f_max = ``frf.f_max_hz``) a model has two errors:

* frequency error: the largest relative error of its natural frequencies in the band; a mode
  the model does not have counts 100 % (massless models miss every cable mode, fem with n
  elements has only n - 1 per cable and direction);
* FRF error: the largest relative error max_f |A(f) - A_ref(f)| / |A_ref(f)| of the damped
  complex response of the centroid over the FRF sweep (it bounds the error of |A|), to the
  configured force and to unit forces along x, y and z (:func:`frf_loads`).

Estimates are not capped: 3.8 means 380 % (a massless model on a heavy-sag robot); only the
charts of ``cdpr_tradeoff`` cap them. They are cheap: closed forms per cable
(:mod:`cdpr_dynamics.selection.closed_forms`) and 3x3/6x6 algebra on the platform DOFs, no
eigen-solution and no reference run (10-30 ms for a whole choice).

* The "truth" is the closed-form sag-aware continuous cable
  (:func:`~cdpr_dynamics.selection.closed_forms.true_end_stiffness`); each model's end stiffness
  S_i is
  known in closed form too, so the platform error dZ = sum_i G_i^T (S_i - S_true,i) G_i is.
* FRF error: the change of the centroid's response, |(Z_true + dZ)^-1 dZ A| / |A|, max over
  the sweep (configured damping) for the configured force and unit forces along x, y, z.
* Platform modes: the first-order shift of the nonlinear eigenvalue problem
  Z(lam) phi = 0 at the spring model's modes (lam_p, phi),
  dlam / lam = phi^T dZ(lam_p) phi / (lam_p phi^T (M - dS/dlam) phi), halved for the
  frequency. -dS/dlam (the truth's or the model's cables, whichever is larger) is the cables'
  effective mass seen by the mode: negligible away from cable modes, large near one, where dZ
  has a pole too and the ratio stays the shift of that cable mode (with M alone the formula
  blows up there: 5.9 % for fem_sag n = 16 on rigid_cdpr.yaml, measured 0.64 %).
* Cable modes in the band: a model without cable DOFs misses them (100 %); fem with n
  elements has the chain's dispersion error sqrt(6(1 - cos t)/(2 + cos t))/t - 1, t = j pi/n,
  on the j-th mode (and misses modes j >= n); straight models add Irvine's shift of the first
  symmetric in-plane mode (100 % once lambda^2 >= 4 pi^2, where it crosses the antisymmetric
  one) or a quarter of the relative tension variation, gamma dz/(4 T), along the cable,
  whichever is larger.

Straight models (spring, fem, dsm) fail where lambda^2 is not small: their axial stiffness is
off by ~lambda^2/12 statically and their symmetric in-plane cable modes by ~4 lambda^2/pi^4, so
at 1 % they need lambda^2 below about 0.1-0.2 (the paper's lower cables, lambda^2 = 0.20, are
at the edge; a 20 N steel cable has lambda^2 ~ 300). No fixed threshold is used: the estimate
itself is compared with the tolerance.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from cdpr_dynamics import models
from cdpr_dynamics.selection.closed_forms import (straight_end_stiffness, dispersion_error,
                                                  model_end_stiffness, scene, true_end_stiffness)
from cdpr_dynamics.dynamics.system import Damping, configured_damping, platform_system
from cdpr_dynamics.models.base import CableAssembly
from cdpr_dynamics.models.dsm import clamped_roots
from cdpr_dynamics.mechanics.statics import SAG_METHODS, StaticsError, equilibrium_for

MISSED = 1.0                # error of a mode the model does not have (100 %)
INERTIA_STEP = 1e-4         # relative step in lam of the cables' effective mass (central)
SAG_ELEMENTS = 8            # fem_sag's own sag discretisation error is measured at n and 2n
SAG_ELEMENTS_MAX = 64       # ... n doubled from SAG_ELEMENTS until it resolves the band's modes


@dataclass(frozen=True)
class ErrorEstimate:
    """Estimated relative errors of one model over the band (uncapped), and the main cause."""

    method: str
    elements_per_cable: int
    freq_error: float
    frf_error: float
    cause: str
    missed_modes: int = 0          # cable modes in the band the model does not have

    @property
    def error(self) -> float:
        return max(self.freq_error, self.frf_error)


def percent(fraction: float) -> str:
    """A relative error as a percentage, two significant digits ('0.73', '100', '380')."""
    value = 100.0 * float(fraction)
    return f'{value:.2g}' if value < 99.5 else f'{value:.0f}'


def band_damping(settings, eq) -> Damping:
    """The configured damping, fitted on the spring model where ``damping.modal_ratio`` > 0
    (:func:`cdpr_dynamics.dynamics.system.configured_damping`)."""
    spring = platform_system(settings.robot, eq.geometry, models.build('spring', eq.cables))
    return configured_damping(settings, spring)


def frf_loads(settings, platform_dofs: int) -> np.ndarray:
    """(platform_dofs, 4) the loads FRF errors are taken over: the configured force
    (``frf.force_n``; z where it is zero) and unit forces along x, y and z (the node sees any
    direction)."""
    loads = np.zeros((platform_dofs, 4))
    loads[:3, 0] = settings.frf_force_n
    loads[:3, 1:] = np.eye(3)
    if not np.any(loads[:, 0]):
        loads[2, 0] = 1.0
    return loads


def load_responses(dynamic_stiffness: np.ndarray, settings) -> np.ndarray:
    """(nf, nd, 4) responses Z^-1 F to the loads of :func:`frf_loads` for Z (nf, nd, nd)."""
    nf, nd = dynamic_stiffness.shape[:2]
    loads = np.broadcast_to(frf_loads(settings, nd).astype(complex), (nf, nd, 4))
    with np.errstate(all='ignore'):
        return np.linalg.solve(dynamic_stiffness, loads)


class Estimator:
    """Error estimates of any model for one scene, band and damping (see the module)."""

    def __init__(self, settings, eq, f_max_hz: float | None = None,
                 damping: Damping | None = None):
        self.settings = settings
        f_max = settings.f_max_hz if f_max_hz is None else float(f_max_hz)
        # the truth: the cables as they hang (sag-consistent statics where they have weight
        # and it exists); each candidate at the statics it runs with (chord or sag)
        chord_eq = eq
        self.chord_scene = scene(eq.cables, f_max)
        if eq.statics == 'chord' and eq.cables.weight_per_length_n_per_m > 0:
            try:
                eq = equilibrium_for(settings, eq, 'fem_sag')
            except StaticsError:
                pass            # no sag-consistent state: judged at the chord one
        self.eq = eq
        self.scene = scene(eq.cables, f_max) if eq.statics == 'sag' else self.chord_scene
        self.damping = band_damping(settings, eq) if damping is None else damping
        grid = settings.frequencies_hz
        grid = grid[(grid > 0) & (grid <= f_max)]
        self.omega = 2.0 * math.pi * grid
        self.damped = self.damping.mass_factor > 0 or self.damping.stiffness_factor > 0
        w = self.omega
        self.lam = (w * w - 1j * w * self.damping.mass_factor) / (
            1.0 + 1j * w * self.damping.stiffness_factor)
        end_force = eq.end_force_n if eq.end_force_n is not None \
            else eq.cables.tension_n[:, None] * eq.cables.unit
        truth = CableAssembly('truth', 0, lambda lam: true_end_stiffness(self.scene, lam),
                              end_force, None)
        self.truth_system = platform_system(settings.robot, eq.geometry, truth)
        # a chord-statics candidate's rotational geometric stiffness (its end forces along the
        # chords) less the truth's: part of its dZ on a 6-DOF platform
        chord_force = chord_eq.cables.tension_n[:, None] * chord_eq.cables.unit
        self._chord_geometric = platform_system(
            settings.robot, eq.geometry, dataclasses.replace(truth, end_force_n=chord_force)
        ).platform_stiffness - self.truth_system.platform_stiffness
        self._truth_frf = self.truth_system.dynamic_stiffness(self.omega, self.damping) \
            if self.omega.size else None
        self._truth_frf_ends = true_end_stiffness(self.scene, self.lam)
        self._platform_modes()
        self._truth_modes_ends = true_end_stiffness(self.scene, self.mode_omega ** 2)
        self._straight_frf_ends = straight_end_stiffness(eq.cables, None, self.lam)
        self._straight_modes_ends = straight_end_stiffness(eq.cables, None,
                                                           self.mode_omega ** 2)

    def _platform_modes(self) -> None:
        """Modes of the spring model on the platform DOFs that lie in (or near) the band, their
        modal mass and the truth's cable mass in each."""
        spring = platform_system(self.settings.robot, self.eq.geometry,
                                 models.build('spring', self.eq.cables))
        m = spring.platform_mass
        values, vectors = scipy.linalg.eigh(spring.static_stiffness(), m)
        omega = np.sqrt(np.clip(values, 0.0, None))
        keep = omega <= 2.0 * math.pi * self.scene.f_max_hz * 1.1
        self.mode_omega = omega[keep]
        phi = self.mode_shapes = vectors[:, keep]
        self.mode_mass = np.einsum('ik,ij,jk->k', phi, m, phi)
        self.mode_cable_mass = self._cable_mass(lambda lam: true_end_stiffness(self.scene, lam))

    def _cable_mass(self, ends) -> np.ndarray:
        """-phi^T dS/dlam phi per platform mode, S = the cables' ``ends`` (lam) on the platform:
        the cables' effective mass in the mode (>= 0 for passive cables; a pole within the
        central difference's step counts 0)."""
        lam = self.mode_omega ** 2
        if lam.size == 0:
            return np.zeros(0)
        step = INERTIA_STEP * np.maximum(lam, 1.0)
        on = self.truth_system.cables_on_platform
        phi = self.mode_shapes
        with np.errstate(all='ignore'):
            slope = (on(ends(lam + step)).real - on(ends(lam - step)).real) \
                / (2 * step)[:, None, None]
            mass = -np.einsum('ak,kab,bk->k', phi, slope, phi)
        return np.where(np.isfinite(mass), np.maximum(mass, 0.0), 0.0)

    @functools.cached_property
    def sag_elements(self) -> int:
        """n0 of fem_sag's own error measurement (:meth:`sag_error`): SAG_ELEMENTS, doubled
        (up to SAG_ELEMENTS_MAX) until the chain of n0 elements resolves every cable mode in
        the band. Where the band holds modes the chains of n0 and 2 n0 miss, their difference
        has poles the cables do not (over 0-10 Hz on the CoGiRo-sized robot, 28 modes per
        cable and direction, n0 = 8 estimated fem_sag n = 8 at 256 % and n = 16 at 34 %,
        measured 120 % and 47 %)."""
        sc = self.scene
        top = int(max(sc.transverse_in_band.max(initial=0), sc.axial_in_band.max(initial=0)))
        n0 = SAG_ELEMENTS
        while n0 <= top and n0 < SAG_ELEMENTS_MAX:
            n0 *= 2
        return n0

    @functools.cached_property
    def _sag_chains(self):
        """fem_sag and fem at :attr:`sag_elements` and twice that, or None where fem_sag is
        invalid."""
        n0, cables = self.sag_elements, self.eq.cables
        chains = [models.build(m, cables, n) for m in ('fem_sag', 'fem') for n in (n0, 2 * n0)]
        return chains if chains[0].valid and chains[1].valid else None

    def sag_error(self, lam) -> np.ndarray | None:
        """n^2 times fem_sag's error from the sag its n straight elements lose, at ``lam``:
        (4/3) n0^2 [(S_sag(n0) - S_sag(2 n0)) - (S_fem(n0) - S_fem(2 n0))], n0 =
        :attr:`sag_elements` (Richardson on the
        n^-2 error of fem_sag beyond the straight chain's; constant in n to 3 % from n = 4 on
        the robots of test_cli_estimate_table). None where fem_sag is invalid. Used for the FRF
        (damped: lam off the real axis); the undamped platform modes keep the closed form,
        as the extrapolated difference of two chains has both chains' poles."""
        chains = self._sag_chains
        if chains is None:
            return None
        lam = np.asarray(lam, dtype=complex).reshape(-1)
        sag_a, sag_b, fem_a, fem_b = (c.end_stiffness(lam) for c in chains)
        return (4.0 / 3.0) * self.sag_elements ** 2 * ((sag_a - sag_b) - (fem_a - fem_b))

    @functools.cached_property
    def _sag_error_frf(self):
        return self.sag_error(self.lam)

    @functools.cached_property
    def _anchor_node_error(self) -> np.ndarray:
        """n times the relative frequency error of fem's and fem_sag's cable modes in the band
        from their massless anchor node, per cable (0 without an anchor end). On the anchor
        springs the span's end moves: in the j-th mode sin(z_j (L - x)/L) (z_j of
        :func:`~cdpr_dynamics.models.dsm.clamped_roots`) by sin z_j. The chain's first element
        keeps its mass where the anchor is fixed, so it misses about (2/3) mu (L/n) sin^2 z_j of
        the modal mass mu L (1 - sin(2 z_j)/(2 z_j))/2: by Rayleigh's quotient the mode is
        (2/(3n)) sin^2 z_j / (1 - sin(2 z_j)/(2 z_j)) high (0.32 % at n = 16, measured 0.38 %,
        on paper_pulleys' second out-of-plane mode), along the cable and normal to the pulley
        plane."""
        cables, sc = self.scene.cables, self.scene
        end = cables.anchor_end
        if end is None:
            return np.zeros(cables.n_cables)
        f_axial, f_normal = end.compliance(cables.ea_n, cables.tension_n)
        worst = np.zeros(cables.n_cables)
        length = cables.length_m
        for count, beta in ((sc.axial_in_band, cables.ea_n * f_axial / length),
                            (sc.transverse_in_band, cables.tension_n * f_normal / length)):
            j = np.arange(1, int(np.max(count, initial=0)) + 1)[:, None]
            if j.size == 0:
                continue
            z = clamped_roots(j, beta)
            with np.errstate(invalid='ignore', divide='ignore'):
                shift = (2.0 / 3.0) * np.sin(z) ** 2 / (1.0 - np.sin(2.0 * z) / (2.0 * z))
            worst = np.maximum(worst, np.where(j <= count, np.nan_to_num(shift), 0.0).max(axis=0))
        return worst

    def _coarse_sag_frf_error(self, n: int) -> np.ndarray:
        """fem_sag's end stiffness error on the FRF sweep for n < 2 n0 (n0 =
        :attr:`sag_elements`), from the model itself: S_sag(n) - S_sag(2 n0) plus the estimated
        error of n = 2 n0 (``sag_error`` / (2 n0)^2 and the straight chain's S_fem(2 n0) -
        S_dsm). Below 2 n0 the n^-2 law extrapolates (4x too high at n = 4 on heavy sag)."""
        n0 = 2 * self.sag_elements
        fine = self._sag_chains[1].end_stiffness(self.lam)
        coarse = models.build('fem_sag', self.eq.cables, n).end_stiffness(self.lam)
        return (coarse - fine + self._sag_error_frf / n0 ** 2
                + self._sag_chains[3].end_stiffness(self.lam) - self._straight_frf_ends)

    def _scene_of(self, method: str, straight):
        """(scene, precomputed straight end stiffness or None, rotational geometric stiffness
        less the truth's) of the statics ``method`` runs with: the sag-consistent scene for
        SAG_METHODS, the chord scene for the others."""
        if method in SAG_METHODS or self.chord_scene is self.scene:
            return self.scene, straight, 0.0
        return self.chord_scene, None, self._chord_geometric

    def frf_error(self, method: str, n: int) -> float:
        """Relative FRF error of the centroid's translation, max over the sweep.

        A - A_true = -(Z_true + dZ)^-1 dZ A_true (exact on the platform DOFs, no
        linearisation: straight models on heavy sag are off by 100 % and more, not by the
        first order's 10^4 %) for the configured force and for unit forces along x, y and z
        (the node sees any direction): max |dA[:3]| / |A_true[:3]|. Not capped; a response the
        estimate cannot evaluate (a singular model) counts as missed (100 %).
        """
        if not self.damped or self._truth_frf is None:
            return 0.0
        sc, straight, geometric = self._scene_of(method, self._straight_frf_ends)
        if method == 'fem_sag' and n < 2 * self.sag_elements and self._sag_chains is not None:
            ends = self._truth_frf_ends + self._coarse_sag_frf_error(n)
        else:
            ends = model_end_stiffness(sc, method, n, self.lam, straight,
                                       self._sag_error_frf if method == 'fem_sag' else None)
        scale = 1.0 + 1j * self.omega * self.damping.stiffness_factor
        dz = scale[:, None, None] * (self.truth_system.cables_on_platform(
            ends - self._truth_frf_ends) + geometric)
        response = self._truth_response                                  # (nf, nd, loads)
        with np.errstate(all='ignore'):
            change = np.linalg.solve(self._truth_frf + dz, dz @ response)
            rel = np.linalg.norm(change[:, :3], axis=1) / np.linalg.norm(response[:, :3], axis=1)
        if not np.all(np.isfinite(rel)):
            return MISSED
        return float(rel.max())

    @functools.cached_property
    def _truth_response(self) -> np.ndarray:
        """(nf, nd, 4) truth responses to the loads of :func:`frf_loads`."""
        return load_responses(self._truth_frf, self.settings)

    def platform_mode_error(self, method: str, n: int) -> float:
        """Relative shift of the platform modes in the band (undamped, uncapped), first order:
        |phi^T dZ phi| / (2 lam phi^T (M - dS/dlam) phi), dS/dlam the truth's or the model's
        cables, whichever adds more inertia (near a cable mode of either, dZ has its pole and
        the ratio stays the shift of that cable mode; see the module)."""
        if self.mode_omega.size == 0:
            return 0.0
        lam = self.mode_omega ** 2
        sc, straight, geometric = self._scene_of(method, self._straight_modes_ends)
        ends = model_end_stiffness(sc, method, n, lam, straight)
        model = self._cable_mass(lambda x: model_end_stiffness(sc, method, n, x))
        inertia = self.mode_mass + np.maximum(self.mode_cable_mass, model)
        with np.errstate(all='ignore'):
            dz = self.truth_system.cables_on_platform(ends - self._truth_modes_ends).real \
                + geometric
            phi = self.mode_shapes
            shift = np.abs(np.einsum('ak,kab,bk->k', phi, dz, phi)) / (2.0 * lam * inertia)
        return float(np.max(np.where(np.isfinite(shift), shift, MISSED)))

    def cable_mode_error(self, method: str, n: int) -> tuple[float, str, int]:
        """(estimated error on the cable modes in the band, its cause, modes missed)."""
        sc = self.scene
        jt, ja = sc.transverse_in_band, sc.axial_in_band
        if not np.any(jt) and not np.any(ja):
            return 0.0, '', 0
        modes = sc.cable_modes_in_band
        if method in ('spring', 'catenary', 'catenary_exact') or (method == 'fem' and n == 1) \
                or (method == 'fem_sag' and n == 1):
            return MISSED, f'no cable DOFs: {modes} cable modes in the band missed', modes
        error = 0.0
        cause = ''
        if method in ('fem', 'fem_sag'):
            top = int(max(jt.max(), ja.max()))
            if n <= top:
                missed = int(2 * np.maximum(jt - (n - 1), 0).sum()
                             + np.maximum(ja - (n - 1), 0).sum())
                return MISSED, (f'n = {n} resolves {n - 1} of the {top} modes per cable in '
                                'the band'), missed
            disc = float(max(dispersion_error(np.pi * jt / n).max(),
                             dispersion_error(np.pi * ja / n).max()))
            disc += float(self._anchor_node_error.max(initial=0.0)) / n
            error, cause = disc, f'cable mode {top} off by {percent(disc)} % (n = {n})'
        if method in models.STRAIGHT_METHODS:
            with_mode = jt > 0
            sym = np.where(with_mode, np.minimum(sc.symmetric_shift, MISSED), 0.0).max()
            tension = np.where(with_mode, sc.tension_shift, 0.0).max()
            straight = float(max(sym, tension))
            if straight > 0:
                i = int(np.argmax(np.where(with_mode, sc.sag_parameter, -1.0)))
                what = (f'ignores sag (lambda^2 = {sc.sag_parameter[i]:.3g}: symmetric '
                        f'in-plane cable mode off by {percent(min(sym, MISSED))} %)'
                        if sym >= tension else
                        f'takes the end tension for the whole cable (it varies by '
                        f'{400 * tension:.2g} %)')
                cause = f'{cause} and {what}' if cause else what
                error += straight
        return float(error), cause, 0

    def estimate(self, method: str, n: int, full: bool = True) -> ErrorEstimate:
        """:class:`ErrorEstimate` of ``method`` with ``n`` elements per cable.

        With ``full`` False a model that misses cable modes is not looked at further (its
        FRF error is then nan): what :func:`cdpr_dynamics.selection.auto.choose_model` needs first,
        at a fraction of the cost.
        """
        n = int(n) if method in ('fem', 'fem_sag') else 1
        cable, cause, missed = self.cable_mode_error(method, n)
        if missed and not full:
            return ErrorEstimate(method, n, MISSED, math.nan, cause, missed)
        platform = self.platform_mode_error(method, n)
        frf = self.frf_error(method, n)
        freq = max(cable, platform)
        if platform > cable:
            cause = f'platform modes off by ~{percent(platform)} %'
        if frf > freq:
            cause = f'FRF off by ~{percent(frf)} %'
        return ErrorEstimate(method, n, freq, frf, cause, missed)
