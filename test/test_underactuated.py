"""Underactuated and suspended robots: closed forms, the geometrico-static solve against an
independent constrained minimisation, refusals (slack, unstable, rank), and the pipeline, the
live predictor and cdpr_analyze taking such poses."""
import json
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.optimize import least_squares, minimize
from scipy.spatial.transform import Rotation

from cdpr_dynamics.analysis.config import read_params_file, settings_from_params
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.analysis.pipeline import (AnalysisError, build_system, equilibrium,
                                             equilibrium_summary, system_modes)
from cdpr_dynamics.mechanics.robot import Robot, geometry, quaternion_to_matrix
from cdpr_dynamics.mechanics.underactuated import (HeldWrenchSet, UnderactuatedError, balance,
                                                   geometrico_static, loaded_stiffness)
from conftest import analyze, write_config

REPO = Path(__file__).resolve().parents[1]
PAPER = read_params_file(REPO / 'config' / 'paper_cdpr.yaml')
G = 9.81
GRAVITY = np.array([0.0, 0.0, -G])
EA = 2.01e10 * 5.0265e-05


def settings_of(anchors, attachments=(), position=(0.0, 0.0, 0.0), method='spring',
                mass_kg=8.0, inertia=(0.1, 0.1, 0.15, 0.0, 0.0, 0.0), **extra):
    """Settings of a robot on the paper's cable with tension.min_n 1 N."""
    params = {**PAPER, 'robot.anchors': np.ravel(anchors).tolist(),
              'robot.attachments': np.ravel(attachments).tolist(),
              'robot.initial_position': list(position), 'robot.mass_kg': mass_kg,
              'robot.inertia_kg_m2': list(inertia), 'tension.min_n': 1.0,
              'model.method': method, 'model.elements_per_cable': 8, 'frf.f_max_hz': 100.0,
              **extra}
    return settings_from_params(params)


def ring(radius_m, count, z_m=0.0, phase_deg=90.0):
    angle = np.deg2rad(phase_deg + 360.0 * np.arange(count) / count)
    return np.c_[radius_m * np.cos(angle), radius_m * np.sin(angle), np.full(count, z_m)]


def lowest(settings, eq, count):
    system = build_system(settings, eq)
    return system_modes(settings, system).frequency_hz[:count]


# ----------------------------------------------------------------------------- closed forms

@pytest.mark.parametrize('method, rtol', [('spring', 1e-12), ('fem', 1e-3), ('dsm', 1e-3),
                                          ('fem_sag', 1e-3), ('catenary_exact', 1e-3)])
def test_point_mass_on_one_cable_is_a_pendulum_with_an_axial_mode(method, rtol):
    """sqrt(g/L) twice (swing) and sqrt(k/m), k = EA/L (axial); the straight spring exactly,
    the models with the cable's own mass (0.05 kg of 30) within it."""
    s = settings_of([0.0, 0.0, 2.5], position=(0.0, 0.0, 0.5), method=method, mass_kg=30.0,
                    inertia=(0.0,) * 6)
    eq = equilibrium(s, method=method)
    length = 2.0
    assert_allclose(eq.tensions.tension_n, [30.0 * G], rtol=1e-3)
    swing, axial = math.sqrt(G / length), math.sqrt(EA / length / 30.0)
    assert_allclose(lowest(s, eq, 3), np.array([swing, swing, axial]) / (2 * math.pi),
                    rtol=rtol)


@pytest.mark.parametrize('radius_m, length_m', [(0.2, 1.0), (0.35, 2.4)])
def test_trifilar_torsion_pendulum(radius_m, length_m):
    """Three parallel vertical cables at radius R, length L: omega^2 = m g R^2 / (I L) for the
    twist about the vertical, and sqrt(g/L) for the two swings."""
    mass, izz = 3.0, 0.08
    attachments = ring(radius_m, 3)
    s = settings_of(attachments + [0.0, 0.0, length_m], attachments, mass_kg=mass,
                    inertia=(0.05, 0.05, izz, 0.0, 0.0, 0.0))
    eq = equilibrium(s)
    assert eq.balance is not None and not eq.balance.moved
    assert_allclose(eq.tensions.tension_n, mass * G / 3.0, rtol=1e-12)
    found = lowest(s, eq, 3)
    twist = math.sqrt(mass * G * radius_m ** 2 / (izz * length_m)) / (2 * math.pi)
    swing = math.sqrt(G / length_m) / (2 * math.pi)
    assert_allclose(np.sort(found), np.sort([swing, swing, twist]), rtol=1e-9)


def test_bifilar_without_an_offset_centre_of_mass_is_refused_as_unstable_about_its_line():
    """Two parallel cables hold the platform's twist (omega^2 = m g R^2 / (I L)), but nothing
    holds a rotation about the line through both attachments: refused, naming rx."""
    attachments = np.array([[-0.2, 0.0, 0.0], [0.2, 0.0, 0.0]])
    s = settings_of(attachments + [0.0, 0.0, 1.0], attachments, mass_kg=3.0)
    with pytest.raises(AnalysisError, match=r'unstable: .*mostly rx'):
        equilibrium(s)


@pytest.mark.parametrize('half_span_m, length_m, drop_m', [(0.2, 1.0, 0.25), (0.35, 2.4, 0.1)])
def test_bifilar_pendulum_with_its_centre_of_mass_below_the_attachments(half_span_m, length_m,
                                                                        drop_m):
    """Two parallel vertical cables of length L at x = +-d/2, the centre of mass h below the
    line through the attachments. Lagrange, inextensible cables: the twist about the vertical
    through the centre of mass, omega^2 = m g d^2 / (4 I_zz L); the swing along x translates the
    platform (a parallelogram), g / L; the swing along y (the line's displacement y on its
    circle of radius L) and the rotation theta about the line couple: T = m (y' + h theta')^2/2
    + I_xx theta'^2 / 2 (the parallel-axis term m h^2 in M), V = m g (y^2 / (2L) + h theta^2/2).
    The spring model's axial stiffness (EA/L ~ 1e6 N/m) shifts them by < 1e-4."""
    mass, ixx, izz = 3.0, 0.04, 0.07
    attachments = np.array([[-half_span_m, 0.0, 0.0], [half_span_m, 0.0, 0.0]])
    s = settings_of(attachments + [0.0, 0.0, length_m], attachments, mass_kg=mass,
                    inertia=(ixx, 0.05, izz, 0.0, 0.0, 0.0),
                    **{'robot.center_of_mass_m': [0.0, 0.0, -drop_m]})
    eq = equilibrium(s)
    assert eq.balance is not None and not eq.balance.moved
    assert_allclose(eq.tensions.tension_n, mass * G / 2.0, rtol=1e-12)
    coupled_m = np.array([[mass, mass * drop_m], [mass * drop_m, mass * drop_m ** 2 + ixx]])
    coupled_k = np.diag([mass * G / length_m, mass * G * drop_m])
    coupled = np.sqrt(np.linalg.eigvals(np.linalg.solve(coupled_m, coupled_k)).real)
    twist = math.sqrt(mass * G * (2 * half_span_m) ** 2 / (4 * izz * length_m))
    expected = np.sort(np.r_[coupled, math.sqrt(G / length_m), twist]) / (2 * math.pi)
    assert_allclose(lowest(s, eq, 4), expected, rtol=1e-4)


def test_bifilar_twist_is_held_by_its_geometric_stiffness():
    """The bifilar's twist stiffness in the loaded stiffness is m g R^2 / L (closed form)."""
    radius, length, mass = 0.2, 1.3, 3.0
    attachments = np.array([[-radius, 0.0, 0.0], [radius, 0.0, 0.0]])
    robot = Robot('world', attachments + [0.0, 0.0, length], attachments, mass,
                  np.diag([0.05, 0.05, 0.08]), GRAVITY)
    geo = geometry(robot, [0.0, 0.0, 0.0])
    k = loaded_stiffness(robot, geo, np.full(2, mass * G / 2.0), EA)
    assert k[5, 5] == pytest.approx(mass * G * radius ** 2 / length, rel=1e-12)
    assert k[0, 0] == pytest.approx(mass * G / length, rel=1e-12)    # the swing along x
    assert k[3, 3] == 0.0


# ----------------------------------------------------------------------------- geometrico-static

def _suspended_4():
    anchors = np.array([[-1.5, -1.0, 2.5], [1.5, -1.0, 2.5], [1.5, 1.0, 2.5], [-1.5, 1.0, 2.5]])
    attachments = np.array([[-0.2, -0.1, 0.0], [0.2, -0.1, 0.0], [0.2, 0.1, 0.0],
                            [-0.2, 0.1, 0.0]])
    return Robot('world', anchors, attachments, 8.0, np.diag([0.1, 0.1, 0.15]), GRAVITY)


def _suspended_3():
    return Robot('world', ring(1.5, 3, 2.5), ring(0.15, 3), 8.0, np.diag([0.1, 0.1, 0.15]),
                 GRAVITY)


def _pose_of(x):
    return x[:3], Rotation.from_rotvec(x[3:]).as_matrix()


def _lengths(robot, x):
    p, r = _pose_of(x)
    return np.linalg.norm(robot.anchors_m - p - robot.attachments_m @ r.T, axis=1)


def _energy(robot, x):
    return -robot.mass_kg * GRAVITY @ _pose_of(x)[0]


@pytest.mark.parametrize('robot, start, quaternion', [
    (_suspended_4(), [0.1, 0.05, 1.0], [0.0, 0.0, 0.0, 1.0]),
    (_suspended_4(), [-0.3, 0.2, 1.4], [0.05, -0.03, 0.1, 1.0]),
    (_suspended_3(), [0.1, 0.05, 1.0], [0.0, 0.0, 0.0, 1.0]),
    (_suspended_3(), [0.2, -0.25, 0.8], [0.04, 0.02, -0.2, 1.0]),
])
@pytest.mark.slow
def test_geometrico_static_equilibrium_is_the_constrained_energy_minimum(
        robot, start, quaternion):
    """The solve keeps the pose's cable lengths, balances gravity with positive tensions, and
    lands where SLSQP minimising the energy under the same length constraints lands; random
    moves that keep the lengths (projected by least squares) all raise the energy."""
    rotation = quaternion_to_matrix(quaternion)
    x0 = np.r_[start, Rotation.from_matrix(rotation).as_rotvec()]
    lengths = _lengths(robot, x0)
    found = geometrico_static(robot, start, rotation)
    x = np.r_[found.geometry.position_m,
              Rotation.from_matrix(found.geometry.rotation).as_rotvec()]
    assert_allclose(_lengths(robot, x), lengths, rtol=1e-12)
    assert np.all(found.tension_n > 0)
    assert np.abs(found.residual).max() < 1e-9 * robot.mass_kg * G
    assert found.distance_m == pytest.approx(np.linalg.norm(x[:3] - x0[:3]), rel=1e-12)

    reference = minimize(lambda y: _energy(robot, y), x0, method='SLSQP',
                         constraints={'type': 'eq',
                                      'fun': lambda y: _lengths(robot, y) - lengths},
                         options={'ftol': 1e-12, 'maxiter': 500})
    assert np.abs(_lengths(robot, reference.x) - lengths).max() < 1e-8
    assert_allclose(reference.x[:3], x[:3], atol=1e-5)
    assert _energy(robot, reference.x) > _energy(robot, x) - 1e-9

    rng = np.random.default_rng(3)
    e0 = _energy(robot, x)
    for _ in range(40):
        trial = x + rng.normal(0.0, [0.01] * 3 + [0.02] * 3)
        kept = least_squares(lambda y: _lengths(robot, y) - lengths, trial, xtol=1e-15,
                             ftol=1e-15, gtol=1e-15).x
        assert np.abs(_lengths(robot, kept) - lengths).max() < 1e-9
        assert _energy(robot, kept) > e0


def test_a_pose_that_balances_is_kept_and_reported_so():
    robot = _suspended_3()
    held = geometrico_static(robot, [0.1, 0.05, 1.0])
    again = balance(robot, held.geometry, 1.0, 1000.0)
    assert not again.moved and again.distance_m == 0.0
    assert_allclose(again.tension_n, held.tension_n, rtol=1e-8)


def test_slack_cable_at_the_equilibrium_is_refused_naming_it():
    """A mass beside two anchors on a line: the lowest point with their lengths needs cable 1
    to push."""
    robot = Robot('world', np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]]), np.zeros((2, 3)), 5.0,
                  np.zeros((3, 3)), GRAVITY)
    with pytest.raises(UnderactuatedError, match=r'cable (0|1) is slack \(tension -'):
        balance(robot, geometry(robot, [3.0, 0.0, 1.9]), 1.0, 1000.0)
    # a V at 45 degrees: each cable holds m g / (2 sin 45) = 34.68 N
    s = settings_of([[-1.0, 0.0, 2.0], [1.0, 0.0, 2.0]], position=(0.0, 0.0, 1.0),
                    mass_kg=5.0, inertia=(0.0,) * 6, **{'tension.min_n': 100.0})
    with pytest.raises(AnalysisError, match=r'cable 0 is slack \(tension 34.68 N < '
                                            r'tension.min_n 100 N\)'):
        equilibrium(s)


def test_rank_below_the_cables_is_still_a_design_defect():
    s = settings_of([[-1.25, 0.0, 1.0], [-2.5, 0.0, 1.0]], position=(0.0, 0.0, 1.0),
                    inertia=(0.0,) * 6)
    with pytest.raises(AnalysisError, match=r'rank 1 < 2 \(min of 2 cables and 3'):
        equilibrium(s)


# ----------------------------------------------------------------------------- the tools

def test_pipeline_analyses_at_the_equilibrium_and_reports_the_distance():
    robot = _suspended_4()
    s = settings_of(robot.anchors_m, robot.attachments_m, position=(0.1, 0.05, 1.0))
    eq = equilibrium(s)
    summary = equilibrium_summary(s, eq)['underactuated']
    assert summary['moved'] and summary['distance_m'] > 0.01
    assert any('not an equilibrium' in w and f'{summary["distance_m"]:.4g} m' in w
               for w in eq.warnings)
    assert_allclose(summary['position_m'], eq.geometry.position_m)
    for method in ('fem', 'fem_sag', 'dsm'):         # every model at that equilibrium
        other = equilibrium(s.replace(method=method), method=method)
        assert_allclose(other.geometry.position_m, eq.geometry.position_m, rtol=1e-12)
        assert lowest(s.replace(method=method), other, 1)[0] > 0.1


def test_live_predictor_takes_an_underactuated_pose_and_predicts_about_the_equilibrium():
    robot = _suspended_4()
    s = settings_of(robot.anchors_m, robot.attachments_m, position=(0.0, 0.0, 1.0))
    predictor = LivePredictor(s)
    update = predictor.update_pose([0.1, 0.05, 1.0])
    assert any('not an equilibrium' in w for w in update.warnings)
    assert not predictor.update_pose([0.1, 0.05, 1.0]).rebuilt    # the same input: kept
    assert_allclose(predictor.prediction().position_m, predictor.eq.geometry.position_m)
    assert isinstance(predictor.wrench_set, HeldWrenchSet)
    assert predictor.wrench_reason([2.0, 0.0, 0.0]) == ''        # a push the swing takes
    assert 'cable' in predictor.wrench_reason([0.0, 0.0, -5000.0])    # beyond tension.max_n


def test_held_wrench_set_tensions_and_limit_against_least_squares():
    robot = _suspended_4()
    held = geometrico_static(robot, [0.1, 0.05, 1.0])
    wt = held.geometry.structure_matrix
    required = np.r_[-robot.mass_kg * GRAVITY, 0.0, 0.0, 0.0]
    wrenches = HeldWrenchSet(wt, 1.0, 1000.0, required)
    force = np.array([3.0, -2.0, 10.0])
    expect = np.linalg.lstsq(wt, required - np.r_[force, 0.0, 0.0, 0.0], rcond=None)[0]
    assert_allclose(wrenches.tensions(force), expect, rtol=1e-10)
    limit = wrenches.symmetric_limit(force)
    assert wrenches.reason(0.999 * limit * force) == ''
    assert wrenches.reason(-0.999 * limit * force) == ''
    assert wrenches.reason(1.001 * limit * force) or wrenches.reason(-1.001 * limit * force)


def test_cdpr_analyze_on_a_suspended_underactuated_robot(tmp_path):
    robot = _suspended_3()
    path = write_config(tmp_path, **{
        'robot.anchors': robot.anchors_m.ravel().tolist(),
        'robot.attachments': robot.attachments_m.ravel().tolist(),
        'robot.initial_position': [0.1, 0.05, 1.0], 'robot.mass_kg': 8.0,
        'robot.inertia_kg_m2': [0.1, 0.1, 0.15, 0.0, 0.0, 0.0], 'tension.min_n': 1.0,
        'model.method': 'auto', 'damping.mass_factor': 0.0, 'damping.stiffness_factor': 0.0,
        'damping.modal_ratio': 0.02, 'frf.force_n': [1.0, 0.0, 0.0]})
    out = analyze('--config', path, '--json', tmp_path / 'out.json', '--excitation-hz', '1.0',
                  '--duration', '0.2')
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / 'out.json').read_text())
    block = doc['equilibrium']['underactuated']
    assert block['moved'] and 0.01 < block['distance_m'] < 0.1
    assert any('not an equilibrium' in w for w in doc['warnings'])
    assert doc['platform_natural_frequencies_hz'][0] == pytest.approx(0.72, abs=0.02)


def test_loaded_stiffness_is_the_spring_models_static_stiffness():
    """Two computations of the stiffness at a geometrico-static equilibrium: the module's
    closed form and the spring model assembled by the dynamics layer."""
    from cdpr_dynamics import models
    from cdpr_dynamics.dynamics.system import platform_system
    from cdpr_dynamics.models.base import CableSet
    robot = _suspended_4()
    held = geometrico_static(robot, [-0.3, 0.2, 1.4], quaternion_to_matrix([0.05, -0.03, 0.1, 1]))
    geo = held.geometry
    cables = CableSet(geo.chord_m, held.tension_n, EA, 0.0, GRAVITY)
    spring = platform_system(robot, geo, models.build('spring', cables)).static_stiffness()
    ours = loaded_stiffness(robot, geo, held.tension_n, EA)
    assert_allclose(ours, spring, rtol=0, atol=1e-9 * np.abs(spring).max())


@pytest.mark.parametrize('name', ['suspended_3cable', 'suspended_4cable'])
def test_shipped_suspended_robots_hang_at_their_initial_pose(name):
    """Symmetric, so their initial pose is an equilibrium (to the round-off of the file's
    coordinates: no warning); the lowest modes are the sways gravity holds (0.4-4 Hz), the
    same in every model to 1 %."""
    from cdpr_dynamics.analysis.config import load_settings
    settings = load_settings(REPO / 'config' / f'{name}.yaml')
    lowest_two = []
    for method in ('spring', 'fem', 'fem_sag'):
        s = settings.replace(method=method)
        eq = equilibrium(s, method=method)
        assert eq.balance.distance_m < 1e-6 and not any('equilibrium' in w for w in eq.warnings)
        platform = system_modes(s, build_system(s, eq)).platform_hz
        lowest_two.append(platform[:2])
    lowest_two = np.array(lowest_two)
    assert np.all((lowest_two > 0.4) & (lowest_two < 4.0))
    assert_allclose(lowest_two, np.broadcast_to(lowest_two[0], lowest_two.shape), rtol=0.01)
