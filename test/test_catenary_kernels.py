"""The in-plane catenary kernels against the 3D formulas they replace.

The solve, the tension sensitivity, the stiffness and fem_sag's chains work in each cable's
vertical plane with closed-form eliminations (``catenary`` module docstring, "In the plane").
Here they are checked against the 3D references computed independently: the dense 4x4 Newton
system of ``_jacobian`` solved by numpy, ``inv(flexibility)``, the closure of the 3D Eq. 25,
and the chain blocks assembled from 3D node positions of ``end_position``.
"""
import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.models import catenary, fem_sag
from cdpr_dynamics.models.base import CableSet

G = np.array([0.0, 0.0, -9.81])
UP = np.array([0.0, 0.0, 1.0])


def cable_sets():
    """Paper-like, heavy and tilted-gravity cables, a vertical chord among them."""
    rng = np.random.default_rng(3)
    chords = rng.normal(size=(7, 3)) * [1.5, 1.5, 1.0]
    chords[0] = [0.0, 0.0, 1.7]                  # vertical, anchor above
    chords[1] = [0.0, 0.0, -1.2]                 # vertical, anchor below
    chords[2] = [2.0, 0.5, 0.0]                  # level
    tension = np.array([40.0, 30.0, 25.0, 60.0, 45.0, 80.0, 35.0])
    tilted = np.array([0.3, -0.4, -np.sqrt(0.75)]) * 9.81
    return [CableSet(chords, tension, 1e6, 0.251, G),
            CableSet(chords, tension, 1e5, 7.5, G),
            CableSet(chords, tension, 1e6, 3.0, tilted)]


@pytest.mark.parametrize('k', range(3))
def test_solve_closes_the_3d_catenary(k):
    """Every valid solution closes Eq. 25 in 3D on its chord with |F| = T."""
    cables = cable_sets()[k]
    state = catenary.solve(cables)
    assert state.valid.sum() >= 5
    up, gamma = catenary.up_and_weight(cables)
    ok = state.valid
    end = catenary.end_position(state.force_n[ok], state.unstrained_length_m[ok], cables.ea_n,
                                gamma, up)
    assert_allclose(end, -cables.chord_m[ok], rtol=0, atol=1e-12)
    assert_allclose(np.linalg.norm(state.force_n[ok], axis=1), cables.tension_n[ok], rtol=1e-13)


@pytest.mark.parametrize('k', range(3))
def test_in_plane_newton_step_equals_the_dense_4x4_solve(k):
    """_newton_step at a perturbed state equals numpy's solve of the 3D Jacobian system."""
    cables = cable_sets()[k]
    planes = catenary._planes(cables)
    state = catenary.solve(cables)
    ok = state.valid
    f_h, f_v = catenary._in_plane(state.force_n, planes)
    x = np.array([1.01 * f_h, 0.98 * f_v + 0.3, 1.0005 * state.unstrained_length_m])[:, ok]
    sub = CableSet(cables.chord_m[ok], cables.tension_n[ok], cables.ea_n,
                   cables.weight_per_length_n_per_m, cables.gravity_m_s2)
    sub_planes = catenary._planes(sub)
    t_inv = 1.0 / sub.tension_n
    with np.errstate(all='ignore'):     # the private kernels leave warnings to their callers
        res, parts = catenary._residual(x, sub_planes, t_inv, sub.length_m)
        step = catenary._newton_step(x, res, sub_planes, sub.length_m * t_inv, parts)
    up, gamma = catenary.up_and_weight(sub)
    force = catenary._lift(x[0], x[1], sub_planes)
    jac = catenary._jacobian(force, x[2], sub.ea_n, gamma, up, sub.length_m * t_inv)
    closure = catenary.end_position(force, x[2], sub.ea_n, gamma, up) + sub.chord_m
    res3 = np.concatenate([closure, res[2][:, None]], axis=1)
    assert_allclose(res[:2].T, np.stack([np.sum(closure * sub_planes.horizontal, axis=1),
                                         closure @ up], axis=1), rtol=1e-9, atol=1e-14)
    dense = np.linalg.solve(jac, -res3[..., None])[..., 0]
    lifted = np.concatenate([catenary._lift(step[0], step[1], sub_planes), step[2][:, None]],
                            axis=1)
    scale = np.abs(dense).max(axis=1, keepdims=True)
    assert_allclose(lifted, dense, rtol=0, atol=1e-9 * scale.max())
    assert_allclose(lifted / scale, dense / scale, rtol=0, atol=1e-8)


@pytest.mark.parametrize('k', range(3))
def test_tension_sensitivity_equals_the_dense_4x4_solve(k):
    cables = cable_sets()[k]
    state = catenary.solve(cables)
    d_force, d_length = catenary.tension_sensitivity(state, cables)
    up, gamma = catenary.up_and_weight(cables)
    ok = state.valid
    jac = catenary._jacobian(state.force_n[ok], state.unstrained_length_m[ok], cables.ea_n,
                             gamma, up, np.ones(ok.sum()))
    rhs = np.zeros((ok.sum(), 4, 1))
    rhs[:, 3] = 1.0
    dense = np.linalg.solve(jac, rhs)[..., 0]
    assert_allclose(d_force[ok], dense[:, :3], rtol=1e-9, atol=1e-12)
    assert_allclose(d_length[ok], dense[:, 3], rtol=1e-9, atol=1e-15)
    assert np.all(np.isnan(d_force[~ok])) and np.all(np.isnan(d_length[~ok]))


@pytest.mark.parametrize('method', ['catenary', 'catenary_exact'])
@pytest.mark.parametrize('k', range(3))
def test_stiffness_equals_the_inverse_of_the_3d_flexibility(method, k):
    cables = cable_sets()[k]
    up, gamma = catenary.up_and_weight(cables)
    if method == 'catenary':
        assembly = catenary.build(cables)
        force, l0 = -cables.tension_n[:, None] * cables.unit, cables.length_m
    else:
        assembly = catenary.build_exact(cables)
        force, l0 = -assembly.end_force_n, catenary.solve(cables).unstrained_length_m
    stiffness = assembly.constant_stiffness
    reference = np.linalg.inv(catenary.flexibility(force, l0, cables.ea_n, gamma, up))
    invalid = {int(w.split()[1].rstrip(':')) for w in assembly.warnings}
    for i in range(cables.n_cables):
        if i in invalid:
            continue
        scale = np.abs(reference[i]).max()
        assert_allclose(stiffness[i], reference[i], rtol=0, atol=1e-11 * scale)
        assert_allclose(stiffness[i], stiffness[i].T, rtol=0, atol=1e-14 * scale)


def test_warm_start_out_of_the_plane_gives_the_cold_solution():
    """A start whose force leaves the chord's plane (another pose's) ends at the same root."""
    cables = cable_sets()[0]
    cold = catenary.solve(cables)
    tilt = np.cross(cables.unit, UP) * 3.0                 # normal to each plane
    start = cold._replace(force_n=cold.force_n * 1.02 + tilt,
                          unstrained_length_m=cold.unstrained_length_m * 1.0003)
    warm = catenary.solve(cables, start=start)
    assert np.array_equal(warm.valid, cold.valid)
    ok = cold.valid
    assert_allclose(warm.force_n[ok], cold.force_n[ok], rtol=0, atol=1e-10)
    assert_allclose(warm.unstrained_length_m[ok], cold.unstrained_length_m[ok], rtol=1e-13)


def test_planes_are_kept_by_value_not_by_array():
    """Changing a chord array in place gives new planes, never stale ones."""
    chord = np.array([[1.0, 0.5, 1.2], [-1.0, 0.3, 0.8]])
    cables = CableSet(chord, np.array([50.0, 60.0]), 1e6, 0.251, G)
    first = catenary.solve(cables).force_n.copy()
    chord[0] = [0.4, -1.0, 1.5]
    moved = CableSet(chord, np.array([50.0, 60.0]), 1e6, 0.251, G)
    second = catenary.solve(moved)
    up, gamma = catenary.up_and_weight(moved)
    end = catenary.end_position(second.force_n, second.unstrained_length_m, 1e6, gamma, up)
    assert_allclose(end, -chord, atol=1e-12)
    assert not np.allclose(first[0], second.force_n[0])


@pytest.mark.parametrize('config', ['config/paper_cdpr.yaml', 'config/heavy_sag_6dof.yaml'])
def test_sag_chains_equal_the_3d_assembly(config):
    """fem_sag's chain blocks (built in the cables' planes) against the 3D construction from
    end_position's node positions: K_e = EA/l0 e e^T + T_e/l_e (I - e e^T)."""
    from cdpr_dynamics.analysis.pipeline import equilibrium
    s = load_settings(config)
    eq = equilibrium(s, method='fem_sag')
    n = 8
    blocks, elements, state = fem_sag.sag_chains(eq.cables, n)
    up, gamma = catenary.up_and_weight(eq.cables)
    sigma = state.unstrained_length_m[:, None] * (n - np.arange(n + 1))[None, :] / n
    force = np.broadcast_to(state.force_n[:, None, :], sigma.shape + (3,))
    points = -catenary.end_position(force, sigma, eq.cables.ea_n, gamma, up)
    assert_allclose(fem_sag.node_positions(state, eq.cables, n), points, rtol=0, atol=1e-13)
    d = np.diff(points, axis=1)
    length = np.linalg.norm(d, axis=2)
    e = d / length[..., None]
    l0 = state.unstrained_length_m / n
    sigma_mid = l0[:, None] * (n - 0.5 - np.arange(n))[None, :]
    t_mid = np.linalg.norm(state.force_n[:, None, :] - gamma * sigma_mid[..., None] * up, axis=2)
    ee = e[..., :, None] * e[..., None, :]
    ke = (eq.cables.ea_n / l0)[:, None, None, None] * ee \
        + (t_mid / length)[..., None, None] * (np.eye(3) - ee)
    scale = np.abs(ke).max()
    assert_allclose(blocks.k_off, -ke[:, 1:], rtol=0, atol=1e-12 * scale)
    assert_allclose(blocks.k_diag[:, -1], ke[:, -1], rtol=0, atol=1e-12 * scale)
    assert_allclose(blocks.k_diag[:, :-1], ke[:, :-1] + ke[:, 1:], rtol=0, atol=1e-12 * scale)
    assert_allclose(elements[2], (t_mid / length).T, rtol=1e-12)
    assert_allclose(elements[0][1], ee[..., 0, 1].T, rtol=0, atol=1e-14)


# --------------------------------------------------------------------- the explicit existence

def random_cables(rng, n, ratio_low, ratio_high, length_low=0.1):
    """n chords of random direction (vertical both ways among them) and length, end tensions
    T = ratio gamma L with ratio log-uniform in [ratio_low, ratio_high], EA from 1.6 to 1e12 T."""
    d = rng.normal(size=(n, 3))
    d[:6] = [[0, 0, 1], [0, 0, -1], [1e-9, 0, 1], [1e-9, 0, -1], [1e-3, 0, 1], [1e-3, 0, -1]]
    d /= np.linalg.norm(d, axis=1)[:, None]
    length = length_low * 10 ** rng.uniform(0.0, 3.0, n)
    gamma = 10 ** rng.uniform(-2, 1)
    ratio = ratio_low * (ratio_high / ratio_low) ** rng.uniform(0.0, 1.0, n)
    ratio[rng.random(n) < 0.3] = ratio_low
    tension = ratio * gamma * length
    ea = float(tension.max() * 10 ** rng.uniform(0.2, 12.0))
    return CableSet(d * length[:, None], tension, ea, gamma, G)


def solved_verdict(cables):
    return catenary.solve(cables, tolerance=catenary.EXISTENCE_TOLERANCE).valid


@pytest.mark.slow
def test_explicit_existence_is_the_solves_verdict():
    """Where T >= 2 gamma L and L >= 0.1 m the solve finds every catenary (so the explicit test
    may skip it); elsewhere exists() is the solve's verdict, found or not."""
    rng = np.random.default_rng(11)
    for _ in range(16):                                # gamma and EA per set
        sure = random_cables(rng, 500, catenary.EXPLICIT_EXISTENCE_RATIO, 1e5)
        assert solved_verdict(sure).all()
        assert catenary.exists(sure).all()
    found = missing = 0
    for _ in range(6):
        mixed = random_cables(rng, 200, 0.3, 5.0, length_low=0.01)
        verdict = solved_verdict(mixed)
        assert np.array_equal(catenary.exists(mixed), verdict)
        found, missing = found + verdict.sum(), missing + (~verdict).sum()
    assert found > 200 and missing > 200          # both verdicts are exercised


def test_least_spanning_tension_is_well_below_the_explicit_bound():
    """The least end tension at which a catenary spans a chord (statics.lowest_tension) is at
    most ~1.05 gamma L over all inclinations (the bound the explicit test relies on)."""
    from cdpr_dynamics.mechanics.statics import lowest_tension
    angle = np.radians(np.linspace(-90.0, 90.0, 37))
    chords = np.column_stack([np.cos(angle), 0.0 * angle, np.sin(angle)]) * 5.0
    for ea in (1e3, 1e8):
        cables = CableSet(chords, np.full(angle.size, 1e-3), ea, 1.0, G)
        least = lowest_tension(cables, np.ones(angle.size, dtype=bool), 1e4) / 5.0
        assert least.max() < 1.06 and least.max() > 1.0
        assert least[angle.size // 2] == pytest.approx(0.7544, abs=2e-3)   # level: u tanh u = 1


@pytest.mark.parametrize('config', ['config/paper_cdpr.yaml', 'test/data/rigid_cdpr.yaml',
                                    'config/heavy_sag_6dof.yaml',
                                    'config/low_tension_cdpr.yaml'])
def test_paper_catenary_is_the_one_with_the_solved_existence(config, monkeypatch):
    """catenary.build with the explicit existence test gives the stiffness, forces, validity and
    warnings of the build that solves every existence, over random poses and tensions."""
    from cdpr_dynamics.analysis.pipeline import equilibrium
    s = load_settings(config)
    rng = np.random.default_rng(2)
    sets = []
    for _ in range(24):
        try:
            eq = equilibrium(s, s.initial_position_m + rng.uniform(-0.3, 0.3, 3))
        except Exception:
            continue
        scale = rng.choice([1.0, 0.05, 0.01, -1.0], size=eq.cables.n_cables, p=[.7, .1, .1, .1])
        sets += [eq.cables, eq.cables.with_tension(eq.cables.tension_n * scale)]
    assert len(sets) > 24
    fast = [catenary.build(c) for c in sets]
    monkeypatch.setattr(catenary, 'exists', solved_verdict)
    slow = [catenary.build(c) for c in sets]
    assert sum(not a.valid for a in slow) > 2
    for a, b in zip(fast, slow):
        assert a.valid == b.valid and a.warnings == b.warnings
        assert np.array_equal(a.static_end_stiffness(), b.static_end_stiffness())
        assert np.array_equal(a.end_force_n, b.end_force_n)


def test_paper_misclosure_is_the_3d_closure():
    """paper_misclosure against Eq. 25 in 3D at L0 = chord, F = -T u (the paper's catenary)."""
    for cables in cable_sets():
        up, gamma = catenary.up_and_weight(cables)
        end = catenary.end_position(-cables.tension_n[:, None] * cables.unit, cables.length_m,
                                    cables.ea_n, gamma, up)
        assert_allclose(catenary.paper_misclosure(cables),
                        np.linalg.norm(end + cables.chord_m, axis=1), rtol=1e-9, atol=1e-14)


def test_paper_robot_catenary_needs_no_solve(monkeypatch):
    """The paper robot's cables (T >= 170 gamma L) pass the explicit test: no Newton solve."""
    from cdpr_dynamics.analysis.pipeline import equilibrium
    eq = equilibrium(load_settings('config/paper_cdpr.yaml'))

    def no_solve(*args, **kwargs):
        raise AssertionError('solved')
    monkeypatch.setattr(catenary, 'solve', no_solve)
    assert catenary.build(eq.cables).valid
    with pytest.raises(AssertionError, match='solved'):
        catenary.build(eq.cables.with_tension(eq.cables.tension_n * 0.001))
