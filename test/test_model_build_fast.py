"""The pose update's model build and factorisation reuse what depends on the model's size only,
and give the numbers of the general code.

* ChainNewmark gathers its [M K] (CSR) and its chain band from one concatenation of the blocks
  through a pattern kept per (platform DOFs, cables, interior nodes) (``_pair_pattern``): the
  assembled K and M of ``PlatformSystem.matrices`` exactly, whatever size, robot and values
  came before (the cache is keyed by the sizes, its structure shared read-only, the values
  fresh per model);
* the step maps E and L (``_step_maps``) are kept per (Newmark coefficients, damping): a new
  dt or damping gives new maps;
* fem_sag's per-n shapes (``_chain_shapes``: node fractions, midpoints, mass templates) give
  the consistent mass mu l0/6 [2I I; I 2I] assembled element by element, for any n and mass,
  and its end stiffness's element data, now made on the first call, is ``sag_chains``'.
"""
import numpy as np
import pytest
import scipy.sparse as sp

from cdpr_dynamics.analysis.pipeline import build_system, damping_for, equilibrium
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import ChainNewmark, Damping, Newmark, _pair_pattern, _step_maps
from cdpr_dynamics.models import fem_sag
from cdpr_dynamics.models.base import CableSet
from test_pose_update import HEAVY, PAPER, RIGID, _history

LOW = PAPER.parent / 'low_tension_cdpr.yaml'


def _system_at(config, method, elements, offset_m=(0.0, 0.0, 0.0)):
    settings = load_settings(config).replace(method=method, elements_per_cable=elements)
    position = settings.initial_position_m + np.asarray(offset_m)
    system = build_system(settings, equilibrium(settings, position, method=method))
    return settings, system, damping_for(settings, system)


def _assembled_band(full: np.ndarray, nd: int) -> np.ndarray:
    """(6, ni) lower band (band[k, c] = A[c + k, c], zero past the end) of the interior block
    of an assembled matrix."""
    interior = full[nd:, nd:]
    ni = interior.shape[0]
    band = np.zeros((6, ni))
    for k in range(6):
        band[k, :ni - k] = np.diagonal(interior, -k)
    return band


# a sequence that changes robot, model size and values (pose) back and forth: a stale
# pattern or band would give another model's entries
SEQUENCE = [(PAPER, 'fem', 4, (0.0, 0.0, 0.0)), (PAPER, 'fem', 6, (0.0, 0.0, 0.0)),
            (RIGID, 'fem', 4, (0.0, 0.0, 0.0)), (PAPER, 'fem', 4, (0.1, -0.05, 0.2)),
            (HEAVY, 'fem_sag', 5, (0.0, 0.0, 0.0)), (PAPER, 'fem_sag', 5, (0.0, 0.0, 0.0)),
            (HEAVY, 'fem_sag', 5, (0.05, 0.02, -0.03)), (RIGID, 'fem', 4, (0.02, 0.0, 0.0)),
            (LOW, 'fem_sag', 3, (0.0, 0.0, 0.0))]


def test_pair_pattern_gives_each_model_its_own_assembled_m_and_k_through_the_cache():
    """Along robot, size and pose changes: [M K] equals the assembled matrices side by side
    entry for entry, the bands their interior bands; one pattern per size (the same object
    for the same size), its shared template never written."""
    patterns = {}
    for config, method, elements, offset in SEQUENCE:
        _, system, damping = _system_at(config, method, elements, offset)
        chain = ChainNewmark(system, damping, 1e-3)
        k, m = (a.toarray() for a in system.matrices())
        nd = system.platform_dofs
        assert sp.issparse(chain._pair_matrix)
        assert np.array_equal(chain._pair_matrix.toarray(), np.hstack([m, k]))
        assert np.array_equal(chain._k_band, _assembled_band(k, nd))
        assert np.array_equal(chain._m_band, _assembled_band(m, nd))
        size = (nd, system.geometry.n_cables, system.assembly.blocks.nodes - 1)
        pattern = _pair_pattern(*size)
        assert patterns.setdefault(size, pattern) is pattern
        assert chain._pattern is pattern
        assert not pattern.template.data.any()               # the shared template: unwritten
        assert not (pattern.template.indices.flags.writeable
                    or pattern.template.indptr.flags.writeable)
        assert chain._pair_matrix.indices is pattern.template.indices
    assert len(patterns) >= 5           # sizes differ along the sequence


def test_chain_newmark_follows_a_dense_lu_along_changing_models():
    """Each model of the sequence steps as the dense LU of its own assembled matrices (an
    integrator built from another model's cached structure would not)."""
    for config, method, elements, offset in SEQUENCE:
        settings, system, damping = _system_at(config, method, elements, offset)
        k, m = system.matrices(dense=True)
        nd = system.platform_dofs
        chain = _history(ChainNewmark(system, damping, settings.dt_s), system.dofs, nd, 200)
        dense = _history(Newmark(k, m, damping, settings.dt_s), system.dofs, nd, 200)
        assert np.abs(dense).max() > 0
        assert np.abs(chain - dense).max() <= 1e-8 * np.abs(dense).max()


@pytest.mark.parametrize('dt_s, mass_factor, stiffness_factor', [
    (1e-3, 0.05, 0.05), (2e-3, 0.05, 0.05), (1e-3, 0.0, 0.01), (1e-3, 0.3, 0.0)])
def test_step_maps_are_the_newmark_formulas_for_their_own_numbers(dt_s, mass_factor,
                                                                  stiffness_factor):
    """E and L of Eqs. 47-49 from a0..a7 and dM, dK written out here; a cached pair is the
    one of the same numbers (read-only), another dt or damping gets its own."""
    settings, system, _ = _system_at(PAPER, 'fem', 4)
    damping = Damping(mass_factor, stiffness_factor)
    chain = ChainNewmark(system, damping, dt_s)
    beta, alpha, dt = 0.25, 0.5, dt_s
    a0, a1, a2 = 1 / (beta * dt * dt), alpha / (beta * dt), 1 / (beta * dt)
    a3, a4, a5 = 1 / (2 * beta) - 1, alpha / beta - 1, dt / 2 * (alpha / beta - 2)
    a6, a7 = dt * (1 - alpha), alpha * dt
    dm, dk = mass_factor, stiffness_factor
    expected_e = [[a0 + dm * a1, a2 + dm * a4, a3 + dm * a5], [dk * a1, dk * a4, dk * a5],
                  [-a0, -a2, -a3], [0.0, 1.0, a6]]
    expected_l = [[1.0, 0.0, 0.0], [a7 * a0, a7, 1.0], [a0, 1.0, 0.0]]
    assert np.allclose(chain._state_map, expected_e, rtol=1e-15, atol=0)
    assert np.allclose(chain._update, expected_l, rtol=1e-15, atol=0)
    assert not chain._state_map.flags.writeable
    assert _step_maps(chain.a, dm, dk)[0] is chain._state_map
    other = ChainNewmark(system, Damping(dm + 0.01, dk), dt_s)
    assert not np.array_equal(other._state_map, chain._state_map)


def _consistent_mass(mu: float, l0: float, n: int):
    """Block-tridiagonal consistent mass over the free nodes of a chain of n elements (anchor
    fixed), assembled element by element: (diag (n, 3, 3), off (n - 1, 3, 3))."""
    full = np.zeros((3 * (n + 1), 3 * (n + 1)))
    element = mu * l0 / 6.0 * np.kron([[2.0, 1.0], [1.0, 2.0]], np.eye(3))
    for e in range(n):
        full[3 * e:3 * e + 6, 3 * e:3 * e + 6] += element
    free = full[3:, 3:]
    diag = np.array([free[3 * j:3 * j + 3, 3 * j:3 * j + 3] for j in range(n)])
    off = np.array([free[3 * j:3 * j + 3, 3 * j + 3:3 * j + 6] for j in range(n - 1)])
    return diag, off


@pytest.mark.parametrize('config, n', [(PAPER, 3), (PAPER, 16), (HEAVY, 5), (HEAVY, 3),
                                       (LOW, 16)])
def test_fem_sag_mass_and_elements_from_the_per_n_shapes(config, n):
    """Mass blocks mu l0/6 [2I I; I 2I] assembled here for each cable (n, mu and l0 changing
    between cases, the shapes cached per n); the end stiffness's element data, made on its
    first call, is sag_chains'; the node fractions those of node_positions."""
    settings = load_settings(config).replace(method='fem_sag', elements_per_cable=n)
    eq = equilibrium(settings, method='fem_sag')
    blocks, elements, state = fem_sag.sag_chains(eq.cables, n)
    mu = eq.cables.mass_per_length_kg_m
    for c, l0_total in enumerate(state.unstrained_length_m):
        diag, off = _consistent_mass(mu, l0_total / n, n)
        assert np.allclose(blocks.m_diag[c], diag, rtol=1e-15, atol=0)
        assert np.allclose(blocks.m_off[c], off, rtol=1e-15, atol=0)
    assembly = fem_sag.build(eq.cables, n)
    lam = np.array([0.0, 400.0, 9e4])
    reference = fem_sag.series_end_stiffness(*elements, lam)
    assert np.array_equal(assembly.end_stiffness(lam), reference.astype(complex))
    points = fem_sag.node_positions(state, eq.cables, n)
    assert np.allclose(points[:, -1], 0.0, atol=1e-12)      # point n: the platform end


def test_mass_per_length_follows_gravity_and_weight():
    """weight / |g| (numpy's norm) for each CableSet: a new gravity or weight, a new value;
    no gravity, 0."""
    chord = np.array([[1.0, 0.0, 1.0]])
    for gravity, weight in (([0.0, 0.0, -9.81], 0.251), ([0.0, -3.0, -4.0], 0.251),
                            ([0.0, -3.0, -4.0], 2.0), ([0.0, 0.0, 0.0], 2.0)):
        cables = CableSet(chord, np.array([100.0]), 1e6, weight, np.array(gravity))
        g = np.linalg.norm(gravity)
        assert cables.mass_per_length_kg_m == (weight / g if g > 0 else 0.0)
