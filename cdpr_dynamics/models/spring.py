"""``spring``: each cable a massless straight axial spring with geometric stiffness.

At the platform end (paper Eq. 18 with one element, no cable mass)

    K_i = EA/L_i u_i u_i^T + T_i/L_i (I - u_i u_i^T)    (N/m)

so only the platform moves; DOFs are the platform's (3 or 6).
"""
from __future__ import annotations

import numpy as np

from cdpr_dynamics.models.base import (CableAssembly, CableSet, ChainBlocks, axial_transverse,
                                       slack_warnings)


def build(cables: CableSet, elements_per_cable: int = 1) -> CableAssembly:
    """Massless spring of every cable; ``elements_per_cable`` is ignored (always 1)."""
    length = cables.length_m
    stiffness = axial_transverse(cables.unit, cables.ea_n / length, cables.tension_n / length)
    zeros = np.zeros((cables.n_cables, 0, 3, 3))
    blocks = ChainBlocks(stiffness[:, None], zeros, np.zeros_like(stiffness)[:, None], zeros)
    warnings = slack_warnings(cables.tension_n)

    def end_stiffness(lam):
        return np.broadcast_to(stiffness, (np.size(lam),) + stiffness.shape).astype(complex)

    return CableAssembly('spring', 1, end_stiffness, cables.tension_n[:, None] * cables.unit,
                         blocks, valid=not warnings, warnings=warnings)
