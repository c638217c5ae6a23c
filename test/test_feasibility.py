"""Wrench-feasible set and cable crossing checks against the tension QP and plain geometry."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdpr_dynamics.analysis.config import (default_config_path, load_settings, read_params_file,
                                           settings_from_params)
from cdpr_dynamics.mechanics.feasibility import WrenchSet, cable_crossing
from cdpr_dynamics.mechanics.robot import geometry, required_wrench
from cdpr_dynamics.mechanics.tensions import TensionSolver


def rigid_settings():
    """The paper's frame with a 0.2 m cube platform: cables to its nearest corners."""
    flat = read_params_file(default_config_path())
    anchors = np.array(flat['robot.anchors']).reshape(-1, 3)
    corners = np.column_stack([np.sign(anchors[:, 0]), np.sign(anchors[:, 1]),
                               np.where(anchors[:, 2] > 1.0, 1.0, -1.0)]) * 0.1
    flat['robot.attachments'] = corners.ravel().tolist()
    flat['robot.inertia_kg_m2'] = [0.2, 0.2, 0.2, 0.0, 0.0, 0.0]
    return settings_from_params(flat)


@pytest.mark.parametrize('rigid', [False, True])
def test_wrench_set_agrees_with_the_tension_qp(rigid):
    settings = rigid_settings() if rigid else load_settings()
    robot = settings.robot
    rng = np.random.default_rng(3)
    d = robot.platform_dofs
    for _ in range(3):
        p = np.array([0.0, 0.0, 1.25]) + rng.uniform(-0.4, 0.4, 3)
        rot = Rotation.from_euler('xyz', rng.uniform(-0.05, 0.05, 3)).as_matrix()
        geo = geometry(robot, p, rot if rigid else None)
        need = required_wrench(robot)
        wset = WrenchSet(geo.structure_matrix, settings.tension_min_n, settings.tension_max_n,
                         need)
        solver = TensionSolver(robot.n_cables, d, settings.tension_min_n, settings.tension_max_n)
        # wrenches the cables can hold (tensions inside the box), pushed out by a factor
        inside = 0
        for _ in range(150):
            t = rng.uniform(settings.tension_min_n, settings.tension_max_n, robot.n_cables)
            cables = geo.structure_matrix @ t
            for scale in (1.0, rng.uniform(1.0, 2.0)):
                ext = np.zeros(6)
                ext[:d] = need - (geo.structure_matrix @ np.full(robot.n_cables, 550.0)
                                  + scale * (cables - geo.structure_matrix
                                             @ np.full(robot.n_cables, 550.0)))
                qp = solver.solve(geo.structure_matrix, need - ext[:d])
                if abs(wset.margin(ext[:3], ext[3:])) < 1e-6 * settings.tension_max_n:
                    continue   # on the boundary: either answer is right
                assert (wset.reason(ext[:3], ext[3:]) == '') == qp.feasible
                inside += qp.feasible
        assert inside >= 150


def test_wrench_set_reason_is_one_line():
    settings = load_settings()
    geo = geometry(settings.robot, [0.0, 0.0, 1.25])
    wset = WrenchSet(geo.structure_matrix, 100.0, 1000.0, required_wrench(settings.robot))
    assert wset.reason([0.0, 0.0, 1500.0]) == ''
    reason = wset.reason([0.0, 0.0, -5000.0])
    assert reason.startswith('wrench outside the feasible set') and '\n' not in reason
    assert wset.reason([np.nan, 0.0, 0.0]) == 'wrench is not finite'


def test_point_mass_cables_never_cross():
    settings = load_settings()
    rng = np.random.default_rng(0)
    for p in rng.uniform([-1.2, -1.2, 0.05], [1.2, 1.2, 2.45], (50, 3)):
        geo = geometry(settings.robot, p)
        assert cable_crossing(settings.robot.anchors_m, geo.position_m + geo.lever_m,
                              0.008) == ''


def test_rotated_platform_crosses_cables():
    settings = rigid_settings()
    robot = settings.robot
    geo = geometry(robot, [0.0, 0.0, 1.25])
    assert cable_crossing(robot.anchors_m, geo.position_m + geo.lever_m, 0.008) == ''
    turned = geometry(robot, [0.0, 0.0, 1.25], Rotation.from_euler('z', 180, degrees=True)
                      .as_matrix())
    reason = cable_crossing(robot.anchors_m, turned.position_m + turned.lever_m, 0.008)
    assert reason.startswith('cables ') and ' cross: ' in reason


def test_parallel_and_skew_segments():
    anchors = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]])
    ends = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert cable_crossing(anchors, ends, 0.01) == ''          # parallel, 1 m apart
    anchors = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.001]])
    ends = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 0.001]])     # skew, 1 mm apart mid-span
    assert cable_crossing(anchors, ends, 0.0005) == ''
    reason = cable_crossing(anchors, ends, 0.008)
    assert reason.startswith('cables 0 and 1 cross: 1.0 mm apart at [0.5, 0.5, 0.0]')


# ------------------------------------------------------------- cross-check with an LP (HiGHS)

def _many_cables(n_cables: int):
    """A 6-DOF platform on ``n_cables`` cables from two rings of anchors."""
    flat = read_params_file(default_config_path())
    k = np.arange(n_cables)
    angle = 2 * np.pi * k / n_cables
    high = k % 2 == 0
    flat['robot.anchors'] = np.column_stack([2.0 * np.cos(angle), 2.0 * np.sin(angle),
                                             np.where(high, 2.5, 0.0)]).ravel().tolist()
    flat['robot.attachments'] = np.column_stack([
        0.1 * np.cos(angle + 0.3), 0.1 * np.sin(angle + 0.3),
        np.where(high, 0.05, -0.05)]).ravel().tolist()
    flat['robot.inertia_kg_m2'] = [0.5, 0.5, 0.5, 0.0, 0.0, 0.0]
    return settings_from_params(flat)


def _lp_feasible(wt, w, t_min, t_max) -> bool:
    """Independent answer: is there T in [t_min, t_max]^n with W^T T = w? (HiGHS)"""
    from scipy.optimize import linprog
    n = wt.shape[1]
    return linprog(np.zeros(n), A_eq=wt, b_eq=w, bounds=[(t_min, t_max)] * n,
                   method='highs').status == 0


def _candidate_wrenches(wt, t_min, t_max, rng, count):
    """Wrenches the cables must supply: inside, on and just outside the boundary, far out."""
    d, n = wt.shape
    centre = wt @ np.full(n, 0.5 * (t_min + t_max))
    for _ in range(count):
        direction = rng.normal(size=d)
        support = wt @ np.where(wt.T @ direction > 0, t_max, t_min)     # on the boundary
        inner = wt @ rng.uniform(t_min, t_max, n)
        for base in (support, inner):
            for scale in (1.0, 1.0 - 1e-9, 1.0 + 1e-9, 0.999, 1.001, rng.uniform(0.3, 1.7)):
                yield centre + scale * (base - centre)


ROBOTS = {
    'paper point mass': lambda: load_settings(),
    'rigid_cdpr.yaml 6-DOF': lambda: settings_from_params(read_params_file(
        Path(__file__).parent / 'data' / 'rigid_cdpr.yaml')),
    '12 cables 6-DOF': lambda: _many_cables(12),
    '24 cables 6-DOF (sampled normals)': lambda: _many_cables(24),
}


@pytest.mark.slow
@pytest.mark.parametrize('name', list(ROBOTS))
def test_wrench_set_never_rejects_what_an_lp_finds_feasible(name):
    """Issue 9: the node rejected a wrench an LP (HiGHS) shows feasible. Over random wrenches,
    on and near the boundary too, at three poses of each robot: every LP-feasible wrench is
    accepted; and every wrench accepted away from the boundary is LP-feasible."""
    settings = ROBOTS[name]()
    robot = settings.robot
    t_min, t_max = settings.tension_min_n, settings.tension_max_n
    rng = np.random.default_rng(11)
    need = required_wrench(robot)
    counts = {'feasible': 0, 'infeasible': 0}
    for _ in range(3):
        p = settings.initial_position_m + rng.uniform(-0.15, 0.15, 3)
        rot = (Rotation.from_euler('xyz', rng.uniform(-0.03, 0.03, 3)).as_matrix()
               if robot.platform_dofs == 6 else None)
        wt = geometry(robot, p, rot).structure_matrix
        wset = WrenchSet(wt, t_min, t_max, need)
        for w in _candidate_wrenches(wt, t_min, t_max, rng, 12):
            ext = np.zeros(6)
            ext[:w.size] = need - w
            accepted = wset.reason(ext[:3], ext[3:]) == ''
            lp = _lp_feasible(wt, w, t_min, t_max)
            counts['feasible' if lp else 'infeasible'] += 1
            if lp:
                assert accepted, (name, w, wset.reason(ext[:3], ext[3:]))
            elif accepted:      # only within the tolerance of the boundary
                shrunk = w + 1e-6 * t_max * (wt @ np.full(wt.shape[1], 0.5 * (t_min + t_max))
                                             - w) / max(1.0, np.linalg.norm(w))
                assert _lp_feasible(wt, shrunk, t_min - 1e-6 * t_max, t_max + 1e-6 * t_max), w
    assert counts['feasible'] > 60 and counts['infeasible'] > 30, counts


@pytest.mark.parametrize('name', list(ROBOTS))
def test_symmetric_limit_is_where_an_lp_stops_holding_the_load(name):
    """WrenchSet.symmetric_limit s of a load f (cdpr_demo's amplitude hint): an LP (HiGHS)
    holds +-0.999 s f and not both of +-1.001 s f, at two poses and three directions; the
    closed form (all facets) and the bisection (sampled normals) alike; 0 where the state
    itself cannot be held, inf for no load."""
    settings = ROBOTS[name]()
    robot = settings.robot
    t_min, t_max = settings.tension_min_n, settings.tension_max_n
    rng = np.random.default_rng(5)
    d = robot.platform_dofs
    for _ in range(2):
        p = settings.initial_position_m + rng.uniform(-0.15, 0.15, 3)
        wt = geometry(robot, p).structure_matrix
        need = wt @ rng.uniform(t_min, t_max, wt.shape[1])   # held at rest (not every
        wset = WrenchSet(wt, t_min, t_max, need)             # test robot holds its weight)
        for _ in range(3):
            load = np.zeros(6)
            load[:d] = rng.normal(size=d) * np.array([100.0] * 3 + [10.0] * 3)[:d]
            s = wset.symmetric_limit(load[:3], load[3:])
            assert 0.0 < s < np.inf
            assert all(_lp_feasible(wt, need - sign * 0.999 * s * load[:d], t_min, t_max)
                       for sign in (1.0, -1.0))
            assert not all(_lp_feasible(wt, need - sign * 1.001 * s * load[:d], t_min, t_max)
                           for sign in (1.0, -1.0))
    assert wset.symmetric_limit(np.zeros(3), np.zeros(3)) == np.inf     # no load: no limit
    lifted = WrenchSet(wt, t_min, t_max, need * 1e3)      # the pose itself cannot be held
    assert lifted.symmetric_limit([0.0, 0.0, 1.0]) == 0.0
