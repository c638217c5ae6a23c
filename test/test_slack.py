"""Slack-aware time history: cables that carry no compression (cdpr_dynamics.dynamics.slack).

The paper's own load case (1500 N along z at 5 Hz, lower cables at 100 N) slackens cables:
the linear model's tension goes to -76 N. Measured here (spring model, dt = 1 ms, the paper's
Rayleigh damping dM = dK = 0.05): linear peak |u_z| 0.760 mm; slack-aware 1.118 mm with the
damping inside the cables (default), 0.760 mm (down-swing 0.651 -> 0.709 mm) with the damping
kept linear. Undamped: 1.423 mm linear, 2.351 mm slack-aware.
"""
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics import models
from cdpr_dynamics.analysis.pipeline import build_system, damping_for, equilibrium
from cdpr_dynamics.analysis.config import load_settings, read_params_file, settings_from_params
from cdpr_dynamics.dynamics.system import Damping, DynamicsError, time_history, tension_change
from cdpr_dynamics.dynamics.slack import (CompressionFreeCables, peak_displacement,
                                          platform_only_method, slack_time_history)

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'paper_cdpr.yaml'
PAPER_FORCE = np.array([0.0, 0.0, 1500.0])


@pytest.fixture(scope='module')
def paper():
    settings = load_settings(CONFIG)
    eq = equilibrium(settings)
    system = build_system(settings, eq, 'spring', 1)
    return settings, eq, system, damping_for(settings, system)


@pytest.fixture(scope='module')
def paper_5hz(paper):
    """Linear and slack-aware (both damping placements) 5 Hz, 1500 N, 1 s histories."""
    settings, eq, system, damping = paper
    linear = time_history(system, PAPER_FORCE, 5.0, 1.0, damping, 1e-3)
    slack = slack_time_history(system, PAPER_FORCE, 5.0, 1.0, damping, 1e-3)
    kept = slack_time_history(system, PAPER_FORCE, 5.0, 1.0, damping, 1e-3,
                              cable_damping=False)
    return linear, slack, kept


def six_dof_settings():
    """The paper robot with a 0.2 m cube platform attached as test/data/rigid_cdpr.yaml
    (corners facing their anchors would make every cable pass the centroid: rank 3)."""
    flat = read_params_file(CONFIG)
    rigid = read_params_file(Path(__file__).parent / 'data' / 'rigid_cdpr.yaml')
    flat['robot.attachments'] = (0.5 * np.asarray(rigid['robot.attachments'])).tolist()
    flat['robot.inertia_kg_m2'] = [0.4, 0.4, 0.4, 0.0, 0.0, 0.0]
    return settings_from_params(flat)


def test_small_load_equals_the_linear_time_history(paper):
    settings, eq, system, damping = paper
    force = np.array([20.0, -10.0, 50.0])
    linear = time_history(system, force, 5.0, 0.5, damping, 1e-3)
    slack = slack_time_history(system, force, 5.0, 0.5, damping, 1e-3)
    assert not slack.slack.any()
    # the only difference is the geometric non-linearity, |d|/L ~ 1e-5 here
    assert_allclose(slack.u, linear.u, rtol=0, atol=1e-6 * np.abs(linear.u).max())


def test_rigid_platform_small_load_equals_the_linear_time_history():
    settings = six_dof_settings()
    eq = equilibrium(settings)
    system = build_system(settings, eq, 'spring', 1)
    assert system.platform_dofs == 6
    damping = damping_for(settings, system)
    mismatch = []
    for scale in (1.0, 0.1):       # the slack model is geometrically exact: the difference
        force = scale * np.array([30.0, 20.0, 40.0])         # is second order in the motion
        linear = time_history(system, force, 3.0, 0.4, damping, 1e-3)
        slack = slack_time_history(system, force, 3.0, 0.4, damping, 1e-3)
        assert not slack.slack.any()
        mismatch.append(np.abs(slack.u - linear.u).max() / np.abs(linear.u).max())
    assert mismatch[0] < 2e-3
    assert mismatch[1] == pytest.approx(0.1 * mismatch[0], rel=0.05)


def test_paper_load_case_slackens_cables_and_the_peak_grows(paper, paper_5hz):
    settings, eq, system, damping = paper
    linear, slack, kept = paper_5hz
    linear_tension = eq.tensions.tension_n + tension_change(system, linear.u)
    assert linear_tension.min() < -70.0                         # -75.5 N: invalid
    assert peak_displacement(linear.u_m) == pytest.approx(0.760e-3, rel=0.01)
    assert peak_displacement(slack.u_m) == pytest.approx(1.118e-3, rel=0.01)
    assert peak_displacement(kept.u_m) == pytest.approx(0.760e-3, rel=0.01)
    assert -kept.u_m[:, 2].min() == pytest.approx(0.709e-3, rel=0.01)
    # lower cables (0-3) slack about 40 % of the time, the upper ones 26 %; the upper ones
    # first, 25 ms into the first up-swing, the lower ones at 111 ms
    assert_allclose(slack.slack.mean(axis=0), [0.40] * 4 + [0.26] * 4, atol=0.02)
    assert slack.slack_intervals(4)[0][0] == pytest.approx(0.025, abs=0.003)
    assert slack.slack_intervals(0)[0][0] == pytest.approx(0.111, abs=0.003)


def test_slack_intervals_are_where_the_tensions_say(paper, paper_5hz):
    settings, eq, system, damping = paper
    linear, slack, kept = paper_5hz
    cables = CompressionFreeCables(system)
    for history, dk in ((slack, damping.stiffness_factor), (kept, 0.0)):
        for i in range(0, history.t_s.size, 7):
            pull = cables.state(history.u[i], history.v[i], dk)[0]
            assert_allclose(history.tension_n[i], pull, rtol=1e-12, atol=1e-9)
        assert np.array_equal(history.slack, ~(history.tension_n > 0))
    # before the first slack instant the slack-aware and linear responses coincide, and the
    # first slack instant is where the linear model's cable force first reaches zero
    for history, include_damping in ((slack, True), (kept, False)):
        first = int(np.argmax(history.slack.any(axis=1)))
        assert first > 0
        assert_allclose(history.u[:first], linear.u[:first], atol=1e-9)
        stretch_force = eq.tensions.tension_n + tension_change(system, linear.u)
        if include_damping:
            rate = np.gradient(linear.u, linear.t_s, axis=0)
            stretch_force = stretch_force + damping.stiffness_factor * tension_change(system,
                                                                                      rate)
        linear_first = int(np.argmax((stretch_force <= 0).any(axis=1)))
        assert abs(first - linear_first) <= 1


def test_equation_of_motion_holds_at_every_step(paper, paper_5hz):
    """M a + dM M v + R(q, v) = F at every step (the Newton residual)."""
    settings, eq, system, damping = paper
    _, slack, _ = paper_5hz
    cables = CompressionFreeCables(system)
    m = cables.mass
    for i in range(1, slack.t_s.size, 13):
        force = PAPER_FORCE * np.sin(2 * np.pi * 5.0 * slack.t_s[i])
        _, restoring, _ = cables.state(slack.u[i], slack.v[i], damping.stiffness_factor)
        residual = m @ slack.a[i] + damping.mass_factor * m @ slack.v[i] + restoring - force
        assert np.linalg.norm(residual) <= 1e-8 * (1500.0 + cables.tension.sum())


@pytest.mark.parametrize('rigid', [False, True])
def test_jacobians_are_the_derivatives_of_the_restoring_force(paper, rigid):
    """dR/dq and dR/dq' (Newton's matrices) against central differences of R, at a moving
    state with a slack cable, for a point mass and a rigid platform."""
    if rigid:
        settings = six_dof_settings()
        system = build_system(settings, equilibrium(settings), 'spring', 1)
    else:
        settings, _, system, _ = paper
    cables = CompressionFreeCables(system)
    nd = cables.nd
    rng = np.random.default_rng(3)
    q = np.zeros(nd)
    q[:3] = 2.0 * cables.tension[0] / cables.k_axial[0] * cables.unit[0]  # cable 0 slack
    q[3:] = rng.normal(0.0, 2e-4, nd - 3)
    v = rng.normal(0.0, 0.002, nd)
    dk = 0.05
    pull, _, parts = cables.forces(q, v, dk)
    assert pull[0] == 0.0 and (pull > 1.0).sum() >= nd      # slack and taut cables
    jq, jv = cables.jacobians(parts)
    h = 1e-8
    for matrix, moved in ((jq, lambda e: (q + e, v)), (jv, lambda e: (q, v + e))):
        numeric = np.column_stack([
            (cables.forces(*moved(h * e), dk)[1] - cables.forces(*moved(-h * e), dk)[1])
            / (2 * h) for e in np.eye(nd)])
        assert_allclose(matrix, numeric, rtol=0, atol=1e-6 * np.abs(jq).max())


@pytest.mark.slow
def test_undamped_free_vibration_through_slack_keeps_its_energy(paper):
    settings, eq, system, _ = paper
    cables = CompressionFreeCables(system)
    v0 = np.array([0.02, 0.01, 0.15])          # m/s: enough to slacken cables every cycle
    history = slack_time_history(system, None, 0.0, 0.5, Damping(), 2e-4,
                                 initial_velocity=v0, load=lambda t: np.zeros(3))
    assert history.slack.any()
    m = cables.mass
    energy = np.array([0.5 * v @ m @ v + cables.potential(q)
                       for q, v in zip(history.u, history.v)])
    assert np.ptp(energy) <= 2e-3 * energy[0]


@pytest.mark.slow
def test_time_step_convergence(paper):
    """Second order through the slack kinks, like the linear Newmark: errors against dt/8 of
    the 1500 N, 5 Hz history (0.4 s) were 3.2e-4, 9.2e-5, 2.1e-5 at dt = 2, 1, 0.5 ms."""
    settings, eq, system, damping = paper
    steps = (2e-3, 1e-3, 5e-4, 2.5e-4)
    fine = slack_time_history(system, PAPER_FORCE, 5.0, 0.4, damping, steps[-1]).u[:, 2]
    errors = []
    for dt in steps[:-1]:
        u = slack_time_history(system, PAPER_FORCE, 5.0, 0.4, damping, dt).u[:, 2]
        errors.append(np.abs(u - fine[::round(dt / steps[-1])]).max() / np.abs(fine).max())
    assert errors[1] < 2e-4                                    # the paper's dt = 1 ms
    assert errors[0] / errors[1] > 2.8 and errors[1] / errors[2] > 2.8


def test_refuses_models_with_cable_dofs_and_unstable_steps(paper):
    settings, eq, system, damping = paper
    fem = build_system(settings, eq, 'fem', 16)
    with pytest.raises(DynamicsError, match='without cable DOFs'):
        slack_time_history(fem, PAPER_FORCE, 5.0, 0.1, damping)
    with pytest.raises(DynamicsError, match='unconditionally stable'):
        slack_time_history(system, PAPER_FORCE, 5.0, 0.1, damping, beta=0.1)
    assert platform_only_method('fem_sag') == 'catenary_exact'
    assert platform_only_method('dsm') == 'fem'


def test_catenary_and_fem_n1_stand_ins_run(paper):
    """Platform-only forms of the other models: same slack pattern, similar peaks."""
    settings, eq, system, damping = paper
    peaks = {}
    for method in ('fem', 'catenary', 'catenary_exact'):
        s = build_system(settings, eq, method, 1)
        history = slack_time_history(s, PAPER_FORCE, 5.0, 0.4, damping)
        peaks[method] = peak_displacement(history.u_m)
        assert history.slack[:, :4].any() and history.slack[:, 4:].any()
    spring = peak_displacement(slack_time_history(system, PAPER_FORCE, 5.0, 0.4, damping).u_m)
    for value in peaks.values():
        assert value == pytest.approx(spring, rel=0.05)


def test_invalid_model_is_refused():
    settings = load_settings(CONFIG)
    eq = equilibrium(settings)
    cables = eq.cables.with_tension(np.where(np.arange(8) == 0, 0.0, eq.cables.tension_n))
    from cdpr_dynamics.dynamics.system import platform_system
    system = platform_system(settings.robot, eq.geometry, models.build('spring', cables))
    with pytest.raises(DynamicsError, match='invalid model'):
        slack_time_history(system, PAPER_FORCE, 5.0, 0.1, Damping())


@pytest.mark.parametrize('speed_m_s', [1.5, 2.5])
def test_a_thrown_platform_flies_ballistically_until_beyond_small_displacements(speed_m_s):
    """The suspended 3-cable robot's platform thrown straight up: every cable slack, it flies
    as a projectile, z = v t - g t^2 / 2 (Newmark's average acceleration is exact for a
    constant one). At 1.5 m/s it turns back 0.115 m up, its chords within SMALL_ANGLE_RAD; at
    2.5 m/s the step whose chord turns past it is refused with the displacement."""
    from cdpr_dynamics.dynamics.slack import SMALL_ANGLE_RAD, SlackStepper
    settings = load_settings(CONFIG.parent / 'suspended_3cable.yaml')
    system = build_system(settings, equilibrium(settings), 'spring')
    stepper = SlackStepper(system, Damping(), 1e-3)
    cables, nd = stepper.cables, stepper.cables.nd
    thrown = np.zeros(nd)
    thrown[2] = speed_m_s
    stepper.start(np.zeros(nd), thrown, np.zeros(nd))
    g = -settings.robot.gravity_m_s2[2]
    stepper.acc = np.zeros(nd)
    stepper.acc[2] = -g                                # released: the cables already slack
    steps = int(speed_m_s / g / 1e-3)                  # to the top of the flight
    heights, turned = [], []
    try:
        for _ in range(steps):
            stepper.step(np.zeros(nd))
            assert not stepper.pull.any()
            heights.append(stepper.q[2])
            turned.append((np.linalg.norm(cables.g @ stepper.q, axis=1) / cables.length).max())
    except DynamicsError as exc:
        assert speed_m_s == 2.5 and 'beyond the small-displacement model' in str(exc)
        assert turned[-1] <= SMALL_ANGLE_RAD < turned[-1] + 2 * (turned[-1] - turned[-2])
    else:
        assert speed_m_s == 1.5 and max(turned) <= SMALL_ANGLE_RAD
    t = 1e-3 * np.arange(1, len(heights) + 1)
    assert_allclose(heights, speed_m_s * t - 0.5 * g * t ** 2, rtol=0, atol=1e-12)
