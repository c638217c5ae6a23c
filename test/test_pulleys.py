"""Swivelling pulleys and the winch-side cable against computations of their own.

Exit points and lengths against the tangent point found numerically (roots over the swivel
and groove angles); the platform stiffness against finite differences of the static balance
with the exact pulley kinematics; the series springs against closed forms; the chain models'
matrices against their own end stiffness; zero pulleys against the ideal robot.
"""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize
from numpy.testing import assert_allclose

from cdpr_dynamics import models
from cdpr_dynamics.analysis import pipeline
from cdpr_dynamics.analysis.config import (ConfigError, load_settings, read_params_file,
                                           settings_from_params)
from cdpr_dynamics.dynamics.system import platform_system
from cdpr_dynamics.mechanics.robot import (Geometry, GeometryError, Robot, geometry,
                                           pulley_exits, quaternion_to_matrix,
                                           rotation_vector_quaternion)
from cdpr_dynamics.models.base import AnchorEnd, CableSet

DATA = Path(__file__).parent / 'data'
CONFIG = Path(__file__).parent.parent / 'config'


def with_pulleys(path, radius_m=0.05, winch_m=3.0, tilt=0.2, **more):
    """The robot of ``path`` with a pulley at every anchor: swivel axes vertical (up at the
    upper anchors, down at the lower ones) tilted by ``tilt`` towards x, so the pulley
    planes are not special."""
    flat = dict(read_params_file(path))
    anchors = np.asarray(flat['robot.anchors'], dtype=float).reshape(-1, 3)
    up = anchors[:, 2] > anchors[:, 2].mean()
    axes = np.where(up[:, None], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]) + [tilt, 0.0, 0.0]
    n = anchors.shape[0]
    flat.update({'robot.pulley_axes': axes.ravel().tolist(),
                 'robot.pulley_radii_m': [radius_m] * n,
                 'cable.winch_side_lengths_m': [winch_m] * n})
    flat.update(more)
    return settings_from_params(flat)


def tangent_exit(d, k, r, a):
    """(length from D, exit point, wrap) of the cable D -> groove -> A found numerically: the
    swivel angle where the pulley plane holds A (a root over the swivel angle), then the
    groove angle where the line to A is tangent to the groove and leaves it the way the cable
    travels (a root over the groove angle)."""
    k = k / np.linalg.norm(k)
    e0 = np.cross(k, [0.3, 0.5, 0.7])
    e0 /= np.linalg.norm(e0)
    e1 = np.cross(k, e0)

    def plane(swivel):
        e = np.cos(swivel) * e0 + np.sin(swivel) * e1
        return e, np.cross(k, e)

    def roots(f, lo, hi):
        grid = np.linspace(lo, hi, 721)
        values = [f(x) for x in grid]
        return [scipy.optimize.brentq(f, x0, x1, xtol=1e-15)
                for x0, x1, f0, f1 in zip(grid, grid[1:], values, values[1:]) if f0 * f1 < 0]

    swivel = next(x for x in roots(lambda x: np.dot(plane(x)[1], a - d), -np.pi, np.pi)
                  if np.dot(plane(x)[0], a - d) > 0)
    e = plane(swivel)[0]
    centre = d + r * e

    def point(wrap):
        return centre + r * (np.sin(wrap) * k - np.cos(wrap) * e)

    def travel(wrap):
        return np.sin(wrap) * e + np.cos(wrap) * k

    wrap = next(x for x in roots(lambda x: np.dot(point(x) - centre, a - point(x)),
                                 1e-9, 2 * np.pi - 1e-9)
                if np.dot(a - point(x), travel(x)) > 0)
    return r * wrap + np.linalg.norm(a - point(wrap)), point(wrap), wrap


def test_exit_points_and_lengths_are_the_numerical_tangent_points():
    rng = np.random.default_rng(7)
    d = rng.uniform(-1.0, 1.0, (6, 3))
    k = rng.normal(size=(6, 3))
    k /= np.linalg.norm(k, axis=1)[:, None]
    r = rng.uniform(0.02, 0.2, 6)
    a = d + rng.uniform(-2.0, 2.0, (6, 3))
    exit_m, wrap, normal, centre, _, pivot = pulley_exits(d, k, r, a)
    for i in range(6):
        length, exit_ref, wrap_ref = tangent_exit(d[i], k[i], r[i], a[i])
        assert_allclose(r[i] * wrap[i] + np.linalg.norm(a[i] - exit_m[i]), length, atol=1e-9)
        assert_allclose(exit_m[i], exit_ref, atol=1e-6)
        assert_allclose(wrap[i], np.mod(wrap_ref, 2 * np.pi), atol=1e-6)
        # the exit point is on the groove and the free span is tangent to it there
        assert_allclose(np.linalg.norm(exit_m[i] - centre[i]), r[i], rtol=1e-12)
        assert abs(np.dot(exit_m[i] - centre[i], a[i] - exit_m[i])) < 1e-12
        # the plane holds the swivel axis and the attachment
        assert abs(np.dot(normal[i], k[i])) < 1e-12
        assert abs(np.dot(normal[i], a[i] - d[i])) < 1e-12
        # the span's line, extended back by the pivot c beyond the exit, meets the swivel axis
        travel = (a[i] - exit_m[i]) / np.linalg.norm(a[i] - exit_m[i])
        assert np.linalg.norm(np.cross(exit_m[i] - pivot[i] * travel - d[i], k[i])) < 1e-12


def test_geometry_with_pulleys_reports_the_path_through_the_wrap():
    s = with_pulleys(DATA / 'rigid_cdpr.yaml')
    geo = geometry(s.robot, s.initial_position_m, s.initial_rotation)
    attach = geo.position_m + geo.lever_m
    assert_allclose(geo.chord_m, geo.pulleys.exit_m - attach, rtol=1e-15)
    for i in range(s.robot.n_cables):
        length, _, _ = tangent_exit(s.robot.anchors_m[i], s.robot.pulley_axes[i],
                                    s.robot.pulley_radii_m[i], attach[i])
        assert_allclose(geo.cable_length_m[i], length, atol=1e-9)
    assert_allclose(geo.anchor_end.series_length_m,
                    s.robot.pulley_radii_m * geo.pulleys.wrap_rad + 3.0, rtol=1e-15)


def test_a_platform_on_a_swivel_axis_or_in_a_pulley_is_refused():
    d, k = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(GeometryError, match='swivel axis'):
        pulley_exits(d, k, np.array([0.05]), np.array([[0.0, 0.0, -1.0]]))
    with pytest.raises(GeometryError, match='inside its pulley'):
        pulley_exits(d, k, np.array([0.05]), np.array([[0.05, 0.0, 0.01]]))


def platform_wrench(settings, eq, q):
    """The wrench of the cables and gravity on the platform displaced by q (translation,
    rotation vector) from ``eq``, the cables' tensions changing with their path length from
    the winch: T = T0 + EA/l0 (l - l0) (the spring model's axial law)."""
    robot, geo = settings.robot, eq.geometry
    rotation = quaternion_to_matrix(rotation_vector_quaternion(q[3:])) @ geo.rotation
    moved = geometry(robot, geo.position_m + q[:3], rotation)
    ell0 = geo.cable_length_m + robot.winch_side_lengths_m
    ell = moved.cable_length_m + robot.winch_side_lengths_m
    tension = eq.tensions.tension_n + settings.cable.ea_n / ell0 * (ell - ell0)
    force = tension[:, None] * moved.unit
    weight = robot.mass_kg * robot.gravity_m_s2
    com = rotation @ robot.center_of_mass_m
    return np.concatenate([force.sum(axis=0) + weight,
                           np.cross(moved.lever_m, force).sum(axis=0) + np.cross(com, weight)])


def balance_jacobian(s, eq, h=1e-6):
    """Minus the central-difference Jacobian of the platform wrench (6, 6): the stiffness."""
    return -np.array([(platform_wrench(s, eq, h * e) - platform_wrench(s, eq, -h * e)) / (2 * h)
                      for e in np.eye(6)]).T


@pytest.mark.parametrize('com', [[0.0, 0.0, 0.0], [0.04, -0.03, -0.12]])
def test_stiffness_is_the_derivative_of_the_static_balance(com):
    """Pulleys, winch side and an offset centre of mass: the spring model's platform
    stiffness is minus the Jacobian of the wrench on the displaced platform (central
    differences), every model's static stiffness the same (fem exactly, catenary to its sag)."""
    s = with_pulleys(DATA / 'rigid_cdpr.yaml', **{'robot.center_of_mass_m': com})
    eq = pipeline.equilibrium(s)
    assert np.abs(platform_wrench(s, eq, np.zeros(6))).max() < 1e-8
    k = pipeline.build_system(s, eq, 'spring').static_stiffness()
    scale = np.abs(k).max(axis=0)
    assert np.all(np.abs(balance_jacobian(s, eq) - k).max(axis=0) < 1e-7 * scale)
    fem = pipeline.build_system(s, eq, 'fem', 6).static_stiffness()
    assert_allclose(fem, k, rtol=0, atol=1e-12 * np.abs(k).max())


def single(tension=180.0, radius=0.04, winch=2.5, chord=(1.1, -0.4, 1.7)):
    """One cable over a pulley whose plane is normal to x, its anchor end's springs."""
    chord = np.array([chord], dtype=float)
    u = chord[0] / np.linalg.norm(chord)
    normal = np.cross(u, [0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal)
    end = AnchorEnd(np.array([radius * 1.3 + winch]), normal[None], np.array([radius * 0.7]))
    return CableSet(chord, np.array([tension]), 1.0e6, 0.3, np.array([0.0, 0.0, -9.81]),
                    anchor_end=end)


@pytest.mark.parametrize('method,n', [('spring', 1), ('fem', 1), ('fem', 9)])
def test_series_springs_closed_form(method, n):
    """EA/(L + wrapped + winch side) along the cable, T/(L + c) normal to the pulley plane,
    T/L across the cable in it."""
    cables = single()
    end = cables.anchor_end
    k = models.build(method, cables, n).static_end_stiffness()[0]
    u, m = cables.unit[0], end.plane_normal[0]
    in_plane = np.cross(u, m)
    length = cables.length_m[0]
    assert_allclose(u @ k @ u, 1.0e6 / (length + end.series_length_m[0]), rtol=1e-12)
    assert_allclose(m @ k @ m, 180.0 / (length + end.pivot_m[0]), rtol=1e-12)
    assert_allclose(in_plane @ k @ in_plane, 180.0 / length, rtol=1e-12)
    assert_allclose(k, k.T, atol=1e-9)


def condensed_matrices(assembly, cables, lam):
    """The dense Schur complement of K - lam M of one cable's model on a massless point
    platform: its matrices condensed onto the platform end."""
    point = Robot('world', np.zeros((1, 3)), np.zeros((1, 3)), 0.0, np.zeros((3, 3)),
                  np.array([0.0, 0.0, -9.81]))
    geo = Geometry(np.zeros(3), np.eye(3), np.zeros((1, 3)), cables.chord_m, cables.length_m,
                   cables.unit, cables.unit.T.copy())
    k, m = platform_system(point, geo, assembly).matrices(dense=True)
    z = k - lam * m
    return z[:3, :3] - z[:3, 3:] @ np.linalg.solve(z[3:, 3:], z[3:, :3])


@pytest.mark.parametrize('method,n,tension', [('fem', 7, 180.0), ('fem_sag', 6, 60.0)])
@pytest.mark.parametrize('lam', [0.0, 3.0e3, 5.0e5, -3.0e4 + 2.0e4j])
def test_chain_end_stiffness_condenses_its_own_matrices(method, n, tension, lam):
    """The end stiffness of chains with an anchor end (fem: closed form from a softened
    first node; fem_sag: the recursion from the anchor element in series) equals the
    condensation of the model's own block matrices."""
    cables = single(tension=tension)
    assembly = models.build(method, cables, n)
    assert assembly.valid
    schur = condensed_matrices(assembly, cables, lam)
    assert_allclose(assembly.end_stiffness(np.array([lam]))[0, 0], schur, rtol=1e-8,
                    atol=1e-8 * np.abs(schur).max())


@pytest.mark.parametrize('method', ['spring', 'fem', 'catenary', 'catenary_exact'])
def test_zero_anchor_end_gives_the_fixed_anchor_model(method):
    """An anchor end of zero lengths takes the anchor-end code path and gives the model of a
    fixed anchor to round-off."""
    s = load_settings(CONFIG / 'low_tension_cdpr.yaml')
    eq = pipeline.equilibrium(s)
    n = eq.cables.n_cables
    cables = eq.cables
    zero = CableSet(cables.chord_m, cables.tension_n, cables.ea_n,
                    cables.weight_per_length_n_per_m, cables.gravity_m_s2,
                    anchor_end=AnchorEnd(np.zeros(n), np.zeros((n, 3)), np.zeros(n)))
    lam = np.array([0.0, 400.0, 9.0e4])
    plain = models.build(method, cables, 8).end_stiffness(lam)
    assert_allclose(models.build(method, zero, 8).end_stiffness(lam), plain, rtol=1e-13,
                    atol=1e-13 * np.abs(plain).max())


@pytest.mark.parametrize('config', [CONFIG / 'paper_cdpr.yaml', DATA / 'rigid_cdpr.yaml',
                                    CONFIG / 'low_tension_cdpr.yaml'])
def test_zero_radii_and_winch_side_give_todays_frequencies(config):
    """Swivel axes with zero radii and zero winch-side lengths: the ideal robot's numbers."""
    ideal = load_settings(config)
    zero = with_pulleys(config, radius_m=0.0, winch_m=0.0)
    eqs = [pipeline.equilibrium(s) for s in (ideal, zero)]
    assert_allclose(eqs[1].tensions.tension_n, eqs[0].tensions.tension_n, rtol=1e-14)
    for method, n in (('spring', 1), ('fem', 4)):
        values = []
        for s, eq in zip((ideal, zero), eqs):
            k, m = pipeline.build_system(s, eq, method, n).matrices(dense=True)
            values.append(scipy.linalg.eigh(k, m, eigvals_only=True))
        assert_allclose(values[1], values[0], rtol=1e-13)


def test_pulleys_in_the_configuration_are_checked():
    with pytest.raises(ConfigError, match='pulley_radii_m has 3 values'):
        with_pulleys(DATA / 'rigid_cdpr.yaml', **{'robot.pulley_radii_m': [0.05] * 3})
    with pytest.raises(ConfigError, match='negative'):
        with_pulleys(DATA / 'rigid_cdpr.yaml', **{'cable.winch_side_lengths_m': [-1.0] * 8})
    axes = [0.0] * 24
    with pytest.raises(ConfigError, match='no swivel axis'):
        with_pulleys(DATA / 'rigid_cdpr.yaml', **{'robot.pulley_axes': axes})


def test_markers_draw_the_pulleys_and_the_wrap():
    from msg_adapters.markers import PULLEY_SEGMENTS, equilibrium_markers
    s = with_pulleys(DATA / 'rigid_cdpr.yaml', radius_m=0.1)
    eq = pipeline.equilibrium(s)
    pulleys = eq.geometry.pulleys
    array = equilibrium_markers(s, eq)
    by_ns = {}
    for m in array.markers:
        by_ns.setdefault(m.ns, []).append(m)
    circle = np.array([[p.x, p.y, p.z] for p in by_ns['pulleys'][0].points])
    circle = circle.reshape(s.robot.n_cables, 2 * PULLEY_SEGMENTS, 3)
    assert_allclose(np.linalg.norm(circle - pulleys.center_m[:, None], axis=-1), 0.1, rtol=1e-12)
    for i, m in enumerate(by_ns['cables']):
        line = np.array([[p.x, p.y, p.z] for p in m.points])
        assert_allclose(line[-1], s.robot.anchors_m[i], atol=1e-12)     # ends at D_i
        assert np.min(np.linalg.norm(line - pulleys.exit_m[i], axis=1)) < 1e-12
        drawn = np.linalg.norm(np.diff(line, axis=0), axis=1).sum()     # chords of the arc
        assert drawn <= eq.geometry.cable_length_m[i] + 1e-12
        wrapped = eq.geometry.cable_length_m[i] - eq.geometry.length_m[i]
        assert drawn > eq.geometry.length_m[i] + 0.99 * wrapped
    assert 'pulleys' not in {m.ns for m in equilibrium_markers(
        load_settings(DATA / 'rigid_cdpr.yaml'), pipeline.equilibrium(
            load_settings(DATA / 'rigid_cdpr.yaml'))).markers}


@pytest.mark.parametrize('method', ['fem_sag', 'catenary_exact'])
def test_sagged_models_take_the_anchor_end_in_series_statically(method):
    """Statically the anchor end's compliance adds to the cable's flexibility."""
    cables = single(tension=60.0)
    plain = CableSet(cables.chord_m, cables.tension_n, cables.ea_n,
                     cables.weight_per_length_n_per_m, cables.gravity_m_s2)
    with_end = models.build(method, cables, 8).static_end_stiffness()[0]
    flexibility = np.linalg.inv(models.build(method, plain, 8).static_end_stiffness()[0])
    end = cables.anchor_end
    u, m = cables.unit[0], end.plane_normal[0]
    flexibility += end.series_length_m[0] / cables.ea_n * np.outer(u, u) \
        + end.pivot_m[0] / cables.tension_n[0] * np.outer(m, m)
    assert_allclose(with_end, np.linalg.inv(flexibility), rtol=1e-9,
                    atol=1e-9 * np.abs(with_end).max())


def test_dsm_with_an_anchor_end_is_the_limit_of_fem():
    """dsm's closed form of a continuous cable on anchor springs against fem's chains on the
    same springs: the error falls at least as n^-1 (fem's anchor node is massless: the half
    element of cable beside it moving with the springs is its first-order error) below the
    first cable mode, and dsm equals the matrix form of :func:`anchor_series` with mass."""
    cables = single(tension=120.0)
    lam = np.array([2.0e3, 2.0e4])
    exact = models.build('dsm', cables).end_stiffness(lam)
    errors = [np.abs(models.build('fem', cables, n).end_stiffness(lam) - exact).max()
              for n in (8, 16, 32)]
    assert 1.9 < errors[0] / errors[1] < 4.4 and 1.9 < errors[1] / errors[2] < 4.4
    assert errors[2] < 1e-4 * np.abs(exact).max()
    from cdpr_dynamics.models.base import anchor_series
    plain = CableSet(cables.chord_m, cables.tension_n, cables.ea_n,
                     cables.weight_per_length_n_per_m, cables.gravity_m_s2)
    matrix_form = anchor_series(models.build('dsm', plain).end_stiffness(lam), cables, lam)
    assert_allclose(exact, matrix_form, rtol=1e-10, atol=1e-10 * np.abs(exact).max())


@pytest.mark.parametrize('method,n', [('fem', 16), ('fem_sag', 6)])
def test_counted_frequencies_with_pulleys_are_the_matrices_eigenvalues(method, n):
    """The Wittrick-Williams count of chains with a softened anchor node finds the dense
    eigenvalues of the same matrices (paper_pulleys, 0-40 Hz)."""
    from cdpr_dynamics.dynamics.modes import natural_frequencies
    s = load_settings(CONFIG / 'paper_pulleys.yaml')
    system = pipeline.build_system(s, pipeline.equilibrium(s), method, n)
    k, m = system.matrices(dense=True)
    dense = np.sqrt(scipy.linalg.eigh(k, m, eigvals_only=True)) / (2 * np.pi)
    dense = dense[dense <= 40.0]
    assert dense.size > 20
    assert_allclose(natural_frequencies(system, f_max_hz=40.0), dense, rtol=1e-8)


def test_clamped_roots_solve_the_anchor_spring_condition():
    """The j-th mode of a span on an anchor spring: tan z = -beta z in ((j - 1/2) pi, j pi),
    j pi without the spring, and the count passes each root (platform end fixed)."""
    from cdpr_dynamics.models.dsm import ContinuousCables, clamped_roots
    j = np.arange(1, 40)[:, None]
    beta = np.array([0.0, 1e-4, 0.3, 7.0])
    z = clamped_roots(j, beta)
    assert_allclose(z[:, 0], np.pi * j[:, 0], rtol=1e-15)
    assert_allclose(np.tan(z[:, 1:]), -beta[1:] * z[:, 1:], rtol=1e-9, atol=1e-12)
    assert np.all((z[:, 1:] > (j - 0.5) * np.pi) & (z[:, 1:] < j * np.pi))
    cables = single(tension=120.0)
    end = cables.anchor_end
    f_axial, f_normal = end.compliance(cables.ea_n, cables.tension_n)
    members = ContinuousCables(cables.unit, cables.length_m, cables.tension_n, cables.ea_n,
                               cables.mass_per_length_kg_m,
                               anchor_compliance=np.stack([f_axial, f_normal]),
                               normal=end.plane_normal)
    w1 = np.pi * np.sqrt(120.0 / cables.mass_per_length_kg_m) / cables.length_m[0]
    normal = clamped_roots(np.arange(1, 4), 120.0 * f_normal[0] / cables.length_m[0]) / np.pi
    # below the first axial mode: transverse in the plane at j w1, normal to it at z_j w1 / pi
    for w, expected in ((0.99 * normal[0] * w1, 0), (1.001 * normal[0] * w1, 1),
                        (1.001 * w1, 2), (1.001 * normal[2] * w1, 5)):
        assert members.fixed_end_mode_count([w])[0] == expected


@pytest.mark.slow
@pytest.mark.parametrize('config', ['paper_pulleys', 'suspended_3cable'])
def test_dsm_frequencies_with_pulleys_are_the_limit_of_fem(config):
    """dsm's counted frequencies with anchor ends against fem's dense eigenvalues (other
    matrices, other solver): fem's error falls by 2-4.4x per doubling of n (first order at
    the massless anchor node) towards dsm, down to 1e-4 at n = 256."""
    from cdpr_dynamics.dynamics.modes import natural_frequencies
    s = load_settings(CONFIG / f'{config}.yaml')
    eq = pipeline.equilibrium(s)
    assert eq.cables.anchor_end is not None
    dsm = natural_frequencies(pipeline.build_system(s, eq, 'dsm', 0), 12)
    errors = [np.abs(natural_frequencies(pipeline.build_system(s, eq, 'fem', n), 12) / dsm
                     - 1.0).max() for n in (64, 128, 256)]
    assert 2.0 < errors[0] / errors[1] < 4.4 and 2.0 < errors[1] / errors[2] < 4.4, errors
    assert errors[2] < 1e-4


def suspended_three_cables(com=(0.0, 0.02, -0.2)):
    """A suspended 3-cable robot: pulleys (22.5 mm) on the ceiling fed horizontally from
    outside, a 6-DOF platform hanging below with its centre of mass below its attachments."""
    angles = np.radians([90.0, 210.0, 330.0])
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros(3)], axis=1)
    anchors = 1.0 * ring + [0.0, 0.0, 2.0]
    flat = {'robot.anchors': anchors.ravel().tolist(),
            'robot.attachments': (0.15 * ring).ravel().tolist(),
            'robot.mass_kg': 8.0, 'robot.inertia_kg_m2': [0.1, 0.1, 0.15, 0.0, 0.0, 0.0],
            'robot.center_of_mass_m': list(com),
            'robot.initial_position': [0.05, 0.0, 0.9],
            'robot.pulley_axes': (-ring).ravel().tolist(),
            'robot.pulley_radii_m': [0.0225] * 3,
            'cable.winch_side_lengths_m': [1.5] * 3,
            'cable.area_m2': 1.0e-6, 'cable.youngs_modulus_pa': 1.0e11,
            'cable.weight_per_length_n_per_m': 0.01,
            'tension.min_n': 1.0, 'tension.max_n': 500.0, 'model.method': 'spring'}
    return settings_from_params(flat)


def test_suspended_underactuated_robot_with_pulleys():
    """At the equilibrium the underactuated statics find (cable lengths from the winch kept),
    the spring model's stiffness is the derivative of the balance, and the stability check's
    loaded stiffness is the same matrix."""
    from cdpr_dynamics.mechanics.underactuated import loaded_stiffness
    s = suspended_three_cables()
    eq = pipeline.equilibrium(s)
    assert eq.geometry.pulleys is not None
    assert np.abs(platform_wrench(s, eq, np.zeros(6))).max() < 1e-8
    k = pipeline.build_system(s, eq, 'spring').static_stiffness()
    assert np.all(np.abs(balance_jacobian(s, eq) - k).max(axis=0) < 1e-6 * np.abs(k).max(axis=0))
    loaded = loaded_stiffness(s.robot, eq.geometry, eq.tensions.tension_n, s.cable.ea_n)
    assert_allclose(loaded, k, rtol=0, atol=1e-9 * np.abs(k).max())
    assert np.all(np.linalg.eigvalsh(k) > 0)


def test_swivel_angle_of_a_vertical_pulley_is_the_azimuth_of_its_attachment():
    s = suspended_three_cables()
    robot = dataclasses.replace(s.robot, pulley_axes=np.tile([0.0, 0.0, -1.0], (3, 1)))
    geo = geometry(robot, s.initial_position_m + [0.1, -0.05, 0.0], s.initial_rotation)
    towards = geo.position_m + geo.lever_m - robot.anchors_m
    # k = -z: the reference is x (z has no part across the axis); angles about -z
    assert_allclose(geo.pulleys.swivel_rad, -np.arctan2(towards[:, 1], towards[:, 0]),
                    atol=1e-12)


@pytest.mark.parametrize('name', ['suspended_3cable.yaml', 'suspended_4cable.yaml'])
def test_pulleys_on_the_suspended_configs(name):
    """The suspended lab robots over 22.5 mm pulleys fed from outside, 2 m of winch-side
    cable and the centre of mass 0.2 m below the attachments: held, stable, and the spring
    stiffness the derivative of their balance."""
    flat = dict(read_params_file(CONFIG / name))
    anchors = np.asarray(flat['robot.anchors'], dtype=float).reshape(-1, 3)
    n = anchors.shape[0]
    inward = -anchors[:, :2] / np.linalg.norm(anchors[:, :2], axis=1)[:, None]
    flat.update({'robot.pulley_axes': np.hstack([inward, np.zeros((n, 1))]).ravel().tolist(),
                 'robot.pulley_radii_m': [0.0225] * n, 'cable.winch_side_lengths_m': [2.0] * n,
                 'robot.center_of_mass_m': [0.0, 0.0, -0.2]})
    s = settings_from_params(flat)
    eq = pipeline.equilibrium(s)
    assert np.abs(platform_wrench(s, eq, np.zeros(6))).max() < 1e-8
    k = pipeline.build_system(s, eq, 'spring').static_stiffness()
    assert np.all(np.abs(balance_jacobian(s, eq) - k).max(axis=0) < 1e-6 * np.abs(k).max(axis=0))
    assert np.all(np.linalg.eigvalsh(k) > 0)


def test_crossing_is_judged_on_the_free_spans_from_the_exit_points():
    """Two cables whose lines from their anchors D_i cross 3.4 cm below them: over point
    anchors they cross (refused); over 0.1 m pulleys each leaves its groove at an exit point
    7 cm lower and the free spans from there diverge (accepted)."""
    s = load_settings(CONFIG / 'paper_cdpr.yaml')
    for radius in (0.1, 0.0):
        robot = Robot('world', np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]),
                      np.array([[1.0, 0.0, -1.0], [-1.0, 0.0, -1.0]]), 5.0, np.diag([0.1] * 3),
                      np.array([0.0, 0.0, -9.81]), pulley_axes=np.array([[0.0, 0.0, -1.0]] * 2),
                      pulley_radii_m=np.full(2, radius))
        geo = geometry(robot, [0.0, 0.0, 0.0])
        settings = dataclasses.replace(s, robot=robot)
        if radius:
            assert np.all(geo.pulleys.exit_m[:, 2] < -0.07)
            pipeline._check_design(settings, geo)
        else:
            with pytest.raises(pipeline.AnalysisError, match='cables 0 and 1 cross'):
                pipeline._check_design(settings, geo)
