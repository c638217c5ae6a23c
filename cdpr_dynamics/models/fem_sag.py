"""``fem_sag``: the FEM linearised about each cable's sagged static shape.

Each cable is the elastic catenary of ``catenary_exact`` (:func:`catenary.solve`: end tension
T_i, chord closed exactly) cut into n elements of equal unstrained length l0 = L0/n. The nodes
lie on that curve; element e is the straight truss between consecutive nodes, with chord length
l_e, direction e_e and the catenary tension T_e at its middle. Its tangent stiffness and
consistent mass (mu = gamma/g per unstrained length) are

    K_e = EA/l0 e_e e_e^T + T_e/l_e (I - e_e e_e^T),    M_e = mu l0/6 [2I I; I 2I],

the exact linearisation of a stretched straight element. A chain of such elements statically
condensed onto its end has the flexibility sum_e K_e^-1 = sum_e [l0/EA e e^T + l_e/T_e
(I - e e^T)], a midpoint rule of the catenary's integral of (I/EA + (I - t t^T)/T) d sigma: it
converges to ``catenary_exact``'s 3x3 stiffness as n^-2. With the weight -> 0 it is ``fem``
except for the axial term EA/l0 = (EA + T)/l instead of the paper's EA/l (and the mass of the
unstrained length): a relative T/EA.

The directions differ element to element, so the 3x3 blocks do not decouple: the end dynamic
stiffness eliminates the chain from the anchor, element by element, in flexibility form
(:func:`series_end_stiffness`: exact like the block Schur recursion S_k = D_k - O^T S^-1 O, but
without its loss of about EA/T digits), vectorised over frequencies and cables. Cables without
a taut catenary (slack, no solution) are replaced by a straight chain at a finite placeholder
tension and the assembly is invalid with a warning.

An anchor end (:class:`cdpr_dynamics.models.base.AnchorEnd`) is a massless spring in series
with the first element (as in ``fem``): that element's stiffness K_1 becomes
(K_1^-1 + F)^-1 (:func:`cdpr_dynamics.models.base.anchor_series`) in the matrices and in the
recursion, which then starts from that element's general 3x3 flexibility.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from cdpr_dynamics.models import catenary
from cdpr_dynamics.models.base import CableAssembly, CableSet, ChainBlocks, anchor_series


_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))   # symmetric 3x3 as 6 components
_UPPER_FLAT = np.array([3 * i + k for i, k in _UPPER])        # the same in a flat 3x3


def _sym_inverse_parts(a):
    """Adjugate (6 components) and determinant of symmetric 3x3 matrices given as components."""
    a00, a01, a02, a11, a12, a22 = a
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    adj = (c00, c01, c02, a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01)
    return adj, a00 * c00 + a01 * c01 + a02 * c02


def _sym_product(p, q):
    """Components of p q for commuting symmetric 3x3 p, q (so that p q is symmetric)."""
    p00, p01, p02, p11, p12, p22 = p
    q00, q01, q02, q11, q12, q22 = q
    return (p00 * q00 + p01 * q01 + p02 * q02, p00 * q01 + p01 * q11 + p02 * q12,
            p00 * q02 + p01 * q12 + p02 * q22, p01 * q01 + p11 * q11 + p12 * q12,
            p01 * q02 + p11 * q12 + p12 * q22, p02 * q02 + p12 * q12 + p22 * q22)


def series_end_stiffness(ee, axial, transverse, mass, lam) -> np.ndarray:
    """End dynamic stiffness of chains of straight elements (anchor fixed), in series form.

    Element j of a cable has stiffness k_j = a e_j e_j^T + b_j (I - e_j e_j^T) and consistent
    mass m [2I I; I 2I] (m = mu l0/6); ``ee`` (6, n, ncab) are the components of e_j e_j^T,
    ``axial`` a (ncab,), ``transverse`` b (n, ncab), ``mass`` m (ncab,), ``lam`` (nl,).

    With c = lam m, condensing the chain from the anchor element by element is, in the
    flexibility G = (R - 3c I)^-1 of the part already condensed (R its end stiffness),

        G_0 = 0,   P = G_{j-1} + (k_j + c I)^-1,   G_j = P (I - 6 c P)^-1,   S = G_n^-1 + 3 c I,

    where (k + c I)^-1 = e e^T/(a + c) + (I - e e^T)/(b + c) needs no solve. At lam = 0 this is
    the sum of the element flexibilities: no cancellation between the stiff axial and the soft
    transverse terms, unlike the stiffness form S_k = D_k - O^T S_{k-1}^-1 O (which loses about
    EA/T digits). Result (nl, ncab, 3, 3), real for real ``lam``, complex otherwise.

    Each catenary lies in the vertical plane of its chord, so every e_j is normal to one n:
    the chain splits exactly into a 2x2 in-plane chain and a scalar chain along n (stiffness
    b_j), about a third of the work (:func:`planar_chains`, :func:`_series_planar`); a chain
    that is not planar to round-off takes the 3x3 recursion (:func:`_series_3d`). Work arrays
    are (ncab, nl), frequency last; 1/(a + c), -6c and one reciprocal per determinant replace
    the divisions of the loop.
    """
    return _series(planar_chains(ee), ee, axial, transverse, mass, lam)


def _series(planar, ee, axial, transverse, mass, lam) -> np.ndarray:
    """:func:`series_end_stiffness` given :func:`planar_chains` of ``ee``."""
    if planar is None:
        return _series_3d(ee, axial, transverse, mass, lam)
    return _series_planar(planar, axial, transverse, mass, lam)


def planar_chains(ee):
    """The plane of each chain: (basis (ncab, 3, 3) rows u1, u2, n; in-plane e e^T components
    (3, n, ncab): u1 u1, u1 u2, u2 u2), or None where some e_j leaves the plane normal to n (the
    eigenvector of sum_j e_j e_j^T with the least eigenvalue) by more than round-off."""
    ncab = ee.shape[2]
    full = np.empty((ee.shape[1], ncab, 3, 3))
    for v, (i, k) in zip(ee, _UPPER):
        full[..., i, k] = full[..., k, i] = v
    values, vectors = np.linalg.eigh(full.sum(axis=0))                 # ascending
    if not np.all(values[:, 0] <= 1e-14 * ee.shape[1]):       # n^T (sum e e^T) n: round-off
        return None
    basis = np.stack([vectors[:, :, 1], vectors[:, :, 2], vectors[:, :, 0]], axis=1)
    inplane = np.einsum('jcik,cai,cbk->abjc', full, basis[:, :2], basis[:, :2])
    return basis, np.stack([inplane[0, 0], inplane[0, 1], inplane[1, 1]])


def _series_planar(planar, axial, transverse, mass, lam) -> np.ndarray:
    """:func:`series_end_stiffness` of planar chains: the same recursion on the in-plane 2x2
    flexibility (3 components) and the scalar one along n, then S in the world frame.

    For a 2x2 P, P adj(I - 6 c P) = P - 6 c det(P) I (Cayley-Hamilton), so
    G = (P - 6 c det P I) / (1 - 6 c (tr P - 6 c det P))."""
    basis, ee2 = planar
    lam = np.asarray(lam).ravel()
    dtype = float if np.isrealobj(lam) else complex
    c = mass[:, None] * lam.astype(dtype)[None, :]                       # (ncab, nl)
    if dtype is float and not lam.any():        # static: G is the sum of the flexibilities
        beta = 1.0 / transverse                                          # (n, ncab)
        delta = 1.0 / axial - beta
        g0, g1, g2, gn = (np.broadcast_to(a.sum(axis=0)[:, None], c.shape)
                          for a in (delta * ee2[0] + beta, delta * ee2[1],
                                    delta * ee2[2] + beta, beta))
        return _planar_end(basis, g0, g1, g2, gn, c, lam.size)
    six_c = 6.0 * c
    axial_flexibility = 1.0 / (axial[:, None] + c)
    ee2 = ee2[..., None].astype(dtype)            # columns of c's type: no mixed broadcasts
    transverse = transverse[..., None].astype(dtype)
    g0 = g1 = g2 = gn = 0.0
    # the loop's scratch arrays, written in place (the recursion is allocation-bound on
    # cables x frequencies of a few thousand entries): 10-15 % of its time
    beta, delta, e, det, qn, inv, scratch = (np.empty_like(c) for _ in range(7))
    for j in range(ee2.shape[1]):
        np.reciprocal(np.add(transverse[j], c, out=beta), out=beta)
        np.subtract(axial_flexibility, beta, out=delta)
        p0 = delta * ee2[0, j]                   # P = G + (k_j + c I)^-1
        p0 += g0
        p0 += beta
        p1 = delta * ee2[1, j]
        p1 += g1
        p2 = delta * ee2[2, j]
        p2 += g2
        p2 += beta
        pn = beta + gn
        np.multiply(p0, p2, out=e)               # 6 c det P
        e -= np.multiply(p1, p1, out=scratch)
        e *= six_c
        np.add(p0, p2, out=det)                  # det(I - 6 c P) = 1 - 6 c (tr P - e)
        det -= e
        det *= six_c
        np.subtract(1.0, det, out=det)
        np.subtract(1.0, np.multiply(six_c, pn, out=qn), out=qn)
        np.reciprocal(np.multiply(det, qn, out=inv), out=inv)   # 1/det and 1/qn at once
        gn = pn
        gn *= det
        gn *= inv
        inv *= qn
        g0, g1, g2 = p0, p1, p2                  # (P - e I) / det
        g0 -= e
        g0 *= inv
        g1 *= inv
        g2 -= e
        g2 *= inv
    return _planar_end(basis, g0, g1, g2, gn, c, lam.size)


def _planar_end(basis, g0, g1, g2, gn, c, nl) -> np.ndarray:
    """S = G^-1 + 3 c I (nl, ncab, 3, 3) in the world frame from the condensed chains'
    in-plane flexibility (g0, g1, g2) and normal one gn (ncab, nl) in their planes ``basis``."""
    inv_det = 1.0 / (g0 * g2 - g1 * g1)
    three_c = 3.0 * c
    parts = np.stack([g2 * inv_det + three_c, -g1 * inv_det, g0 * inv_det + three_c,
                      1.0 / gn + three_c])                               # (4, ncab, nl)
    u1, u2, normal = basis[:, 0], basis[:, 1], basis[:, 2]
    shapes = np.stack([u1[:, :, None] * u1[:, None, :],
                       u1[:, :, None] * u2[:, None, :] + u2[:, :, None] * u1[:, None, :],
                       u2[:, :, None] * u2[:, None, :], normal[:, :, None] * normal[:, None, :]],
                      axis=1).reshape(-1, 4, 9)                          # (ncab, 4, 9)
    out = parts.transpose(1, 2, 0) @ shapes                              # (ncab, nl, 9)
    return out.transpose(1, 0, 2).reshape(nl, basis.shape[0], 3, 3)


def _series_3d(ee, axial, transverse, mass, lam, first=None) -> np.ndarray:
    """:func:`series_end_stiffness` on the full symmetric 3x3 flexibility (6 components);
    ``first`` (ncab, 3, 3): the anchor element's stiffness where it is not of the form
    a e e^T + b (I - e e^T) (an anchor end in series)."""
    lam = np.asarray(lam).ravel()
    dtype = float if np.isrealobj(lam) else complex
    c = mass[:, None] * lam.astype(dtype)[None, :]                       # (ncab, nl)
    minus_6c = -6.0 * c
    axial_flexibility = 1.0 / (axial[:, None] + c)
    g = (0.0,) * 6
    for j in range(ee.shape[1]):
        if j == 0 and first is not None:         # (K_1 + c I)^-1
            q = [first[:, i, k][:, None] + (c if i == k else 0.0) for i, k in _UPPER]
            adj, det = _sym_inverse_parts(q)
            p = [v / det for v in adj]
        else:
            beta = 1.0 / (transverse[j][:, None] + c)
            delta = axial_flexibility - beta
            p = [g[k] + delta * ee[k, j][:, None] for k in range(6)]
            for k in (0, 3, 5):
                p[k] += beta
        q = [minus_6c * pk for pk in p]
        for k in (0, 3, 5):
            q[k] += 1.0
        adj, det = _sym_inverse_parts(q)
        inv_det = 1.0 / det
        g = tuple(v * inv_det for v in _sym_product(p, adj))
    adj, det = _sym_inverse_parts(g)
    inv_det = 1.0 / det
    three_c = 3.0 * c
    out = np.empty((c.shape[1], c.shape[0], 3, 3), dtype=dtype)
    for v, (i, k) in zip(adj, _UPPER):
        value = v * inv_det
        if i == k:
            value += three_c
        out[..., i, k] = out[..., k, i] = value.T
    return out


def _plane_points(state: catenary.CatenaryState, planes, n: int):
    """((p_h, p_v) (ncab, n + 1), (f_h, f_v) (ncab,)): the points of :func:`node_positions` in
    each cable's plane (point = p_h h + p_v e, :mod:`~cdpr_dynamics.models.catenary`, "In the
    plane") and the end force in it; ``planes`` the cables' ``catenary._planes``."""
    f_h, f_v = catenary._in_plane(state.force_n, planes)
    gamma = planes.gamma
    sigma = state.unstrained_length_m[:, None] * _chain_shapes(n).fractions
    h, v = f_h[:, None], f_v[:, None]
    r = catenary._closed_forms(v, h, h * h, sigma, gamma)      # l(F, sigma) of Eq. 25
    elastic = sigma / planes.ea
    return (-(elastic + r.q) * h, -(elastic * (v - (0.5 * gamma) * sigma) + r.s)), (f_h, f_v)


def node_positions(state: catenary.CatenaryState, cables: CableSet, n: int) -> np.ndarray:
    """Points of each cable relative to its platform attachment, (ncab, n + 1, 3).

    Point 0 is the anchor, point n the platform end; point k at unstrained arc length
    L0 (n - k)/n from the platform end, on the elastic catenary (-l(F, sigma) of Eq. 25).
    """
    planes = catenary._planes(cables)
    with np.errstate(all='ignore'):
        (p_h, p_v), _ = _plane_points(state, planes, n)
    return p_h[..., None] * planes.horizontal[:, None, :] + p_v[..., None] * planes.up


def sag_chains(cables: CableSet, n: int, state: catenary.CatenaryState | None = None):
    """The chains on the sagged shapes (straight where the catenary is invalid).

    Returns (ChainBlocks, element data for :func:`series_end_stiffness`, CatenaryState).
    The shapes are computed in each cable's plane (:func:`_plane_points`) and lifted to 3D.
    """
    blocks, elements, state, _ = _chains(cables, n, state)
    return blocks, _series_elements(*elements), state


def _series_elements(ee, axial, transverse, lumped):
    """The element data of :func:`series_end_stiffness` from :func:`_chains`' (ee (ncab, n,
    3, 3), axial (ncab,), transverse (ncab, n), lumped (ncab,))."""
    return ee.reshape(ee.shape[:2] + (9,))[:, :, _UPPER_FLAT].transpose(2, 1, 0), axial, \
        transverse.T, lumped


def _chains(cables: CableSet, n: int, state: catenary.CatenaryState | None = None):
    """:func:`sag_chains` with its element data as (e e^T, axial, transverse, lumped mass):
    :func:`_series_elements` gives the components where the end stiffness is asked for; and
    :func:`planar_chains`' answer for these chains, known: the planes of :func:`_plane_basis`
    and the in-plane components (h h, h e, e e) of each e e^T, (3, n, ncab)."""
    state = catenary.state_of(cables) if state is None else state
    planes = catenary._planes(cables)
    with np.errstate(all='ignore'):          # invalid cables: replaced just below
        (p_h, p_v), (f_h, f_v) = _plane_points(state, planes, n)
    valid = state.valid
    all_valid = valid.all()
    if not all_valid:
        fraction = _chain_shapes(n).fractions          # the chord, straight
        p_h = np.where(valid[:, None], p_h, -planes.span_h[:, None] * fraction)
        p_v = np.where(valid[:, None], p_v, -planes.span_v[:, None] * fraction)
    d_h, d_v = p_h[:, 1:] - p_h[:, :-1], p_v[:, 1:] - p_v[:, :-1]        # (ncab, n)
    chord_e = np.sqrt(d_h * d_h + d_v * d_v)
    e_h, e_v = d_h / chord_e, d_v / chord_e
    e = e_h[..., None] * planes.horizontal[:, None, :] + e_v[..., None] * planes.up  # (ncab, n, 3)
    shapes = _chain_shapes(n)
    l0 = state.unstrained_length_m / n                                    # (ncab,)
    sigma_mid = l0[:, None] * shapes.midpoints
    a1 = f_v[:, None] - planes.gamma * sigma_mid
    t_mid = np.sqrt((f_h * f_h)[:, None] + a1 * a1)
    if not all_valid:
        t_mid = np.where(valid[:, None], t_mid, catenary.placeholder_tension(cables)[:, None])
    ee = e[..., :, None] * e[..., None, :]
    axial = cables.ea_n / l0
    transverse = t_mid / chord_e
    # (not (axial - transverse) ee + transverse I: its rounding differs between mirror-image
    # cables, which splits the paper robot's equal clamped-chain frequencies by ~1e-13 and
    # sends the modes' classification to the eigensolver)
    ke = axial[:, None, None, None] * ee \
        + transverse[..., None, None] * (_EYE - ee)                       # (ncab, n, 3, 3)
    k_diag = np.empty_like(ke)                    # D_j = K_j + K_j+1, the last node K_n
    np.add(ke[:, :-1], ke[:, 1:], out=k_diag[:, :-1])
    k_diag[:, -1] = ke[:, -1]
    k_off = -ke[:, 1:]
    lumped = cables.mass_per_length_kg_m * l0 / 6.0                      # (ncab,) kg
    m_diag = lumped[:, None, None, None] * shapes.mass_diag
    m_off = lumped[:, None, None, None] * shapes.mass_off
    planar = (_plane_basis(planes), np.stack([e_h * e_h, e_h * e_v, e_v * e_v]).transpose(0, 2, 1))
    return ChainBlocks(k_diag, k_off, m_diag, m_off), (ee, axial, transverse, lumped), state, \
        planar


class _ChainShapes(NamedTuple):
    """What :func:`sag_chains` needs of n alone: the nodes' unstrained arc lengths from the
    platform end in units of L0, (n - k)/n for node k, (1, n + 1); the midpoints' in units of
    l0 = L0/n, (n - 1/2 - e) for element e, (1, n); the consistent mass
    blocks per unit of mu l0/6 over the free nodes, 4 I at the interior nodes and 2 I at the
    platform end (n, 3, 3), I between neighbours (n - 1, 3, 3). Read-only."""

    fractions: np.ndarray
    midpoints: np.ndarray
    mass_diag: np.ndarray
    mass_off: np.ndarray


_EYE = np.eye(3)
_EYE.flags.writeable = False


@functools.lru_cache(maxsize=8)
def _chain_shapes(n: int) -> _ChainShapes:
    """:class:`_ChainShapes` of chains of n elements (kept: they depend on n only)."""
    mass_diag = np.repeat(4.0 * _EYE[None], n, axis=0)
    mass_diag[-1] = 2.0 * _EYE
    shapes = _ChainShapes(((n - np.arange(n + 1)) / n)[None, :],
                          (n - 0.5 - np.arange(n))[None, :], mass_diag,
                          np.repeat(_EYE[None], n - 1, axis=0))
    for array in shapes:
        array.flags.writeable = False
    return shapes


def build(cables: CableSet, elements_per_cable: int = 16) -> CableAssembly:
    """``fem_sag`` with ``elements_per_cable`` elements per cable."""
    n = int(elements_per_cable)
    if n < 1:
        raise ValueError('fem_sag needs at least one element per cable')
    blocks, parts, state, planar = _chains(cables, n)
    first = None
    if cables.anchor_end is not None:
        ee, axial, transverse, _ = parts
        ee0 = ee[:, 0]
        element = axial[:, None, None] * ee0 + transverse[:, 0, None, None] * (_EYE - ee0)
        first = anchor_series(element, cables)
        k_diag = blocks.k_diag.copy()
        k_diag[:, 0] += first - element
        blocks = blocks._replace(k_diag=k_diag)
    warnings = tuple(state.reasons)
    if warnings:
        warnings += ('fem_sag: the cables above are modelled as straight chains at a placeholder '
                     'tension max(T, gamma L, 1e-9 EA); the results are not valid',)
    series = []           # (planar_chains, element data): on the first call, not per pose

    def end_stiffness(lam):
        lam = np.asarray(lam)
        if np.iscomplexobj(lam) and not np.any(lam.imag):
            lam = lam.real                   # undamped: the real recursion is twice as fast
        if first is None and np.isrealobj(lam) and not lam.any():
            _, axial, transverse, lumped = parts          # static: the planes are known
            return _series_planar(planar, axial, transverse.T, lumped, lam).astype(complex)
        if not series:
            elements = _series_elements(*parts)
            series.append((planar_chains(elements[0]), elements))
        planar_found, elements = series[0]
        if first is not None:
            return _series_3d(*elements, lam, first).astype(complex, copy=False)
        return _series(planar_found, *elements, lam).astype(complex, copy=False)

    return CableAssembly('fem_sag', n, end_stiffness, -state.force_n, blocks,
                         valid=bool(state.valid.all()), warnings=warnings,
                         plane_basis=None if first is not None else planar[0])


def _plane_basis(planes) -> np.ndarray:
    """(ncab, 3, 3) rows h, e, h x e: the plane each chain lies in (h horizontal from the
    anchor towards the attachment, e up: ``planes``, the cables' :func:`catenary._planes`)
    and its normal."""
    h = planes.horizontal
    up = np.broadcast_to(planes.up, h.shape)
    normal = h[:, [1, 2, 0]] * up[:, [2, 0, 1]] - h[:, [2, 0, 1]] * up[:, [1, 2, 0]]
    return np.stack([h, up, normal], axis=1)
