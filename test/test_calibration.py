"""cdpr_calibrate fit: sensitivities, pairing, synthetic campaigns recovered, the YAML and CLI.

The campaigns' frequencies come from the package's own model at random poses (the pipeline's
statics and assembly, eig(K, M) of the platform: :func:`campaign`) with 1 % noise; the fit
starts from the config's values and must find the true ones.
"""
import json
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.calibration import (CalibrationError, FitProblem, PoseModel,
                                                calibrated_yaml, eigenvalue_derivatives, fit,
                                                pair_modes, parse_targets, resolved_method)
from cdpr_dynamics.analysis.config import read_params_file, settings_from_params
from cdpr_dynamics.analysis.modes_table import (ModesTable, TableError, read_modes_table,
                                                write_modes_table)
from cdpr_dynamics.analysis.synthetic import campaign
from cdpr_dynamics.cli.calibrate import main
from cdpr_dynamics.dynamics.system import Damping

ROOT = Path(__file__).resolve().parents[1]
RIGID = ROOT / 'test' / 'data' / 'rigid_cdpr.yaml'
SAGGING = ROOT / 'test' / 'data' / 'sagging_6dof.yaml'
PAPER = ROOT / 'config' / 'paper_cdpr.yaml'
PULLEYS = ROOT / 'config' / 'paper_pulleys.yaml'


def fitted(report, name):
    return next(p for p in report['parameters'] if p['name'] == name)


def recovers_modulus_and_inertia(config, truth, table) -> dict:
    """Fit E and the inertia diagonal with a quarter of the poses held out: E within 5 %, the
    inertia within 10 %, the held-out error at the 1 % noise."""
    report = fit(config, table, ['cable.youngs_modulus_pa', 'robot.inertia_kg_m2[0]',
                                 'robot.inertia_kg_m2[1]', 'robot.inertia_kg_m2[2]'],
                 holdout=0.25).report
    modulus = fitted(report, 'cable.youngs_modulus_pa')['fitted']
    assert abs(modulus / truth['cable.youngs_modulus_pa'] - 1) < 0.05
    for i in range(3):
        true = truth['robot.inertia_kg_m2'][i]
        assert abs(fitted(report, f'robot.inertia_kg_m2[{i}]')['fitted'] / true - 1) < 0.10
    assert report['rms_error_pct']['holdout']['after'] < 1.5
    return report


# --------------------------------------------------------------------------- pieces

def test_eigenvalue_derivatives_match_finite_differences():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((6, 6))
    k = a @ a.T + 6 * np.eye(6)
    b = rng.standard_normal((6, 6))
    m = b @ b.T + 6 * np.eye(6)
    dk, dm = rng.standard_normal((2, 6, 6))
    dk, dm = dk + dk.T, dm + dm.T
    lam, phi = scipy.linalg.eigh(k, m)
    h = 1e-7
    numeric = (scipy.linalg.eigh(k + h * dk, m + h * dm, eigvals_only=True) - lam) / h
    assert_allclose(eigenvalue_derivatives(PoseModel(k, m, lam, phi), dk, dm), numeric,
                    rtol=1e-5, atol=1e-5)
    # a repeated eigenvalue: the perturbed pair splits as the projected derivative says
    k2, m2 = np.diag([1.0, 4.0, 4.0]), np.eye(3)
    dk2 = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 2.0], [0.0, 2.0, -1.0]])
    lam2, phi2 = scipy.linalg.eigh(k2, m2)
    numeric2 = (scipy.linalg.eigh(k2 + h * dk2, m2, eigvals_only=True) - lam2) / h
    got = eigenvalue_derivatives(PoseModel(k2, m2, lam2, phi2), dk2, np.zeros((3, 3)))
    assert_allclose(got, numeric2, atol=1e-5)
    assert_allclose(got[1:], [-np.sqrt(5), np.sqrt(5)], rtol=1e-9)


def test_jacobian_matches_finite_differences_of_the_residuals():
    flat = read_params_file(RIGID)
    flat['model.method'] = 'spring'
    table = campaign(flat, 4, 6, tilt_rad=0.1)
    targets = parse_targets(['cable.youngs_modulus_pa', 'robot.mass_kg',
                             'robot.inertia_kg_m2[0]', 'robot.inertia_kg_m2[4]'], flat)
    settings = settings_from_params(flat)
    methods = {p: resolved_method(settings, table.pose[table.rows_of(p)[0]])
               for p in table.poses}
    problem = FitProblem(flat, targets, table, table.poses, methods)
    x = problem.p0 / problem.scale
    jac = problem.jacobian(x)
    for k in range(len(targets)):
        h = 1e-4
        up, down = x.copy(), x.copy()
        up[k] += h
        down[k] -= h
        numeric = (problem.residuals(up) - problem.residuals(down)) / (2 * h)
        assert_allclose(jac[:, k], numeric, rtol=2e-3, atol=2e-3 * np.abs(numeric).max())
        assert np.abs(numeric).max() > 0


def test_pairing_follows_the_direction_where_the_table_has_it():
    model_hz = np.array([10.0, 10.3])
    shapes = np.array([[1.0, 0.0], [0.0, 1.0]])
    measured = np.array([10.25, 10.05])            # by frequency alone: swapped
    directions = np.full((2, 6), np.nan)
    assert pair_modes(model_hz, shapes, measured, directions).tolist() == [1, 0]
    directions[:, :2] = [[1.0, 0.02], [0.01, 1.0]]
    assert pair_modes(model_hz, shapes, measured, directions).tolist() == [0, 1]
    # a measured mode far from every model mode (a cable mode) stays unpaired
    far = pair_modes(model_hz, shapes, [10.05, 40.0], np.full((2, 6), np.nan))
    assert far.tolist() == [0, -1]


def test_modes_table_round_trip_and_errors(tmp_path):
    flat = read_params_file(RIGID)
    flat['model.method'] = 'spring'
    table = campaign(flat, 2, 3, directions=True)
    path = tmp_path / 'modes.csv'
    write_modes_table(path, table, ['a comment'])
    back = read_modes_table(path)
    assert_allclose(back.frequency_hz, table.frequency_hz, rtol=1e-9)
    assert_allclose(back.direction, table.direction, rtol=1e-9, atol=1e-12)
    assert np.isnan(back.damping_ratio).all()
    text = path.read_text()
    for broken, message in ((text.replace('frequency_hz', 'freq'), 'lacks column frequency_hz'),
                            (text.replace(',0,0,0,1,', ',0,0,0,2,', 1), 'unit quaternion'),
                            ('pose_id,x_m\n', 'lacks column')):
        path.write_text(broken)
        with pytest.raises(TableError, match=message):
            read_modes_table(path)


# --------------------------------------------------------------------------- campaigns

@pytest.mark.slow
def test_rigid_platform_stiffness_inertia_and_damping_recovered(tmp_path):
    """Rigid robot (6 DOF, spring model): EA +15 %, inertia changed, Rayleigh damping; the
    fit starts from the config's values, 30 % of the poses held out."""
    config = read_params_file(RIGID)
    config['model.method'] = 'spring'
    truth = dict(config, **{'cable.youngs_modulus_pa': 2.01e10 * 1.15,
                            'robot.inertia_kg_m2': [0.26, 0.21, 0.16, 0.0, 0.0, 0.0]})
    damping = Damping(0.4, 1.5e-4)
    table = campaign(truth, 30, 6, tilt_rad=0.15, damping=damping)
    result = fit(config, table, ['cable.youngs_modulus_pa', 'robot.inertia_kg_m2[0]',
                                 'robot.inertia_kg_m2[1]', 'robot.inertia_kg_m2[2]',
                                 'damping.mass_factor', 'damping.stiffness_factor'],
                 holdout=0.3)
    report = result.report
    ea = fitted(report, 'cable.youngs_modulus_pa')
    assert abs(ea['fitted'] / (2.01e10 * 1.15) - 1) < 0.05
    assert abs(ea['fitted'] - 2.01e10 * 1.15) < 4 * ea['std']
    for i, true in enumerate((0.26, 0.21, 0.16)):
        inertia = fitted(report, f'robot.inertia_kg_m2[{i}]')
        assert abs(inertia['fitted'] / true - 1) < 0.10, inertia
        assert 0 < inertia['std'] < 0.1 * true
    held = report['rms_error_pct']['holdout']
    assert held['before'] > 4.0 and held['after'] < 1.5, held     # noise 1 %
    f = table.frequency_hz
    found = Damping(result.flat['damping.mass_factor'], result.flat['damping.stiffness_factor'])
    assert np.all(np.abs(found.ratios(f) / damping.ratios(f) - 1) < 0.2)
    assert result.flat['damping.modal_ratio'] == 0.0
    assert report['unidentifiable'] == []


def test_point_mass_paper_robot_stiffness_recovered():
    """The paper's point-mass robot with its fem model (3 DOF): EA -20 %."""
    config = read_params_file(PAPER)
    config['model.elements_per_cable'] = 4
    truth = dict(config, **{'cable.youngs_modulus_pa': 2.01e10 * 0.8})
    table = campaign(truth, 12, 3, spread_m=0.3)
    report = fit(config, table, ['cable.youngs_modulus_pa'], holdout=0.25).report
    ea = fitted(report, 'cable.youngs_modulus_pa')
    assert abs(ea['fitted'] / (2.01e10 * 0.8) - 1) < 0.05
    assert report['rms_error_pct']['holdout']['after'] < 1.5


@pytest.mark.slow
def test_sagging_robot_with_a_sag_aware_model_recovered():
    """Heavy-sag robot with fem_sag: EA and the inertia diagonal; the sag makes the platform
    modes depend on EA through the catenary, not as EA/L."""
    config = read_params_file(SAGGING)
    config.update({'model.method': 'fem_sag', 'model.elements_per_cable': 4})
    truth = dict(config, **{'cable.youngs_modulus_pa': 2.0e11 * 0.7,
                            'robot.inertia_kg_m2': [0.18, 0.14, 0.12, 0.0, 0.0, 0.0]})
    recovers_modulus_and_inertia(config, truth, campaign(truth, 12, 6, spread_m=0.5))


def test_underactuated_suspended_robot_recovered():
    """Three cables from a ring above to a ring on the platform (a trifilar, 6 DOF held by
    gravity): the table's poses are its equilibria; each trial parameter set hangs the
    platform again (the direct geometrico-static problem at the pose's cable lengths)."""
    def ring(radius_m, z_m):
        angle = np.deg2rad(90.0 + 120.0 * np.arange(3))
        return np.c_[radius_m * np.cos(angle), radius_m * np.sin(angle), np.full(3, z_m)]
    config = dict(read_params_file(PAPER), **{
        'robot.anchors': ring(1.5, 2.5).ravel().tolist(),
        'robot.attachments': ring(0.15, 0.0).ravel().tolist(),
        'robot.initial_position': [0.0, 0.0, 1.0], 'robot.mass_kg': 8.0,
        'robot.inertia_kg_m2': [0.1, 0.1, 0.15, 0.0, 0.0, 0.0], 'tension.min_n': 1.0,
        'model.method': 'spring'})
    truth = dict(config, **{'cable.youngs_modulus_pa': 2.01e10 * 0.8,
                            'robot.inertia_kg_m2': [0.12, 0.11, 0.18, 0.0, 0.0, 0.0]})
    report = recovers_modulus_and_inertia(config, truth, campaign(truth, 16, 6, spread_m=0.3))
    assert report['skipped_poses'] == []


def test_an_unidentifiable_combination_is_named_and_left_unfitted():
    """Only EA = E A enters the model: fitting E and A names their difference."""
    config = read_params_file(RIGID)
    config['model.method'] = 'spring'
    truth = dict(config, **{'cable.youngs_modulus_pa': 2.01e10 * 1.1})
    table = campaign(truth, 10, 6)
    result = fit(config, table, ['cable.area_m2', 'cable.youngs_modulus_pa'])
    (item,) = result.report['unidentifiable']
    assert set(item['combination']) == {'cable.area_m2', 'cable.youngs_modulus_pa'}
    coefficients = list(item['combination'].values())
    assert_allclose(coefficients[0], -coefficients[1], rtol=1e-3)
    left = item['left_unfitted']
    assert fitted(result.report, left)['fitted'] is None
    product = result.flat['cable.area_m2'] * result.flat['cable.youngs_modulus_pa']
    assert abs(product / (5.0265e-05 * 2.01e10 * 1.1) - 1) < 0.02


def test_modal_damping_ratio_fitted_as_a_weighted_mean():
    config = read_params_file(RIGID)
    config['model.method'] = 'spring'
    table = campaign(config, 6, 6, damping=Damping(0.0, 0.0))
    zeta = 0.03 * (1 + 0.05 * np.random.default_rng(0).standard_normal(table.pose_id.size))
    table = ModesTable(table.pose_id, table.pose, table.frequency_hz, table.std_hz, zeta,
                       np.full(zeta.size, 0.0015), table.direction)
    result = fit(config, table, ['damping.modal_ratio'])
    (p,) = result.report['parameters']
    assert abs(p['fitted'] - 0.03) < 3 * p['std'] and p['std'] < 0.001
    assert_allclose(p['fitted'], np.mean(zeta), rtol=1e-9)     # equal weights: the mean
    assert result.flat['damping.mass_factor'] == result.flat['damping.stiffness_factor'] == 0


# --------------------------------------------------------------------------- YAML and CLI

def test_calibrated_yaml_replaces_and_adds_values_keeping_the_rest(tmp_path):
    text = RIGID.read_text()
    out = calibrated_yaml(text, {'robot.mass_kg': 31.5, 'robot.inertia_kg_m2': [1, 2, 3, 0, 0, 0],
                                 'damping.modal_ratio': 0.02},
                          {'robot.mass_kg': {None: (31.5, 0.25)},
                           'robot.inertia_kg_m2': {0: (1.0, 0.1)}})
    assert out.startswith(text.splitlines()[0])            # the comments stay
    assert 'mass_kg: 31.5  # calibrated, standard uncertainty 0.25' in out
    assert '[0] 0.1' in out
    (tmp_path / 'calibrated.yaml').write_text(out)
    flat = read_params_file(tmp_path / 'calibrated.yaml')
    assert flat['robot.mass_kg'] == 31.5 and flat['damping.modal_ratio'] == 0.02
    assert flat['robot.inertia_kg_m2'] == [1, 2, 3, 0, 0, 0]
    assert flat['cable.area_m2'] == read_params_file(RIGID)['cable.area_m2']


@pytest.mark.slow
def test_cli_fit_writes_yaml_report_and_figures(tmp_path, capsys):
    config = read_params_file(RIGID)
    config['model.method'] = 'spring'
    truth = dict(config, **{'cable.youngs_modulus_pa': 2.2e10})
    table = campaign(truth, 8, 4, directions=True, damping=Damping(0.0, 4e-4))
    write_modes_table(tmp_path / 'modes.csv', table)
    yaml_in = tmp_path / 'robot.yaml'
    yaml_in.write_text(RIGID.read_text().replace('method: fem', 'method: spring'))
    out = tmp_path / 'calibrated.yaml'
    code = main(['fit', '--config', str(yaml_in), '--measurements', str(tmp_path / 'modes.csv'),
                 '--fit', 'cable.youngs_modulus_pa', 'damping.modal_ratio', '--output', str(out),
                 '--holdout', '0.25', '--report', str(tmp_path / 'report')])
    assert code == 0
    calibrated = read_params_file(out)
    settings = settings_from_params(calibrated)       # the file's Rayleigh factors set to 0
    assert settings.damping_modal_ratio > 0 and settings.damping_mass_factor == 0
    value = calibrated['cable.youngs_modulus_pa']
    assert abs(value / 2.2e10 - 1) < 0.02
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    assert report['parameters'][0]['fitted'] == pytest.approx(value, rel=1e-9)
    assert len(report['holdout_poses']) == 2
    for name in ('frequencies.png', 'residuals.png'):
        assert (tmp_path / 'report' / name).stat().st_size > 10000
    assert 'youngs_modulus_pa' in capsys.readouterr().out


@pytest.mark.parametrize('args, message', [
    (['--fit', 'robot.mass_kgg'], 'did you mean robot.mass_kg'),
    (['--fit', 'model.method'], 'not a real-valued parameter'),
    (['--fit', 'robot.inertia_kg_m2[6]'], 'has 6 values'),
    (['--fit', 'robot.mass_kg', '--holdout', '1.5'], 'must be in [0, 1)'),
])
def test_cli_fit_errors_are_one_line(tmp_path, capsys, args, message):
    config = read_params_file(RIGID)
    config['model.method'] = 'spring'
    write_modes_table(tmp_path / 'modes.csv', campaign(config, 2, 2))
    code = main(['fit', '--config', str(RIGID), '--measurements', str(tmp_path / 'modes.csv'),
                 '--output', str(tmp_path / 'out.yaml')] + args)
    err = capsys.readouterr().err
    assert code == 1 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / 'out.yaml').exists()


@pytest.mark.slow
def test_centre_of_mass_and_inertia_recovered():
    """Rigid robot with its centre of mass off the platform frame's origin: the centre of mass
    within 5 mm and the inertia diagonal within 10 %, from 6 modes a pose."""
    config = read_params_file(RIGID)
    config['model.method'] = 'spring'
    true_com = [0.01, -0.015, 0.03]
    truth = dict(config, **{'robot.center_of_mass_m': true_com,
                            'robot.inertia_kg_m2': [0.26, 0.21, 0.16, 0.0, 0.0, 0.0]})
    table = campaign(truth, 30, 6, tilt_rad=0.15)
    report = fit(config, table, ['robot.center_of_mass_m', 'robot.inertia_kg_m2[0]',
                                 'robot.inertia_kg_m2[1]', 'robot.inertia_kg_m2[2]'],
                 holdout=0.3).report
    for i, true in enumerate(true_com):
        com = fitted(report, f'robot.center_of_mass_m[{i}]')
        assert abs(com['fitted'] - true) < 0.005 and 0 < com['std'] < 0.005, com
    for i, true in enumerate((0.26, 0.21, 0.16)):
        assert abs(fitted(report, f'robot.inertia_kg_m2[{i}]')['fitted'] / true - 1) < 0.10
    held = report['rms_error_pct']['holdout']
    assert held['before'] > 2.0 and held['after'] < 1.5, held


@pytest.mark.slow
def test_one_pulley_radius_shared_by_every_pulley_recovered(tmp_path, capsys):
    """The rigid robot over the pulleys of paper_pulleys.yaml (1 m winch side), all of one
    radius: ``robot.pulley_radii_m[*]`` fits that one radius beside EA (true 65 mm, start
    50 mm) within a few %, every pulley set to it."""
    config = read_params_file(RIGID)
    config.update({'model.method': 'spring',
                   'robot.pulley_axes': read_params_file(PULLEYS)['robot.pulley_axes'],
                   'robot.pulley_radii_m': [0.05] * 8, 'cable.winch_side_lengths_m': [1.0] * 8})
    truth = dict(config, **{'robot.pulley_radii_m': [0.065] * 8,
                            'cable.youngs_modulus_pa': 2.2e10})
    table = campaign(truth, 40, 6, tilt_rad=0.15, spread_m=0.3)
    result = fit(config, table, ['robot.pulley_radii_m[*]', 'cable.youngs_modulus_pa'],
                 holdout=0.25)
    radius = fitted(result.report, 'robot.pulley_radii_m[*]')
    assert abs(radius['fitted'] / 0.065 - 1) < 0.05, radius
    assert abs(radius['fitted'] - 0.065) < 4 * radius['std'] and radius['std'] < 0.003
    assert result.flat['robot.pulley_radii_m'] == [radius['fitted']] * 8
    assert abs(fitted(result.report, 'cable.youngs_modulus_pa')['fitted'] / 2.2e10 - 1) < 0.02
    assert result.report['rms_error_pct']['holdout']['after'] < 1.5
    text = calibrated_yaml(PULLEYS.read_text(), {'robot.pulley_radii_m': result.flat[
        'robot.pulley_radii_m']}, {'robot.pulley_radii_m': result.values['robot.pulley_radii_m']})
    assert 'calibrated (one value for all), standard uncertainty' in text
    (tmp_path / 'calibrated.yaml').write_text(text)
    assert read_params_file(tmp_path / 'calibrated.yaml')['robot.pulley_radii_m'] == \
        pytest.approx([radius['fitted']] * 8, rel=1e-9)


@pytest.mark.parametrize('names, message', [
    (['robot.pulley_radii_m[*]', 'robot.pulley_radii_m[2]'], 'both shared ([*]) and by component'),
    (['robot.pulley_radii_m[0]', 'robot.pulley_radii_m[*]'], 'both shared ([*]) and by component'),
    (['robot.mass_kg[*]'], 'is a single number'),
])
def test_shared_target_errors(names, message):
    flat = read_params_file(PULLEYS)
    with pytest.raises(CalibrationError, match=re.escape(message)):
        parse_targets(names, flat)
