"""cdpr_analyze and the settings it reads: JSON contract, plots, one-line errors."""
import json
import os
import subprocess

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.config import ConfigError, default_config_path, load_settings, \
    read_params_file, settings_from_params
from conftest import analyze, installed, write_config


def test_paper_config_is_the_default_and_matches_table_1():
    s = load_settings()
    assert default_config_path().name == 'paper_cdpr.yaml'
    assert s.robot.n_cables == 8 and s.robot.point_mass
    assert_allclose(s.cable.ea_n, 2.01e10 * 50.265e-6)
    assert (s.tension_min_n, s.tension_max_n, s.robot.mass_kg) == (100.0, 1000.0, 30.0)
    assert_allclose(s.frequencies_hz[:2], [1.0, 1.1])
    assert s.n_points == 391 and s.frequencies_hz[-1] == 40.0


@pytest.mark.parametrize('changes,message', [
    ({'robot.anchors': [0.0, 1.0]}, 'robot.anchors needs 3 values per cable'),
    ({'robot.mass_kg': -3.0}, 'robot.mass_kg = -3.0 is outside'),
    ({'model.method': 'magic'}, 'model.method must be one of'),
    ({'tension.min_n': 2000.0}, 'tension.min_n = 2000.0 exceeds tension.max_n'),
    ({'robot.initial_orientation': [0.0, 0.0, 0.0, 2.0]}, 'not a unit quaternion'),
    ({'cable.area_m2': 'thick'}, 'cable.area_m2 must be a number'),
    ({'robot.attachments': [0.1] * 24}, 'inertia_kg_m2 must be positive definite'),
])
def test_bad_settings_name_the_parameter(tmp_path, changes, message):
    with pytest.raises(ConfigError, match=message):
        load_settings(write_config(tmp_path, **changes))


def test_unknown_parameter_and_unparsable_file(tmp_path):
    with pytest.raises(ConfigError, match='unknown parameter robot.colour'):
        settings_from_params({'robot.colour': 'red'})
    bad = tmp_path / 'bad.yaml'
    bad.write_text('cdpr_dynamics: [unclosed\n')
    with pytest.raises(ConfigError, match='not valid YAML at line'):
        read_params_file(bad)


@pytest.mark.slow
def test_analyze_json_contract_and_plots(tmp_path):
    out = analyze('--method', 'fem', 'spring', '--elements', '4', '--json', tmp_path / 'a.json',
                  '--plot-dir', tmp_path / 'plots', '--excitation-hz', '5', '10',
                  '--duration', '0.5')
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / 'a.json').read_text())
    assert doc['method'] == 'fem' and doc['dofs'] == 3 + 8 * 3 * 3
    assert_allclose(sorted(doc['tensions_n']), [100.0] * 4 + [100 + 30 * 9.81 * 3 ** 0.5 / 4] * 4,
                    rtol=1e-6)
    assert_allclose(doc['cable_lengths_m'], [2.5 * 3 ** 0.5 / 2] * 8)
    freqs = doc['natural_frequencies_hz']
    assert len(freqs) >= 12 and freqs == sorted(freqs)
    frf = doc['frf']
    assert len(frf['frequency_hz']) == 391
    assert np.shape(frf['amplitude_m']) == (391, 3) and np.shape(frf['phase_rad']) == (391, 3)
    assert [h['excitation_hz'] for h in doc['time_history']] == [5.0, 10.0]
    h = doc['time_history'][0]
    assert len(h['t_s']) == 501 and np.shape(h['u_m']) == (501, 3)
    assert isinstance(h['slack'], bool) and isinstance(h['min_tension_n'], float)
    assert doc['model_choice']['method'] == 'fem' and doc['model_choice']['reason']
    assert {'tensions', 'assembly', 'frf', 'time_history'} <= set(doc['timings_s'])
    assert [m['method'] for m in doc['methods']] == ['fem', 'spring']
    assert (tmp_path / 'plots' / 'frf.png').stat().st_size > 10000
    assert (tmp_path / 'plots' / 'time_history.png').stat().st_size > 10000
    # the paper's 1500 N load slackens the lower cables (T = 100 N) in the linear response
    assert h['slack'] and any('slack' in w for w in doc['warnings'])


@pytest.mark.parametrize('changes,args,message', [
    ({}, ['--config', '/nonexistent.yaml'], 'cannot read config /nonexistent.yaml'),
    ({'robot.initial_position': [5.0, 0.0, 1.25]}, [], 'force x -0 is outside the reachable'),
    ({'robot.initial_position': [1.25, 1.25, 2.5]}, [], 'cable 6 has zero length'),
    ({'tension.max_n': 120.0}, [], 'infeasible tension distribution'),
    ({'model.elements_per_cable': 0}, [], 'model.elements_per_cable = 0 is outside'),
])
def test_analyze_errors_are_one_line_with_nonzero_status(tmp_path, changes, args, message):
    if changes or not args:
        args = ['--config', write_config(tmp_path, **changes)] + args
    out = analyze(*args)
    assert out.returncode != 0
    assert 'Traceback' not in out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], out.stderr


def test_analyze_without_ament_prefix_path_finds_the_paper_config(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != 'AMENT_PREFIX_PATH'}
    out = subprocess.run([installed('cdpr_analyze'), '--method', 'spring', '--json',
                          str(tmp_path / 'a.json')],
                         capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / 'a.json').read_text())['dofs'] == 3


@pytest.mark.slow
def test_sag_parameter_reported_and_straight_models_warned_on_slack_ish_cables(tmp_path):
    """Low tensions make lambda^2 large: straight models get a sag warning, catenary not."""
    config = write_config(tmp_path, **{'tension.min_n': 10.0, 'model.tolerance': 0.01})
    docs = {}
    for method in ('fem', 'catenary_exact'):
        out = analyze('--config', config, '--method', method, '--elements', '4',
                      '--json', tmp_path / f'{method}.json', '--duration', '0.05')
        assert out.returncode == 0, out.stderr
        docs[method] = json.loads((tmp_path / f'{method}.json').read_text())
    sag = np.array(docs['fem']['sag_parameter'])
    assert sag.shape == (8,) and sag.max() > 12 * 0.01
    assert any(w.startswith('sag: lambda^2') for w in docs['fem']['warnings'])
    assert not any(w.startswith('sag:') for w in docs['catenary_exact']['warnings'])


@pytest.mark.parametrize('args,message', [
    (['--n-points', '0'], 'frf.n_points = 0 is outside'),
    (['--f-min', '-5'], 'frf.f_min_hz = -5.0 is outside'),
    (['--elements', '5000'], 'model.elements_per_cable = 5000 is outside'),
    (['--json', '/proc/forbidden/a.json'], 'cannot write'),
])
def test_analyze_checks_command_line_overrides_like_the_config(args, message):
    out = analyze('--method', 'spring', '--duration', '0.01', *args)
    assert out.returncode == 1 and 'Traceback' not in out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], out.stderr


@pytest.mark.slow
def test_shaper_command_prints_what_the_node_publishes(tmp_path):
    """cdpr_analyze --shaper at a pose: the JSON's controller block is the library's (the
    shaper of the lowest platform modes, its notches, the modes table, the length offsets),
    and the lines printed carry the impulses."""
    from cdpr_dynamics.analysis.controller import controller_shaping, length_offsets
    from cdpr_dynamics.analysis.pipeline import (build_system, damping_for, equilibrium,
                                                 system_modes)
    config = write_config(tmp_path, **{'damping.modal_ratio': 0.02, 'damping.mass_factor': 0.0,
                                       'damping.stiffness_factor': 0.0})
    out = analyze('--config', config, '--method', 'spring', '--shaper', 'ei', '--shaper-modes',
                  '2', '--notch-sample-rate', '500', '--position', '0.3', '-0.2', '1.1',
                  '--duration', '0.01', '--json', tmp_path / 'a.json')
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / 'a.json').read_text())['controller']
    settings = load_settings(config).replace(method='spring',
                                             initial_position_m=np.array([0.3, -0.2, 1.1]))
    eq = equilibrium(settings)
    system = build_system(settings, eq)
    shaping = controller_shaping(system_modes(settings, system),
                                 damping_for(settings, system), 'ei', 2, 500.0)
    assert_allclose(doc['shaper']['times_s'], shaping.shaper.times_s)
    assert_allclose(doc['shaper']['amplitudes'], shaping.shaper.amplitudes)
    assert_allclose(doc['shaper']['notches'], shaping.notches)
    assert_allclose(doc['length_offsets_m'], length_offsets(settings.robot, eq))
    labels = doc['vibration_modes']['labels']
    assert labels[:4] == ['frequency_hz', 'damping_ratio', 'platform_energy_fraction', 'kind']
    assert 'ei shaper for ' in out.stdout and out.stdout.count('  t = ') == 9
    bad = analyze('--shaper', 'zvd', '--shaper-modes', '0', '--duration', '0.01')
    assert bad.returncode == 1 and bad.stderr.count('\n') == 1, bad.stderr
