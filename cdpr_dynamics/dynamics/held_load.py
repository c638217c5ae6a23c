"""Many Newmark steps at once in modal coordinates: a held load in closed form, a run of loads
mode by mode.

With Rayleigh damping C = dM M + dK K the modes of (K, M), K phi = w^2 M phi with
phi^T M phi = I, decouple Newmark's recursion (Eqs. 46-50): each mode j steps its own
(u_j, v_j, a_j) under its load f_j = phi_j^T F with c_j = dM + dK w_j^2,

    u' = (f + (a0 + a1 c) u + (a2 + a4 c) v + (a3 + a5 c) a) / (w^2 + a0 + a1 c),
    a' = a0 (u' - u) - a2 v - a3 a,       v' = v + a6 a + a7 a',

a linear map of (u, v, a, f) with f held: a 4 x 4 matrix T_j. N steps are T_j^N (repeated
squaring, log2 N products of 4 x 4 matrices for every mode at once), so a gap of any length
costs the projections onto the modes and back: the same state as N steps to round-off.

Under a load that changes from step to step (a run of wrenches, :meth:`HeldLoadSteps.run`)
every mode steps its own recursion, all of them in one sparse product per step (T_j's 3 x 3
parts in a block of 9 n values, the loads' parts added), and the platform's rows come back
through the modes' platform rows: the steps of the physical model to round-off (a different
order of the same arithmetic), for 9 n products a step instead of a solve.
"""
from __future__ import annotations

import functools

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from cdpr_dynamics.dynamics.system import Damping, DynamicsError, _csr_matvec

MAX_DOFS = 1500     # a dense generalised eigenproblem above this costs seconds: step instead
RUN_CHUNK_STEPS = 256     # the steps of a run held at once in modal coordinates (memory)


class HeldLoadSteps:
    """N Newmark steps of M u'' + C u' + K u = F, F held, in closed form, and runs of loads
    that change, mode by mode (:meth:`run`) (module docstring).

    ``stiffness``, ``mass``: the integrator's K and M (dense or sparse, n <= MAX_DOFS);
    ``a``: its coefficients a0..a7 (:attr:`~cdpr_dynamics.dynamics.system.Newmark.a`).
    """

    def __init__(self, stiffness, mass, damping: Damping, a: tuple):
        k = stiffness.toarray() if sp.issparse(stiffness) else np.asarray(stiffness, float)
        m = mass.toarray() if sp.issparse(mass) else np.asarray(mass, float)
        if k.shape[0] > MAX_DOFS:
            raise DynamicsError(f'{k.shape[0]} DOFs: the held-load closed form takes at most '
                                f'{MAX_DOFS}')
        if not (isinstance(damping, Damping) and np.isfinite(k).all()
                and np.isfinite(m).all()):
            raise DynamicsError('the modal form needs finite K, M and Rayleigh damping')
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

    @functools.cached_property
    def _run_parts(self) -> tuple:
        """What :meth:`run` steps with: the map of the modal states x = (u, v, a) of all the
        modes in turn (3 n,) to the next, sparse (CSR: each mode's 3 x 3 part of T_j), the
        load's column (3, n) of T_j (u', v', a' per unit modal load), and the buffers of a
        chunk: the modal states (RUN_CHUNK_STEPS + 1, 3 n), a view of each row, the modal
        loads (RUN_CHUNK_STEPS, n)."""
        n = self.w2.size
        modes = np.arange(n)
        rows = np.broadcast_to(np.arange(3)[:, None, None] * n + modes, (3, 3, n))
        cols = np.broadcast_to(np.arange(3)[None, :, None] * n + modes, (3, 3, n))
        values = np.moveaxis(self.step[:, :3, :3], 0, -1)                   # (3, 3, n)
        matrix = sp.csr_matrix((values.ravel(), (rows.ravel(), cols.ravel())),
                               shape=(3 * n, 3 * n))
        matrix.sort_indices()
        x = np.empty((RUN_CHUNK_STEPS + 1, 3 * n))
        return (matrix, np.ascontiguousarray(self.step[:, :3, 3].T), x, list(x),
                np.empty((RUN_CHUNK_STEPS, n)))

    def run(self, state: np.ndarray, loads: np.ndarray, steps: np.ndarray,
            platform_dofs: int) -> tuple[np.ndarray, np.ndarray]:
        """``steps[k]`` steps under the k-th load, in turn, from ``state`` (3, n) rows u, v, a;
        ``loads`` (k, nd): the loads' platform parts (the first ``platform_dofs`` DOFs; the
        others unloaded). Returns (the platform rows u, v after every step (s, 2, nd), the
        state after the last (3, n)): the steps' numbers to round-off (module docstring),
        in chunks of ``RUN_CHUNK_STEPS``."""
        matrix, column, x, rows, modal_loads = self._run_parts
        n, nd = self.w2.size, platform_dofs
        shapes = self.phi[:nd]                           # (nd, n) the modes' platform rows
        total = int(steps.sum())
        taken = np.empty((total, 2, nd))
        which = np.repeat(np.arange(len(steps)), steps)  # the load of every step
        x[0] = (self.phi.T @ (self.m @ state.T)).T.ravel()
        size3, indptr, indices, data = 3 * n, matrix.indptr, matrix.indices, matrix.data
        done = 0
        while done < total:
            size = min(RUN_CHUNK_STEPS, total - done)
            block = x[1:size + 1]
            np.matmul(loads[which[done:done + size]], shapes, out=modal_loads[:size])
            np.multiply(modal_loads[:size, None, :], column, out=block.reshape(size, 3, n))
            for k in range(size):           # x' = T x + the load's part (scipy's CSR kernel)
                _csr_matvec(size3, size3, indptr, indices, data, rows[k], rows[k + 1])
            np.matmul(block[:, :n], shapes.T, out=taken[done:done + size, 0])
            np.matmul(block[:, n:2 * n], shapes.T, out=taken[done:done + size, 1])
            x[0] = x[size]
            done += size
        return taken, (self.phi @ x[0].reshape(3, n).T).T
