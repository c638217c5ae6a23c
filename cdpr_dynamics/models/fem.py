"""``fem``: the paper's finite-element cable (Eqs. 13-19), n straight 2-node truss elements.

Each element of length l = L/n under the cable tension T has (Eq. 18, with G = u u^T)

    K_e = (EA - T)/l [G -G; -G G] + T/l [I -I; -I I]
        = EA/l [uu^T ...] + T/l [(I - uu^T) ...]                                  (N/m)

and the consistent mass of Eq. 17, M_e = mu l / 6 [2I I; I 2I] with mu = gamma/g (kg/m).
The anchor node is fixed and the last node moves with the platform attachment. An anchor end
(:class:`cdpr_dynamics.models.base.AnchorEnd`: pulley, winch-side cable) is a massless spring
of compliance f between the anchor and the first element, along the cable and normal to the
pulley plane: in series with that element, it lowers the first node's stiffness by
delta = k (k f) / (1 + k f) in that direction (:func:`anchor_chain_end_stiffness`).

Because the cable is straight and its tension uniform, axial and transverse motions decouple:
the chain is a scalar tridiagonal chain in each direction, with element stiffness
k = EA/l (axial) or T/l (transverse). Its dynamic stiffness at the platform end follows from
eliminating the nodes one by one from the anchor (Schur complement of a tridiagonal chain),

    S_1 = d11,   S_k = d11 - d12^2 / (S_{k-1} + d11),
    d11 = k - lam 2 mu l / 6,   d12 = -k - lam mu l / 6,

(O(n) per frequency). The recursion is a linear
recurrence with constant coefficients, so it has a closed form (:func:`chain_end_stiffness`):
with r = cos(theta) = -d11/d12,

    S_n = d11 + d12 sin((n-1) theta) / sin(n theta) = -d12 T_n(r) / U_{n-1}(r)
        = -d12 sqrt(q) (z^-n + z^n) / (z^-n - z^n),   q = r^2 - 1,  z = e^{i theta},

T and U the Chebyshev polynomials. It is evaluated without trigonometric functions or square
roots from V_m = z^m + z^-m = 2 T_m(r) and U_{m-1} by binary powering,

    V_2m = V_m^2 - 2,   U_2m-1 = U_m-1 V_m,   V_m+1 = r V_m + 2 q U_m-1,   U_m = r U_m-1 + V_m/2,

from V_1 = 2r, U_0 = 1 and q = -3c(2k - c)/d12^2 (c = lam mu l/6, no cancellation near
lam = 0): log2(n) steps, the same in the pass band (|r| <= 1, z on the unit circle) and the
stop band, real for real lam and complex for damped lam, vectorised over frequencies and cables.
"""
from __future__ import annotations

import numpy as np

from cdpr_dynamics.models.base import (AxialTransverse, CableAssembly, CableSet, ChainBlocks,
                                       axial_transverse, slack_warnings)


def anchor_softening(k_element: np.ndarray, compliance: np.ndarray) -> np.ndarray:
    """delta = k - (1/k + f)^-1 = k (k f)/(1 + k f): what a massless spring of compliance f
    in series with an element of stiffness k takes off its stiffness (0 where f = 0)."""
    kf = k_element * compliance
    return k_element * kf / (1.0 + kf)


def anchor_chain_end_stiffness(end: np.ndarray, k_element, m_element, delta,
                               lam: np.ndarray) -> np.ndarray:
    """End dynamic stiffness (..., nl) of uniform chains whose first node's stiffness is
    lowered by ``delta`` (..., from :func:`anchor_softening`), from ``end`` (..., nl), the same
    chains' :func:`chain_end_stiffness_last` with a fixed anchor.

    The chain's recursion S_k = d11 - d12^2/(S_{k-1} + d11) is a Moebius map; the softened
    first node S_1 = d11 - delta is the map of a grounding S_0 = d12^2/delta - d11, and n maps
    of S_0 give (S_inf S_0 + d11^2 - d12^2) / (S_inf + S_0) with S_inf = ``end``, evaluated
    with g = 1/S_0 (so S_inf itself where delta = 0)."""
    k = np.asarray(k_element, dtype=float)[..., None]
    c = lam * (np.asarray(m_element, dtype=float)[..., None] / 6.0)
    d11, d12 = k - 2.0 * c, -k - c
    delta = np.asarray(delta, dtype=float)[..., None]
    g = delta / (d12 * d12 - delta * d11)
    return (end - 3.0 * c * (2.0 * k - c) * g) / (end * g + 1.0)


def chain_end_stiffness(k_element: np.ndarray, m_element: np.ndarray, n: int,
                        lam: np.ndarray) -> np.ndarray:
    """End dynamic stiffness S_n of uniform scalar chains of n elements fixed at the far end.

    Closed form -d12 T_n(r)/U_{n-1}(r) (module doc), cost independent of n. ``k_element``
    (N/m) and ``m_element`` (element mass mu l, kg) broadcast over the cables, ``lam`` (nl,)
    (1/s^2): result (nl, ...), real for real ``lam``, complex for complex ``lam``. Agrees with
    the recursion, inf at an exact pole, 0 where k = 0 at lam = 0.
    """
    k = np.asarray(k_element, dtype=float)
    m = np.asarray(m_element, dtype=float)
    shape = np.broadcast_shapes(k.shape, m.shape)
    out = chain_end_stiffness_last(np.broadcast_to(k, shape), np.broadcast_to(m, shape), n,
                                   np.ravel(lam))
    return np.moveaxis(out, -1, 0)


def chain_end_stiffness_last(k_element: np.ndarray, m_element: np.ndarray, n: int,
                             lam: np.ndarray) -> np.ndarray:
    """:func:`chain_end_stiffness` with the frequency axis last: ``k_element``, ``m_element``
    (...) and ``lam`` (nl,) give (..., nl), the layout whose elementwise work is contiguous."""
    lam = np.asarray(lam)
    if lam.dtype.kind != 'c':
        lam = lam.astype(float)
    k = np.asarray(k_element, dtype=float)[..., None]
    c = lam * (np.asarray(m_element, dtype=float)[..., None] / 6.0)     # lam m / 6
    with np.errstate(all='ignore'):       # poles, d12 = 0 and overflow: fixed below
        d11 = k - 2.0 * c
        d12 = -k - c
        inv = 1.0 / d12
        r = d11 * inv
        r *= -1.0
        q = 2.0 * k - c                   # q = (d11 - d12)(d11 + d12)/d12^2
        q *= c
        q *= -3.0
        q *= inv
        q *= inv
        v = 2.0 * r                       # V_1 = 2 r, U_0 = 1
        u = np.ones_like(r)
        for bit in bin(int(n))[3:]:
            u *= v                        # U_2m-1 = U_m-1 V_m
            v *= v
            v -= 2.0                      # V_2m = V_m^2 - 2
            if bit == '1':
                step = q * u
                step *= 2.0
                step += r * v             # V_m+1 = r V_m + 2 q U_m-1
                u *= r
                v *= 0.5
                u += v                    # U_m = r U_m-1 + V_m / 2
                v = step
        out = v / u
        out *= d12
        out *= -0.5                       # S_n = -d12 V_n / (2 U_n-1)
        # where the powering cannot give it: u or v not finite (u = inf alone gives out = 0)
        if not np.isfinite(out).all() or np.isinf(u).any():
            bad = ~(np.isfinite(u) & np.isfinite(v)) | (u == 0)
            out[bad] = _chain_special(d11[bad], d12[bad], r[bad], q[bad], u[bad])
    return out


def _chain_special(d11, d12, r, q, u):
    """S_n where the powering cannot give it: a decoupled chain (d12 = 0: S = d11, so 0 for
    k = 0 at lam = 0), an exact pole (U_n-1 = 0: inf) and overflow deep in the stop band
    (|z|^n beyond the float range: the semi-infinite chain -d12 sqrt(q), |r + sqrt(q)| > 1)."""
    root = np.sqrt(q.astype(complex))
    root = np.where(np.abs(r + root) < np.abs(r - root), -root, root)
    out = -d12 * root
    out = np.where(u == 0, np.inf, out)
    out = np.where(d12 == 0, d11, out)
    return out if np.iscomplexobj(d11) else out.real


def uniform_chain_blocks(unit, k_axial, k_transverse, m_element, n) -> ChainBlocks:
    """Block-tridiagonal matrices of straight uniform chains of n elements (anchor fixed)."""
    ke = axial_transverse(unit, k_axial, k_transverse)               # (ncab, 3, 3)
    me = (np.asarray(m_element) / 6.0)[..., None, None] * np.eye(3)  # (ncab, 3, 3)
    node_count = np.full(n, 2.0)
    node_count[-1] = 1.0
    k_diag = node_count[None, :, None, None] * ke[:, None]
    m_diag = 2.0 * node_count[None, :, None, None] * me[:, None]
    k_off = np.empty((ke.shape[0], n - 1, 3, 3))       # every element's block: broadcast
    k_off[...] = -ke[:, None]                           # copies (np.repeat's numbers)
    m_off = np.empty_like(k_off)
    m_off[...] = me[:, None]
    return ChainBlocks(k_diag, k_off, m_diag, m_off)


def build(cables: CableSet, elements_per_cable: int = 16) -> CableAssembly:
    """The paper's FEM with ``elements_per_cable`` elements per cable."""
    n = int(elements_per_cable)
    if n < 1:
        raise ValueError('fem needs at least one element per cable')
    element_length = cables.length_m / n
    k_axial = cables.ea_n / element_length
    k_transverse = cables.tension_n / element_length
    m_element = cables.mass_per_length_kg_m * element_length
    unit = cables.unit
    warnings = slack_warnings(cables.tension_n)

    blocks = uniform_chain_blocks(unit, k_axial, k_transverse, m_element, n)
    if cables.anchor_end is not None:
        return _with_anchor_end(cables, n, unit, k_axial, k_transverse, m_element, blocks,
                                warnings)
    k_both = np.empty((2,) + k_transverse.shape)          # (2, n): axial, transverse
    k_both[0], k_both[1] = k_axial, k_transverse
    m_both = np.empty_like(k_both)
    m_both[...] = m_element
    chains = AxialTransverse(unit, lambda lam: chain_end_stiffness_last(k_both, m_both, n, lam))
    return CableAssembly('fem', n, chains.end_stiffness, cables.tension_n[:, None] * unit, blocks,
                         valid=not warnings, warnings=warnings, decoupled=chains)


def _with_anchor_end(cables: CableSet, n, unit, k_axial, k_transverse, m_element, blocks,
                     warnings) -> CableAssembly:
    """The fem assembly of chains with an anchor end: three scalar chains per cable (along
    the cable, across it in the pulley plane, normal to the plane), the first node softened
    (in place in ``blocks``, which are the caller's fresh arrays)."""
    end = cables.anchor_end
    f_axial, f_normal = end.compliance(cables.ea_n, cables.tension_n)
    k_both = np.empty((2,) + k_transverse.shape)          # (2, n): axial, transverse
    k_both[0], k_both[1] = k_axial, k_transverse
    m_both = np.empty_like(k_both)
    m_both[...] = m_element
    delta = np.empty_like(k_both)                         # along the cable, normal to the plane
    delta[0] = anchor_softening(k_axial, f_axial)
    delta[1] = anchor_softening(k_transverse, f_normal)
    normal = end.plane_normal
    uu = unit[:, :, None] * unit[:, None, :]
    mm = normal[:, :, None] * normal[:, None, :]
    blocks.k_diag[:, 0] -= delta[0][:, None, None] * uu + delta[1][:, None, None] * mm

    def stiffness(lam):
        fixed = chain_end_stiffness_last(k_both, m_both, n, lam)      # (2, ncab, nl)
        softened = anchor_chain_end_stiffness(fixed, k_both, m_both, delta, np.asarray(lam))
        return np.stack([softened[0], fixed[1], softened[1]])

    chains = AxialTransverse(unit, stiffness, end.plane_normal)
    return CableAssembly('fem', n, chains.end_stiffness, cables.tension_n[:, None] * unit, blocks,
                         valid=not warnings, warnings=warnings, decoupled=chains)
