"""Classified modes in cdpr_analyze's JSON, the 6-DOF FRF at a tool point, live 6-DOF output.

Independent answers: the effective masses over all modes against the mass matrix's platform
diagonal; reciprocity of H = Z^-1; the point response against u + theta x r with numpy's
cross product; the predicted pose against a rotation built by scipy from the DOF response.
"""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdpr_dynamics.analysis.pipeline import (POINT_MASS_ROTATION, build_system, damping_for,
                                             equilibrium, frf_arrays, frf_response, receptance,
                                             system_modes)
from cdpr_dynamics.cli.analyze import analyze_method
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import frequency_response
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.dynamics.modes import modes
from msg_adapters.frf_service import parse_request, settings_changes

HERE = Path(__file__).parent
RIGID = HERE / 'data' / 'rigid_cdpr.yaml'
TOOL_M = np.array([0.3, 0.0, 0.0])


@pytest.fixture(scope='module')
def paper():
    settings = load_settings(None).replace(method='fem', elements_per_cable=16)
    return settings, equilibrium(settings)


@pytest.fixture(scope='module')
def rigid():
    settings = load_settings(RIGID).replace(method='fem', elements_per_cable=4, n_points=61)
    return settings, equilibrium(settings)


def test_paper_fem16_json_lists_the_platform_triple(paper):
    settings, eq = paper
    doc = analyze_method(settings, eq, [], 1.0)
    entries = doc['modes']
    assert [m['frequency_hz'] for m in entries] == doc['natural_frequencies_hz']
    assert len(entries) >= 12 and all(m['frequency_hz'] <= settings.f_max_hz
                                      for m in entries[12:])
    platform = [m for m in entries if m['kind'] == 'platform']
    assert len(platform) == 3
    for m in platform:
        assert m['frequency_hz'] == pytest.approx(32.4, abs=0.05)
        assert m['platform_energy_fraction'] > 0.9 and m['cable'] is None
        assert len(m['effective_mass']) == 3 and m['damping_ratio'] > 0
    assert doc['platform_natural_frequencies_hz'] == [m['frequency_hz'] for m in platform]
    cable = [m for m in entries if m['kind'] == 'cable']
    assert cable and all(0 <= m['cable'] < 8 for m in cable)
    assert cable[0]['frequency_hz'] < 20.0          # the cables' modes lie below the platform's
    gain = np.asarray(doc['frf']['receptance']['real']) \
        + 1j * np.asarray(doc['frf']['receptance']['imag'])
    assert gain.shape == (settings.n_points, 3, 3)
    np.testing.assert_allclose(np.abs(gain[:, 2, 2]) * settings.frf_force_n[2],
                               np.asarray(doc['frf']['amplitude_m'])[:, 2], rtol=1e-9)


@pytest.mark.parametrize('config', ['paper', 'rigid'])
def test_effective_masses_over_all_modes_sum_to_the_platform_diagonal(config, paper, rigid):
    settings, eq = {'paper': paper, 'rigid': rigid}[config]
    system = build_system(settings.replace(elements_per_cable=3), eq)
    found = modes(system, None, count=system.dofs)
    assert found.frequency_hz.size == system.dofs
    _, mass = system.matrices(dense=True)
    nd = system.platform_dofs
    np.testing.assert_allclose(found.effective_mass.sum(axis=0), np.diag(mass)[:nd], rtol=1e-8)
    assert np.diag(mass)[0] > settings.robot.mass_kg      # the cables' end-node share


def test_massless_models_list_platform_modes(rigid):
    settings, eq = rigid
    system = build_system(settings, eq, 'spring')
    found = system_modes(settings, system)
    assert found.kind == ('platform',) * 6
    arrays = frf_arrays(settings, system)
    np.testing.assert_allclose(arrays['mode_platform_fraction'], 1.0)
    np.testing.assert_allclose(arrays['platform_natural_frequencies_hz'],
                               arrays['natural_frequencies_hz'])


def test_receptance_is_reciprocal_and_gives_the_tool_point(rigid):
    settings, eq = rigid
    system = build_system(settings, eq)
    tool = settings.replace(frf_point_m=TOOL_M, frf_moment_nm=np.array([0.0, 4.0, 1.0]))
    damping = damping_for(tool, system)
    gain = receptance(system, tool.frequencies_hz, damping)
    assert gain.shape == (tool.n_points, 6, 6)
    scale = np.abs(gain).max()
    assert np.abs(gain - gain.transpose(0, 2, 1)).max() < 1e-9 * scale   # H = H^T
    response, point = frf_response(tool, system)
    load = np.concatenate([tool.frf_force_n, tool.frf_moment_nm])
    q = gain @ load
    np.testing.assert_allclose(response.response, q, rtol=1e-9, atol=1e-12 * np.abs(q).max())
    r = eq.geometry.rotation @ TOOL_M
    expected = q[:, :3] + np.cross(q[:, 3:], r)
    np.testing.assert_allclose(point, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    assert np.abs(point - q[:, :3]).max() > 1e-3 * np.abs(q[:, :3]).max()   # the arm matters
    arrays = frf_arrays(tool, system)
    np.testing.assert_allclose(arrays['amplitude_y_m'], np.abs(expected[:, 1]), rtol=1e-9)
    np.testing.assert_allclose(arrays['rotation_y_rad'], np.abs(q[:, 4]), rtol=1e-9)


def test_point_mass_frf_is_unchanged_by_the_new_settings(paper):
    settings, eq = paper
    settings = settings.replace(elements_per_cable=4, frf_point_m=TOOL_M,
                                frf_moment_nm=np.array([1.0, 2.0, 3.0]))
    system = build_system(settings, eq)
    arrays = frf_arrays(settings, system)
    plain = frequency_response(system, settings.frequencies_hz, settings.frf_force_n,
                               damping=damping_for(settings, system))
    np.testing.assert_array_equal(arrays['amplitude_z_m'], plain.amplitude_m[:, 2])
    np.testing.assert_array_equal(arrays['phase_x_rad'], plain.phase_rad[:, 0])
    assert arrays['rotation_x_rad'] == POINT_MASS_ROTATION


def test_service_moment_overrides():
    request = parse_request(['amplitude_z_m', 'moment_y_nm=2.5', 'force_x_n=1'])
    assert not request.error and request.names == ['amplitude_z_m']
    changes = settings_changes(request.overrides, [0.0, 0.0, 1500.0], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(changes['frf_moment_nm'], [1.0, 2.5, 0.0])
    np.testing.assert_array_equal(changes['frf_force_n'], [1.0, 0.0, 1500.0])
    assert parse_request(['moment_q_nm=1']).error.startswith('unknown override')


def test_live_prediction_at_a_tool_point(rigid):
    settings, _ = rigid
    predictor = LivePredictor(settings)
    turn = Rotation.from_euler('zx', [0.2, 0.05])        # a turned platform: order matters
    assert predictor.update_pose(settings.initial_position_m, turn.as_quat()).rebuilt
    dt_ns = round(settings.dt_s * 1e9)
    force, moment = np.array([20.0, -10.0, 50.0]), np.array([3.0, -2.0, 4.0])
    for k in range(40):
        u = predictor.advance(k * dt_ns, force, moment)
    centre = predictor.prediction()
    np.testing.assert_array_equal(centre.displacement_m, u)     # default: today's output
    q = predictor.integrator.u[:6]
    theta = q[3:]
    assert np.linalg.norm(theta) > 1e-8
    tool = predictor.prediction(TOOL_M)
    r = predictor.rotation @ TOOL_M
    np.testing.assert_allclose(tool.displacement_m, q[:3] + np.cross(theta, r), rtol=1e-12)
    np.testing.assert_allclose(tool.position_m, predictor.position_m + r + tool.displacement_m)
    want = Rotation.from_matrix(Rotation.from_rotvec(theta).as_matrix() @ predictor.rotation)
    assert (Rotation.from_quat(tool.quaternion) * want.inv()).magnitude() < 1e-12
    np.testing.assert_allclose(centre.position_m, predictor.position_m + u)
