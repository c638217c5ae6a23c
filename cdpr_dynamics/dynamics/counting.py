"""Wittrick-Williams counting: how many natural frequencies lie below w, and where they are.

With D(lam) = K - lam M (lam = w^2) split into the platform DOFs and the cables' interior
(both cable ends clamped), Sylvester's law of inertia gives the number of natural frequencies
below w

    J(lam) = J0(lam) + s{Z(lam)},

J0 the eigenvalues of the clamped interiors below lam and s{Z} the negative eigenvalues of
the undamped condensed dynamic stiffness Z(lam) = D_pp - D_pi D_ii^-1 D_ip on the platform DOFs
(:meth:`PlatformSystem.dynamic_stiffness`). J0 is closed form for ``fem``'s uniform chains
(n elements, clamped: lam_j = (6k/m)(1 - cos(j pi/n))/(2 + cos(j pi/n)), j = 1..n-1, axial
k = EA/l and twice transverse k = T/l, m = mu l) and for ``dsm`` (j pi c / L); for ``fem_sag``
(or any :class:`ChainBlocks`) the negative pivots of the block LDL^T of each chain's
K_ii - lam M_ii, whose last step is also the chain's end stiffness. Every frequency is
bracketed to :data:`TOL_HZ`; a bracket narrower than that with J rising by m is a frequency of
multiplicity m (exact, no splitting). Where the clamped eigenvalues are known (``fem``,
``dsm``) the first sweep brackets them tightly and samples Z between them, and each
frequency is the zero of one of Z's eigenvalues, found by safeguarded Newton
(:meth:`Counter._roots`) and accepted only where J confirms it; elsewhere (and where that
fails) multisection on J, all brackets at once. The
interiors also give their clamped modes (the chains' end motion in them), which
:mod:`cdpr_dynamics.dynamics.modes` needs where a mode leaves the platform at rest.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.linalg

from cdpr_dynamics.dynamics.system import DynamicsError, PlatformSystem
from cdpr_dynamics.models.dsm import ContinuousCables, clamped_roots

TOL_HZ = 1e-9           # brackets of the counted frequencies (Hz)
SECTIONS = 5            # points per bracket and sweep of the multisection
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))   # symmetric 3x3 components
_UPPER_ROWS, _UPPER_COLS = (np.array(a) for a in zip(*_UPPER))
_DIAGONAL = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])           # of the 6 components
_FULL = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])                 # 3x3 row-major from the 6
_GUARDS = np.array([1e-2, 1e-3, 1e-5, 1e-9])   # brackets around a guess (of the width)
# Newton's starts: samples of Z between the clamped-chain eigenvalues, 9 crowding towards each
# end (1e-9 to 10^-1.5 of the bracket's width) and 7 across it (13 and 9 before: over ~300
# states of three robots 7 % more Newton steps, the same frequencies and no fallback)
_SAMPLES = np.concatenate([np.logspace(-9, -1.5, 9), np.linspace(0.05, 0.45, 7)])
_FRACTIONS = np.unique(np.concatenate([_SAMPLES, 1.0 - _SAMPLES]))   # of a bracket's width
NEWTON_STEPS = 40       # safeguarded Newton steps per frequency at most (then multisection)
STEP = 1e-20            # complex step (relative to lam) of the derivatives Z', S'


def counter(system: PlatformSystem) -> 'Counter | None':
    """The Wittrick-Williams counter of ``system``, or None (no cable DOFs: dense is exact)."""
    assembly = system.assembly
    if assembly.blocks is None:
        members = assembly.end_stiffness
        if not isinstance(members, ContinuousCables):
            raise DynamicsError(f'method {assembly.method} has neither finite matrices nor a '
                                'fixed-end mode count: no natural frequencies')
        if np.any(~(np.asarray(members.tension_n) > 0.0)):
            raise DynamicsError('dsm natural frequencies need every cable taut (T > 0): '
                                + '; '.join(assembly.warnings))
        return Counter(system, _ContinuousInterior(members))
    if assembly.blocks.nodes < 2:
        return None
    if assembly.method == 'fem' and assembly.decoupled.normal is None:   # uniform chains
        return Counter(system, _UniformInterior(system))
    if assembly.plane_basis is not None:
        return Counter(system, _PlanarChainInterior(assembly.blocks, assembly.plane_basis))
    return Counter(system, _ChainInterior(assembly.blocks))


class _UniformInterior:
    """J0 of ``fem``'s uniform straight chains and their clamped eigenvalues, closed form
    (module doc); the cables' end stiffness is the model's own (closed form too)."""

    def __init__(self, system: PlatformSystem):
        blocks = system.assembly.blocks
        unit = system.geometry.unit
        element = -blocks.k_off[:, 0]                                     # (ncab, 3, 3)
        k_axial = np.einsum('ci,cij,cj->c', unit, element, unit)
        k_transverse = 0.5 * (np.trace(element, axis1=1, axis2=2) - k_axial)
        self.n = blocks.nodes                                             # elements
        self.rate = np.stack([k_axial, k_transverse]) / blocks.m_off[:, 0, 0, 0]   # 6k/m
        self.weight = np.array([1, 2])[:, None]                           # axial, transverse
        self.m_element = 6.0 * blocks.m_off[:, 0, 0, 0]
        self.unit = unit
        self.blocks = blocks
        self._directions = None
        self.end_stiffness = system.assembly.end_stiffness

    def counts(self, lam) -> np.ndarray:
        """(nl, ncab) clamped-chain eigenvalues below each lam: lam_j < lam iff
        cos(j pi/n) > (1 - 2r)/(1 + r), r = lam / rate, rate = 6k/m."""
        r = np.asarray(lam, dtype=float)[:, None, None] / self.rate[None]   # (nl, 2, ncab)
        x = np.clip((1.0 - 2.0 * r) / (1.0 + r), -1.0, 1.0)
        below = np.clip(np.ceil(self.n * np.arccos(x) / math.pi) - 1.0, 0.0, self.n - 1)
        return (below * self.weight[None]).sum(axis=1).astype(int)

    def poles(self, lam_max: float) -> np.ndarray:
        """Sorted clamped-chain eigenvalues lam_j = rate (1 - cos)/(2 + cos) up to lam_max."""
        c = np.cos(np.arange(1, self.n) * math.pi / self.n)
        values = (self.rate.ravel()[:, None] * (1.0 - c) / (2.0 + c)).ravel()
        return np.unique(values[values <= lam_max])

    def sweep(self, lam, count: bool = True):
        """(J0 per cable, None: Z from the model) or, ``count=False``, (None, S_c(lam))."""
        return (self.counts(lam), None) if count else (None, self.end_stiffness(lam))

    def clamped_ends(self, lam: np.ndarray, jumps: np.ndarray):
        """The end reactions of the clamped modes at the eigenvalues ``lam`` (g,), ``jumps[k, c]``
        of chain c at lam_k (:func:`_stacked_ends`), closed form and all at once: the last
        interior node moves v sin(j pi (n-1)/n) / sqrt(m n (2 + cos(j pi/n)) / 6) along the
        mode's direction v (axial u first, then the transverse plane), j from lam_j = lam; the
        last element's block O = -(k_a uu^T + k_t (I - uu^T)) - lam (m/6) I gives the reaction
        O^T psi = (-k - lam m/6) psi and the mass coupling (m/6) psi."""
        n = self.n
        lam = np.asarray(lam, dtype=float)[:, None, None]                  # (g, 1, 1)
        c = (self.rate - 2.0 * lam) / (self.rate + lam)                     # (g, 2, ncab)
        j = n * np.arccos(np.clip(c, -1.0, 1.0)) / math.pi
        whole = np.round(j)
        hit = (np.abs(j - whole) < 1e-6) & (whole >= 1) & (whole <= n - 1)
        mass = self.m_element * n * (2.0 + np.cos(whole * math.pi / n)) / 6.0
        amplitude = np.where(hit, np.sin(whole * math.pi * (n - 1) / n) / np.sqrt(mass), 0.0)
        sixth = self.m_element / 6.0
        reaction = -(self.rate * sixth) - lam * sixth                       # (g, 2, ncab)
        size = np.sqrt(reaction[:, 0] ** 2 + 2.0 * reaction[:, 1] ** 2)      # ||O||_F (g, ncab)
        if self._directions is None:
            self._directions = _directions(self.unit)
        return _closed_form_ends(self._directions, 1.0, jumps, hit, reaction * amplitude,
                                 sixth * amplitude, size[:, None] * np.abs(amplitude))


class _ChainInterior:
    """General chains (ChainBlocks, e.g. ``fem_sag``): the block LDL^T of K_ii - lam M_ii from
    the anchor. Each interior node is first turned into the frame of its own stiffness block
    (stiff axial direction first, an orthogonal congruence: inertia unchanged), so the scalar
    LDL^T of each 3x3 pivot needs no pivoting and keeps the soft directions accurate; the
    negative pivots count J0 and the last step condenses the chain onto its end (world frame):
    S = D_ee - O^T P^-1 O."""

    def __init__(self, blocks):
        self.blocks = blocks
        self.interior = blocks.nodes - 1
        kd, ko, md, mo = blocks
        _, frames = np.linalg.eigh(kd[:, :self.interior])                # ascending
        frames = np.concatenate([frames[..., ::-1],                       # axial first
                                 np.broadcast_to(np.eye(3), (kd.shape[0], 1, 3, 3))], axis=1)
        ft = np.swapaxes(frames, -1, -2)
        rows, cols = np.array(_UPPER).T
        local_kd = (ft @ kd @ frames)[..., rows, cols]                    # (ncab, nodes, 6)
        local_ko = (ft[:, :-1] @ ko @ frames[:, 1:]).reshape(kd.shape[0], -1, 9)
        local_mo = (ft[:, :-1] @ mo @ frames[:, 1:]).reshape(kd.shape[0], -1, 9)

        # per node, the components stacked ahead of (frequency, cable): (nodes, 6 or 9, 1, ncab)
        def stacked(a):
            return np.ascontiguousarray(np.moveaxis(a, 0, -1))[:, :, None, :]

        self._kd = stacked(local_kd)
        self._md = stacked(md[:, :, 0, 0][..., None] * _DIAGONAL)         # isotropic: m I
        self._ko = stacked(local_ko)
        self._mo = stacked(local_mo)

    def poles(self, lam_max: float):
        return None

    def counts(self, lam) -> np.ndarray:
        return self.sweep(lam)[0]

    def sweep(self, lam, count: bool = True):
        """(J0 per cable (nl, ncab) or None, end dynamic stiffness (nl, ncab, 3, 3)), and in
        ``last_det`` the determinant of each chain's last interior pivot; complex ``lam``
        (a complex step) with ``count=False``. Pivots as their 6 components stacked,
        (6, nl, ncab); the coupling blocks as 9 (row-major)."""
        lam = np.asarray(lam)[:, None]                                     # (nl, 1)
        p = self._kd[0] - lam * self._md[0]
        pivots = np.empty((self.interior, 3) + p.shape[1:], dtype=p.dtype) if count else None
        for k in range(self.interior):
            p00, p01, p02, p11, p12, p22 = p
            l10, l20 = p01 / p00, p02 / p00
            d1 = p11 - l10 * p01
            l21 = (p12 - l20 * p01) / d1
            d2 = p22 - l20 * p02 - l21 * l21 * d1
            if count:
                pivots[k, 0], pivots[k, 1], pivots[k, 2] = p00, d1, d2
            b = self._ko[k] - lam * self._mo[k]                            # (9, nl, ncab)
            y0 = b[0:3]
            y1 = b[3:6] - l10 * y0
            y2 = b[6:9] - l20 * y0 - l21 * y1
            z0, z1, z2 = y0 / p00, y1 / d1, y2 / d2
            rows, cols = _UPPER_ROWS, _UPPER_COLS
            p = self._kd[k + 1] - lam * self._md[k + 1]
            p -= y0[rows] * z0[cols] + y1[rows] * z1[cols] + y2[rows] * z2[cols]
        neg = None
        if count:
            neg = (pivots.real < 0).sum(axis=(0, 1))
            self.last_det = pivots[-1, 0] * pivots[-1, 1] * pivots[-1, 2]   # 0 at the
            # chain's clamped eigenvalues
        out = np.moveaxis(p[_FULL], 0, -1)                                 # (nl, ncab, 9)
        return neg, out.reshape(out.shape[:-1] + (3, 3))

    def clamped_ends(self, lam: np.ndarray, jumps: np.ndarray):
        return _stacked_ends(self, lam, jumps)

    def clamped_end(self, lam, cable: int, count: int):
        """(end reactions (3, count), mass coupling (3, count), scale of the reactions' terms)
        of ``count`` M-orthonormal clamped modes of chain ``cable`` at its eigenvalue ``lam``:
        O^T psi_last, M_e,last psi_last and ||O|| ||psi_last||."""
        return _chain_end(self.blocks, lam, cable, self.clamped_modes(lam, cable, count)[1])

    def clamped_modes(self, lam: float, cable: int, count: int):
        """``count`` M-orthonormal clamped modes of chain ``cable`` at its eigenvalue ``lam``
        by two steps of inverse iteration (banded LU): (interior (3(n-1), count), the last
        interior node's motion (3, count))."""
        kd, ko, md, mo = (a[cable] for a in self.blocks)
        ni = self.interior
        size = 3 * ni
        band = np.zeros((11, size))
        i3 = np.arange(3)
        base = 3 * np.arange(ni)[:, None, None]
        rows, cols = base + i3[:, None], base + i3[None, :]                # (ni, 3, 3)
        band[5 + rows - cols, cols] = kd[:ni] - lam * md[:ni]
        if ni > 1:
            off = ko[:ni - 1] - lam * mo[:ni - 1]
            r, c = rows[:-1], cols[:-1] + 3
            band[5 + r - c, c] = off
            band[5 + c - r, r] = off
        y = np.random.default_rng(cable).standard_normal((size, count))
        for _ in range(2):
            try:
                y = scipy.linalg.solve_banded((5, 5), band, y, check_finite=False)
            except np.linalg.LinAlgError:       # lam on the eigenvalue to the last bit
                band[5] *= 1.0 + 1e-13
                y = scipy.linalg.solve_banded((5, 5), band, y, check_finite=False)
            y /= np.linalg.norm(y, axis=0)
        gram = y.T @ _chain_mass(md, mo, ni, y)
        y = y @ np.linalg.inv(np.linalg.cholesky(gram)).T          # M-orthonormal
        return y, y[-3:]


class _PlanarChainInterior(_ChainInterior):
    """:class:`_ChainInterior` of chains that each lie in a plane (``fem_sag`` without anchor
    ends): in the basis (u1, u2, n) of a chain's plane, K_ii - lam M_ii splits exactly into
    an in-plane chain of 2x2 blocks and a scalar chain along n, so each step is a 2x2 LDL^T
    (each interior node in the frame of its in-plane stiffness block, stiff direction first)
    and a scalar division: the same pivots' signs, the same end stiffness, less work."""

    def __init__(self, blocks, basis):
        self.blocks = blocks
        self.interior = ni = blocks.nodes - 1
        kd, ko, md, mo = blocks
        plane, normal = basis[:, None, :2], basis[:, None, 2]        # (ncab, 1, 2, 3), (.., 3)
        plane_t = np.swapaxes(plane, -1, -2)

        def split(a):                     # in-plane 2x2 blocks and the normal component
            return plane @ a @ plane_t, np.einsum('cni,cnij,cnj->cn', normal, a, normal)

        (kd2, kdn), (ko2, kon), (mo2, mon) = split(kd), split(ko), split(mo)
        _, frames = np.linalg.eigh(kd2[:, :ni])                          # ascending
        frames = np.concatenate([frames[..., ::-1],                       # stiff first
                                 np.broadcast_to(np.eye(2), (kd.shape[0], 1, 2, 2))], axis=1)
        ft = np.swapaxes(frames, -1, -2)
        local_kd = (ft @ kd2 @ frames)[..., [0, 0, 1], [0, 1, 1]]          # (ncab, nodes, 3)
        local_ko = (ft[:, :-1] @ ko2 @ frames[:, 1:]).reshape(kd.shape[0], -1, 4)
        local_mo = (ft[:, :-1] @ mo2 @ frames[:, 1:]).reshape(kd.shape[0], -1, 4)
        mass = md[:, :, 0, 0]                                              # isotropic: m I

        # per node, components stacked ahead of (frequency, cable): the pivot's (00, 01, 11,
        # normal) (nodes, 4, 1, ncab), the coupling's (00, 01, 10, 11, normal)
        def stacked(plane_part, normal_part):
            both = np.concatenate([plane_part, normal_part[..., None]], axis=-1)
            return np.ascontiguousarray(np.moveaxis(both, 0, -1))[:, :, None, :]

        self._kd = stacked(local_kd, kdn)
        self._md = stacked(mass[..., None] * np.array([1.0, 0.0, 1.0]), mass)
        self._ko = stacked(local_ko, kon)
        self._mo = stacked(local_mo, mon)
        u1, u2, n = basis[:, 0], basis[:, 1], basis[:, 2]
        self._shapes = np.stack([u1[:, :, None] * u1[:, None, :],
                                 u1[:, :, None] * u2[:, None, :] + u2[:, :, None] * u1[:, None, :],
                                 u2[:, :, None] * u2[:, None, :], n[:, :, None] * n[:, None, :]],
                                axis=1).reshape(-1, 4, 9)                 # (ncab, 4, 9)

    def sweep(self, lam, count: bool = True):
        """:meth:`_ChainInterior.sweep` on the split chains: pivots (p00, p01, p11, q), the
        in-plane coupling blocks row-major and the normal one, (5, nl, ncab)."""
        lam = np.asarray(lam)[:, None]                                     # (nl, 1)
        p = self._kd[0] - lam * self._md[0]
        pivots = np.empty((self.interior, 3) + p.shape[1:], dtype=p.dtype) if count else None
        rows, cols = [0, 0, 1], [0, 1, 1]
        for k in range(self.interior):
            p00, p01, p11, q = p
            l10 = p01 / p00
            d1 = p11 - l10 * p01
            if count:
                pivots[k, 0], pivots[k, 1], pivots[k, 2] = p00, d1, q
            b = self._ko[k] - lam * self._mo[k]                            # (5, nl, ncab)
            y0 = b[0:2]
            y1 = b[2:4] - l10 * y0
            z0, z1 = y0 / p00, y1 / d1
            bn = b[4]
            p = self._kd[k + 1] - lam * self._md[k + 1]
            p[:3] -= y0[rows] * z0[cols] + y1[rows] * z1[cols]
            p[3] -= bn * bn / q
        neg = None
        if count:
            neg = (pivots.real < 0).sum(axis=(0, 1))
            self.last_det = pivots[-1, 0] * pivots[-1, 1] * pivots[-1, 2]
        out = np.moveaxis(p, 0, -1).transpose(1, 0, 2) @ self._shapes        # (ncab, nl, 9)
        out = out.transpose(1, 0, 2)
        return neg, out.reshape(out.shape[:-1] + (3, 3))


class _ContinuousInterior:
    """J0, clamped eigenvalues and end stiffness of ``dsm``'s continuous cables."""

    def __init__(self, members: ContinuousCables):
        self.members = members
        self._directions = None

    def counts(self, lam) -> np.ndarray:
        return self.members.fixed_end_mode_count(np.sqrt(np.asarray(lam, dtype=float)),
                                                 per_cable=True)

    def poles(self, lam_max: float) -> np.ndarray:
        """Sorted clamped eigenvalues up to lam_max: (z_j w_1 / pi)^2 per direction, w_1 = pi c/L
        and z_j = j pi, or the roots of :func:`~cdpr_dynamics.models.dsm.clamped_roots` on
        an anchor spring."""
        fundamental, beta, _ = self.members.clamped_kinds()
        found = []
        for w1, b in zip(fundamental, beta):
            j = np.arange(1, int(math.sqrt(lam_max) / w1.min()) + 2)[:, None]
            found.append(((clamped_roots(j, b) / math.pi * w1) ** 2).ravel())
        values = np.concatenate(found)
        return np.unique(values[values <= lam_max])

    def sweep(self, lam, count: bool = True):
        """(J0 per cable, None: Z from the model) or, ``count=False``, (None, S_c(lam))."""
        return (self.counts(lam), None) if count else (None, self.members(lam))

    def clamped_ends(self, lam: np.ndarray, jumps: np.ndarray):
        """:meth:`_UniformInterior.clamped_ends` of continuous cables, closed form: a clamped
        mode sin(z_j (L - x)/L) (x from the anchor end, z_j = j pi on a fixed anchor, else
        :func:`~cdpr_dynamics.models.dsm.clamped_roots`), of modal mass
        mu L (1 - sin(2 z_j)/(2 z_j))/2 (the anchor springs are massless), pushes the end with
        k z_j / L per unit amplitude along its direction (k = EA axially, T transversely;
        up to sign), with no end-node mass; the scale is the largest force component."""
        members = self.members
        length = members.length_m
        fundamental, beta, k = members.clamped_kinds()
        x = np.sqrt(np.asarray(lam, dtype=float))[:, None, None] / fundamental   # (g, 3, ncab)
        z = clamped_roots(np.maximum(np.ceil(x - 1e-6), 1.0), beta)
        hit = np.abs(x - z / math.pi) < 1e-6
        modal_mass = 0.5 * members.mass_per_length_kg_m * length * (1.0 - np.sin(2 * z) / (2 * z))
        force = np.where(hit, k * z / length / np.sqrt(modal_mass), 0.0)
        if self._directions is None:
            self._directions = _directions(members.unit, members.normal)
        return _closed_form_ends(self._directions, np.abs(self._directions).max(axis=2), jumps,
                                 hit, force, np.zeros_like(force), np.abs(force))


def _groups(lo, up) -> np.ndarray:
    """(4 + ncab, b) the brackets [lo, up] as groups: centre, J's rise (the multiplicity), lo,
    up, then J0's rise per chain (the bracket tuples: omega, J, J0 per chain, ...)."""
    return np.concatenate([np.stack([0.5 * (lo[0] + up[0]), up[1] - lo[1], lo[0], up[0]]),
                           (up[2] - lo[2]).T])


def _inverse_quadratic(f0, f1, f2, x0, x1, x2):
    """The zero of the quadratic x(f) through (f0, x0), (f1, x1), (f2, x2) (inverse
    quadratic interpolation, as in Brent's method); nan or inf where two f coincide."""
    return (x0 * f1 * f2 / ((f0 - f1) * (f0 - f2)) + x1 * f0 * f2 / ((f1 - f0) * (f1 - f2))
            + x2 * f0 * f1 / ((f2 - f0) * (f2 - f1)))


def _stacked_ends(interior, lam: np.ndarray, jumps: np.ndarray):
    """(reactions (r, 3), mass couplings (r, 3), owning cable (r,), eigenvalue (r,), scale
    (g,)) of the clamped modes at the eigenvalues ``lam`` (g,) of every chain c with
    ``jumps[k, c]`` > 0 at lam_k (that many each; eigenvalues, then cables ascending): each
    chain's ``clamped_end`` stacked."""
    forces, masses, owner, group = [], [], [], []
    scale = np.zeros(len(lam))
    for k, c in zip(*np.nonzero(jumps)):
        force, mass, size = interior.clamped_end(float(lam[k]), int(c), int(jumps[k, c]))
        forces.append(force.T)
        masses.append(mass.T)
        owner += [c] * force.shape[1]
        group += [k] * force.shape[1]
        scale[k] = max(scale[k], size)
    if not forces:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int), scale
    return np.concatenate(forces), np.concatenate(masses), np.array(owner, dtype=int), \
        np.array(group, dtype=int), scale


def _chain_end(blocks, lam, cable: int, last):
    """(O^T last, M_e,last last, ||O|| ||last||) for the last interior node's motion ``last``
    (3, k) of chain ``cable``, O its last element's dynamic-stiffness block at ``lam``."""
    _, ko, _, mo = blocks
    off = ko[cable, -1] - lam * mo[cable, -1]
    return off.T @ last, mo[cable, -1].T @ last, \
        float(np.linalg.norm(off) * np.linalg.norm(last, axis=0).max())


def _chain_mass(md, mo, interior, y) -> np.ndarray:
    """M_ii y for one chain's block-tridiagonal mass over its interior nodes."""
    y3 = y.reshape(interior, 3, -1)
    out = np.einsum('kij,kjr->kir', md[:interior], y3)
    if interior > 1:
        out[:-1] += np.einsum('kij,kjr->kir', mo[:interior - 1], y3[1:])
        out[1:] += np.einsum('kji,kjr->kir', mo[:interior - 1], y3[:-1])
    return out.reshape(y.shape)


class Counter:
    """J(lam) = J0(lam) + s{Z(lam)} of one system and the brackets of its frequencies."""

    def __init__(self, system: PlatformSystem, interior):
        self.system = system
        self.interior = interior
        self.nd = system.platform_dofs
        blocks = system.assembly.blocks
        self.blocks = blocks

    # ---------------------------------------------------------------- Z and the count
    def z(self, lam, ends=None) -> np.ndarray:
        """Real undamped Z(lam) (nl, nd, nd) from the cables' S_c(lam) (None: the system's
        own :meth:`PlatformSystem.dynamic_stiffness`), symmetrised."""
        s = self.system
        if ends is None:
            z = s.platform_stiffness[None] - lam[:, None, None] * s.platform_mass[None] \
                + s.cables_at(lam).real
        else:
            z = s.platform_stiffness[None] - lam[:, None, None] * s.platform_mass[None] \
                + s.cables_on_platform(ends.real)
        return 0.5 * (z + np.swapaxes(z, -1, -2))

    def count(self, lam):
        """(J (nl,), J0 per cable (nl, ncab), eigenvalues of Z ascending (nl, nd), each chain's
        last interior pivot determinant (nl, ncab) where known, else zeros)."""
        lam = np.asarray(lam, dtype=float)
        j0, ends = self.interior.sweep(lam)
        z = self.z(lam, ends)
        bad = ~np.all(np.isfinite(z), axis=(1, 2))        # a sample exactly on a pole
        if np.any(bad):
            lam = np.where(bad, lam * (1.0 + 1e-13) + 1e-300, lam)
            j0, ends = self.interior.sweep(lam)
            z = self.z(lam, ends)
        scale = np.abs(z).max(axis=(1, 2))
        scale = np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
        mu = np.linalg.eigvalsh(z / scale[:, None, None]) * scale[:, None]
        pivot = getattr(self.interior, 'last_det', None)
        pivot = np.zeros(j0.shape) if pivot is None else pivot
        return j0.sum(axis=1) + (mu < 0.0).sum(axis=1), j0, mu, pivot

    # ---------------------------------------------------------------- the frequencies
    def frequencies(self, f_max_hz, count, tol_hz):
        """(omega (g,), multiplicity (g,), bracket lo (g,), hi (g,), modes to report, J0's rise
        across each bracket per chain (g, ncab): the clamped-chain eigenvalues in it): every
        distinct frequency below ``f_max_hz`` and the lowest ``count`` (the last group can hold
        more than the report takes).

        The first sweep: 0, each known clamped-chain eigenvalue +- tol/4, the top and, between
        them, samples for :meth:`_roots` (Newton on Z's eigenvalues, then one sweep of J to
        confirm). Otherwise, or where that does not confirm, multisection of J on all
        brackets at once: each sweep cuts a bracket at
        :data:`SECTIONS` equal steps and around a guess (:meth:`_guess`) at
        :data:`_GUARDS` of its width: a good guess ends the bracket in a sweep or two, a bad
        one costs nothing. Brackets narrower than ``tol_hz`` are the frequencies, J's rise
        across them their multiplicity.
        """
        if not tol_hz > 0.0:
            raise ValueError('tol_hz must be positive')
        two_pi = 2.0 * math.pi
        total = self.system.dofs if self.blocks is not None else None
        want = int(count or 0) if total is None else min(int(count or 0), total)
        hi = two_pi * float(f_max_hz) if f_max_hz is not None and f_max_hz > 0 else two_pi
        while True:     # 0, tight around every known pole (clamped chains), the top
            poles = self.interior.poles(hi * hi)
            poles_w = None if poles is None else np.sqrt(poles)
            tol = max(two_pi * tol_hz, 8.0 * np.finfo(float).eps * hi)
            cut = np.zeros(0) if poles_w is None else \
                np.stack([poles_w - tol / 4, poles_w + tol / 4], axis=1).ravel()
            points = np.concatenate([[0.0], cut[(cut > 0.0) & (cut < hi)], [hi]])
            wide = np.zeros(0, dtype=int) if poles_w is None else \
                np.flatnonzero(np.diff(points) > tol)      # Newton's samples, same sweep
            samples = points[wide, None] + np.diff(points)[wide, None] * _FRACTIONS
            both = np.concatenate([points, samples.ravel()])
            at = self.count(both * both)
            sampled = at[2][points.size:].reshape(samples.shape + (self.nd,))
            at = (points,) + tuple(a[:points.size] for a in at)
            if at[1][-1] >= want:
                break
            hi *= 2.0
            if hi > two_pi * 1e12:
                raise DynamicsError('mode count does not grow: no natural frequencies found')
        j_lo = int(at[1][0])
        # a bracket's ends: omega, then J, J0 per cable, Z's eigenvalues, pivot determinants
        at = (at[0], np.maximum.accumulate(at[1])) + at[2:]
        keep = (at[1][1:] > at[1][:-1]) & (at[0][1:] > at[0][:-1])
        lo = tuple(e[:-1][keep] for e in at)
        up = tuple(e[1:][keep] for e in at)
        found = []
        if poles_w is not None:       # closed-form interiors: Newton on Z's eigenvalues
            done = up[0] - lo[0] <= tol
            todo = ~done
            interval = np.flatnonzero(keep)[todo]
            rows = np.minimum(np.searchsorted(wide, interval), max(wide.size - 1, 0))
            roots = None if not np.array_equal(wide[rows], interval) else self._roots(
                tuple(a[todo] for a in lo), tuple(a[todo] for a in up), poles_w, tol,
                (samples[rows], sampled[rows]))
            if roots is not None:
                found = [_groups(lo, up)[:, done], roots]
                lo = up = (np.zeros(0),)
        t = np.arange(1, SECTIONS + 1) / (SECTIONS + 1)
        while lo[0].size:
            done = up[0] - lo[0] <= tol
            if np.any(done):
                found.append(_groups(lo, up)[:, done])
                todo = ~done
                lo, up = (tuple(a[todo] for a in x) for x in (lo, up))
                if not lo[0].size:
                    break
            width = up[0] - lo[0]
            guess = self._guess(lo, up, poles_w)
            step = np.maximum(tol / 4, width[:, None] * _GUARDS[None])
            points = np.concatenate([lo[0][:, None] + width[:, None] * t[None],
                                     guess[:, None] - step, guess[:, None] + step], axis=1)
            points = np.where(np.isfinite(points) & (points > lo[0][:, None])
                              & (points < up[0][:, None]), points,
                              0.5 * (lo[0] + up[0])[:, None])
            points.sort(axis=1)
            shape = points.shape
            at = self.count((points * points).ravel())
            at = (points,) + tuple(a.reshape(shape + a.shape[1:]) for a in at)
            j = np.clip(np.maximum.accumulate(at[1], axis=1), lo[1][:, None], up[1][:, None])
            at = (at[0], j) + at[2:]
            edges = [np.concatenate([a[:, None], b, c[:, None]], axis=1)
                     for a, b, c in zip(lo, at, up)]
            keep = (edges[1][:, 1:] > edges[1][:, :-1]) & (edges[0][:, 1:] > edges[0][:, :-1])
            lo = tuple(e[:, :-1][keep] for e in edges)
            up = tuple(e[:, 1:][keep] for e in edges)
        n_cables = self.system.geometry.n_cables
        if j_lo:
            found.insert(0, np.concatenate([[[0.0], [j_lo], [0.0], [0.0]],
                                            np.zeros((n_cables, 1))]))
        if not found:
            return np.zeros(0), np.zeros(0, dtype=int), np.zeros(0), np.zeros(0), 0, \
                np.zeros((0, n_cables), dtype=int)
        groups = np.concatenate(found, axis=1)
        groups = groups[:, np.argsort(groups[0], kind='stable')]
        omega, mult = groups[0], groups[1].astype(int)
        limit = np.inf if f_max_hz is None else two_pi * float(f_max_hz)
        before = np.cumsum(mult) - mult          # modes below each group
        keep = (before < want) | (omega <= limit)
        mult = mult[keep]
        take = int(mult.sum()) if f_max_hz is not None else min(int(mult.sum()), want)
        return omega[keep], mult, groups[2][keep], groups[3][keep], take, \
            groups[4:, keep].T.astype(int)

    def _roots(self, lo, up, poles_w, tol, sampled):
        """(4 + ncab, g) groups [omega, multiplicity, lo, hi, J0's rise per chain]
        (:func:`_groups`) of the frequencies inside pole-free
        brackets (J0 constant across each, closed-form interiors), or None (then multisection).

        Inside such a bracket Z(lam) is analytic with Z' = -(mass) negative definite, so its
        sorted eigenvalues mu_k decrease strictly and the bracket's r frequencies are the zeros
        of mu_k, k = s..s+r-1 (s: Z's negative eigenvalues at the lower end). Each is found by
        safeguarded Newton (:data:`NEWTON_STEPS` at most, bisection where a step leaves the
        bracket) on g = mu_k (lam - p_a)(p_b - lam), p_a, p_b the clamped-chain eigenvalues at
        the bracket's ends (factor 1 at 0 and at the top), which takes out mu's poles;
        mu_k' = v^T Z' v (v its eigenvector, Z' by a complex step). Zeros closer than
        ``tol`` / 2 are one frequency; each is accepted only where J rises by exactly its
        multiplicity across [omega - tol/2, omega + tol/2], as multisection would end.
        """
        (lo_w, lo_j, lo_0, lo_mu, _), (up_w, up_j, up_0, up_mu, _) = lo, up
        if not lo_w.size:
            return np.zeros((4 + lo_0.shape[1], 0))
        first = lo_j - lo_0.sum(axis=1)                   # Z's negative eigenvalues at lo
        rise = up_j - lo_j
        if np.any(lo_0 != up_0) or np.any(first < 0) or np.any(first + rise > self.nd):
            return None
        bracket = np.repeat(np.arange(lo_w.size), rise)
        index = first[bracket] + np.arange(bracket.size) - np.repeat(np.cumsum(rise) - rise,
                                                                     rise)
        a, b = lo_w[bracket] ** 2, up_w[bracket] ** 2
        # the weight (lam - p_a)(p_b - lam) = (ka lam + ca)(cb - kb lam): k = 1, c = -p_a or
        # p_b at a pole, else k = 0, c = 1
        ka = np.isin(lo_w, poles_w + tol / 4)[bracket].astype(float)
        kb = np.isin(up_w, poles_w - tol / 4)[bracket].astype(float)
        ca = np.where(ka > 0, -(lo_w[bracket] - tol / 4) ** 2, 1.0)
        cb = np.where(kb > 0, (up_w[bracket] + tol / 4) ** 2, 1.0)
        every = np.arange(bracket.size)
        # Z's eigenvalues at points crowding towards both ends of each bracket (``sampled``:
        # (omega (b, p), eigenvalues (b, p, nd)), from the first sweep) narrow every task
        # to neighbouring samples around its zero: Newton's start
        points = np.concatenate([lo_w[:, None], sampled[0], up_w[:, None]], axis=1)
        lam = (points * points)[bracket]                                    # (tasks, points)
        mu = np.concatenate([lo_mu[:, None], sampled[1], up_mu[:, None]],
                            axis=1)[bracket, :, index]
        negative = mu < 0.0
        cut = np.argmax(negative, axis=1)          # first sample below zero (never the 0th)
        if np.any(~negative[every, cut]) or np.any(cut == 0):
            return None
        g = mu * (ka[:, None] * lam + ca[:, None]) * (cb[:, None] - kb[:, None] * lam)
        a, b = lam[every, cut - 1], lam[every, cut]
        third = np.where(cut + 1 < lam.shape[1], cut + 1, cut - 2)   # another neighbour
        with np.errstate(all='ignore'):
            x = _inverse_quadratic(g[every, cut - 1], g[every, cut], g[every, third],
                                   a, b, lam[every, third])
            rf = a + (b - a) * g[every, cut - 1] / (g[every, cut - 1] - g[every, cut])
            x = np.where(np.isfinite(x) & (x > a) & (x < b), x,
                         np.where(np.isfinite(rf) & (rf > a) & (rf < b), rf, 0.5 * (a + b)))
            # the unfinished tasks' data, compacted as tasks finish: ids, iterate, bracket
            # [a, b], weight terms, eigenvalue index, previous step
            active = (every, x, a, b, ka, ca, cb, kb, index, np.full(x.size, np.inf))
            for _ in range(NEWTON_STEPS):
                ids, xa, a, b, ka, ca, cb, kb, k, before = active
                z, dz = self.z_slope(xa)
                values, vectors = np.linalg.eigh(z)
                rows = np.arange(k.size)
                mu = values[rows, k]
                v = vectors[rows, :, k]
                slope = np.einsum('ti,tij,tj->t', v, dz, v)
                a = np.where(mu >= 0.0, xa, a)
                b = np.where(mu < 0.0, xa, b)
                left = ka * xa + ca
                right = cb - kb * xa
                w = left * right
                new = xa - mu * w / (slope * w + mu * (ka * right - kb * left))
                new = np.where(np.isfinite(new) & (new >= a) & (new <= b), new, 0.5 * (a + b))
                moved = np.abs(np.sqrt(new) - np.sqrt(xa))
                x[ids] = new                    # (the first xa is x itself: after ``moved``)
                ahead = moved * (moved / before) ** 2   # the next step, were it quadratic
                keep = (moved > tol / 4) & ~((ahead < 1e-3 * tol) & (moved < 1e-3 * before)
                                             & (before < np.inf))
                active = (ids, new, a, b, ka, ca, cb, kb, k, moved)
                if not keep.all():
                    active = tuple(e[keep] for e in active)
                    if not keep.any():
                        break
            else:
                return None
        omega = np.sqrt(x)
        order = np.lexsort((omega, bracket))
        omega, bracket = omega[order], bracket[order]
        new_group = np.ones(omega.size, dtype=bool)
        new_group[1:] = (bracket[1:] != bracket[:-1]) | (np.diff(omega) > tol / 2)
        starts = np.flatnonzero(new_group)
        ends = np.append(starts[1:], omega.size) - 1
        mult = ends - starts + 1
        centre = 0.5 * (omega[starts] + omega[ends])
        owner = bracket[starts]
        lo_v, hi_v = centre - tol / 2, centre + tol / 2
        below = lo_j[owner] + starts - np.searchsorted(bracket, owner)   # modes before each
        if np.any(lo_v <= lo_w[owner]) or np.any(hi_v >= up_w[owner]) \
                or np.any(lo_v[1:] <= hi_v[:-1]):
            return None
        j, j0 = self.count(np.concatenate([lo_v, hi_v]) ** 2)[:2]
        j = j.reshape(2, -1)
        if np.any(j[0] != below) or np.any(j[1] != below + mult):
            return None
        j0 = j0.reshape(2, -1, j0.shape[1])
        return np.concatenate([np.stack([centre, mult, lo_v, hi_v]), (j0[1] - j0[0]).T])

    def z_slope(self, lam):
        """(Z(lam), Z'(lam)), (nl, nd, nd) each, undamped, from one complex step of the
        cables' end stiffness (exact to round-off: Z is real analytic in lam)."""
        s = self.system
        step = STEP * np.maximum(lam, 1.0)
        cables = s.cables_at(lam + 1j * step)
        z = s.platform_stiffness[None] - lam[:, None, None] * s.platform_mass[None] \
            + cables.real
        z = 0.5 * (z + np.swapaxes(z, -1, -2))
        dz = cables.imag / step[:, None, None] - s.platform_mass[None]
        return z, 0.5 * (dz + np.swapaxes(dz, -1, -2))

    @staticmethod
    def _guess(lo, up, poles_w) -> np.ndarray:
        """Where each bracket's lowest frequency probably is (nan: no guess).

        Where J0 does not jump in the bracket: the regula falsi of the eigenvalue of Z that
        crosses zero (times |p^2 - w^2|, p the nearest clamped-chain eigenvalue where known:
        Z ~ c/(p^2 - w^2) there). Where it jumps: that eigenvalue (fem, dsm: closed form), or
        the regula falsi of the jumping chain's last pivot determinant (general chains).
        """
        (lo_w, lo_j, lo_0, lo_mu, lo_det), (hi_w, _, hi_0, hi_mu, hi_det) = lo, up
        jump = hi_0 - lo_0                                                  # (b, ncab)
        smooth = ~np.any(jump, axis=1)
        index = np.clip(lo_j - lo_0.sum(axis=1), 0, lo_mu.shape[1] - 1)[:, None]
        f_lo = np.take_along_axis(lo_mu, index, axis=1)[:, 0]
        f_hi = np.take_along_axis(hi_mu, index, axis=1)[:, 0]
        if poles_w is not None and poles_w.size:
            mid = 0.5 * (lo_w + hi_w)
            at = np.searchsorted(poles_w, mid)
            below = poles_w[np.maximum(at - 1, 0)]
            above = poles_w[np.minimum(at, poles_w.size - 1)]
            p = np.where(np.abs(below - mid) < np.abs(above - mid), below, above)
            f_lo, f_hi = f_lo * np.abs(p * p - lo_w * lo_w), f_hi * np.abs(p * p - hi_w * hi_w)
        valid = smooth & (f_lo >= 0) & (f_hi < 0)
        if poles_w is None:
            cable = np.argmax(jump, axis=1)[:, None]
            d_lo = np.take_along_axis(lo_det, cable, axis=1)[:, 0]
            d_hi = np.take_along_axis(hi_det, cable, axis=1)[:, 0]
            chain = ~smooth & (d_lo * d_hi < 0)
            f_lo, f_hi = np.where(chain, d_lo, f_lo), np.where(chain, d_hi, f_hi)
            valid = valid | chain
        with np.errstate(divide='ignore', invalid='ignore'):
            guess = np.where(valid, lo_w + (hi_w - lo_w) * f_lo / (f_lo - f_hi), np.nan)
        if poles_w is not None and poles_w.size:
            first = poles_w[np.minimum(np.searchsorted(poles_w, lo_w, side='right'),
                                       poles_w.size - 1)]
            guess = np.where(~smooth & (first > lo_w) & (first < hi_w), first, guess)
        return guess


def _closed_form_ends(directions, row_size, jumps, hit, force, mass, size):
    """:func:`_stacked_ends` from closed-form clamped modes: ``hit``, ``force``, ``mass`` and
    ``size`` (g, 2 or 3, ncab) per eigenvalue, kind (axial, transverse: two directions; or
    axial and each transverse direction) and chain,
    whether a clamped mode of that kind sits at the eigenvalue, its end reaction and mass
    coupling along each of its directions (``directions`` (ncab, 3, 3), axial row first) and
    the scale of its reaction's terms per unit ``row_size`` (scalar or (ncab, 3)); ``jumps``
    (g, ncab) modes taken per chain, directions in order."""
    def per_row(a):
        return np.swapaxes(a if a.shape[1] == 3 else a[:, [0, 1, 1]], 1, 2)  # (g, ncab, 3)

    valid = per_row(hit)
    take = valid & (np.cumsum(valid, axis=2) <= np.asarray(jumps)[:, :, None])
    group, owner = np.nonzero(take)[:2]
    rows = np.broadcast_to(directions, take.shape + (3,))[take]             # (r, 3)
    scale = (per_row(size) * row_size * take).max(axis=(1, 2), initial=0.0)
    return per_row(force)[take][:, None] * rows, per_row(mass)[take][:, None] * rows, owner, \
        group, scale


def _directions(unit, normal=None) -> np.ndarray:
    """(n, 3, 3) the clamped modes' directions of straight cables as rows: the axial u, then
    the basis of the transverse plane (:func:`_normal_planes`); where ``normal`` (n, 3) has a
    pulley plane's normal, the in-plane direction normal x u and the normal last."""
    rows = np.concatenate([unit[:, None], np.swapaxes(_normal_planes(unit), 1, 2)], axis=1)
    if normal is not None:
        normal = np.asarray(normal, dtype=float)
        pulley = np.einsum('ci,ci->c', normal, normal) > 0.0
        m = normal[pulley] - np.sum(normal[pulley] * unit[pulley], axis=1, keepdims=True) \
            * unit[pulley]
        m /= np.linalg.norm(m, axis=1, keepdims=True)
        rows[pulley, 1] = np.cross(m, unit[pulley])
        rows[pulley, 2] = m
    return rows


def _normal_planes(unit) -> np.ndarray:
    """(n, 3, 2) orthonormal bases of the planes normal to the unit vectors ``unit`` (n, 3):
    the least aligned axis less its component along u, then u x that."""
    unit = np.asarray(unit, dtype=float)
    first = np.eye(3)[np.argmin(np.abs(unit), axis=1)]
    first = first - np.sum(first * unit, axis=1, keepdims=True) * unit
    first /= np.sqrt(np.einsum('ci,ci->c', first, first))[:, None]
    second = unit[:, [1, 2, 0]] * first[:, [2, 0, 1]] - unit[:, [2, 0, 1]] * first[:, [1, 2, 0]]
    return np.stack([first, second], axis=2)
