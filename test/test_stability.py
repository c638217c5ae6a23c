"""Stability where methods fail: each case is detected, flagged or refused, never a NaN or a
traceback. The stability table of doc/failures.md (method, condition, what happens,
what the package does) lists the same cases in the same order:

catenary models at and near a hanging vertical cable, tension -> 0, no catenary solution;
straight models at zero or negative tension (K indefinite); fem with too few elements for the
band; Newmark with beta < 1/4 beyond its critical step; the undamped FRF exactly at a
resonance; a linear response that would slacken a cable (flagged; --slack-aware).
"""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cdpr_dynamics import models
from cdpr_dynamics.analysis.pipeline import (AnalysisError, Equilibrium, build_system, equilibrium,
                                             frf_arrays, safe)
from cdpr_dynamics.cli.analyze import analyze_method
from cdpr_dynamics.analysis.config import load_settings, read_params_file, settings_from_params
from cdpr_dynamics.dynamics.system import Damping, DynamicsError, Newmark, frequency_response
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.mechanics.robot import geometry
from cdpr_dynamics.mechanics.statics import EXIST_MARGIN, lowest_tension
from cdpr_dynamics.mechanics.tensions import TensionResult
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.dynamics.modes import natural_frequencies
from cdpr_dynamics.selection.reference import measure_error, reference_solution
from cdpr_dynamics.selection.auto import accuracy_warnings, choose_model
from conftest import analyze, write_config

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'paper_cdpr.yaml'
GRAVITY = np.array([0.0, 0.0, -9.81])
CATENARIES = ('catenary', 'catenary_exact', 'fem_sag')
STRAIGHT = ('spring', 'fem', 'dsm')


def one_cable(chord, tension, gamma=0.251, ea=1.01e6):
    return CableSet(np.atleast_2d(np.asarray(chord, float)),
                    np.atleast_1d(np.asarray(tension, float)), ea, gamma, GRAVITY)


def finite_stiffness(assembly):
    k = assembly.static_end_stiffness()
    dynamic = assembly.end_stiffness(np.array([(2 * np.pi * 5.0) ** 2 * (1 - 0.01j)]))
    return np.all(np.isfinite(k)) and np.all(np.isfinite(dynamic))


# --------------------------------------------------------------------------- catenary

def test_vertical_hanging_cable_is_finite_and_continuous():
    """At H = 0 (anchor straight above) and a hair away from it the stiffness is the same."""
    vertical = one_cable([0.0, 0.0, 2.0], 100.0)
    tilted = one_cable([2e-6, 0.0, 2.0], 100.0)
    assert sag_parameter(vertical)[0] == 0.0
    for method in CATENARIES:
        a, b = models.build(method, vertical, 8), models.build(method, tilted, 8)
        assert a.valid and b.valid and finite_stiffness(a), method
        ka, kb = a.static_end_stiffness()[0], b.static_end_stiffness()[0]
        assert np.all(np.linalg.eigvalsh(ka) > 0)
        np.testing.assert_allclose(kb, ka, rtol=1e-5, atol=1e-6 * np.abs(ka).max())
        # transverse: the hanging chain's T_mean / L (end tension 100 N, 0.5 N of cable)
        assert ka[0, 0] == pytest.approx((100.0 + 0.251) / 2.0, rel=1e-3), method


def test_pendulum_robot_on_one_vertical_cable():
    """A 5 kg mass on one vertical cable: every model, the pendulum frequency sqrt(g/L)/2pi."""
    flat = read_params_file(CONFIG)
    flat.update({'robot.anchors': [0.0, 0.0, 3.0], 'robot.attachments': [0.0] * 3,
                 'robot.mass_kg': 5.0, 'robot.initial_position': [0.0, 0.0, 1.0],
                 'tension.min_n': 1.0})
    settings = settings_from_params(flat)
    # an underactuated robot: the one cable carries the weight, gravity holds the sideways DOFs
    robot_eq = equilibrium(settings)
    assert robot_eq.tensions.tension_n == pytest.approx([5 * 9.81], rel=1e-9)
    # the models describe the pendulum the mass hangs as
    geo = geometry(settings.robot, settings.initial_position_m)
    tension = np.array([5 * 9.81])
    cables = CableSet(geo.chord_m, tension, settings.cable.ea_n,
                      settings.cable.weight_per_length_n_per_m, settings.robot.gravity_m_s2)
    eq = Equilibrium(geo, TensionResult(tension, 'solved', True, 0.0, 0), cables)
    pendulum = math.sqrt(9.81 / 2.0) / (2 * math.pi)
    for method in ('spring', 'catenary', 'catenary_exact', 'fem_sag', 'fem'):
        system = build_system(settings, eq, method, 4)
        assert system.assembly.valid
        assert natural_frequencies(system, 1)[0] == pytest.approx(pendulum, rel=0.02), method


@pytest.mark.slow
@pytest.mark.parametrize('tension', [10.0, 1.0, 0.3, 0.1, 0.01, 1e-6])
def test_tension_to_zero_never_gives_nan(tension):
    """A 3 m cable (0.75 N of weight), 1 m drop: valid while a taut catenary exists."""
    cables = one_cable([3.0, 0.0, 1.0], tension)
    for method in CATENARIES + STRAIGHT:
        assembly = models.build(method, cables, 8)
        assert finite_stiffness(assembly), (method, tension)
        if not assembly.valid:
            assert assembly.warnings, method
    exact = models.build('catenary_exact', cables)
    assert exact.valid == (tension >= 1.0)
    if not exact.valid:
        assert 'no taut elastic catenary' in exact.warnings[0]
        assert not models.build('fem_sag', cables, 8).valid


def test_cable_below_its_load_cannot_hold_its_weight():
    """Anchor under the platform and T < the cable's weight: no catenary, flagged."""
    cables = one_cable([0.0, 0.0, -2.0], 0.3)
    for method in CATENARIES:
        assembly = models.build(method, cables, 4)
        assert not assembly.valid and assembly.warnings and finite_stiffness(assembly), method


@pytest.mark.slow
def test_a_scene_without_a_catenary_at_tension_min(tmp_path):
    """Low-tension steel robot at tension.min_n = 0.05 N: no taut catenary spans the lower
    chords below ~5.7 N. The paper's catenary (L0 = chord at the chord tensions 0.05 N)
    refuses with one line; the sag-consistent statics lift those cables' lower bound to the
    least tension a catenary exists at (with a warning) and balance the platform."""
    flat = read_params_file(CONFIG)
    flat.update({'tension.min_n': 0.05, 'cable.weight_per_length_n_per_m': 2.0})
    settings = settings_from_params(flat)
    eq = equilibrium(settings)
    with pytest.raises(AnalysisError, match="fails for this scene: cable 0: no taut elastic "
                                            "catenary .* the paper's catenary assumes one"):
        analyze_method(settings.replace(method='catenary'), eq, [5.0], 0.1)
    doc = analyze_method(settings.replace(method='catenary_exact'), eq, [5.0], 0.1)
    lower = np.array(doc['tensions_n'][:4])
    exist = lowest_tension(eq.cables, np.ones(8, bool), settings.tension_max_n)[:4]
    assert np.all(lower >= EXIST_MARGIN * exist * (1 - 1e-9)) and np.all(exist > 20 * 0.05)
    assert any('no taut catenary spans its chord below' in w for w in doc['warnings'])
    assert doc['equilibrium']['relative_residual'] < 1e-9
    config = write_config(tmp_path, **{'tension.min_n': 0.05,
                                       'cable.weight_per_length_n_per_m': 2.0})
    out = analyze('--config', config, '--method', 'catenary', '--json', tmp_path / 'a.json')
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and 'method catenary fails for this scene' in lines[0]


# --------------------------------------------------------------------------- straight models

@pytest.mark.parametrize('tension', [0.0, -10.0])
def test_zero_or_negative_tension_is_invalid(tension):
    paper = load_settings(CONFIG)
    eq = equilibrium(paper)
    cables = eq.cables.with_tension(np.where(np.arange(8) == 3, tension,
                                             eq.cables.tension_n))
    for method in STRAIGHT:
        assembly = models.build(method, cables, 8)
        assert not assembly.valid and 'cable 3 is slack' in assembly.warnings[0], method
    spring = models.build('spring', cables).static_end_stiffness()[3]
    if tension < 0:                              # K_G makes K indefinite
        assert np.linalg.eigvalsh(spring).min() < 0
    broken = Equilibrium(eq.geometry, eq.tensions, cables)
    for method in ('spring', 'fem', 'auto'):
        with pytest.raises(AnalysisError, match='cable 3'):
            analyze_method(paper.replace(method=method), broken, [5.0], 0.1)


def test_fem_static_stiffness_is_finite_at_zero_tension():
    cables = one_cable([3.0, 0.0, 1.0], 0.0)
    assert np.all(np.isfinite(models.build('fem', cables, 8).static_end_stiffness()))


@pytest.mark.slow
def test_too_few_elements_for_the_band_are_detected_and_warned(tmp_path):
    paper = load_settings(CONFIG)
    eq = equilibrium(paper)
    warning = accuracy_warnings(paper, eq, 'fem', 2)
    assert warning and 'resolves 1 of the 2 modes per cable' in warning[0]
    reference = reference_solution(paper, eq)
    assert measure_error(paper, eq, 'fem', 2, reference).freq_error == 1.0
    assert measure_error(paper, eq, 'fem', 8, reference).freq_error > 0.02
    assert 'cable mode 2 off by 2.6 %' in accuracy_warnings(paper, eq, 'fem', 8)[0]
    out = analyze('--method', 'fem', '--elements', '2', '--json', tmp_path / 'a.json',
                  '--duration', '0.01')
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / 'a.json').read_text())
    assert any(w.startswith('accuracy: fem n=2') for w in doc['warnings'])


# --------------------------------------------------------------------------- Newmark

@pytest.mark.slow
def test_newmark_beta_below_a_quarter_beyond_its_critical_step_is_refused(tmp_path):
    """beta = 0.1: stable for w_max dt <= 1/sqrt(alpha/2 - beta) = 2.58 only."""
    paper = load_settings(CONFIG)
    eq = equilibrium(paper)
    fem = build_system(paper, eq, 'fem', 16)
    k, m = fem.matrices()
    with pytest.raises(DynamicsError, match='unstable'):
        Newmark(k, m, Damping(), 1e-3, 0.5, 0.1)          # axial cable modes at kHz
    spring = build_system(paper, eq, 'spring', 1)          # 32.4 Hz: dt_crit = 12.7 ms
    k, m = spring.matrices()
    Newmark(k, m, Damping(), 1e-3, 0.5, 0.1)
    with pytest.raises(DynamicsError, match='unstable'):
        Newmark(k, m, Damping(), 1.3e-2, 0.5, 0.1)
    config = write_config(tmp_path, **{'newmark.beta': 0.1})
    out = analyze('--config', config, '--method', 'fem', '--elements', '4',
                  '--json', tmp_path / 'a.json', '--duration', '0.01')
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and 'unstable' in lines[0], out.stderr


# --------------------------------------------------------------------------- FRF

def test_undamped_frf_exactly_at_a_resonance_is_flagged():
    paper = load_settings(CONFIG)
    eq = equilibrium(paper)
    for method, n in (('spring', 1), ('fem', 16)):
        system = build_system(paper, eq, method, n)
        freqs = natural_frequencies(system, 30)
        platform = freqs[np.argmin(np.abs(freqs - 32.4))]
        r = frequency_response(system, [platform, 5.0], [0.0, 0.0, 1500.0])
        assert r.singular.tolist() == [True, False], method
        assert np.isinf(r.amplitude_m[0]).all() and np.isfinite(r.amplitude_m[1]).all()
    spring = build_system(paper, eq, 'spring', 1)
    undamped = paper.replace(damping_mass_factor=0.0, damping_stiffness_factor=0.0,
                             f_min_hz=float(natural_frequencies(spring, 1)[0]),
                             f_max_hz=40.0, n_points=2)
    arrays = frf_arrays(undamped, spring)              # the service's arrays
    assert np.isinf(arrays['amplitude_z_m'][0]) and np.isinf(arrays['log10_amplitude_z'][0])
    assert not any(np.isnan(v).any() for v in arrays.values() if not isinstance(v, str))
    # dsm (Wittrick-Williams frequencies, 1e-9 Hz): huge but finite, never NaN or a raise
    dsm = build_system(paper, eq, 'dsm', 0)
    f = natural_frequencies(dsm, 25)
    r = frequency_response(dsm, f[[0, 24]], [0.0, 0.0, 1500.0])
    assert not np.isnan(r.amplitude_m).any() and np.all(r.amplitude_m[:, 2] > 1e3)
    # auto judges an undamped FRF by the frequencies alone: no inf in its estimate
    assert math.isfinite(choose_model(undamped.replace(f_min_hz=1.0, n_points=40), eq)
                         .estimated_error)


# --------------------------------------------------------------------------- linear validity

@pytest.mark.slow
def test_linear_response_that_slackens_a_cable_is_flagged(tmp_path):
    out = analyze('--method', 'spring', '--slack-aware', '--duration', '0.3',
                  '--json', tmp_path / 'a.json')
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / 'a.json').read_text())
    history = doc['time_history'][0]
    assert history['slack'] is True and history['min_tension_n'] < 0
    assert any('would go slack' in w for w in doc['warnings'])
    aware = history['slack_aware']
    assert aware['method'] == 'spring' and aware['min_tension_n'] == 0.0
    assert aware['peak_uz_m'] > 1.2 * aware['peak_uz_linear_m']
    assert len(aware['u_m']) == len(history['t_s'])
    small = analyze('--config', write_config(tmp_path, **{'frf.force_n': [0.0, 0.0, 100.0]}),
                    '--method', 'fem', '--elements', '1', '--slack-aware', '--duration',
                    '0.3', '--json', tmp_path / 'b.json')
    assert small.returncode == 0, small.stderr
    history = json.loads((tmp_path / 'b.json').read_text())['time_history'][0]
    assert history['slack'] is False and max(history['slack_aware']['slack_fraction']) == 0
    assert history['slack_aware']['peak_uz_m'] == pytest.approx(
        history['slack_aware']['peak_uz_linear_m'], rel=1e-4)


@pytest.mark.slow
def test_auto_reason_reaches_the_analyze_json(tmp_path):
    config = write_config(tmp_path, **{'model.method': 'auto', 'model.tolerance': 0.01})
    out = analyze('--config', config, '--json', tmp_path / 'a.json', '--duration', '0.01')
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / 'a.json').read_text())
    choice = doc['model_choice']
    assert (choice['method'], choice['elements_per_cable']) == ('fem_sag', 15)
    assert choice['reason'].startswith('auto: fem_sag n=15') and choice['estimated_error'] < 0.01
    assert doc['method'] == 'fem_sag' and doc['dofs'] == 339
    assert safe(choose_model, load_settings(config), equilibrium(load_settings(config))) \
        .reason == choice['reason']
