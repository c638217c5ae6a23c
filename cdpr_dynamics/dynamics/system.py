"""Platform dynamics: assembly, frequency response (Eq. 38), damping (Eq. 41), Newmark.

DOFs are ordered platform first (3 translations, then 3 small rotations for a rigid platform),
then every cable's interior nodes. A cable end moves with its attachment, d_i = G_i q with
G_i = [I, -[r_i]x]. Besides the cables, the platform stiffness has the geometric term of the
cable forces f_i turning with the platform, K_rot = -sym(sum_i [f_i]x [r_i]x), whose
antisymmetric part is the (non-conservative) external moment and is dropped.

Damping is Rayleigh, C = dM M + dK K (Eq. 41). The modal damping ratio of a mode at w is
zeta = dM / (2 w) + dK w / 2; :func:`rayleigh_from_modal_ratio` fits dM, dK to a ratio.
Natural frequencies and classified modes: :mod:`cdpr_dynamics.dynamics.modes` (above this module).
"""
from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg.lapack import dgesv as _gesv, dpbtrf as _pbtrf, dpbtrs as _pbtrs

try:     # y += A x of a CSR matrix (scipy.sparse's kernel since scipy 0.7; private module)
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
except ImportError:          # pragma: no cover - a scipy without it: the public product
    def _csr_matvec(rows, cols, indptr, indices, data, x, out):
        out += sp.csr_matrix((data, indices, indptr), shape=(rows, cols)) @ x

from cdpr_dynamics.models.base import CableAssembly
from cdpr_dynamics.mechanics.robot import Geometry, Robot, skew


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
    platform_stiffness: np.ndarray    # (ndof, ndof) geometric rotation terms (load's included)
    load_stiffness: np.ndarray | float = 0.0   # (ndof, ndof) gravity's part of it, or 0

    @property
    def platform_dofs(self) -> int:
        return self.platform_mass.shape[0]

    @property
    def dofs(self) -> int:
        return self.platform_dofs + self.assembly.interior_dofs

    def dynamic_stiffness(self, omega_rad_s, damping: Damping = Damping()) -> np.ndarray:
        """Condensed complex dynamic stiffness Z(w) = K + i w C - w^2 M on the platform DOFs.

        Shape (len(omega), ndof, ndof); the cables' interior DOFs are eliminated exactly. With
        Rayleigh damping Z = (1 + i w dK) (K_p - lam M_p + sum_i G_i^T S_i(lam) G_i) at
        lam = (w^2 - i w dM)/(1 + i w dK); undamped, lam = w^2 is real and so is the arithmetic.
        """
        w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
        z = self._stiffness_components(w, damping)                       # (ndof^2, nw)
        nd = self.platform_dofs
        return np.ascontiguousarray(z.T, dtype=complex).reshape(w.size, nd, nd)

    def _stiffness_components(self, w: np.ndarray, damping: Damping) -> np.ndarray:
        """:meth:`dynamic_stiffness` with the frequency axis last: (ndof^2, nw), row a ndof + b
        the entry Z_ab, real undamped, complex damped (each entry's work contiguous)."""
        if damping.mass_factor == 0.0 and damping.stiffness_factor == 0.0:
            lam = w * w
            own = self.platform_stiffness.reshape(-1, 1) - self.platform_mass.reshape(-1, 1) * lam
            return own + self._cables_components(lam)    # complex where the model's S_c is
        scale = np.empty(w.size, dtype=complex)     # 1 + i w dK, built from its parts
        scale.real, scale.imag = 1.0, w * damping.stiffness_factor
        lam = np.empty(w.size, dtype=complex)       # (w^2 - i w dM) / (1 + i w dK)
        lam.real, lam.imag = w * w, w * -damping.mass_factor
        lam /= scale
        z = self.platform_stiffness.reshape(-1, 1) - self.platform_mass.reshape(-1, 1) * lam
        z += self._cables_components(lam)
        z *= scale
        return z

    def cables_at(self, lam: np.ndarray) -> np.ndarray:
        """sum_i G_i^T S_i(lam) G_i, (nl, ndof, ndof) or (ndof, ndof) where it is constant."""
        if self.assembly.constant_stiffness is not None:
            return self._constant_cables
        return self._cables_components(lam).T.reshape(-1, self.platform_dofs, self.platform_dofs)

    def _cables_components(self, lam: np.ndarray) -> np.ndarray:
        """:meth:`cables_at` with the frequency axis last: (ndof^2, nl), or (ndof^2, 1) where
        constant.

        Shortcuts of :meth:`cables_on_platform` (same numbers): a constant end stiffness
        (massless models) is condensed once; axial/transverse cables (``fem``, ``dsm``) map
        their 2n scalars per frequency with one small GEMM instead of forming 3x3 blocks.
        """
        assembly = self.assembly
        if assembly.constant_stiffness is not None:
            return self._constant_cables.reshape(-1, 1)
        if assembly.decoupled is None:
            ends = assembly.end_stiffness(lam)
            flat = ends.reshape(ends.shape[0], self._congruence.shape[0]).T   # (9n, nl)
            congruence = self._congruence.T
        else:
            cables = assembly.decoupled
            parts = cables.stiffness(lam)                                # (2 or 3, n, nl)
            flat = parts.reshape(parts.shape[0] * parts.shape[1], lam.size)
            congruence = self._decoupled_congruence.T
        if not np.iscomplexobj(flat):
            return congruence @ flat
        out = np.empty((congruence.shape[0], flat.shape[1]), dtype=complex)
        out.real = congruence @ flat.real    # two real GEMMs: far faster than a complex one
        out.imag = congruence @ flat.imag
        return out

    def cables_on_platform(self, ends: np.ndarray) -> np.ndarray:
        """sum_i G_i^T S_i G_i: stacked cable end stiffnesses (nl, n, 3, 3) on the platform
        DOFs, (nl, ndof, ndof); real in, real out."""
        flat = ends.reshape(ends.shape[0], self._congruence.shape[0])
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

    @functools.cached_property
    def _decoupled_congruence(self) -> np.ndarray:
        """(2n, ndof^2): rows G_i^T u_i u_i^T G_i (axial), then G_i^T (I - u_i u_i^T) G_i; with
        pulley normals m_i (3n, ndof^2): the transverse rows without m_i m_i^T, then
        G_i^T m_i m_i^T G_i."""
        cables = self.assembly.decoupled
        unit = cables.unit
        n = unit.shape[0]
        uu = (unit[:, :, None] * unit[:, None, :]).reshape(n, 9)
        per_cable = self._congruence.reshape(n, 9, -1)
        tensors = [uu, np.eye(3).ravel() - uu]
        if cables.normal is not None:
            mm = (cables.normal[:, :, None] * cables.normal[:, None, :]).reshape(n, 9)
            tensors = [uu, tensors[1] - mm, mm]
        return np.concatenate([np.einsum('ck,ckm->cm', t, per_cable) for t in tensors])

    @functools.cached_property
    def _constant_cables(self) -> np.ndarray:
        """(ndof, ndof) sum_i G_i^T S_i G_i of a constant (massless) end stiffness."""
        return self.cables_on_platform(self.assembly.constant_stiffness[None])[0]

    def static_stiffness(self) -> np.ndarray:
        """(ndof, ndof) static stiffness of the platform, all cable DOFs condensed (N/m, ...)."""
        return self._static_stiffness.copy()

    @functools.cached_property
    def _static_stiffness(self) -> np.ndarray:
        assembly = self.assembly
        if assembly.decoupled is None and assembly.constant_stiffness is None:
            # the cables' static end stiffness, shared with the other users of the pose's model
            return self.platform_stiffness + self.cables_on_platform(
                assembly.static_end_stiffness()[None])[0]
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
    dense = _platform_block(platform, diag, g)
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
        coupling = _end_coupling(off, g)                           # (ncab, 3, nd)
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


def _platform_block(platform: np.ndarray, diag: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(ndof, ndof) platform block of a global matrix: P + sum_c G_c^T D_c,end G_c (one GEMM
    over the stacked cables)."""
    nd = g.shape[2]
    return platform + g.reshape(-1, nd).T @ (diag[:, -1] @ g).reshape(-1, nd)


def _end_coupling(off: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(ncab, 3, ndof): each cable's last interior node to the platform, O_c,last G_c."""
    return off[:, -1] @ g


def platform_system(robot: Robot, geometry: Geometry, assembly: CableAssembly) -> PlatformSystem:
    """Combine the platform (mass, rotational geometric stiffness) with the cables.

    The rotational term sums over the cable forces at their attachments and, where the centre
    of mass is off the reference point, the weight m g at c = R c_P (gravity's load
    stiffness)."""
    nd = robot.platform_dofs
    stiffness = np.zeros((nd, nd))
    load = 0.0
    if nd == 6:
        k_rot = -np.einsum('cij,cjk->ik', skew(assembly.end_force_n), skew(geometry.lever_m))
        stiffness[3:, 3:] = 0.5 * (k_rot + k_rot.T)
        if robot.offset_mass:
            load = np.zeros((nd, nd))
            load[3:, 3:] = gravity_load_stiffness(robot, geometry.rotation)
            stiffness += load
    return PlatformSystem(geometry, assembly, robot.platform_mass_matrix(geometry.rotation),
                          stiffness, load)


def gravity_load_stiffness(robot: Robot, rotation: np.ndarray) -> np.ndarray:
    """(3, 3) load stiffness of gravity's moment on the rotations, -sym([m g]x [c]x) with
    c = R c_P the centre of mass off the reference point (the weight turning with it)."""
    k = -skew(robot.mass_kg * robot.gravity_m_s2) @ skew(rotation @ robot.center_of_mass_m)
    return 0.5 * (k + k.T)


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
    ``singular`` marks the frequency instead of raising. Singular means sigma_min(Z) <= 1e-12 s,
    s the larger of ||Z||_F and the stiffness and inertia scale max|K_static| + w^2 max|M_p|
    (Z itself can vanish entirely at a repeated resonance, so its own norm is no scale), with
    sigma_min estimated as 1/||Z^-1||_F = |det Z| / ||adj Z||_F (between sigma_min/sqrt(ndof)
    and sigma_min) from the adjugate (3 DOFs) or inverse (6 DOFs) that also solves.
    """
    f = np.atleast_1d(np.asarray(frequency_hz, dtype=float))
    w = 2.0 * np.pi * f
    z = system._stiffness_components(w, damping)            # (ndof^2, nf): Z_ab in row a ndof + b
    nd = system.platform_dofs
    load = np.concatenate([np.asarray(force_n, dtype=float),
                           np.asarray(moment_nm, dtype=float)])[:nd]
    scale = np.maximum(_column_norms(z), np.abs(system._static_stiffness).max()
                       + w * w * np.abs(system.platform_mass).max())
    with np.errstate(all='ignore'):   # singular frequencies: replaced below
        if nd == 3:
            cofactor = z[_COFACTOR[0]] * z[_COFACTOR[1]]                # C_ab, row 3 a + b
            cofactor -= z[_COFACTOR[2]] * z[_COFACTOR[3]]
            det = np.einsum('kn,kn->n', z[:3], cofactor[:3])
            response = (load @ cofactor.reshape(3, -1)).reshape(3, -1)  # sum_a F_a C_ab
            response /= det
            response = np.ascontiguousarray(response.T, dtype=complex)
            sigma = np.abs(det) / _column_norms(cofactor)
        else:
            z = np.ascontiguousarray(z.T, dtype=complex).reshape(f.size, nd, nd)
            try:
                inverse = np.linalg.inv(z)
            except np.linalg.LinAlgError:       # exactly singular somewhere: one at a time
                inverse = np.stack([_inverse_or_nan(a) for a in z])
            response = inverse @ load.astype(complex)
            sigma = 1.0 / _frobenius(inverse)
    singular = ~(sigma > 1e-12 * scale)
    response[singular] = np.inf
    return FrequencyResponse(f, response, singular)


def _frobenius(a: np.ndarray) -> np.ndarray:
    """||a_k||_F of stacked complex matrices (n, m, m): one dot product over the float view."""
    flat = np.ascontiguousarray(a).reshape(a.shape[0], a[0].size if a.size else 0).view(float)
    return np.sqrt(np.einsum('ni,ni->n', flat, flat))


def _column_norms(a: np.ndarray) -> np.ndarray:
    """sqrt(sum_k |a_kn|^2) of (k, n) real or complex components (C-contiguous): the
    Frobenius norms of matrices stored entry by entry along the first axis."""
    if not np.iscomplexobj(a):
        return np.sqrt(np.einsum('kn,kn->n', a, a))
    parts = a.view(float)
    squares = np.einsum('kn,kn->n', parts, parts)          # re^2 and im^2 side by side
    return np.sqrt(squares[0::2] + squares[1::2])


# the signed cofactors C_ij = a_(i+1)(j+1) a_(i+2)(j+2) - a_(i+1)(j+2) a_(i+2)(j+1) (indices
# mod 3) of a 3x3 matrix stored entry by entry (row 3 i + j): adj a = C^T, det a = sum_j a_0j C_0j
_COFACTOR = tuple(np.array([3 * ((i + di) % 3) + (j + dj) % 3 for i in range(3) for j in range(3)])
                  for di, dj in ((1, 1), (2, 2), (1, 2), (2, 1)))


def _inverse_or_nan(a: np.ndarray) -> np.ndarray:
    """a^-1, or nan where LAPACK finds a exactly singular (its sigma_min estimate is then nan)."""
    try:
        return np.linalg.inv(a)
    except np.linalg.LinAlgError:
        return np.full(a.shape, np.nan + 0j)


# --------------------------------------------------------------------------- platform modes

def platform_frequencies(system: PlatformSystem) -> np.ndarray:
    """Natural frequencies (Hz) of the platform mass on the statically condensed cables:
    eig(K_static, M_platform), ascending; the cables' own inertia left out."""
    values = scipy.linalg.eigh(system.static_stiffness(), system.platform_mass,
                               eigvals_only=True)
    return np.sqrt(np.clip(values, 0.0, None)) / (2.0 * np.pi)


# --------------------------------------------------------------------------- Newmark

class _StateRow:
    """Row ``row`` of an integrator's (3, n) state ``_state`` as an attribute: reading gives
    the row itself (a view), assigning copies into it."""

    def __init__(self, row: int, doc: str):
        self.row, self.__doc__ = row, doc

    def __get__(self, integrator, owner=None):
        return self if integrator is None else integrator._state[self.row]

    def __set__(self, integrator, value) -> None:
        integrator._state[self.row] = value


class Newmark:
    """Newmark's method (Eqs. 42-50) for M u'' + C u' + K u = F(t), factorised once.

    Sparse K, M use a sparse LU of the effective stiffness; dense arrays (small models) a dense
    LU.

    ``alpha`` is the velocity weight (often called gamma) and ``beta`` the displacement weight.
    Unconditionally stable for alpha >= 1/2 and beta >= alpha/2; otherwise stable only for
    w_max dt <= 1 / sqrt(alpha/2 - beta), which :meth:`__init__` checks (undamped bound) and
    refuses with :class:`DynamicsError` rather than integrate a diverging answer.

    The state of motion is one (3, n) array, rows u (m, rad), v (m/s, rad/s) and a
    (m/s^2, rad/s^2); :attr:`u`, :attr:`v` and :attr:`acc` are views of its rows (assigning
    to them copies into it), so a step allocates nothing for the state.
    """

    def __init__(self, stiffness, mass, damping: Damping, dt_s: float, alpha: float = 0.5,
                 beta: float = 0.25):
        self._setup(dt_s, alpha, beta)
        dense = not sp.issparse(stiffness)
        self.k = np.asarray(stiffness, dtype=float) if dense else sp.csc_matrix(stiffness)
        self.m = np.asarray(mass, dtype=float) if dense else sp.csc_matrix(mass)
        self.c = damping.mass_factor * self.m + damping.stiffness_factor * self.k
        self._check_stability(alpha, beta)
        effective = self.k + self.a[0] * self.m + self.a[1] * self.c         # Eq. 46
        if dense:   # small models: a dense LU beats a sparse one's call overhead
            factor = scipy.linalg.lu_factor(effective)
            self._solve = lambda rhs: scipy.linalg.lu_solve(factor, rhs, check_finite=False)
        else:
            self._solve = spla.splu(sp.csc_matrix(effective), permc_spec='NATURAL').solve
        self._state = np.zeros((3, self.k.shape[0]))

    def _setup(self, dt_s: float, alpha: float, beta: float) -> None:
        """Check the parameters; the coefficients a0..a7 of Eqs. 46-50."""
        if not (dt_s > 0 and alpha >= 0.5 and beta > 0):
            raise DynamicsError(f'Newmark needs dt > 0, alpha >= 0.5 and beta > 0 (got dt = '
                                f'{dt_s}, alpha = {alpha}, beta = {beta})')
        dt = dt_s
        self.a = (1 / (beta * dt * dt), alpha / (beta * dt), 1 / (beta * dt), 1 / (2 * beta) - 1,
                  alpha / beta - 1, dt / 2 * (alpha / beta - 2), dt * (1 - alpha), alpha * dt)
        self.dt_s = dt

    def _check_stability(self, alpha: float, beta: float) -> None:
        """Refuse (DynamicsError) a conditionally stable scheme whose dt is too long."""
        if beta < alpha / 2.0:
            w_max = math.sqrt(max(_largest_eigenvalue(self.k, self.m), 0.0))
            limit = 1.0 / math.sqrt(alpha / 2.0 - beta)
            if w_max * self.dt_s > limit:
                raise DynamicsError(
                    f'Newmark with beta = {beta} < alpha/2 is unstable for dt = {self.dt_s} s: '
                    f'the highest mode ({w_max / 2 / math.pi:.4g} Hz) needs dt <= '
                    f'{limit / w_max:.3g} s')

    u = _StateRow(0, 'Displacements (n,) m or rad: a view of the state (a step overwrites it).')
    v = _StateRow(1, 'Velocities (n,): a view of the state.')
    acc = _StateRow(2, 'Accelerations (n,): a view of the state.')

    def reset(self) -> None:
        """Back to rest (u = v = a = 0: Eq. 43 with no load at t = 0)."""
        self._state.fill(0.0)

    def step(self, force: np.ndarray) -> np.ndarray:
        """Advance one step to the load ``force`` at t + dt (Eqs. 47-50); return u (the state's
        own row: copy it to keep it past the next step)."""
        a0, a1, a2, a3, a4, a5, a6, a7 = self.a
        u, v, acc = self._state
        rhs = force + self.m @ (a0 * u + a2 * v + a3 * acc) + self.c @ (a1 * u + a4 * v + a5 * acc)
        u_new = self._solve(rhs)
        acc_new = a0 * (u_new - u) - a2 * v - a3 * acc
        v[:] = v + a6 * acc + a7 * acc_new
        u[:], acc[:] = u_new, acc_new
        return u


class ChainNewmark(Newmark):
    """:class:`Newmark` of a :class:`PlatformSystem` factorised through its chains: the same
    steps (Eqs. 42-50), without assembling or sparse-factorising the global matrices.

    The effective matrix A = K + a0 M + a1 C (Eq. 46; with C = dM M + dK K it is
    (1 + a1 dK) K + (a0 + a1 dM) M) has the platform DOFs p first and then the cables' interior
    nodes i, every cable a block-tridiagonal chain coupled to the platform only through its
    last interior node: an arrow

        A = [A_pp  A_ip^T; A_ip  A_ii],   A_ii = blockdiag(chains): a symmetric band of half
                                          width 5 (3x3 blocks, one node to the next),

    with A_pp = P + sum_c G_c^T D_c,end G_c (P: the platform's own mass or stiffness) and the
    rows of cable c's last interior node in A_ip equal to O_c,last G_c. The band is Cholesky-
    factorised (LAPACK dpbtrf), Z = A_ii^-1 A_ip and the Schur complement S = A_pp - A_ip^T Z
    are formed once, and each step solves A u = r by

        y = A_ii^-1 r_i,   u_p = S^-1 (r_p - A_ip^T y),   u_i = y - Z u_p,

    while its right side (Eq. 47) is F + [M K] [x; y] of the same bands, couplings and
    platform blocks: O(n) per step. Massless models (``spring``, ``catenary``) have no
    interior: u = S^-1 r with S = A_pp. ``k``, ``m`` and ``c`` (sparse, csc) are assembled
    only when asked for (the state carried across a model change, tests).

    Few calls per step, into buffers made here, each operand in the layout its BLAS/LAPACK
    call takes without a copy (the factor Fortran-ordered, vectors contiguous): one GEMM
    (x, y, w_a, w_v) = E (u, v, a) of the state; the right side as one product with
    [M K] (n, 2n) in CSR (:class:`_PairPattern`: the per-column loops of BLAS dsbmv cost 2-4x
    more on bands this narrow), dpbtrs in place, the Schur part as one product
    u_p = [S^-1, -S^-1 A_ip^T] [r_p; y] and u_i = y - Z u_p, and one GEMM for the new state,
    (u', v', a') = L (u', w_a, w_v) with a' = a0 u' + w_a, v' = w_v + a7 a' (Eqs. 48-49).

    Raises :class:`DynamicsError` for invalid parameters (as :class:`Newmark`) and
    ``np.linalg.LinAlgError`` where the band is not positive definite (then use
    :class:`Newmark`: :func:`newmark_for` does).
    """

    def __init__(self, system: PlatformSystem, damping: Damping, dt_s: float,
                 alpha: float = 0.5, beta: float = 0.25):
        blocks = system.assembly.blocks
        if blocks is None:
            raise DynamicsError(f'method {system.assembly.method} has no finite matrices; '
                                'use fem or fem_sag for modes and time histories')
        self._system, self._damping = system, damping
        self._setup(dt_s, alpha, beta)
        a0, a1 = self.a[:2]
        dm, dk = damping.mass_factor, damping.stiffness_factor
        self._state_map, self._update = _step_maps(self.a, dm, dk)
        scale_k, scale_m = 1.0 + a1 * dk, a0 + a1 * dm                   # A = sK K + sM M
        g = system.geometry.attachment_map()
        nd = system.platform_dofs
        k_pp = _platform_block(system.platform_stiffness, blocks.k_diag, g)
        m_pp = _platform_block(system.platform_mass, blocks.m_diag, g)
        self._pp = m_pp, k_pp                       # [M K]'s platform block: _p_pair
        a_pp = scale_k * k_pp + scale_m * m_pp
        interior = blocks.nodes - 1
        n = nd + 3 * interior * blocks.k_diag.shape[0]
        self._state = np.zeros((3, n))                                    # u, v, a
        self._work = np.zeros((4, n))          # x, y, w_a, w_v; after the solve u' over y
        self._xy = self._work[:2].reshape(-1)                             # [x; y] (2 n,)
        self._u_new, self._solved = self._work[1], self._work[1:]
        self._rhs = np.zeros(n)
        if interior == 0:
            self._s_inv = _inverse(a_pp)
            self._factor = None                                           # no interior
            self._pair_matrix = self._p_pair                              # [M K]: (nd, 2 nd)
        else:
            end_m, end_k = _end_coupling(blocks.m_off, g), _end_coupling(blocks.k_off, g)
            pattern = _pair_pattern(nd, blocks.k_diag.shape[0], interior)
            self._pattern = pattern
            self._values = _pair_values((m_pp, end_m, blocks.m_diag, blocks.m_off),
                                        (k_pp, end_k, blocks.k_diag, blocks.k_off))
            values, band = self._values, pattern.band
            factor, info = _pbtrf((scale_k * values.take(band[1])
                                   + scale_m * values.take(band[0])).T, lower=1,
                                  overwrite_ab=1)
            if info != 0:
                raise np.linalg.LinAlgError(f'chain band not positive definite (dpbtrf info '
                                            f'{info})')
            self._factor = factor
            coupling = _chain_coupling(scale_k * end_k + scale_m * end_m, interior)   # A_ip
            z, info = _pbtrs(factor, coupling, lower=1)
            self._z = z
            self._s_inv = _inverse(a_pp - coupling.T @ z)
            self._pair_matrix = pattern.matrix(values.take(pattern.take))  # [M K]: CSR
            self._schur = np.empty((nd, n))                      # [S^-1, -S^-1 A_ip^T]
            self._schur[:, :nd] = self._s_inv
            np.matmul(-self._s_inv, coupling.T, out=self._schur[:, nd:])
            self._r_i = self._rhs[nd:]
            self._u_p, self._u_i = self._u_new[:nd], self._u_new[nd:]
            self._zu = np.zeros(n - nd)
        self._check_stability(alpha, beta)

    @functools.cached_property
    def _p_pair(self) -> np.ndarray:
        """(nd, 2 nd): the platform block of [M K]."""
        return np.concatenate(self._pp, axis=1)

    @functools.cached_property
    def _m_band(self) -> np.ndarray:
        """(6, ni) lower band of the chains' M (:class:`_PairPattern`'s layout), on first use."""
        return self._values.take(self._pattern.band[0]).T

    @functools.cached_property
    def _k_band(self) -> np.ndarray:
        """(6, ni) lower band of the chains' K, on first use."""
        return self._values.take(self._pattern.band[1]).T

    @functools.cached_property
    def _matrices(self):
        return self._system.matrices()

    @property
    def k(self):
        """Global stiffness (csc), assembled on first use."""
        return self._matrices[0]

    @property
    def m(self):
        """Global mass (csc), assembled on first use."""
        return self._matrices[1]

    @functools.cached_property
    def c(self):
        """Rayleigh damping dM M + dK K (csc), assembled on first use."""
        return self._damping.mass_factor * self.m + self._damping.stiffness_factor * self.k

    def _solve(self) -> None:
        """u' = A^-1 r of the right side r in ``_rhs`` (overwritten) into the state's work row
        (class docstring): y = A_ii^-1 r_i (dpbtrs in place), u_p = [S^-1, -S^-1 A_ip^T] [r_p; y],
        u_i = y - Z u_p."""
        if self._factor is None:
            np.matmul(self._s_inv, self._rhs, out=self._u_new)
            return
        _pbtrs(self._factor, self._r_i, lower=1, overwrite_b=1)
        np.matmul(self._schur, self._rhs, out=self._u_p)
        np.matmul(self._z, self._u_p, out=self._zu)
        np.subtract(self._r_i, self._zu, out=self._u_i)

    def step(self, force: np.ndarray) -> np.ndarray:
        """Advance one step to the load ``force`` (n,) at t + dt (Eqs. 47-50); return u (the
        state's own row: copy it to keep it past the next step)."""
        np.matmul(self._state_map, self._state, out=self._work)           # x, y, w_a, w_v
        rhs = self._rhs                                                   # F + M x + K y
        if self._factor is None:
            np.matmul(self._pair_matrix, self._xy, out=rhs)
            np.add(rhs, force, out=rhs)
        else:
            np.copyto(rhs, force)
            _add_product(self._pair_matrix, self._xy, rhs)
        self._solve()
        np.matmul(self._update, self._solved, out=self._state)            # u', v', a'
        return self._state[0]


@functools.lru_cache(maxsize=16)
def _step_maps(a: tuple, dm: float, dk: float) -> tuple[np.ndarray, np.ndarray]:
    """(E (4, 3), L (3, 3)) of :class:`ChainNewmark`'s step for the coefficients ``a`` of
    Eqs. 46-50 and Rayleigh's dM, dK, read-only (kept: they depend on these numbers only).

    E maps the state (u, v, a) to what a step needs, one GEMM: the right side of Eq. 47,
    M (a0 u + a2 v + a3 a) + C (a1 u + a4 v + a5 a) = M x + K y, and the parts of Eqs. 48-49
    known before the solve, a' = a0 u' + w_a, v' = w_v + a7 a'; L gives (u', v', a') from
    (u', w_a, w_v)."""
    a0, a1, a2, a3, a4, a5, a6, a7 = a
    state_map = np.array([[a0 + dm * a1, a2 + dm * a4, a3 + dm * a5],     # x
                          [dk * a1, dk * a4, dk * a5],                    # y
                          [-a0, -a2, -a3],                                # w_a
                          [0.0, 1.0, a6]])                                # w_v
    update = np.array([[1.0, 0.0, 0.0], [a7 * a0, a7, 1.0], [a0, 1.0, 0.0]])
    state_map.flags.writeable = update.flags.writeable = False
    return state_map, update


def _add_product(matrix: sp.csr_matrix, x: np.ndarray, out: np.ndarray) -> None:
    """out += matrix @ x in place (CSR of float64, int32 indices; x, out contiguous float64):
    scipy's own kernel without the operator's checks, dispatch and result array, which cost
    2-3x the product on the live path (and more with cold caches, a wrench every 5 ms)."""
    _csr_matvec(matrix.shape[0], matrix.shape[1], matrix.indptr, matrix.indices, matrix.data,
                x, out)


def _pair_values(m_parts, k_parts) -> np.ndarray:
    """The values :class:`_PairPattern` gathers from: each matrix's (platform block (nd, nd),
    end coupling (ncab, 3, nd) = O_c,last G_c, diagonal blocks (ncab, nodes, 3, 3), off-
    diagonal blocks (ncab, nodes - 1, 3, 3)) flattened, M then K, and one 0.0 (the band's
    structural zeros): one concatenation of views."""
    return np.concatenate([part.ravel() for part in m_parts + k_parts] + [_ZERO])


_ZERO = np.zeros(1)


@dataclass(frozen=True, eq=False)
class _PairPattern:
    """What does not change between the models of one size (nd platform DOFs, ``cables``
    chains of ``interior`` nodes): the CSR structure of the step's [M K] (n, 2n) and where
    each of its entries and each band entry sits in :func:`_pair_values`.

    ``take``: per stored CSR entry its index in the values; ``band`` (2, ni, 6): the indices
    of M's and K's lower band, band[k, c] = A[c + k, c] (LAPACK storage, the C-ordered
    (ni, 6) gather transposed is Fortran (6, ni)) of the chains one after another; column
    c = (cable, node j, component b) holds the column b of the node's 8 x 3 slab
    [D_j; O_j^T; 0] from its row b down (O_j = block (j, j+1), zero past each chain's last
    interior node). ``template``: a CSR matrix of this structure whose index arrays are
    read-only (shared by every :meth:`matrix`)."""

    indptr: np.ndarray
    indices: np.ndarray
    take: np.ndarray
    band: np.ndarray
    shape: tuple
    template: sp.csr_matrix

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """[M K] in CSR with these ``data`` (one per stored entry, in :attr:`take`'s order):
        a shallow copy of the template (its structure shared, never written), no checks."""
        out = copy.copy(self.template)
        out.data = data
        return out


@functools.lru_cache(maxsize=16)
def _pair_pattern(nd: int, cables: int, interior: int) -> _PairPattern:
    """The :class:`_PairPattern` of ``cables`` chains of ``interior`` interior nodes: [M K]
    holds the platform block, the couplings of each cable's last interior node to the
    platform (both triangles) and the band entries (both triangles, the zeros between chains
    included), rows sorted, one gather per model."""
    ni = 3 * interior * cables
    n = nd + ni
    nodes = interior + 1
    coupling_at = nd * nd
    diag_at = coupling_at + cables * 3 * nd
    off_at = diag_at + cables * nodes * 9
    size = off_at + cables * interior * 9           # values of one matrix
    zero = 2 * size
    # band[k, col], col = (c, j, b): row r = b + k of the slab [D_j; O_j^T; 0]
    col, k = np.divmod(np.arange(6 * ni), 6)                 # (ni, 6) C order: [col, k]
    c, rest = np.divmod(col, 3 * interior)
    j, b = np.divmod(rest, 3)
    r = b + k
    band = np.where(r < 3, diag_at + ((c * nodes + j) * 3 + np.minimum(r, 2)) * 3 + b, zero)
    upper = (r >= 3) & (r < 6) & (j < interior - 1)
    band = np.where(upper, off_at + ((c * interior + j) * 3 + b) * 3 + (r - 3), band)
    # platform block: (i, j) = platform[i, j]
    i, jj = np.divmod(np.arange(nd * nd), nd)
    parts = [(i, jj, np.arange(nd * nd))]
    # coupling: cable c's last interior node, component b, to platform DOF j; and its mirror
    cc, bb, jj = np.unravel_index(np.arange(cables * 3 * nd), (cables, 3, nd))
    node = nd + 3 * interior * cc + 3 * (interior - 1) + bb
    at = coupling_at + np.arange(cables * 3 * nd)
    parts += [(node, jj, at), (jj, node, at)]
    # band entries inside the matrix (col + k < ni), and the mirror of k > 0
    keep = col + k < ni
    kk, cl, at = k[keep], col[keep], band[keep]
    mirror = kk > 0
    parts += [(nd + cl + kk, nd + cl, at),
              (nd + cl[mirror], nd + cl[mirror] + kk[mirror], at[mirror])]
    rows, cols, src = (np.concatenate(v) for v in zip(*parts))
    rows, cols, src = (np.concatenate((rows, rows)), np.concatenate((cols, cols + n)),
                       np.concatenate((src, np.where(src == zero, zero, src + size))))  # M, K
    order = np.lexsort((cols, rows))
    indptr = np.concatenate(([0], np.cumsum(np.bincount(rows, minlength=n)))).astype(np.int32)
    indices = cols[order].astype(np.int32)
    band = band.reshape(ni, 6)
    band = np.stack([band, np.where(band == zero, zero, band + size)])
    template = sp.csr_matrix((np.zeros(indices.size), indices, indptr), shape=(n, 2 * n))
    for array in (template.indptr, template.indices, src, band):
        array.flags.writeable = False
    return _PairPattern(template.indptr, template.indices, src[order], band, (n, 2 * n),
                        template)


def _chain_coupling(end: np.ndarray, interior: int) -> np.ndarray:
    """(ni, k) dense rows of the cables' interior nodes, zero but each cable's last interior
    node, which holds ``end`` (ncab, 3, k) (e.g. O_c,last G_c: A_ip)."""
    out = np.zeros((end.shape[0], interior, 3, end.shape[2]))
    out[:, -1] = end
    return out.reshape(-1, end.shape[2])


def _inverse(a: np.ndarray) -> np.ndarray:
    """a^-1 of a small square matrix by LAPACK gesv (A X = I), as ``np.linalg.inv`` computes
    it, without numpy's wrapper; ``np.linalg.LinAlgError`` where a is singular."""
    _, _, inverse, info = _gesv(a, np.eye(a.shape[0], order='F'), overwrite_b=1)
    if info != 0:
        raise np.linalg.LinAlgError('Singular matrix')
    return np.ascontiguousarray(inverse)     # C order, as numpy's: products sum as they did


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
