"""Tension distribution (Eqs. 10-12) against KKT conditions, a closed form and other solvers."""
import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.optimize import linprog, lsq_linear

from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.mechanics.robot import Robot, geometry, required_wrench
from cdpr_dynamics.mechanics.tensions import (TensionSolver, below_text, closest_tensions,
                                              solve_tensions, solve_tensions_qpsolvers)

T_MIN, T_MAX = 100.0, 1000.0
TOL = 1e-4       # N (and N m): TensionSolver's default tolerance for T_max = 1000 N
ACTIVE = 1e-5    # N: a tension this close to a bound counts as on it (solver: ~1e-7 N)
CENTRE = np.array([0.0, 0.0, 1.25])


@pytest.fixture(scope='module')
def paper():
    return load_settings().robot


@pytest.fixture(scope='module')
def rigid():
    """6-DOF platform: a 0.2 m cube, the paper's anchors, crossed cables. The upper cables
    attach to bottom corners mirrored in y, the lower ones to top corners: rank 6 at the centre
    and wrench-feasible for gravity over the central workspace."""
    anchors = load_settings().robot.anchors_m
    s = np.sign(anchors - CENTRE)
    upper = s[:, 2:] > 0
    attachments = 0.1 * s * np.where(upper, [1.0, -1.0, -1.0], [1.0, 1.0, -1.0])
    return Robot('world', anchors, attachments, 30.0, np.eye(3), np.array([0.0, 0.0, -9.81]))


def kkt(wt, w, tension, weights=None, linear=None):
    """Multipliers of the QP at ``tension`` by least squares on the active set.

    Solves C T + c = W lambda + mu_low - mu_up with mu only on cables at a bound; returns the
    stationarity residual (N), lambda, mu_low and mu_up (zero off the active set, so
    complementarity holds by construction and the test is on residual and signs).
    """
    n = wt.shape[1]
    c_mat = np.eye(n) if weights is None else np.asarray(weights, dtype=float)
    c_mat = np.diag(c_mat) if c_mat.ndim == 1 else c_mat
    c_vec = np.zeros(n) if linear is None else np.asarray(linear, dtype=float)
    low = tension <= T_MIN + ACTIVE
    up = tension >= T_MAX - ACTIVE
    eye = np.eye(n)
    basis = np.hstack([wt.T, eye[:, low], -eye[:, up]])
    grad = c_mat @ tension + c_vec
    coef = np.linalg.lstsq(basis, grad, rcond=None)[0]
    ndof = wt.shape[0]
    mu_low, mu_up = np.zeros(n), np.zeros(n)
    mu_low[low] = coef[ndof:ndof + low.sum()]
    mu_up[up] = coef[ndof + low.sum():]
    return basis @ coef - grad, coef[:ndof], mu_low, mu_up


def assert_kkt(wt, w, tension, weights=None, linear=None):
    stationarity, _, mu_low, mu_up = kkt(wt, w, tension, weights, linear)
    assert_allclose(stationarity, 0.0, atol=1e-6)
    assert mu_low.min() >= -1e-5 and mu_up.min() >= -1e-5
    assert_allclose(wt @ tension, w, atol=TOL)                   # primal feasibility
    assert tension.min() >= T_MIN - TOL and tension.max() <= T_MAX + TOL


def random_poses(seed, count, half=(0.6, 0.6, 0.6)):
    rng = np.random.default_rng(seed)
    return CENTRE + rng.uniform(-1.0, 1.0, size=(count, 3)) * half


def weight_case(name, n, seed=3):
    rng = np.random.default_rng(seed)
    if name == 'identity':
        return None, None
    if name == 'diagonal':
        return rng.uniform(0.5, 2.0, n), None
    if name == 'full':
        a = rng.normal(size=(n, n))
        return a @ a.T + n * np.eye(n), rng.normal(scale=50.0, size=n)
    if name == 'linear':
        return None, rng.normal(scale=100.0, size=n)
    raise ValueError(name)


# ---------------------------------------------------------------------------- optimality


@pytest.mark.parametrize('weights_name', ['identity', 'diagonal', 'full', 'linear'])
@pytest.mark.parametrize('platform', ['paper', 'rigid'])
def test_kkt_conditions_hold_at_the_solution(platform, weights_name, request):
    robot = request.getfixturevalue(platform)
    weights, linear = weight_case(weights_name, robot.n_cables)
    w = required_wrench(robot, [20.0, -10.0, 5.0], [1.0, 0.0, -2.0])
    solver = TensionSolver(robot.n_cables, robot.platform_dofs, T_MIN, T_MAX, weights, linear)
    for pose in random_poses(1, 6, half=(0.4, 0.4, 0.4)):
        wt = geometry(robot, pose).structure_matrix
        result = solver.solve(wt, w)
        assert result.feasible, result.reason
        assert result.status == 'solved' and result.reason == ''
        assert_kkt(wt, w, result.tension_n, weights, linear)


def test_kkt_check_rejects_a_feasible_point_that_is_not_optimal(paper):
    """The KKT test above would catch a wrong answer: move the optimum along the null space of
    W^T on the free cables; it stays feasible but stationarity fails."""
    wt = geometry(paper, [0.2, -0.1, 1.0]).structure_matrix
    w = required_wrench(paper)
    tension = solve_tensions(wt, w, T_MIN, T_MAX).tension_n
    free = (tension > T_MIN + 1.0) & (tension < T_MAX - 1.0)
    null = np.linalg.svd(wt[:, free])[2][-1]
    moved = tension.copy()
    moved[free] += 1.0 * null
    assert_allclose(wt @ moved, w, atol=1e-9)
    stationarity = kkt(wt, w, moved)[0]
    assert np.abs(stationarity).max() > 0.1


# ---------------------------------------------------------------------------- closed form


@pytest.mark.parametrize('external_fz_n', [0.0, -500.0, 150.0])
def test_symmetric_paper_robot_matches_the_closed_form(paper, external_fz_n):
    """At the centre every u_i has vertical component +-1/sqrt(3). With C = I the four lower
    cables (anchors at z = 0) pull down and sit at T_min; the four upper ones share the load
    equally: 4 (T_up - T_min) / sqrt(3) = w_z, so T_up = T_min + w_z sqrt(3) / 4, where
    w_z = m g - f_z (for f_z = 0: 100 + 30 * 9.81 * sqrt(3) / 4 = 227.4356 N)."""
    wt = geometry(paper, CENTRE).structure_matrix
    assert_allclose(np.abs(wt[2]), 1.0 / np.sqrt(3.0), rtol=1e-12)
    w = required_wrench(paper, [0.0, 0.0, external_fz_n])
    w_z = paper.mass_kg * 9.81 - external_fz_n
    assert_allclose(w, [0.0, 0.0, w_z], atol=1e-12)
    result = solve_tensions(wt, w, T_MIN, T_MAX)
    assert result.feasible, result.reason
    upper = T_MIN + w_z * np.sqrt(3.0) / 4.0
    lower_cables = paper.anchors_m[:, 2] == 0.0
    assert lower_cables.sum() == 4
    expected = np.where(lower_cables, T_MIN, upper)
    assert_allclose(result.tension_n, expected, rtol=0, atol=1e-6)
    if external_fz_n == 0.0:
        assert_allclose(upper, 227.43563817, atol=1e-8)
    # multipliers of the closed form: lambda_z = sqrt(3) (T_up), mu_low = T_min + T_up - T_min
    _, lam, mu_low, mu_up = kkt(wt, w, result.tension_n)
    assert_allclose(lam, [0.0, 0.0, np.sqrt(3.0) * upper], atol=1e-5)
    assert_allclose(mu_low, np.where(lower_cables, T_MIN + upper, 0.0), atol=1e-5)
    assert_allclose(mu_up, 0.0, atol=1e-12)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_renumbering_the_cables_renumbers_the_tensions(paper, seed):
    wt = geometry(paper, [0.3, 0.1, 1.6]).structure_matrix
    w = required_wrench(paper, [30.0, 0.0, 0.0])
    order = np.random.default_rng(seed).permutation(paper.n_cables)
    direct = solve_tensions(wt, w, T_MIN, T_MAX).tension_n
    swapped = solve_tensions(wt[:, order], w, T_MIN, T_MAX).tension_n
    assert_allclose(swapped, direct[order], atol=1e-6)


# ---------------------------------------------------------------------------- equilibrium


def lp_feasible(wt, w, t_min=T_MIN, t_max=T_MAX) -> bool:
    """Independent oracle: does W^T T = w have a solution in the box? (scipy HiGHS LP)."""
    lp = linprog(np.zeros(wt.shape[1]), A_eq=wt, b_eq=w, bounds=[(t_min, t_max)] * wt.shape[1])
    assert lp.status in (0, 2), lp.message
    return lp.status == 0


@pytest.mark.parametrize('platform, seed', [('paper', 10), ('paper', 11), ('rigid', 12),
                                            ('rigid', 13)])
def test_cable_wrench_balances_the_load_at_random_poses(platform, seed, request):
    """Over random poses and loads: feasible exactly where an LP says so, and there
    W^T T = w holds and the tensions stay in the box."""
    robot = request.getfixturevalue(platform)
    rng = np.random.default_rng(seed)
    solver = TensionSolver(robot.n_cables, robot.platform_dofs, T_MIN, T_MAX)
    feasible_count = 0
    for pose in random_poses(seed, 12, half=(0.6, 0.6, 0.6)):
        w = required_wrench(robot, rng.normal(scale=20.0, size=3), rng.normal(scale=1.0, size=3))
        wt = geometry(robot, pose).structure_matrix
        assert wt.shape == (robot.platform_dofs, robot.n_cables)
        result = solver.solve(wt, w)
        assert result.feasible == lp_feasible(wt, w), result.reason
        assert result.tension_n.min() >= T_MIN and result.tension_n.max() <= T_MAX
        if result.feasible:
            feasible_count += 1
            assert result.residual_n <= result.tolerance_n == pytest.approx(TOL)
            assert_allclose(wt @ result.tension_n, w, atol=1e-6)
        else:
            assert result.status == 'infeasible' and result.residual_n > TOL
    assert feasible_count >= 6


def test_rigid_platform_gravity_needs_no_moment_only_forces(rigid):
    """A 6-DOF check with an independent reading: the tensions' net moment about the centroid
    vanishes and their net force carries m g exactly, rebuilt from u_i and r_i directly."""
    g = geometry(rigid, [0.1, -0.2, 1.1])
    result = solve_tensions(g.structure_matrix, required_wrench(rigid), T_MIN, T_MAX)
    assert result.feasible, result.reason
    forces = result.tension_n[:, None] * g.unit
    assert_allclose(forces.sum(axis=0), [0.0, 0.0, 30.0 * 9.81], atol=1e-6)
    assert_allclose(np.cross(g.lever_m, forces).sum(axis=0), 0.0, atol=1e-6)


# ---------------------------------------------------------------------------- cross-checks


@pytest.mark.parametrize('platform, seed, weights_name', [
    ('paper', 20, 'identity'), ('paper', 21, 'full'), ('rigid', 22, 'identity'),
    ('rigid', 23, 'diagonal')])
def test_agrees_with_qpsolvers(platform, seed, weights_name, request):
    robot = request.getfixturevalue(platform)
    weights, linear = weight_case(weights_name, robot.n_cables, seed)
    w = required_wrench(robot, [10.0, 20.0, -30.0], [0.5, -0.5, 0.0])
    for pose in random_poses(seed, 4, half=(0.4, 0.4, 0.4)):
        wt = geometry(robot, pose).structure_matrix
        ours = solve_tensions(wt, w, T_MIN, T_MAX, weights, linear)
        theirs = solve_tensions_qpsolvers(wt, w, T_MIN, T_MAX, weights, linear)
        assert ours.feasible and theirs.feasible, (ours.reason, theirs.reason)
        assert_allclose(ours.tension_n, theirs.tension_n, rtol=0, atol=1e-6)


@pytest.mark.parametrize('wrench', [[2000.0, 0.0, 294.3], [300.0, -900.0, 50.0],
                                    [1e5, 0.0, 294.3], [0.0, 0.0, 294.3]])
def test_closest_tensions_match_scipy_bounded_least_squares(paper, wrench):
    wt = geometry(paper, [0.2, 0.3, 0.9]).structure_matrix
    ours = closest_tensions(wt, wrench, T_MIN, T_MAX)
    ref = lsq_linear(wt, np.asarray(wrench), bounds=(T_MIN, T_MAX), tol=1e-12)
    assert ours.min() >= T_MIN and ours.max() <= T_MAX
    assert_allclose(np.linalg.norm(wt @ ours - wrench), np.linalg.norm(ref.fun),
                    rtol=1e-6, atol=1e-6)


# ---------------------------------------------------------------------------- warm start


@pytest.mark.parametrize('platform', ['paper', 'rigid'])
def test_warm_start_gives_the_cold_answers_in_no_more_iterations(platform, request):
    robot = request.getfixturevalue(platform)
    w = required_wrench(robot, [15.0, 0.0, 0.0])
    steps = np.linspace(0.0, 1.0, 40)
    path = CENTRE + np.stack([0.4 * np.sin(2 * np.pi * steps), 0.3 * steps,
                              -0.3 * np.cos(np.pi * steps)], axis=1)
    warm = TensionSolver(robot.n_cables, robot.platform_dofs, T_MIN, T_MAX)
    warm_total = cold_total = 0
    for k, pose in enumerate(path):
        wt = geometry(robot, pose).structure_matrix
        a = warm.solve(wt, w)
        b = solve_tensions(wt, w, T_MIN, T_MAX)
        assert a.feasible and b.feasible, (a.reason, b.reason)
        assert_allclose(a.tension_n, b.tension_n, rtol=0, atol=1e-6)
        if k > 0:
            assert a.iterations <= b.iterations
        warm_total += a.iterations
        cold_total += b.iterations
    assert warm_total < cold_total


def test_equal_inputs_give_equal_tensions_bit_for_bit():
    """Node, replay and tools each build their own solver: fed the same structure matrices,
    every fresh solver answers with the same bits, also where the answer comes from a
    warm-started proxsuite QP, whose own last bits differ from one QP object to another
    (~1e-13 N here: the paper robot from its centre to 0.9 m sideways, tensions 100-1000 N)."""
    settings = load_settings()
    w = required_wrench(settings.robot)
    path = [geometry(settings.robot, p).structure_matrix
            for p in (settings.initial_position_m, [0.9005, 0.0, 1.25], [-0.4, 0.6, 0.8])]
    runs = set()
    held = []
    for k in range(12):
        held.append(np.empty(1 + 37 * k))                  # other addresses for each solver
        solver = TensionSolver(settings.robot.n_cables, settings.robot.platform_dofs, 100.0,
                               1000.0)
        answers = [solver.solve(wt, w) for wt in path]
        assert all(a.feasible for a in answers) and answers[1].iterations > 0   # proxsuite's
        runs.add(b''.join(a.tension_n.tobytes() for a in answers))
    assert len(runs) == 1


def test_solver_recovers_after_failures(paper):
    """An infeasible or non-finite request drops the warm start; the next answer is exact."""
    wt = geometry(paper, CENTRE).structure_matrix
    w = required_wrench(paper)
    solver = TensionSolver(8, 3, T_MIN, T_MAX)
    expected = solve_tensions(wt, w, T_MIN, T_MAX).tension_n
    for bad_wt, bad_w in [(wt, [2000.0, 0.0, 294.3]), (wt, [np.nan, 0.0, 0.0]),
                          (np.full_like(wt, np.inf), w)]:
        assert not solver.solve(bad_wt, bad_w).feasible
        again = solver.solve(wt, w)
        assert again.feasible
        assert_allclose(again.tension_n, expected, atol=1e-6)


# ---------------------------------------------------------------------------- failures


def test_sideways_wrench_is_infeasible_with_a_readable_reason(paper):
    wt = geometry(paper, CENTRE).structure_matrix
    result = solve_tensions(wt, [1e5, 0.0, 294.3], T_MIN, T_MAX)
    assert (result.status, result.feasible) == ('infeasible', False)
    assert result.reason.startswith('wrench [1e+05, 0, 294.3] N outside the feasible set for '
                                    'tensions in [100, 1000] N')
    assert 'force x' in result.reason and '\n' not in result.reason
    # best effort: the box tensions closest to the wrench, all cables pulling +x at T_max
    pulls_x = wt[0] > 0
    assert_allclose(result.tension_n, np.where(pulls_x, T_MAX, T_MIN), atol=1e-6)
    assert_allclose(result.residual_n, 1e5 - 4 * 900 / np.sqrt(3), rtol=1e-9)


def test_weight_above_what_the_cables_can_carry_is_infeasible(paper):
    """T_max = 120 N: the four upper cables lift at most 4 (120 - 100) / sqrt(3) = 46 N."""
    wt = geometry(paper, CENTRE).structure_matrix
    result = solve_tensions(wt, required_wrench(paper), T_MIN, 120.0)
    assert not result.feasible and result.status == 'infeasible'
    assert 'force z 294.3 is outside the reachable [-46.19, 46.19]' in result.reason
    assert 'tensions in [100, 120] N' in result.reason


@pytest.mark.parametrize('margin_n, feasible', [(-1e-2, True), (-1.0, True), (1e-2, False),
                                                (1.0, False), (50.0, False)])
def test_edge_of_the_wrench_feasible_set_is_found_exactly(paper, margin_n, feasible):
    """The largest sideways force the paper robot can hold at the centre while carrying its
    weight comes from an LP (scipy); just inside it the QP solves, just outside it is reported
    infeasible although every wrench component alone is reachable (the cheap pre-check
    passes): proxsuite alone never certifies these, the closest-tension test does."""
    wt = geometry(paper, CENTRE).structure_matrix
    w_z = paper.mass_kg * 9.81
    lp = linprog(-wt[0], A_eq=wt[1:], b_eq=[0.0, w_z], bounds=[(T_MIN, T_MAX)] * 8)
    f_max = -lp.fun
    assert 1700.0 < f_max < 1900.0
    result = solve_tensions(wt, [f_max + margin_n, 0.0, w_z], T_MIN, T_MAX)
    assert result.feasible is feasible, result.reason
    if feasible:
        assert_kkt(wt, [f_max + margin_n, 0.0, w_z], result.tension_n)
    else:
        assert result.status == 'infeasible'
        assert 'outside the feasible set' in result.reason and 'closest tensions miss' in \
            result.reason
        assert result.residual_n > 0.5 * margin_n
        assert result.tension_n.min() >= T_MIN and result.tension_n.max() <= T_MAX


def test_rank_deficient_structure_matrix(paper):
    """Coplanar cables (rank 2 in a tilted plane): a wrench in the plane is solved, one with a
    part off the plane is infeasible and the reason names the rank and the direction."""
    rng = np.random.default_rng(5)
    planar = rng.normal(size=(3, 8))
    planar[2] = 0.0
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    wt = rotation @ planar
    in_plane = wt @ rng.uniform(300.0, 700.0, 8)
    ok = solve_tensions(wt, in_plane, T_MIN, T_MAX)
    assert ok.feasible, ok.reason
    assert_kkt(wt, in_plane, ok.tension_n)
    bad = solve_tensions(wt, in_plane + 5.0 * rotation[:, 2], T_MIN, T_MAX)
    assert not bad.feasible and bad.status == 'infeasible'
    assert 'rank 2 < 3' in bad.reason and 'part 5 along' in bad.reason


@pytest.mark.parametrize('where', ['structure_matrix', 'wrench'])
@pytest.mark.parametrize('value', [np.nan, np.inf, -np.inf])
def test_non_finite_input_is_reported_not_raised(paper, where, value):
    wt = geometry(paper, CENTRE).structure_matrix.copy()
    w = required_wrench(paper).copy()
    (wt[1] if where == 'structure_matrix' else w)[1] = value
    result = solve_tensions(wt, w, T_MIN, T_MAX)
    assert (result.status, result.feasible, result.iterations) == ('not_finite', False, 0)
    assert result.reason == f'{where.replace("_", " ")} is not finite'
    assert np.isnan(result.tension_n).all() and result.tension_n.shape == (8,)


@pytest.mark.parametrize('kwargs, message', [
    (dict(t_min_n=500.0, t_max_n=400.0), 'minimum tension 500 N exceeds maximum tension 400 N'),
    (dict(t_max_n=np.nan), 'tension bounds must be finite'),
    (dict(weights=-np.ones(8)), 'positive semi-definite'),
    (dict(weights=np.triu(np.ones((8, 8)))), 'symmetric'),
    (dict(linear=np.ones(3)), 'linear must have shape (8,)'),
    (dict(ndof=4), 'ndof must be 3'),
])
def test_invalid_settings_raise_value_error(kwargs, message):
    args = dict(n_cables=8, ndof=3, t_min_n=T_MIN, t_max_n=T_MAX) | kwargs
    with pytest.raises(ValueError, match=message.replace('(', r'\(').replace(')', r'\)')):
        TensionSolver(**args)


def test_wrong_shapes_raise_value_error(paper):
    solver = TensionSolver(8, 3, T_MIN, T_MAX)
    with pytest.raises(ValueError, match='expected structure matrix'):
        solver.solve(np.ones((6, 8)), np.ones(6))


def test_equal_bounds_pin_every_tension(paper):
    """T_min = T_max leaves one candidate: feasible only if that wrench is the one asked for."""
    wt = geometry(paper, [0.1, 0.2, 1.3]).structure_matrix
    pinned = wt @ np.full(8, 300.0)
    result = solve_tensions(wt, pinned, 300.0, 300.0)
    assert result.feasible, result.reason
    assert_allclose(result.tension_n, 300.0, atol=1e-9)
    assert not solve_tensions(wt, pinned + [0.0, 0.0, 1.0], 300.0, 300.0).feasible


@pytest.mark.parametrize('value, bound, text', [(9.98, 10.0, '9.98'), (6.94, 20.0, '6.9'),
                                                (9.99996, 10.0, '9.99996'), (-0.04, 0.0, '-0.04'),
                                                (99.95001, 100.0, '99.95')])
def test_a_tension_below_its_bound_never_prints_as_the_bound(value, bound, text):
    """'drops to 10.0 N, below tension.min_n' for 9.98 N contradicted itself."""
    assert below_text(value, bound) == text
    assert float(text) < bound
