"""Many Newmark steps under a held load at the cost of one: the modal closed form.

With Rayleigh damping C = dM M + dK K the modes of (K, M), K phi = w^2 M phi with
phi^T M phi = I, decouple Newmark's recursion (Eqs. 46-50): each mode j steps its own
(u_j, v_j, a_j) under its load f_j = phi_j^T F with c_j = dM + dK w_j^2,

    u' = (f + (a0 + a1 c) u + (a2 + a4 c) v + (a3 + a5 c) a) / (w^2 + a0 + a1 c),
    a' = a0 (u' - u) - a2 v - a3 a,       v' = v + a6 a + a7 a',

a linear map of (u, v, a, f) with f held: a 4 x 4 matrix T_j. N steps are T_j^N (repeated
squaring, log2 N products of 4 x 4 matrices for every mode at once), so a gap of any length
costs the projections onto the modes and back: the same state as N steps to round-off.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from cdpr_dynamics.dynamics.system import Damping, DynamicsError

MAX_DOFS = 1500     # a dense generalised eigenproblem above this costs seconds: step instead


class HeldLoadSteps:
    """N Newmark steps of M u'' + C u' + K u = F, F held, in closed form (module docstring).

    ``stiffness``, ``mass``: the integrator's K and M (dense or sparse, n <= MAX_DOFS);
    ``a``: its coefficients a0..a7 (:attr:`~cdpr_dynamics.dynamics.system.Newmark.a`).
    """

    def __init__(self, stiffness, mass, damping: Damping, a: tuple):
        k = stiffness.toarray() if sp.issparse(stiffness) else np.asarray(stiffness, float)
        m = mass.toarray() if sp.issparse(mass) else np.asarray(mass, float)
        if k.shape[0] > MAX_DOFS:
            raise DynamicsError(f'{k.shape[0]} DOFs: the held-load closed form takes at most '
                                f'{MAX_DOFS}')
        w2, phi = scipy.linalg.eigh(k, m, driver='gvd')     # 'gvd': 20-40x 'gv' here
        self.phi = phi                                  # M-orthonormal modes (n, n)
        self.w2 = w2                                    # (rad/s)^2
        self.m = m
        a0, a1, a2, a3, a4, a5, a6, a7 = a
        c = damping.mass_factor + damping.stiffness_factor * w2
        k_eff = w2 + a0 + a1 * c
        step = np.zeros((w2.size, 4, 4))
        # u' row
        step[:, 0, 0] = (a0 + a1 * c) / k_eff
        step[:, 0, 1] = (a2 + a4 * c) / k_eff
        step[:, 0, 2] = (a3 + a5 * c) / k_eff
        step[:, 0, 3] = 1.0 / k_eff
        # a' = a0 u' - a0 u - a2 v - a3 a
        step[:, 2] = a0 * step[:, 0]
        step[:, 2, 0] -= a0
        step[:, 2, 1] -= a2
        step[:, 2, 2] -= a3
        # v' = v + a6 a + a7 a'
        step[:, 1] = a7 * step[:, 2]
        step[:, 1, 1] += 1.0
        step[:, 1, 2] += a6
        step[:, 3, 3] = 1.0                             # the load is held
        self.step = step

    def advance(self, state: np.ndarray, force: np.ndarray, steps: int) -> np.ndarray:
        """The state (3, n) rows u, v, a after ``steps`` steps under ``force`` (n,)."""
        modal = np.empty((self.phi.shape[1], 4))
        modal[:, :3] = (self.phi.T @ (self.m @ state.T))            # (n, 3): u, v, a
        modal[:, 3] = self.phi.T @ force
        power = np.linalg.matrix_power(self.step, int(steps))
        after = np.einsum('jik,jk->ji', power[:, :3, :], modal)      # (n, 3)
        return (self.phi @ after).T

    def static(self, force: np.ndarray) -> np.ndarray:
        """The static deflection K^-1 F (n,) the held load tends to."""
        return self.phi @ ((self.phi.T @ force) / self.w2)
