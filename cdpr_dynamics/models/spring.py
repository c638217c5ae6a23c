"""``spring``: each cable a massless straight axial spring with geometric stiffness.

At the platform end (paper Eq. 18 with one element, no cable mass)

    K_i = EA/L_i u_i u_i^T + T_i/L_i (I - u_i u_i^T)    (N/m)

so only the platform moves; DOFs are the platform's (3 or 6). With an anchor end
(:class:`cdpr_dynamics.models.base.AnchorEnd`) in series, EA/(L_i + series length) along the
cable and T_i/(L_i + c_i) normal to the pulley plane (the swivel's pivot c_i behind the exit).
"""
from __future__ import annotations

from cdpr_dynamics.models.base import (CableAssembly, CableSet, axial_transverse,
                                       massless_assembly, slack_warnings)


def build(cables: CableSet, elements_per_cable: int = 1) -> CableAssembly:
    """Massless spring of every cable; ``elements_per_cable`` is ignored (always 1)."""
    length = cables.length_m
    end = cables.anchor_end
    if end is None:
        stiffness = axial_transverse(cables.unit, cables.ea_n / length,
                                     cables.tension_n / length)
    else:
        stiffness = axial_transverse(cables.unit, cables.ea_n / (length + end.series_length_m),
                                     cables.tension_n / length, end.plane_normal,
                                     cables.tension_n / (length + end.pivot_m))
    warnings = slack_warnings(cables.tension_n)
    return massless_assembly('spring', stiffness, cables.tension_n[:, None] * cables.unit,
                             not warnings, warnings)
