"""LivePredictor, the node's ROS-free core: rebuilds, zero-order hold, auto caching."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.pipeline import AnalysisError, build_system, equilibrium
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import Damping, Newmark
from cdpr_dynamics.analysis.live import AUTO_RECHOOSE_M, LivePredictor, same_model

CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'


@pytest.fixture(scope='module')
def settings():
    return load_settings().replace(method='fem', elements_per_cable=4)


def test_constant_wrench_settles_to_static_deflection(settings):
    predictor = LivePredictor(settings)
    force = np.array([200.0, -100.0, 400.0])
    k = build_system(settings, equilibrium(settings)).static_stiffness()
    u = None
    for i in range(2001):
        u = predictor.advance(i * 1_000_000, force)
    assert_allclose(u, np.linalg.solve(k, force), rtol=1e-6)


def test_zero_order_hold_integrates_the_previous_wrench(settings):
    """Advancing to t_(k+1) uses the wrench of t_k over the interval, in dt sub-steps (the
    linear model: -5000 N slackens cables)."""
    predictor = LivePredictor(settings, slack='linear')
    system = predictor.system
    k, m = system.matrices()
    reference = Newmark(k, m, Damping(settings.damping_mass_factor,
                                      settings.damping_stiffness_factor), settings.dt_s)
    # the predictor solves densely, the reference sparsely: equal to round-off
    load = np.zeros(k.shape[0])
    load[2] = 1000.0
    predictor.advance(0, load[:3])
    got = predictor.advance(10_500_000, [0.0, 0.0, -5000.0])   # 10 steps of 1 ms, 0.5 ms carried
    for _ in range(10):
        expected = reference.step(load)
    assert_allclose(got, expected[:3], rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    got = predictor.advance(12_000_000, [0.0, 0.0, 0.0])        # 0.5 + 1.5 ms: 2 steps at -5000 N
    load[2] = -5000.0
    for _ in range(2):
        expected = reference.step(load)
    assert_allclose(got, expected[:3], rtol=1e-9, atol=1e-12 * np.abs(expected).max())


def test_out_of_order_stamp_is_refused_and_state_kept(settings):
    predictor = LivePredictor(settings)
    predictor.advance(1_000_000_000, [0.0, 0.0, 100.0])
    u = predictor.advance(1_010_000_000, [0.0, 0.0, 100.0])
    with pytest.raises(ValueError, match='older than the last wrench'):
        predictor.advance(1_005_000_000, [0.0, 0.0, 100.0])
    assert_allclose(predictor.integrator.u[:3], u)


def test_pose_within_tolerance_does_not_rebuild_and_bad_pose_keeps_state(settings):
    predictor = LivePredictor(settings, pose_tolerance_m=1e-3)
    system = predictor.system
    assert not predictor.update_pose([0.0005, 0.0, 1.25]).rebuilt
    assert predictor.system is system
    assert predictor.update_pose([0.01, 0.0, 1.25]).rebuilt
    moved = predictor.system
    with pytest.raises(AnalysisError, match='infeasible tension distribution'):
        predictor.update_pose([3.0, 0.0, 1.25])
    assert predictor.system is moved


def test_invalid_model_falls_back_to_spring_with_a_warning(settings):
    """A 0.5 N end tension cannot hold 10.8 N of cable: no catenary exists at the chord
    tensions, so the paper's catenary is invalid; spring needs only T > 0 and takes over,
    saying why. catenary_exact's sag-consistent statics instead lift those cables to the least
    tension a catenary exists at, and say so."""
    s = settings.replace(method='catenary', tension_min_n=0.5)
    s = s.replace(cable=dataclasses.replace(s.cable, weight_per_length_n_per_m=5.0))
    update = LivePredictor(s).last_update
    assert update.method == 'spring'
    assert any("the paper's catenary assumes one that cannot exist" in w
               for w in update.warnings)
    assert 'method catenary failed for this state; fell back to spring' in update.warnings
    exact = LivePredictor(s.replace(method='catenary_exact'))
    assert exact.last_update.method == 'catenary_exact'
    assert exact.eq.statics == 'sag' and exact.eq.tensions.tension_n.min() > 0.5
    assert any('no taut catenary spans its chord below' in w
               for w in exact.last_update.warnings)


def test_auto_choice_is_kept_for_small_moves_and_redone_for_large_ones(settings):
    predictor = LivePredictor(settings.replace(method='auto'))
    choice = predictor._choice
    assert choice is not None and predictor.last_update.method == choice.method
    predictor.update_pose([0.01, 0.0, 1.25])
    assert predictor._choice is choice
    predictor.update_pose([2 * AUTO_RECHOOSE_M, 0.0, 1.25])
    assert predictor._choice is not choice


def test_wall_clock_stamps_count_the_same_steps_as_small_ones(settings):
    """Stamps near 1.7e9 s (a real clock) give the predictions of stamps near 0: float seconds
    there resolve only ~0.2 us and would drop Newmark steps of 5 ms intervals."""
    predictions = []
    for origin_ns in (0, 1_700_000_000_123_456_789):
        predictor = LivePredictor(settings)
        predictions.append([predictor.advance(origin_ns + k * 5_000_000,
                                              [0.0, 0.0, 300.0 * np.sin(0.3 * k)])
                            for k in range(200)])
    assert_allclose(predictions[1], predictions[0], rtol=0, atol=1e-15)


# --------------------------------------------------------------------------- slack, long gaps

PAPER_LOAD = np.array([0.0, 0.0, 1500.0])


def test_slack_aware_prediction_follows_the_compression_free_model():
    """The paper's 1500 N at 5 Hz on spring: the live predictor (linear until a cable's force
    would reach zero) and slack_time_history (compression-free throughout) agree; the linear
    model goes 75 N into compression."""
    from cdpr_dynamics.analysis.live import harmonic_history
    from cdpr_dynamics.analysis.pipeline import damping_for
    from cdpr_dynamics.dynamics.slack import slack_time_history
    settings = load_settings().replace(method='spring')
    live = harmonic_history(settings, 5.0, 1.0)
    linear = harmonic_history(settings, 5.0, 1.0, slack='linear')
    system = build_system(settings, equilibrium(settings))
    offline = slack_time_history(system, PAPER_LOAD, 5.0, 1.0, damping_for(settings, system))
    peak = np.abs(offline.u).max()
    # before a cable slackens the motion is ~1e-5 m: the geometric non-linearity the linear
    # part leaves out is ~1e-10 of the peak
    assert_allclose(live.u, offline.u, rtol=0, atol=1e-6 * peak)
    assert np.array_equal(live.slack, offline.slack)
    assert linear.cable_force_n.min() < -70.0 and live.cable_force_n.min() == 0.0
    assert np.abs(live.u[:, 2]).max() > 1.4 * np.abs(linear.u[:, 2]).max()


def test_slack_then_taut_returns_to_the_linear_model_and_counts_slack_time():
    settings = load_settings().replace(method='fem', elements_per_cable=4)
    predictor = LivePredictor(settings)
    stamps = np.arange(400) * 1_000_000
    slack_steps = 0
    for k, stamp in enumerate(stamps):
        force = PAPER_LOAD if k < 60 else np.zeros(3)      # a 60 ms push, then nothing
        predictor.advance(int(stamp), force)
        slack_steps += bool(predictor.slack_cables)
        if k < 30:          # pushed up, the upper cables (4-7) slacken first
            assert set(predictor.slack_cables) <= {4, 5, 6, 7}
    assert slack_steps > 5
    assert predictor.slack_time_s == pytest.approx(slack_steps * settings.dt_s)
    assert predictor._stepper is None and predictor.slack_cables == ()
    # linear again: the free response decays as the linear model's from here
    assert np.abs(predictor.platform_state()[0]).max() < 1e-5


def test_a_load_that_flings_the_platform_is_refused_and_the_motion_restarts_from_rest():
    """1000 N at 5 Hz on the heavy-sag robot's 15 kg platform slackens most cables: the
    compression-free platform turns past the small-displacement model's 0.1 rad within
    0.11 s. That wrench is refused with the displacement (not a Newton failure on every
    later wrench), the next one starts from rest, and the refusals stay few."""
    from cdpr_dynamics.dynamics.slack import SMALL_ANGLE_RAD
    from cdpr_dynamics.dynamics.system import DynamicsError
    predictor = LivePredictor(load_settings(CONFIG_DIR / 'heavy_sag_6dof.yaml'))
    refused, largest = [], 0.0
    for k in range(1, 1001):
        force = np.array([0.0, 0.0, 1000.0 * np.sin(2 * np.pi * 5.0 * k * 1e-3)])
        try:
            predictor.advance(k * 1_000_000, force)
        except DynamicsError as exc:
            refused.append((k, str(exc)))
            assert predictor._stepper is None and not predictor.platform_state()[0].any()
            continue
        largest = max(largest, np.abs(predictor.platform_state()[0][3:6]).max())
    assert refused and refused[0][0] < 150
    assert 'beyond the small-displacement model' in refused[0][1]
    assert 'the next wrench starts from rest' in refused[0][1]
    assert len(refused) < 20 and largest <= SMALL_ANGLE_RAD


def test_long_gap_is_stepped_in_closed_form(settings, monkeypatch):
    """A held wrench over 5000 steps: the same state as stepping it, no step taken."""
    predictor = LivePredictor(settings, slack='linear')
    reference = LivePredictor(settings, slack='linear')
    reference.max_steps_per_wrench = 10_000
    for p in (predictor, reference):
        p.advance(0, [0.0, 0.0, 300.0])
        p.advance(7_000_000, [50.0, -40.0, 200.0])       # moving when the gap begins
    calls = []
    step = predictor.integrator.step
    monkeypatch.setattr(predictor.integrator, 'step', lambda f: calls.append(1) or step(f))
    got = predictor.advance(5_007_000_000, [0.0, 0.0, 0.0])
    expected = reference.advance(5_007_000_000, [0.0, 0.0, 0.0])
    assert calls == [] and predictor.notice == ''
    assert_allclose(got, expected, rtol=1e-8, atol=1e-12 * np.abs(expected).max())
    assert_allclose(predictor.integrator.v, reference.integrator.v, rtol=0,
                    atol=1e-6 * np.abs(reference.integrator.v).max() + 1e-15)
    # and it carries on as the stepped one does
    for p in (predictor, reference):
        p.advance(5_027_000_000, [10.0, 0.0, 0.0])
    assert_allclose(predictor.advance(5_030_000_000, [0.0, 0.0, 0.0]),
                    reference.advance(5_030_000_000, [0.0, 0.0, 0.0]), rtol=1e-7, atol=1e-12)


def test_long_gap_under_a_slackening_load_is_stepped(settings):
    """Where the held load would slacken a cable the closed form (linear) does not apply."""
    predictor = LivePredictor(settings)
    predictor.advance(0, [0.0, 0.0, 3000.0])
    predictor.advance(2_000_000_000, [0.0, 0.0, 0.0])
    assert 'node.max_steps_per_wrench' in predictor.notice


@pytest.mark.parametrize('name', sorted(p.name for p in CONFIG_DIR.glob('*.yaml')))
def test_every_shipped_robot_starts_without_a_model_warning(name):
    """Each shipped config names a model that meets its own tolerance at its initial pose:
    the node would start at OK, not at a warning the config could avoid."""
    predictor = LivePredictor(load_settings(CONFIG_DIR / name))
    assert predictor.last_update is not None
    assert predictor.last_update.warnings == ()


def _drive(predictor, start_ms: int, stop_ms: int) -> np.ndarray:
    """Wrenches every 1 ms (a 3 Hz / 5 Hz load) and a pose every 20 ms that moves 2 cm
    every 100 ms; the displacements predicted."""
    out = []
    for k in range(start_ms, stop_ms):
        if k % 20 == 0:
            predictor.update_pose([0.02 * (k // 100), 0.0, 1.25])
        t = k * 1e-3
        out.append(predictor.advance(k * 1_000_000, [30 * np.sin(6 * np.pi * t), 0.0,
                                                     200 * np.sin(10 * np.pi * t)]))
    return np.array(out)


@pytest.mark.parametrize('method,elements', [('spring', 1), ('fem', 8)])
def test_a_predictor_restored_from_a_checkpoint_continues_bit_for_bit(method, elements):
    settings = load_settings(CONFIG_DIR / 'paper_cdpr.yaml').replace(
        method=method, elements_per_cable=elements)
    running = LivePredictor(settings)
    _drive(running, 0, 250)
    checkpoint = running.checkpoint()
    restored = LivePredictor(settings)
    restored.restore(checkpoint)
    assert same_model(restored, checkpoint)
    np.testing.assert_array_equal(_drive(restored, 250, 500), _drive(running, 250, 500))
    np.testing.assert_array_equal(restored.integrator._state, running.integrator._state)


def test_a_checkpoint_of_another_model_is_refused():
    settings = load_settings(CONFIG_DIR / 'paper_cdpr.yaml')
    settings = settings.replace(method='fem', elements_per_cable=4)
    running = LivePredictor(settings)
    _drive(running, 0, 50)
    other = LivePredictor(settings.replace(elements_per_cable=5))
    assert not same_model(other, running.checkpoint())
    with pytest.raises(ValueError, match='differs'):
        other.restore(running.checkpoint())


def _alone_and_in_runs(settings, slack, stamps, force, moment, window=None):
    """A wrench stream through ``advance`` one by one and through ``advance_run`` (at most
    ``window`` wrenches a call), ``advance`` taking each wrench a run stops before: (the
    one-by-one predictor, the runs' predictor, q after each wrench (m, nd) alone and in runs,
    the wrenches the runs stopped before)."""
    alone, run = LivePredictor(settings, slack=slack), LivePredictor(settings, slack=slack)
    q_alone = np.array([alone.advance(int(t), f, m) for t, f, m in zip(stamps, force, moment)])
    q_run, start, stops = [], 0, []
    window = window or stamps.size
    while start < stamps.size:
        end = start + window
        done, q = run.advance_run(stamps[start:end], force[start:end], moment[start:end])
        q_run.extend(q[:, :3])
        start += done
        if start < stamps.size and done < window:
            q_run.append(run.advance(int(stamps[start]), force[start], moment[start]))
            stops.append(start)
            start += 1
    return alone, run, q_alone, np.array(q_run), stops


def _wrench_stream(count: int, amplitude_n: float, push_n: float, push_at: int,
                   gap_at: int) -> tuple:
    """(stamps, forces, moments) of ``count`` wrenches: ``amplitude_n`` at 5 Hz along z (and
    a tenth of it as a 3 Hz moment about x), a 40-wrench push of ``push_n`` from ``push_at``,
    intervals of 0, 1, 2 steps and sub-step remainders and one of 150 steps at ``gap_at``."""
    gaps = np.resize([1_000_000, 1_000_000, 0, 2_000_000, 1_300_000, 700_000], count)
    gaps[gap_at] = 150_000_000
    stamps = 1_700_000_000_000_000_000 + np.cumsum(gaps)
    t = (stamps - stamps[0]) * 1e-9
    force = np.zeros((count, 3))
    force[:, 2] = amplitude_n * np.sin(2 * np.pi * 5.0 * t)
    force[push_at:push_at + 40, 2] = push_n
    moment = np.zeros((count, 3))
    moment[:, 0] = 0.1 * amplitude_n * np.cos(2 * np.pi * 3.0 * t)
    return stamps, force, moment


@pytest.mark.parametrize('method, elements, slack', [('spring', 1, 'aware'),
                                                     ('fem', 4, 'aware'),
                                                     ('fem', 4, 'linear')])
def test_a_run_of_wrenches_advances_as_each_wrench_alone(method, elements, slack, monkeypatch):
    """advance_run over a wrench stream equals advance wrench by wrench (state, platform q
    after each wrench, slack time, held load): 200 N at 5 Hz with a 1500 N push that
    slackens cables (the run stops before the wrench whose steps reach slack and advance
    takes it), intervals of 0, 1, 2 and 150 steps (closed form or capped: advance's) and
    sub-step remainders. Bit for bit where the runs step the integrator (spring); fem's runs
    step in the model's modes, a different order of the same arithmetic: equal to round-off
    (test_runs_in_the_modes_equal_the_steps_to_round_off)."""
    from cdpr_dynamics.dynamics.held_load import HeldLoadSteps

    settings = load_settings().replace(method=method, elements_per_cable=elements)
    stamps, force, moment = _wrench_stream(600, 200.0, 1500.0, 300, 250)
    moment[:] = 0.0
    in_modes, run = [], HeldLoadSteps.run
    monkeypatch.setattr(HeldLoadSteps, 'run', lambda self, *args: (
        in_modes.append(1) or run(self, *args)))
    alone, run, q_alone, q_run, stops = _alone_and_in_runs(settings, slack, stamps, force,
                                                           moment)
    modal = method == 'fem'
    assert bool(in_modes) == modal                 # fem's runs went in the modes
    if modal:
        scale = np.abs(q_alone).max()
        assert np.abs(q_run - q_alone).max() <= 1e-9 * scale
        for got, expected in zip(run.integrator._state, alone.integrator._state):
            assert np.abs(got - expected).max() <= 1e-9 * np.abs(expected).max() + 1e-300
    else:
        assert np.array_equal(q_run, q_alone)
        assert np.array_equal(run.integrator._state, alone.integrator._state)
    assert run.slack_time_s == alone.slack_time_s
    assert np.array_equal(run._load, alone._load) and run._remainder_ns == alone._remainder_ns
    if slack == 'aware':
        assert alone.slack_time_s > 0.01           # slack for a while, and the runs stopped
        assert 10 < len(stops) < stamps.size / 4   # for it, but most wrenches went in runs
    disp, position, quaternion = run.predictions(q_run[-5:], (0.0, 0.0, 0.0))
    single = run.prediction()
    for got, expected in ((disp[-1], single.displacement_m), (position[-1], single.position_m),
                          (quaternion[-1], single.quaternion)):
        if modal:     # the run's last row and the state it leaves: two products, one number
            assert np.abs(got - expected).max() <= 1e-12 * np.abs(expected).max()
        else:
            assert np.array_equal(got, expected)


@pytest.mark.parametrize('method, elements', [('spring', 1), ('fem', 4)])
def test_linear_runs_go_on_through_a_long_slack_stretch(method, elements):
    """slack='linear' keeps integrating the linear model while a cable is slack and counts
    the slack time at each stamp: runs take the wrenches clearly slack too (a long push that
    holds cables slack for 300 wrenches is a few runs, not a run stopped at every wrench) and
    count as advance counts: the same slack time bit for bit and the same slack cables after
    every call."""
    settings = load_settings().replace(method=method, elements_per_cable=elements)
    stamps, force, moment = _wrench_stream(900, 200.0, 0.0, 0, 450)
    force[300:600, 2] = 1500.0                       # cables slack while it pushes
    alone, run = LivePredictor(settings, slack='linear'), LivePredictor(settings, slack='linear')
    slack_alone = []
    for t, f, m in zip(stamps, force, moment):
        alone.advance(int(t), f, m)
        slack_alone.append((alone.slack_cables, alone.slack_time_s))
    assert sum(1 for cables, _ in slack_alone if cables) > 250
    start, calls = 0, 0
    while start < stamps.size:
        done, _ = run.advance_run(stamps[start:start + 100], force[start:start + 100],
                                  moment[start:start + 100])
        if not done:
            run.advance(int(stamps[start]), force[start], moment[start])
            done = 1
        start += done
        calls += 1
        assert (run.slack_cables, run.slack_time_s) == slack_alone[start - 1]
    assert calls < 40                                # 9 windows of 100 and a few stops


@pytest.mark.parametrize('slack', ['aware', 'linear'])
@pytest.mark.parametrize('config, amplitude_n, push_n', [('paper_cdpr.yaml', 200.0, 1500.0),
                                                         ('heavy_sag_6dof.yaml', 2.0, 100.0),
                                                         ('low_tension_cdpr.yaml', 5.0, 300.0)])
def test_runs_in_the_modes_equal_the_steps_to_round_off(config, amplitude_n, push_n, slack,
                                                        monkeypatch):
    """fem 16 (363 and 366 DOFs): runs stepped in the model's modes give the predictions of
    advance one wrench at a time within 1e-9 of the peak |u|, and stop before the same
    wrenches as runs of the integrator's own steps (bit for bit with advance): a push that
    slackens a cable mid-run, intervals of 0 to 150 steps, on the paper robot (3 DOFs), a
    heavy-sag 6-DOF platform (moments too) and a low-tension robot. Every run takes the modal
    path here (MODAL_RUN_PAYBACK raised: windows of 256 wrenches)."""
    from cdpr_dynamics.analysis import live
    from cdpr_dynamics.dynamics.held_load import HeldLoadSteps

    settings = load_settings(CONFIG_DIR / config).replace(method='fem', elements_per_cable=16)
    stream = _wrench_stream(1200, amplitude_n, push_n, 800, 300)
    monkeypatch.setattr(live, 'MODAL_RUN_PAYBACK', 0)          # no modes: the steps
    stepped = _alone_and_in_runs(settings, slack, *stream, window=256)
    monkeypatch.setattr(live, 'MODAL_RUN_PAYBACK', 10**6)      # the modes for every run
    steps_in_modes = []
    run = HeldLoadSteps.run
    monkeypatch.setattr(HeldLoadSteps, 'run', lambda self, state, loads, steps, nd: (
        steps_in_modes.append(int(steps.sum())) or run(self, state, loads, steps, nd)))
    alone, modal, q_alone, q_modal, stops = _alone_and_in_runs(settings, slack, *stream,
                                                               window=256)
    assert np.array_equal(stepped[3], q_alone) and not stepped[1]._held
    assert sum(steps_in_modes) > 1000 and modal.integrator.u.size > 360
    assert stops == stepped[4] and 0 < len(stops) < 400         # the same stops, for slack
    assert alone.slack_time_s > 0.01 and modal.slack_time_s == alone.slack_time_s
    difference = np.abs(q_modal - q_alone).max()
    peak = np.abs(q_alone).max()
    print(f'\n{config} {slack}: max |difference| {difference / peak:.2g} x peak |u|')
    assert difference <= 1e-9 * peak
    nd = modal.system.platform_dofs
    assert np.abs(modal.integrator.u[:nd] - alone.integrator.u[:nd]).max() <= 1e-9 * peak


def test_runs_step_where_the_model_has_no_modes(settings, monkeypatch):
    """Where the modes cannot be had (matrices not finite, damping not Rayleigh, more DOFs
    than held_load.MAX_DOFS) runs take the integrator's steps: advance's numbers bit for bit."""
    from cdpr_dynamics.dynamics import held_load
    from cdpr_dynamics.dynamics.held_load import HeldLoadSteps
    from cdpr_dynamics.dynamics.system import DynamicsError

    predictor = LivePredictor(settings)
    k, m, a = predictor.integrator.k, predictor.integrator.m, predictor.integrator.a
    damping = predictor.integrator.damping
    with pytest.raises(DynamicsError, match='finite K, M and Rayleigh damping'):
        HeldLoadSteps(np.where(k.toarray() != 0.0, np.inf, 0.0), m, damping, a)
    with pytest.raises(DynamicsError, match='finite K, M and Rayleigh damping'):
        HeldLoadSteps(k, m, (damping.mass_factor, damping.stiffness_factor), a)
    stream = _wrench_stream(600, 200.0, 0.0, 300, 250)
    for patch in ('no modes', 'too many DOFs'):
        with monkeypatch.context() as context:
            if patch == 'too many DOFs':
                context.setattr(held_load, 'MAX_DOFS', 10)
            else:
                def refused(*args):
                    raise DynamicsError('not Rayleigh')
                context.setattr('cdpr_dynamics.analysis.live.HeldLoadSteps', refused)
            alone, run, q_alone, q_run, stops = _alone_and_in_runs(settings, 'aware', *stream)
        assert run._held is False and stops == [0, 250]   # the first, the 150-step gap
        assert np.array_equal(q_run, q_alone)
        assert np.array_equal(run.integrator._state, alone.integrator._state)


def test_modal_steps_equal_newmark_steps_from_any_state(settings):
    """HeldLoadSteps.run against Newmark.step from a state whose acceleration does not
    balance the load (as after a model change), under loads that change every step and are
    held for several: the platform rows after every step and the final state to round-off."""
    from cdpr_dynamics.dynamics.held_load import HeldLoadSteps

    predictor = LivePredictor(settings)
    integrator, nd = predictor.integrator, predictor.system.platform_dofs
    n = integrator.u.size
    modes = HeldLoadSteps(integrator.k, integrator.m, integrator.damping, integrator.a)
    rng = np.random.default_rng(3)
    state = rng.standard_normal((3, n)) * [[1e-4], [1e-3], [1e-1]]
    loads = rng.standard_normal((700, nd)) * 300.0
    steps = rng.integers(0, 4, size=700)
    taken, after = modes.run(state, loads, steps, nd)
    integrator._state[:] = state
    expected = []
    for load, times in zip(loads, steps):
        full = np.zeros(n)
        full[:nd] = load
        for _ in range(times):
            integrator.step(full)
            expected.append(integrator._state[:2, :nd].copy())
    expected = np.array(expected)
    assert taken.shape == expected.shape == (steps.sum(), 2, nd) and steps.sum() > 256
    for row in range(2):
        peak = np.abs(expected[:, row]).max()
        assert np.abs(taken[:, row] - expected[:, row]).max() <= 1e-9 * peak
    for got, want in zip(after, integrator._state):
        assert np.abs(got - want).max() <= 1e-9 * np.abs(want).max()
