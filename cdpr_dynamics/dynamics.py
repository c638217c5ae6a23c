"""Platform dynamics: assembly, frequency response (Eq. 38), modes, damping (Eq. 41), Newmark.

DOFs are ordered platform first (3 translations, then 3 small rotations for a rigid platform),
then every cable's interior nodes. A cable end moves with its attachment, d_i = G_i q with
G_i = [I, -[r_i]x]. Besides the cables, the platform stiffness has the geometric term of the
cable forces f_i turning with the platform, K_rot = -sym(sum_i [f_i]x [r_i]x), whose
antisymmetric part is the (non-conservative) external moment and is dropped.

Damping is Rayleigh, C = dM M + dK K (Eq. 41). The modal damping ratio of a mode at w is
zeta = dM / (2 w) + dK w / 2; :func:`rayleigh_from_modal_ratio` fits dM, dK to a ratio.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cdpr_dynamics.models.base import CableAssembly
from cdpr_dynamics.robot import Geometry, Robot, skew


DENSE_EIGEN_DOFS = 60   # above: sparse Lanczos (dense LAPACK threads thrash on a busy machine)


class DynamicsError(RuntimeError):
    """A dynamic analysis that cannot give a trustworthy answer (the message says why)."""


@dataclass(frozen=True)
class Damping:
    """Rayleigh damping C = mass_factor M + stiffness_factor K (1/s and s)."""

    mass_factor: float = 0.0
    stiffness_factor: float = 0.0

    def ratios(self, frequency_hz) -> np.ndarray:
        """Modal damping ratios zeta = dM/(2w) + dK w/2 of modes at ``frequency_hz``."""
        w = 2.0 * np.pi * np.asarray(frequency_hz, dtype=float)
        with np.errstate(divide='ignore', invalid='ignore'):
            return self.mass_factor / (2.0 * w) + self.stiffness_factor * w / 2.0


def rayleigh_from_modal_ratio(ratio: float, f1_hz: float, f2_hz: float) -> Damping:
    """Rayleigh factors giving modal damping ``ratio`` at f1 and f2 (and less in between)."""
    w1, w2 = 2 * np.pi * f1_hz, 2 * np.pi * f2_hz
    if math.isclose(w1, w2):
        return Damping(ratio * w1, ratio / w1)
    return Damping(2 * ratio * w1 * w2 / (w1 + w2), 2 * ratio / (w1 + w2))


def configured_damping(settings, system: 'PlatformSystem | None' = None) -> Damping:
    """Rayleigh damping of the settings, or fitted to ``damping.modal_ratio`` when it is > 0.

    ``settings`` has ``damping_modal_ratio``, ``damping_mass_factor``,
    ``damping_stiffness_factor`` and ``f_max_hz``. The fit puts the ratio at the lowest and at
    the highest platform mode below ``frf.f_max_hz`` (modes in between are damped a little
    less): the modes of the platform mass on the model's statically condensed cables
    (:func:`platform_frequencies`), so every model of a scene gets the same damping (to the
    ~1 % its static stiffness differs by) and no cable mode decides it. Raises
    :class:`DynamicsError` when the fit has no system or no positive platform mode.
    """
    if settings.damping_modal_ratio <= 0.0:
        return Damping(settings.damping_mass_factor, settings.damping_stiffness_factor)
    if system is None:
        raise DynamicsError('damping.modal_ratio needs the model to fit Rayleigh factors')
    freqs = platform_frequencies(system)
    freqs = freqs[freqs > 0]
    if freqs.size == 0:
        raise DynamicsError('no positive platform mode to fit damping.modal_ratio to')
    in_band = freqs[freqs <= settings.f_max_hz]
    high = in_band[-1] if in_band.size else freqs[0]
    return rayleigh_from_modal_ratio(settings.damping_modal_ratio, freqs[0], high)


@dataclass(frozen=True, eq=False)
class PlatformSystem:
    """The linear dynamic model of the robot at one state (geometry, tensions, cable model)."""

    geometry: Geometry
    assembly: CableAssembly
    platform_mass: np.ndarray         # (ndof, ndof)
    platform_stiffness: np.ndarray    # (ndof, ndof) geometric rotation term only

    @property
    def platform_dofs(self) -> int:
        return self.platform_mass.shape[0]

    @property
    def dofs(self) -> int:
        return self.platform_dofs + self.assembly.interior_dofs

    def dynamic_stiffness(self, omega_rad_s, damping: Damping = Damping()) -> np.ndarray:
        """Condensed complex dynamic stiffness Z(w) = K + i w C - w^2 M on the platform DOFs.

        Shape (len(omega), ndof, ndof); the cables' interior DOFs are eliminated exactly.
        """
        w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
        scale = 1.0 + 1j * w * damping.stiffness_factor
        lam = (w * w - 1j * w * damping.mass_factor) / scale
        cables = self.cables_on_platform(self.assembly.end_stiffness(lam))
        own = self.platform_stiffness[None] - lam[:, None, None] * self.platform_mass[None]
        return scale[:, None, None] * (own + cables)

    def cables_on_platform(self, ends: np.ndarray) -> np.ndarray:
        """sum_i G_i^T S_i G_i: stacked cable end stiffnesses (nl, n, 3, 3) on the platform
        DOFs, (nl, ndof, ndof); real in, real out."""
        flat = ends.reshape(ends.shape[0], -1)
        out = flat.real @ self._congruence   # real GEMMs: far faster than a complex one here
        if np.iscomplexobj(flat):
            out = out + 1j * (flat.imag @ self._congruence)
        return out.reshape(-1, self.platform_dofs, self.platform_dofs)

    @functools.cached_property
    def _congruence(self) -> np.ndarray:
        """(9n, ndof^2) map of the stacked 3x3 end stiffnesses to sum_i G_i^T S_i G_i."""
        g = self.geometry.attachment_map()
        nd = self.platform_dofs
        return np.einsum('cia,cjb->cijab', g, g).reshape(-1, nd * nd)

    def static_stiffness(self) -> np.ndarray:
        """(ndof, ndof) static stiffness of the platform, all cable DOFs condensed (N/m, ...)."""
        return self.dynamic_stiffness(np.zeros(1))[0].real

    def matrices(self, dense: bool = False):
        """Global stiffness and mass (platform DOFs first, then cable interior nodes): sparse
        (csc), or dense arrays (cheaper to build for small models)."""
        blocks = self.assembly.blocks
        if blocks is None:
            raise DynamicsError(f'method {self.assembly.method} has no finite matrices; '
                                'use fem or fem_sag for modes and time histories')
        g = self.geometry.attachment_map()
        return (_assemble(self.platform_stiffness, blocks.k_diag, blocks.k_off, g, dense),
                _assemble(self.platform_mass, blocks.m_diag, blocks.m_off, g, dense))


def _assemble(platform: np.ndarray, diag: np.ndarray, off: np.ndarray, g: np.ndarray,
              as_dense: bool = False):
    """Global matrix (sparse, or a dense array) from block-tridiagonal cable chains and the
    platform block."""
    nd = platform.shape[0]
    ncab, nodes = diag.shape[:2]
    interior = nodes - 1
    dense = platform + np.einsum('cia,cij,cjb->ab', g, diag[:, -1], g)
    rows, cols, vals = [np.repeat(np.arange(nd), nd)], [np.tile(np.arange(nd), nd)], \
        [dense.ravel()]
    if interior:
        base = nd + 3 * interior * np.arange(ncab)[:, None] + 3 * np.arange(interior)[None, :]
        i3 = np.arange(3)
        # interior diagonal blocks
        r = base[:, :, None, None] + i3[:, None]
        c = base[:, :, None, None] + i3[None, :]
        rows.append(np.broadcast_to(r, diag[:, :-1].shape).ravel())
        cols.append(np.broadcast_to(c, diag[:, :-1].shape).ravel())
        vals.append(diag[:, :-1].ravel())
        # interior-interior off-diagonal blocks, both triangles
        if interior > 1:
            r = base[:, :-1, None, None] + i3[:, None]
            c = base[:, 1:, None, None] + i3[None, :]
            blk = off[:, :-1]
            shape = blk.shape
            rows += [np.broadcast_to(r, shape).ravel(), np.broadcast_to(c, shape).ravel()]
            cols += [np.broadcast_to(c, shape).ravel(), np.broadcast_to(r, shape).ravel()]
            vals += [blk.ravel(), blk.ravel()]      # (c, r) entries: the transpose
        # last interior node to the platform through the attachment map
        coupling = np.einsum('cij,cjb->cib', off[:, -1], g)       # (ncab, 3, nd)
        r = base[:, -1, None, None] + i3[:, None]                  # (ncab, 3, 1)
        c = np.arange(nd)[None, None, :]
        shape = coupling.shape
        rows += [np.broadcast_to(r, shape).ravel(), np.broadcast_to(c, shape).ravel()]
        cols += [np.broadcast_to(c, shape).ravel(), np.broadcast_to(r, shape).ravel()]
        vals += [coupling.ravel(), coupling.ravel()]
    size = nd + 3 * interior * ncab
    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    if as_dense:
        out = np.zeros((size, size))
        np.add.at(out, (rows, cols), vals)
        return out
    return sp.csc_matrix((vals, (rows, cols)), shape=(size, size))


def platform_system(robot: Robot, geometry: Geometry, assembly: CableAssembly) -> PlatformSystem:
    """Combine the platform (mass, rotational geometric stiffness) with the cables."""
    nd = robot.platform_dofs
    stiffness = np.zeros((nd, nd))
    if nd == 6:
        k_rot = -np.einsum('cij,cjk->ik', skew(assembly.end_force_n), skew(geometry.lever_m))
        stiffness[3:, 3:] = 0.5 * (k_rot + k_rot.T)
    return PlatformSystem(geometry, assembly, robot.platform_mass_matrix(geometry.rotation),
                          stiffness)


# --------------------------------------------------------------------------- frequency response

@dataclass(frozen=True, eq=False)
class FrequencyResponse:
    """Steady-state response to a harmonic force F0 e^{i w t} on the platform (Eq. 38).

    ``amplitude_m`` and ``phase_rad`` are (nf, 3): the centroid's translation, u = |A| cos(w t +
    phase); ``response`` (nf, ndof) complex has every platform DOF.
    """

    frequency_hz: np.ndarray
    response: np.ndarray
    singular: np.ndarray      # (nf,) bool: Z(w) singular (undamped resonance): amplitude inf

    @property
    def amplitude_m(self) -> np.ndarray:
        return np.abs(self.response[:, :3])

    @property
    def phase_rad(self) -> np.ndarray:
        return np.angle(self.response[:, :3])


def frequency_response(system: PlatformSystem, frequency_hz, force_n,
                       moment_nm=(0.0, 0.0, 0.0), damping: Damping = Damping()):
    """A(w) = Z(w)^-1 F0 for every frequency, batched over frequencies.

    Where Z(w) is singular (an undamped FRF exactly at a resonance) the amplitude is inf and
    ``singular`` marks the frequency instead of raising.
    """
    f = np.atleast_1d(np.asarray(frequency_hz, dtype=float))
    z = system.dynamic_stiffness(2.0 * np.pi * f, damping)
    load = np.concatenate([np.asarray(force_n, dtype=float),
                           np.asarray(moment_nm, dtype=float)])[:system.platform_dofs]
    # singular: smallest singular value at round-off level of the stiffness and inertia scale
    # (Z itself can vanish entirely at a repeated resonance, so its own norm is no scale)
    sigma = np.linalg.svd(z, compute_uv=False)
    scale = np.maximum(sigma[:, 0], np.abs(system.static_stiffness()).max()
                       + (2 * np.pi * f) ** 2 * np.abs(system.platform_mass).max())
    singular = ~(sigma[:, -1] > 1e-12 * scale)
    response = np.full((f.size, system.platform_dofs), np.inf + 0j)
    ok = ~singular
    if np.any(ok):
        response[ok] = np.linalg.solve(z[ok], np.broadcast_to(load, (ok.sum(), load.size))
                                       [..., None])[..., 0]
    return FrequencyResponse(f, response, singular)


# --------------------------------------------------------------------------- natural frequencies

def natural_frequencies(system: PlatformSystem, count: int = 12) -> np.ndarray:
    """The ``count`` lowest undamped natural frequencies (Hz), ascending (fewer if DOFs lack).

    Solves K phi = w^2 M phi of the global matrices: dense for small models, shift-invert Lanczos
    (scipy eigsh, sigma = 0) for large ones. A model without finite matrices (``dsm``) goes to
    Wittrick-Williams bisection on det Z(w): :func:`models.dsm.natural_frequencies_dsm`.
    """
    if system.assembly.blocks is None:
        from cdpr_dynamics.models.dsm import natural_frequencies_dsm
        return natural_frequencies_dsm(system, count)
    k, m = system.matrices()
    n = k.shape[0]
    count = min(count, n)
    if n <= DENSE_EIGEN_DOFS or count >= n - 1:       # eigsh needs count < n - 1
        values = scipy.linalg.eigh(k.toarray(), m.toarray(), eigvals_only=True,
                                   subset_by_index=[0, count - 1])
    else:
        values = spla.eigsh(k, k=count, M=m, sigma=0.0, which='LM',
                            return_eigenvectors=False)
    return np.sqrt(np.clip(np.sort(values.real), 0.0, None)) / (2.0 * np.pi)


def platform_frequencies(system: PlatformSystem) -> np.ndarray:
    """Natural frequencies (Hz) of the platform mass on the statically condensed cables:
    eig(K_static, M_platform), ascending; the cables' own inertia left out."""
    values = scipy.linalg.eigh(system.static_stiffness(), system.platform_mass,
                               eigvals_only=True)
    return np.sqrt(np.clip(values, 0.0, None)) / (2.0 * np.pi)


# --------------------------------------------------------------------------- Newmark

class Newmark:
    """Newmark's method (Eqs. 42-50) for M u'' + C u' + K u = F(t), factorised once.

    Sparse K, M use a sparse LU of the effective stiffness; dense arrays (small models) a dense
    LU.

    ``alpha`` is the velocity weight (often called gamma) and ``beta`` the displacement weight.
    Unconditionally stable for alpha >= 1/2 and beta >= alpha/2; otherwise stable only for
    w_max dt <= 1 / sqrt(alpha/2 - beta), which :meth:`__init__` checks (undamped bound) and
    refuses with :class:`DynamicsError` rather than integrate a diverging answer.
    """

    def __init__(self, stiffness, mass, damping: Damping, dt_s: float, alpha: float = 0.5,
                 beta: float = 0.25):
        if not (dt_s > 0 and alpha >= 0.5 and beta > 0):
            raise DynamicsError(f'Newmark needs dt > 0, alpha >= 0.5 and beta > 0 (got dt = '
                                f'{dt_s}, alpha = {alpha}, beta = {beta})')
        dense = not sp.issparse(stiffness)
        self.k = np.asarray(stiffness, dtype=float) if dense else sp.csc_matrix(stiffness)
        self.m = np.asarray(mass, dtype=float) if dense else sp.csc_matrix(mass)
        self.c = damping.mass_factor * self.m + damping.stiffness_factor * self.k
        if beta < alpha / 2.0:
            w_max = math.sqrt(max(_largest_eigenvalue(self.k, self.m), 0.0))
            limit = 1.0 / math.sqrt(alpha / 2.0 - beta)
            if w_max * dt_s > limit:
                raise DynamicsError(
                    f'Newmark with beta = {beta} < alpha/2 is unstable for dt = {dt_s} s: the '
                    f'highest mode ({w_max / 2 / math.pi:.4g} Hz) needs dt <= '
                    f'{limit / w_max:.3g} s')
        dt = dt_s
        self.a = (1 / (beta * dt * dt), alpha / (beta * dt), 1 / (beta * dt), 1 / (2 * beta) - 1,
                  alpha / beta - 1, dt / 2 * (alpha / beta - 2), dt * (1 - alpha), alpha * dt)
        self.dt_s = dt
        effective = self.k + self.a[0] * self.m + self.a[1] * self.c         # Eq. 46
        if dense:   # small models: a dense LU beats a sparse one's call overhead
            factor = scipy.linalg.lu_factor(effective)
            self._solve = lambda rhs: scipy.linalg.lu_solve(factor, rhs, check_finite=False)
        else:
            self._solve = spla.splu(sp.csc_matrix(effective), permc_spec='NATURAL').solve
        n = self.k.shape[0]
        self.u, self.v, self.acc = np.zeros(n), np.zeros(n), np.zeros(n)

    def reset(self) -> None:
        """Back to rest (u = v = a = 0: Eq. 43 with no load at t = 0)."""
        n = self.k.shape[0]
        self.u, self.v, self.acc = np.zeros(n), np.zeros(n), np.zeros(n)

    def step(self, force: np.ndarray) -> np.ndarray:
        """Advance one step to the load ``force`` at t + dt (Eqs. 47-50); return u."""
        a0, a1, a2, a3, a4, a5, a6, a7 = self.a
        u, v, acc = self.u, self.v, self.acc
        rhs = force + self.m @ (a0 * u + a2 * v + a3 * acc) + self.c @ (a1 * u + a4 * v + a5 * acc)
        u_new = self._solve(rhs)
        acc_new = a0 * (u_new - u) - a2 * v - a3 * acc
        self.v = v + a6 * acc + a7 * acc_new
        self.u, self.acc = u_new, acc_new
        return u_new


def _largest_eigenvalue(k, m) -> float:
    """Largest w^2 of K phi = w^2 M phi (M positive definite on the DOFs that carry stiffness)."""
    if not sp.issparse(k) or k.shape[0] <= DENSE_EIGEN_DOFS:
        dense = [a.toarray() if sp.issparse(a) else a for a in (k, m)]
        return float(scipy.linalg.eigh(*dense, eigvals_only=True)[-1])
    return float(spla.eigsh(k, k=1, M=m, which='LA', return_eigenvectors=False)[0])


@dataclass(frozen=True, eq=False)
class TimeHistory:
    """Platform response over time: ``t_s`` (nt,), ``u`` (nt, ndof) of the platform DOFs."""

    t_s: np.ndarray
    u: np.ndarray

    @property
    def u_m(self) -> np.ndarray:
        """(nt, 3) displacement of the centroid (m)."""
        return self.u[:, :3]


def time_history(system: PlatformSystem, force_n, excitation_hz: float, duration_s: float,
                 damping: Damping, dt_s: float = 1e-3, alpha: float = 0.5,
                 beta: float = 0.25, progress=None, moment_nm=(0.0, 0.0, 0.0)) -> TimeHistory:
    """Response from rest to ``force_n sin(2 pi f t)`` on the platform, Newmark steps of dt
    (and ``moment_nm sin(2 pi f t)`` on a rigid platform's rotations).

    ``progress`` optionally wraps the step range (e.g. a tqdm progress bar).
    """
    k, m = system.matrices()
    integrator = Newmark(k, m, damping, dt_s, alpha, beta)
    steps = int(round(duration_s / dt_s))
    t = np.arange(steps + 1) * dt_s
    load = np.zeros(k.shape[0])
    load[:3] = force_n
    nd = system.platform_dofs
    load[3:nd] = np.asarray(moment_nm, dtype=float)[:nd - 3]
    u = np.zeros((steps + 1, nd))
    w = 2.0 * np.pi * excitation_hz
    for i in (progress or iter)(range(1, steps + 1)):
        u[i] = integrator.step(load * math.sin(w * t[i]))[:nd]
    return TimeHistory(t, u)


def tension_change(system: PlatformSystem, platform_u: np.ndarray) -> np.ndarray:
    """Quasi-static change of each cable's tension for platform displacements (N).

    dT_i = -(EA_i/L_i)_eff u_i . d_i with d_i = G_i q the attachment displacement (moving the
    attachment toward the anchor shortens the cable), the axial stiffness taken from the
    model's static end stiffness. Accurate while the cables' axial modes (hundreds of Hz)
    lie well above the excitation. ``platform_u`` (..., ndof) -> (..., n).
    """
    g = system.geometry.attachment_map()                        # (n, 3, ndof)
    unit = system.geometry.unit
    k_end = system.assembly.static_end_stiffness()               # (n, 3, 3)
    k_axial = np.einsum('ci,cij,cj->c', unit, k_end, unit)
    d = np.einsum('cia,...a->...ci', g, platform_u)
    return -k_axial * np.einsum('ci,...ci->...c', unit, d)
