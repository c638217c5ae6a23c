"""Cable length offsets (cdpr_dynamics.analysis.controller.length_offsets) against independent
answers: the elastic stretch T L0 / EA and a static solve of the stretched straight cables
(Newton on the platform position), and for sagged cables a quadrature of the elastic catenary
from the platform end: a cable of the offset's unstretched length, under the end force that
balances the platform, reaches its anchor."""
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.integrate import quad

from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.controller import length_offsets
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.analysis.pipeline import equilibrium, equilibrium_for
from cdpr_dynamics.mechanics.robot import required_wrench

CONFIG = Path(__file__).resolve().parents[1] / 'config'


def test_straight_cables_stretch_by_t_l0_over_ea_and_land_on_the_pose():
    settings = load_settings(CONFIG / 'paper_cdpr.yaml')
    eq = equilibrium(settings)
    ea = settings.cable.ea_n
    tension = eq.tensions.tension_n
    offset = length_offsets(settings.robot, eq)
    l0 = eq.geometry.length_m + offset
    assert np.all(offset < 0)
    assert_allclose(-offset, tension * l0 / ea, rtol=1e-9)     # L0 - L: round-off of L
    # the stretched robot: cables of length l0 pulling EA (|a - p| - l0) / l0 toward their
    # anchors; Newton from 1 cm off finds the platform where the commanded pose is
    anchors = np.asarray(settings.robot.anchors_m, dtype=float).reshape(-1, 3)
    load = required_wrench(settings.robot, settings.external_force_n,
                           settings.external_moment_nm)[:3]
    p = settings.initial_position_m + np.array([0.01, -0.01, 0.01])
    for _ in range(30):
        chord = anchors - p
        length = np.linalg.norm(chord, axis=1)
        unit = chord / length[:, None]
        pull = ea * (length - l0) / l0
        residual = unit.T @ pull - load
        stiffness = sum(ea / l0[i] * np.outer(unit[i], unit[i])
                        + pull[i] / length[i] * (np.eye(3) - np.outer(unit[i], unit[i]))
                        for i in range(len(l0)))
        p = p + np.linalg.solve(stiffness, residual)
    assert np.linalg.norm(p - settings.initial_position_m) < 1e-9


def test_cables_over_pulleys_include_the_wrap_and_land_on_the_pose():
    """paper_pulleys: 50 mm swivelling pulleys and 3 m of cable from each winch. A cable of
    the winch's unstretched length (the rigid length, winch side plus |D - A|, plus the offset)
    runs winch side, wrap and free span at one tension, EA (length - L0) / L0; Newton on the
    platform position from 1 cm off (forces along the free spans of the pulleys' geometry at
    each trial position) finds the commanded pose. Offsets without the wrap and the winch
    side's stretch land elsewhere."""
    from cdpr_dynamics.mechanics.robot import geometry
    settings = load_settings(CONFIG / 'paper_pulleys.yaml')
    robot, ea = settings.robot, settings.cable.ea_n
    eq = equilibrium(settings)
    assert eq.geometry.pulleys is not None and np.all(robot.winch_side_lengths_m > 0)
    offset = length_offsets(robot, eq)
    target = settings.initial_position_m
    rigid = robot.winch_side_lengths_m + np.linalg.norm(robot.anchors_m - target, axis=1)
    load = required_wrench(robot, settings.external_force_n, settings.external_moment_nm)[:3]

    def balance(p, l0):
        geo = geometry(robot, p)
        pull = ea * (robot.winch_side_lengths_m + geo.path_length_m - l0) / l0
        return geo.unit.T @ pull - load

    def landing(l0):
        p = target + np.array([0.01, -0.01, 0.01])
        for _ in range(30):
            h = 1e-7
            jacobian = np.column_stack([(balance(p + h * e, l0) - balance(p - h * e, l0))
                                        / (2 * h) for e in np.eye(3)])
            p = p - np.linalg.solve(jacobian, balance(p, l0))
        return p
    assert np.linalg.norm(landing(rigid + offset) - target) < 1e-9
    bare = np.asarray(eq.unstretched_length_m) - eq.geometry.length_m    # span's stretch only
    assert np.linalg.norm(landing(rigid + bare) - target) > 1e-4
    # the wrap lengthens the path: r beta + |B - A| > |D - A|
    wrap = eq.geometry.path_length_m - (rigid - robot.winch_side_lengths_m)
    assert np.all(wrap > 0) and np.all(offset > bare)


def catenary_reach(end_force, l0, ea, gamma, up):
    """The far end of an elastic catenary of unstretched length l0 seen from its platform end,
    by quadrature: the cable's tension vector at unstretched arc s from the platform is the
    force it exerts there plus the weight of what lies between, T(s) = F + gamma s up; the
    cable runs along T and stretches by |T| / EA."""
    def tension(s):
        return end_force + gamma * s * up

    reach = np.array([quad(lambda s, i=i: tension(s)[i] / np.linalg.norm(tension(s))
                           * (1.0 + np.linalg.norm(tension(s)) / ea), 0.0, l0,
                           epsabs=1e-13, epsrel=1e-13, limit=200)[0] for i in range(3)])
    stretch = quad(lambda s: np.linalg.norm(tension(s)) / ea, 0.0, l0, epsabs=1e-13,
                   epsrel=1e-13)[0]
    return reach, stretch


def test_sagged_cables_reach_their_anchors_from_the_commanded_pose():
    settings = load_settings(CONFIG / 'heavy_sag_6dof.yaml')
    eq = equilibrium_for(settings, equilibrium(settings), 'catenary_exact')
    offset = length_offsets(settings.robot, eq)
    l0 = eq.geometry.length_m + offset
    gamma = settings.cable.weight_per_length_n_per_m
    up = -np.asarray(settings.robot.gravity_m_s2, dtype=float)
    up /= np.linalg.norm(up)
    stretches = []
    for i in range(len(l0)):
        reach, stretch = catenary_reach(eq.end_force_n[i], l0[i], settings.cable.ea_n,
                                        gamma, up)
        assert np.linalg.norm(reach - eq.geometry.chord_m[i]) < 1e-9, i
        stretches.append(stretch)
    # sagged cables are longer than their chords (the stretch T L0/EA alone would shorten
    # them): the offset is the sag's excess length minus the elastic stretch
    assert np.any(offset > 0)
    assert np.all(np.asarray(stretches) > 0)


def test_predicted_stretch_rate_is_the_chord_rate_of_the_motion():
    settings = load_settings(CONFIG / 'paper_cdpr.yaml').replace(method='spring')
    predictor = LivePredictor(settings, slack='linear')
    for k in range(40):
        predictor.advance(k * 1_000_000, [30.0, -20.0, 80.0])
    v = predictor.platform_state()[1].copy()
    rate = predictor.stretch_rate_m_s()
    anchors = np.asarray(settings.robot.anchors_m, dtype=float).reshape(-1, 3)
    h = 1e-2            # the chord lengths at p +- h v, central difference over 2 h (the
    #                     rate linearised at the equilibrium, as the prediction is)

    def lengths(x):
        return np.linalg.norm(anchors - (predictor.position_m + x), axis=1)
    expected = (lengths(h * v[:3]) - lengths(-h * v[:3])) / (2 * h)
    assert_allclose(rate, expected, rtol=1e-7, atol=1e-14)
    assert np.any(np.abs(rate) > 0)


@pytest.mark.parametrize('method', ['spring', 'fem'])
def test_length_offsets_of_the_paper_robot_are_micrometres(method):
    """Paper robot: T in [100, 1000] N over EA = 1.01e6 N and L ~ 2.2 m: 0.2-2 mm."""
    settings = load_settings(CONFIG / 'paper_cdpr.yaml').replace(method=method)
    offset = length_offsets(settings.robot, LivePredictor(settings).eq)
    assert np.all((offset < -1e-4) & (offset > -3e-3))
