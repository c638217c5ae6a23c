"""Second computations the tests compare the package's fast paths against.

Each one is the direct, slower form of what the package evaluates another way: the O(n)
recursion of a chain's end stiffness (the package uses its closed form), the complex-arithmetic
z cot z (the package's is real arithmetic), the dense global solve of (K + i w C - w^2 M) (the
package condenses the cables), and the fem assembly whose end stiffness is that recursion.
"""
import cmath
import dataclasses

import numpy as np

from cdpr_dynamics.models import fem
from cdpr_dynamics.models.base import CableAssembly, axial_transverse


def chain_end_stiffness_recursive(k_element, m_element, n: int, lam) -> np.ndarray:
    """End dynamic stiffness of uniform scalar chains of n elements fixed at the far end by
    eliminating the nodes one by one from the anchor,

        S_1 = d11,   S_k = d11 - d12^2 / (S_{k-1} + d11),
        d11 = k - lam 2 mu l / 6,   d12 = -k - lam mu l / 6.

    ``k_element`` and ``m_element`` broadcast over the cables, ``lam`` (nl,): (nl, ...) complex.
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


def fem_recursive(cables, n: int) -> CableAssembly:
    """``fem.build`` of cables without an anchor end, its end stiffness by the recursion and
    through 3x3 blocks (no axial/transverse shortcut)."""
    assembly = fem.build(cables, n)
    element_length = cables.length_m / n
    k_axial = cables.ea_n / element_length
    k_transverse = cables.tension_n / element_length
    m_element = cables.mass_per_length_kg_m * element_length

    def end_stiffness(lam):
        axial = chain_end_stiffness_recursive(k_axial, m_element, n, lam)
        transverse = chain_end_stiffness_recursive(k_transverse, m_element, n, lam)
        return axial_transverse(cables.unit, axial, transverse)

    return dataclasses.replace(assembly, end_stiffness=end_stiffness, decoupled=None)


def z_cot_z_complex(z2) -> np.ndarray:
    """z cot z by complex sqrt, z cos z / sin z (exp(2iz) for Im z > 30), a series near 0;
    the shape of ``z2``."""
    out = []
    for value in np.ravel(z2).astype(complex):
        z = cmath.sqrt(value)
        z = -z if z.imag < 0 else z
        if abs(z) < 1e-3:
            out.append(1.0 - value / 3.0 - value * value / 45.0 - 2.0 * value ** 3 / 945.0)
        elif z.imag > 30.0:
            q = cmath.exp(2j * z)
            out.append(z * 1j * (1.0 + q) / (q - 1.0))
        else:
            out.append(z * cmath.cos(z) / cmath.sin(z))
    return np.array(out).reshape(np.shape(z2))


def naive_frf(system, frequency_hz, force_n, damping) -> np.ndarray:
    """Dense (K + i w C - w^2 M)^-1 F per frequency, Rayleigh damping: (nf, 3) complex."""
    k, m = (a.toarray() for a in system.matrices())
    c = damping.mass_factor * m + damping.stiffness_factor * k
    load = np.zeros(k.shape[0], dtype=complex)
    load[:3] = force_n
    out = np.empty((len(frequency_hz), 3), dtype=complex)
    for i, f in enumerate(frequency_hz):
        w = 2 * np.pi * f
        out[i] = np.linalg.solve(k + 1j * w * c - w * w * m, load)[:3]
    return out
