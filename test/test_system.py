"""Assembly, FRF, modes, damping and Newmark against answers known independently."""
import math

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from cdpr_dynamics import models
from cdpr_dynamics.analysis.pipeline import equilibrium
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import (DENSE_EIGEN_DOFS, Damping, _assemble, DynamicsError,
                                           Newmark, frequency_response, platform_system,
                                           rayleigh_from_modal_ratio, tension_change, time_history)
from cdpr_dynamics.models.base import CableSet
from cdpr_dynamics.dynamics.modes import natural_frequencies
from cdpr_dynamics.mechanics.robot import Robot, geometry, required_wrench

EA = 2.01e10 * 5.0265e-5
GAMMA = 0.251
G = np.array([0.0, 0.0, -9.81])
MU = GAMMA / 9.81


@pytest.fixture(scope='module')
def paper():
    return load_settings()


def one_cable(chord=(2.0, 0.0, 0.0), tension=150.0, gamma=GAMMA):
    return CableSet(np.array([chord], dtype=float), np.array([tension]), EA, gamma, G)


def rigid_robot(half_size=0.1):
    """A 6-DOF robot: 8 cables from the corners of the paper frame to a cube of half-size
    ``half_size``, attached as in test/data/rigid_cdpr.yaml (lower and upper cables to crossed
    corners of the lower and upper faces: rank 6). Attaching every cable to the corner
    diagonally opposite its anchor in x and y instead makes each cable meet the z axis: no yaw
    authority (rank 5), a design the analysis refuses."""
    s = load_settings(Path(__file__).parent / 'data' / 'rigid_cdpr.yaml')
    corners = s.robot.attachments_m * (half_size / 0.2)
    return Robot('world', s.robot.anchors_m, corners, 30.0, np.diag([0.5, 0.6, 0.7]), G)


# ------------------------------------------------------------------------ closed forms

@pytest.mark.parametrize('method,n', [('spring', 1), ('fem', 1), ('fem', 7), ('fem', 64)])
def test_static_end_stiffness_is_axial_spring_ea_over_l(method, n):
    """A straight cable's static stiffness: EA/L along it, T/L across (any FEM mesh)."""
    cables = one_cable((1.2, -0.9, 1.6), tension=250.0)
    length = math.sqrt(1.2 ** 2 + 0.9 ** 2 + 1.6 ** 2)
    k = models.build(method, cables, n).static_end_stiffness()[0]
    u = cables.unit[0]
    assert_allclose(u @ k @ u, EA / length, rtol=1e-12)
    v = np.cross(u, [0.0, 0.0, 1.0])
    v /= np.linalg.norm(v)
    assert_allclose(v @ k @ v, 250.0 / length, rtol=1e-9)
    assert_allclose(k, k.T, atol=1e-9 * EA)


def fixed_fixed_frequencies(assembly):
    """Modes of each cable's chain with both ends fixed (platform end node removed)."""
    b = assembly.blocks
    nodes = b.nodes - 1
    out = []
    for c in range(b.k_diag.shape[0]):
        k = np.zeros((3 * nodes, 3 * nodes))
        m = np.zeros_like(k)
        for i in range(nodes):
            k[3 * i:3 * i + 3, 3 * i:3 * i + 3] = b.k_diag[c, i]
            m[3 * i:3 * i + 3, 3 * i:3 * i + 3] = b.m_diag[c, i]
            if i + 1 < nodes:
                k[3 * i:3 * i + 3, 3 * i + 3:3 * i + 6] = b.k_off[c, i]
                k[3 * i + 3:3 * i + 6, 3 * i:3 * i + 3] = b.k_off[c, i].T
                m[3 * i:3 * i + 3, 3 * i + 3:3 * i + 6] = b.m_off[c, i]
                m[3 * i + 3:3 * i + 6, 3 * i:3 * i + 3] = b.m_off[c, i].T
        out.append(np.sqrt(scipy.linalg.eigh(k, m, eigvals_only=True)) / (2 * np.pi))
    return out


def test_fem_taut_string_modes_converge_at_rate_two():
    """Transverse modes of a fixed-fixed cable approach k/(2L) sqrt(T/mu) as O(n^-2)."""
    length, tension = 2.0, 150.0
    exact = np.arange(1, 4) / (2 * length) * math.sqrt(tension / MU)
    errors = []
    for n in (8, 16, 32, 64):
        freqs = fixed_fixed_frequencies(models.build('fem', one_cable((length, 0, 0), tension),
                                                     n))[0]
        transverse = freqs[freqs < 2 * exact[-1]]
        # each transverse mode appears twice (two directions)
        got = transverse[[0, 2, 4]]
        assert_allclose(transverse[[1, 3, 5]], got, rtol=1e-10)
        errors.append(np.abs(got / exact - 1))
    errors = np.array(errors)
    assert errors[-1].max() < 2e-3
    order = np.log2(errors[:-1] / errors[1:])
    assert np.all((order > 1.9) & (order < 2.1)), order


def test_fem_axial_mode_of_fixed_fixed_cable():
    length = 2.0
    freqs = fixed_fixed_frequencies(models.build('fem', one_cable((0, 0, length)), 64))[0]
    axial = 1 / (2 * length) * math.sqrt(EA / MU)
    assert np.min(np.abs(freqs / axial - 1)) < 1e-3


# ------------------------------------------------------------------------ assembly

def test_condensed_dynamic_stiffness_equals_dense_full_model():
    """Z(w) from the chain elimination equals the Schur complement of K + iwC - w^2 M."""
    robot = rigid_robot()
    geo = geometry(robot, [0.1, -0.05, 1.2], Rotation.from_rotvec([0.02, -0.03, 0.05])
                   .as_matrix())
    tension = np.linspace(120.0, 400.0, 8)
    cables = CableSet(geo.chord_m, tension, EA, GAMMA, G)
    system = platform_system(robot, geo, models.build('fem', cables, 5))
    k, m = (a.toarray() for a in system.matrices())
    assert system.dofs == k.shape[0] == 6 + 8 * 3 * 4
    damping = Damping(0.3, 2e-4)
    omega = 2 * np.pi * np.array([0.0, 7.3, 31.0, 55.5])
    z = system.dynamic_stiffness(omega, damping)
    for zi, w in zip(z, omega):
        full = k + 1j * w * (damping.mass_factor * m + damping.stiffness_factor * k) - w * w * m
        schur = full[:6, :6] - full[:6, 6:] @ np.linalg.solve(full[6:, 6:], full[6:, :6])
        assert_allclose(zi, schur, rtol=1e-9, atol=1e-9 * np.abs(schur).max())


def test_rigid_platform_stiffness_matches_finite_differences_of_cable_wrench():
    """K = -d(wrench)/d(q) of the spring cables, rotation included, at an equilibrium."""
    robot = rigid_robot()
    s = load_settings()
    settings = s.replace(robot=robot)
    eq = equilibrium(settings, [0.05, 0.02, 1.3])
    system = platform_system(robot, eq.geometry, models.build('spring', eq.cables))
    t0, l0 = eq.tensions.tension_n, eq.geometry.length_m

    def cable_wrench(q):
        rot = Rotation.from_rotvec(q[3:]).as_matrix()
        geo = geometry(robot, eq.geometry.position_m + q[:3], rot)
        t = t0 + EA * (geo.length_m - l0) / l0       # dT/dL = EA/L at q = 0 (spring model)
        forces = t[:, None] * geo.unit
        return np.concatenate([forces.sum(0), np.cross(geo.lever_m, forces).sum(0)])

    h = 1e-7
    fd = np.array([-(cable_wrench(h * e) - cable_wrench(-h * e)) / (2 * h)
                   for e in np.eye(6)]).T
    assert_allclose(system.static_stiffness(), fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())


def test_rigid_platform_with_zero_levers_equals_point_mass(paper):
    """b_i -> 0: the translational response of the 6-DOF model is the point-mass one, at the
    same tensions. (The tension distributions themselves differ at any lever size: a rank-6
    platform must balance moments, a constraint homogeneous in b.)"""
    tiny = rigid_robot(half_size=1e-7)
    point = paper.robot
    assert point.platform_dofs == 3 and tiny.platform_dofs == 6
    tension = equilibrium(paper).tensions.tension_n
    frf = []
    for robot in (point, tiny):
        geo = geometry(robot, paper.initial_position_m)
        cables = CableSet(geo.chord_m, tension, paper.cable.ea_n,
                          paper.cable.weight_per_length_n_per_m, G)
        system = platform_system(robot, geo, models.build('fem', cables, 4))
        frf.append(frequency_response(system, [2.0, 17.0, 33.0], [300.0, -200.0, 1500.0],
                                      damping=Damping(0.05, 1e-4)).response[:, :3])
    assert_allclose(frf[1], frf[0], rtol=1e-5)


def test_frf_equals_modal_superposition_with_rayleigh_damping(paper):
    """A(w) = sum_k phi_k phi_k^T F / (w_k^2 - w^2 + 2 i zeta_k w_k w) (mass-normalised)."""
    eq = equilibrium(paper)
    system = platform_system(paper.robot, eq.geometry, models.build('fem', eq.cables, 3))
    k, m = (a.toarray() for a in system.matrices())
    lam, phi = scipy.linalg.eigh(k, m)
    wk = np.sqrt(lam)
    damping = Damping(0.4, 3e-4)
    zeta = damping.ratios(wk / 2 / np.pi)
    force = np.zeros(k.shape[0])
    force[:3] = [100.0, 0.0, 1500.0]
    f = np.linspace(1, 60, 50)
    w = 2 * np.pi * f[:, None]
    modal = ((phi[:3] * (phi.T @ force))[None] /
             (wk ** 2 - w ** 2 + 2j * zeta * wk * w)[:, None, :]).sum(-1)
    got = frequency_response(system, f, force[:3], damping=damping).response[:, :3]
    assert_allclose(got, modal, rtol=1e-7, atol=1e-12)


def test_undamped_frf_at_a_resonance_is_flagged_not_raised(paper):
    eq = equilibrium(paper)
    system = platform_system(paper.robot, eq.geometry, models.build('spring', eq.cables))
    f0 = natural_frequencies(system, 3)[0]
    r = frequency_response(system, [f0 * 0.5, f0, f0 * 1.5], [0, 0, 1500.0])
    assert r.singular.tolist() == [False, True, False]
    assert np.isinf(r.amplitude_m[1]).all() and np.isfinite(r.amplitude_m[[0, 2]]).all()


def test_natural_frequencies_sparse_and_dense_agree(paper):
    eq = equilibrium(paper)
    system = platform_system(paper.robot, eq.geometry, models.build('fem', eq.cables, 20))
    assert system.dofs > DENSE_EIGEN_DOFS           # sparse shift-invert path
    k, m = (a.toarray() for a in system.matrices())
    dense = np.sqrt(scipy.linalg.eigh(k, m, eigvals_only=True)[:12]) / (2 * np.pi)
    assert_allclose(natural_frequencies(system, 12), dense, rtol=1e-9)


def test_rayleigh_fit_gives_the_ratio_at_both_frequencies():
    d = rayleigh_from_modal_ratio(0.02, 3.0, 40.0)
    assert_allclose(d.ratios([3.0, 40.0]), [0.02, 0.02], rtol=1e-12)
    assert d.ratios([10.0])[0] < 0.02


# ------------------------------------------------------------------------ Newmark

def sdof_exact(t, m, k, c, f0, w):
    """Closed-form response from rest of m x'' + c x' + k x = f0 sin(w t) (underdamped)."""
    wn = math.sqrt(k / m)
    zeta = c / (2 * m * wn)
    wd = wn * math.sqrt(1 - zeta ** 2)
    denom = (k - m * w * w) ** 2 + (c * w) ** 2
    a = -f0 * c * w / denom            # particular: a cos + b sin
    b = f0 * (k - m * w * w) / denom
    c1 = -a                            # x(0) = 0
    c2 = (zeta * wn * c1 - b * w) / wd  # x'(0) = 0
    return a * np.cos(w * t) + b * np.sin(w * t) + np.exp(-zeta * wn * t) * (
        c1 * np.cos(wd * t) + c2 * np.sin(wd * t))


def run_sdof(dt, alpha=0.5, beta=0.25, damping=Damping(0.2, 1e-3)):
    m, k = 2.0, 2.0 * (2 * np.pi * 3.0) ** 2
    integ = Newmark(np.array([[k]]), np.array([[m]]), damping, dt, alpha, beta)
    t = np.arange(0, 1.0 + dt / 2, dt)
    u = [0.0]
    for ti in t[1:]:
        u.append(integ.step(np.array([50.0 * math.sin(7.0 * ti)]))[0])
    c = damping.mass_factor * m + damping.stiffness_factor * k
    return np.abs(np.array(u) - sdof_exact(t, m, k, c, 50.0, 7.0)).max()


def test_newmark_matches_closed_form_sdof_with_second_order_convergence():
    errors = [run_sdof(dt) for dt in (2e-3, 1e-3, 5e-4)]
    assert errors[-1] < 1e-5
    order = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all((order > 1.9) & (order < 2.1)), order


def test_newmark_linear_acceleration_also_converges():
    assert run_sdof(1e-3, 0.5, 1 / 6) < 1e-4


def test_newmark_refuses_an_unstable_explicit_step():
    """beta = 1/12 (Fox-Goodwin): stable only for w dt <= 1/sqrt(1/4 - 1/12) = sqrt(6)."""
    k, m = np.array([[1e6]]), np.array([[1.0]])    # w = 1000 rad/s -> dt_crit = 2.449 ms
    Newmark(k, m, Damping(), 2.4e-3, 0.5, 1 / 12)
    with pytest.raises(DynamicsError, match='unstable'):
        Newmark(k, m, Damping(), 2.5e-3, 0.5, 1 / 12)


def test_paper_time_history_settles_to_the_steady_state_amplitude(paper):
    """After the transient the 5 Hz response has the FRF amplitude at 5 Hz."""
    eq = equilibrium(paper)
    system = platform_system(paper.robot, eq.geometry, models.build('fem', eq.cables, 4))
    damping = Damping(paper.damping_mass_factor, paper.damping_stiffness_factor)
    th = time_history(system, paper.frf_force_n, 5.0, 3.0, damping, 5e-4)
    steady = frequency_response(system, [5.0], paper.frf_force_n, damping=damping)
    late = th.u_m[th.t_s > 2.0, 2]
    assert_allclose(np.abs(late).max(), steady.amplitude_m[0, 2], rtol=2e-3)


def test_tension_change_is_axial_stiffness_times_stretch(paper):
    eq = equilibrium(paper)
    system = platform_system(paper.robot, eq.geometry, models.build('spring', eq.cables))
    dz = 1e-4
    dt = tension_change(system, np.array([0.0, 0.0, dz]))
    # moving up by dz shortens the upper cables by dz u_z: tension drops by EA/L * dz u_z
    expected = -EA / eq.geometry.length_m * eq.geometry.unit[:, 2] * dz
    assert_allclose(dt, expected, rtol=1e-12)
    assert np.all(required_wrench(paper.robot) == -30.0 * G)


def test_newmark_dense_and_sparse_paths_agree(paper):
    eq = equilibrium(paper)
    system = platform_system(paper.robot, eq.geometry, models.build('fem', eq.cables, 3))
    damping = Damping(0.05, 1e-3)
    runs = []
    for dense in (False, True):
        k, m = system.matrices(dense=dense)
        integ = Newmark(k, m, damping, 1e-3)
        load = np.zeros(k.shape[0])
        load[:3] = [100.0, -50.0, 1500.0]
        runs.append([integ.step(load * math.sin(30.0 * i * 1e-3)).copy() for i in range(200)])
    # both solves carry round-off ~ cond(K_eff) eps ~ 1e-10 of the response (EA/T ~ 1e4)
    runs = np.array(runs)
    assert_allclose(runs[1], runs[0], rtol=0, atol=1e-9 * np.abs(runs[0]).max())


def test_assembly_places_the_transpose_of_each_off_diagonal_block_below_it():
    """K[c, r] = K[r, c] even for non-symmetric 3x3 off-diagonal blocks."""
    rng = np.random.default_rng(3)
    ncab, nodes = 2, 4
    diag = rng.normal(size=(ncab, nodes, 3, 3))
    diag = diag + np.swapaxes(diag, -1, -2)
    off = rng.normal(size=(ncab, nodes - 1, 3, 3))
    g = np.zeros((ncab, 3, 3))
    g[:] = np.eye(3)
    k = _assemble(np.eye(3), diag, off, g, as_dense=True)
    assert_allclose(k, k.T, atol=1e-12)
    assert_allclose(k[3:6, 6:9], off[0, 0]) and assert_allclose(k[6:9, 3:6], off[0, 0].T)
