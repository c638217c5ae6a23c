"""Cable models behind one interface (:mod:`cdpr_dynamics.models.base`), by method name.

Each module exposes ``build(cables: CableSet, elements_per_cable: int) -> CableAssembly``.
Adding a model means one file and one line in :data:`REGISTRY`.
"""
from __future__ import annotations

from cdpr_dynamics.models import catenary, dsm, fem, fem_sag, spring
from cdpr_dynamics.models.base import CableAssembly, CableSet

#: Models of straight cables: they ignore sag.
STRAIGHT_METHODS = ('spring', 'fem', 'dsm')

REGISTRY = {
    'spring': spring.build,
    'fem': fem.build,
    'catenary': catenary.build,
    'catenary_exact': catenary.build_exact,
    'fem_sag': fem_sag.build,
    'dsm': dsm.build,
}


def build(method: str, cables: CableSet, elements_per_cable: int = 16) -> CableAssembly:
    """The :class:`CableAssembly` of ``method`` for ``cables`` (anchor ends included)."""
    try:
        builder = REGISTRY[method]
    except KeyError:
        raise ValueError(f'unknown cable model {method!r}; known: '
                         f'{", ".join(sorted(REGISTRY))}') from None
    return builder(cables, elements_per_cable)
