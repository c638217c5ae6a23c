"""An offset centre of mass: the mass matrix about the reference point, gravity at the centre
of mass in the statics and its load stiffness.

The check that could fail: the same robot described with its reference point at the centre
of mass (attachments shifted, pose moved by R c) is the same physical system, so its natural
frequencies agree to 1e-9 with the offset description's, whatever the model.
"""
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis import pipeline
from cdpr_dynamics.analysis.config import read_params_file, settings_from_params
from cdpr_dynamics.mechanics.robot import required_wrench, rotation_vector_quaternion, skew

DATA = Path(__file__).parent / 'data'
COM = np.array([0.03, -0.05, -0.15])


def described(reference_at_com: bool, pulleys: bool, turn=(0.05, -0.08, 0.1)):
    """The rigid test robot, centre of mass at COM in the platform frame, turned by the
    rotation vector ``turn``; with ``reference_at_com`` the same robot whose platform frame's
    origin is the centre of mass."""
    flat = dict(read_params_file(DATA / 'rigid_cdpr.yaml'))
    q = rotation_vector_quaternion(turn)
    flat['robot.initial_orientation'] = q.tolist()
    if pulleys:
        n = len(flat['robot.anchors']) // 3
        anchors = np.asarray(flat['robot.anchors']).reshape(-1, 3)
        axes = np.where(anchors[:, 2:] > anchors[:, 2].mean(), [0.1, 0.0, 1.0], [0.1, 0, -1.0])
        flat.update({'robot.pulley_axes': axes.ravel().tolist(),
                     'robot.pulley_radii_m': [0.05] * n,
                     'cable.winch_side_lengths_m': [2.0] * n})
    settings = settings_from_params({**flat, 'robot.center_of_mass_m': COM.tolist()})
    if not reference_at_com:
        return settings
    attachments = np.asarray(flat['robot.attachments']).reshape(-1, 3) - COM
    position = settings.initial_position_m + settings.initial_rotation @ COM
    return settings_from_params({**flat, 'robot.attachments': attachments.ravel().tolist(),
                                 'robot.initial_position': position.tolist()})


def squared_frequencies(settings, method, n):
    eq = pipeline.equilibrium(settings)
    k, m = pipeline.build_system(settings, eq, method, n).matrices(dense=True)
    return scipy.linalg.eigh(k, m, eigvals_only=True)


@pytest.mark.parametrize('pulleys', [False, True])
@pytest.mark.parametrize('method,n', [('spring', 1), ('fem', 3)])
def test_reference_point_at_the_centre_of_mass_gives_the_same_frequencies(method, n, pulleys):
    offset = squared_frequencies(described(False, pulleys), method, n)
    centred = squared_frequencies(described(True, pulleys), method, n)
    assert_allclose(np.sqrt(offset), np.sqrt(centred), rtol=1e-9)
    assert np.all(offset > 0)


def test_an_offset_changes_the_frequencies():
    """The offset matters (else the test above could not fail): the robot with its mass at
    the reference point has other frequencies."""
    flat = dict(read_params_file(DATA / 'rigid_cdpr.yaml'))
    centred = settings_from_params(flat)
    offset = described(False, False, turn=(0.0, 0.0, 0.0))
    a, b = (squared_frequencies(s, 'spring', 1) for s in (centred, offset))
    assert np.max(np.abs(np.sqrt(a / b) - 1.0)) > 1e-3


def test_mass_matrix_is_the_kinetic_energy_of_the_centre_of_mass():
    """v^T M v / 2 = m |v + omega x c|^2 / 2 + omega^T I_w omega / 2 for random velocities."""
    s = described(False, False)
    robot, rotation = s.robot, s.initial_rotation
    mass = robot.platform_mass_matrix(rotation)
    c = rotation @ robot.center_of_mass_m
    inertia = rotation @ robot.inertia_kg_m2 @ rotation.T
    rng = np.random.default_rng(3)
    for v in rng.normal(size=(5, 6)):
        com_velocity = v[:3] + np.cross(v[3:], c)
        energy = robot.mass_kg * com_velocity @ com_velocity + v[3:] @ inertia @ v[3:]
        assert_allclose(v @ mass @ v, energy, rtol=1e-13)


def test_gravity_acts_at_the_centre_of_mass():
    s = described(False, False)
    wrench = required_wrench(s.robot, rotation=s.initial_rotation)
    weight = s.robot.mass_kg * s.robot.gravity_m_s2
    assert_allclose(wrench[3:], -np.cross(s.initial_rotation @ COM, weight), rtol=1e-14)
    eq = pipeline.equilibrium(s)
    assert_allclose(eq.geometry.structure_matrix @ eq.tensions.tension_n, wrench, atol=1e-8)
    # the load stiffness: -sym([m g]x [c]x) on the rotations
    system = pipeline.build_system(s, eq, 'spring')
    load = -skew(weight) @ skew(s.initial_rotation @ COM)
    assert_allclose(system.load_stiffness[3:, 3:], 0.5 * (load + load.T), rtol=1e-14)
