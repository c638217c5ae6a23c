"""``fem``: the paper's finite-element cable (Eqs. 13-19), n straight 2-node truss elements.

Each element of length l = L/n under the cable tension T has (Eq. 18, with G = u u^T)

    K_e = (EA - T)/l [G -G; -G G] + T/l [I -I; -I I]
        = EA/l [uu^T ...] + T/l [(I - uu^T) ...]                                  (N/m)

and the consistent mass of Eq. 17, M_e = mu l / 6 [2I I; I 2I] with mu = gamma/g (kg/m).
The anchor node is fixed and the last node moves with the platform attachment.

Because the cable is straight and its tension uniform, axial and transverse motions decouple:
the chain is a scalar tridiagonal chain in each direction, with element stiffness
k = EA/l (axial) or T/l (transverse). Its dynamic stiffness at the platform end follows from
eliminating the nodes one by one from the anchor (Schur complement of a tridiagonal chain),

    S_1 = d11,   S_k = d11 - d12^2 / (S_{k-1} + d11),
    d11 = k - lam 2 mu l / 6,   d12 = -k - lam mu l / 6,

vectorised over frequencies and cables: O(n) per frequency instead of a dense solve.
"""
from __future__ import annotations

import numpy as np

from cdpr_dynamics.models.base import (CableAssembly, CableSet, ChainBlocks, axial_transverse,
                                       slack_warnings)


def chain_end_stiffness(k_element: np.ndarray, m_element: np.ndarray, n: int,
                        lam: np.ndarray) -> np.ndarray:
    """End dynamic stiffness of uniform scalar chains of n elements fixed at the far end.

    ``k_element`` and ``m_element`` (element stiffness and mass mu l) broadcast over the cables,
    ``lam`` (nl,) complex: result (nl, ...) complex.
    """
    lam = np.asarray(lam, dtype=complex).reshape((-1,) + (1,) * np.ndim(k_element))
    d11 = k_element - lam * (2.0 * m_element / 6.0)
    d12 = -k_element - lam * (m_element / 6.0)
    s = d11
    for _ in range(n - 1):
        denominator = s + d11
        # 0/0: a chain of zero stiffness and mass (T = 0 transversely, at lam = 0) stays zero;
        # x/0: an exact pole of the chain
        at_pole = denominator == 0
        s = np.where(at_pole, np.where(d12 == 0, 0.0, np.inf),
                     d11 - d12 * d12 / np.where(at_pole, 1.0, denominator))
    return s


def uniform_chain_blocks(unit, k_axial, k_transverse, m_element, n) -> ChainBlocks:
    """Block-tridiagonal matrices of straight uniform chains of n elements (anchor fixed)."""
    ke = axial_transverse(unit, k_axial, k_transverse)               # (ncab, 3, 3)
    me = (np.asarray(m_element) / 6.0)[..., None, None] * np.eye(3)  # (ncab, 3, 3)
    node_count = np.full(n, 2.0)
    node_count[-1] = 1.0
    k_diag = node_count[None, :, None, None] * ke[:, None]
    m_diag = 2.0 * node_count[None, :, None, None] * me[:, None]
    k_off = np.repeat(-ke[:, None], n - 1, axis=1)
    m_off = np.repeat(me[:, None], n - 1, axis=1)
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

    def end_stiffness(lam):
        axial = chain_end_stiffness(k_axial, m_element, n, lam)
        transverse = chain_end_stiffness(k_transverse, m_element, n, lam)
        return axial_transverse(unit, axial, transverse)

    return CableAssembly('fem', n, end_stiffness, cables.tension_n[:, None] * unit,
                         uniform_chain_blocks(unit, k_axial, k_transverse, m_element, n),
                         valid=not warnings, warnings=warnings)
