"""Input shapers and notch biquads (cdpr_dynamics.dynamics.shapers) and the controller outputs
built on them (cdpr_dynamics.analysis.controller), checked with the package's own Newmark time
history of the paper robot: a step force through the shaper, the residual vibration of the mode
fitted after the last impulse, against the unshaped step's."""
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.controller import (KIND_CODES, controller_shaping, mode_labels,
                                               mode_table)
from cdpr_dynamics.analysis.pipeline import build_system, damping_for, equilibrium
from cdpr_dynamics.dynamics import shapers
from cdpr_dynamics.dynamics.modes import modes
from cdpr_dynamics.dynamics.system import Newmark

DT = 1e-4


@pytest.fixture(scope='module')
def robot():
    """The paper's robot with the spring model, 2 % modal damping, its modes with shapes."""
    settings = load_settings().replace(method='spring', damping_modal_ratio=0.02,
                                       damping_mass_factor=0.0, damping_stiffness_factor=0.0)
    eq = equilibrium(settings)
    system = build_system(settings, eq)
    damping = damping_for(settings, system)
    return settings, system, damping, modes(system, settings.f_max_hz, shapes=True)


def residual_amplitude(system, damping, mode, shaper, horizon_periods=3.0):
    """Amplitude of the mode's free vibration about its static deflection after a unit step of
    its modal force through ``shaper`` (Newmark, dt = DT), fitted as a damped sinusoid."""
    k, m = (a.toarray() for a in system.matrices())
    frequency, zeta, phi = mode
    w = 2 * math.pi * frequency
    w_d = w * math.sqrt(1 - zeta ** 2)
    force = m @ phi                                  # excites this mode only (Rayleigh C)
    integrator = Newmark(k, m, damping, DT)
    end = shaper.duration_s
    t = np.arange(1, int(round((end + horizon_periods / frequency) / DT)) + 1) * DT
    q = np.empty(t.size)
    for i, ti in enumerate(t):
        height = shaper.amplitudes[shaper.times_s <= ti + 1e-12].sum()
        q[i] = phi @ m @ integrator.step(height * force)
    static = 1.0 / w ** 2
    after = t >= end + DT
    tau = t[after] - end
    basis = np.exp(-zeta * w * tau)[:, None] * np.column_stack([np.cos(w_d * tau),
                                                                np.sin(w_d * tau)])
    coef, *_ = np.linalg.lstsq(basis, q[after] - static, rcond=None)
    return float(np.hypot(*coef))


def lowest_mode(robot):
    settings, system, damping, found = robot
    i = int(np.argmax([k == 'platform' for k in found.kind]))
    f = float(found.frequency_hz[i])
    return f, float(damping.ratios(np.array([f]))[0]), found.shapes[:, i]


def test_theory_zero_vibration_and_insensitivity():
    for zeta in (0.0, 0.05):
        f = 7.0
        zv, zvd, ei = shapers.zv(f, zeta), shapers.zvd(f, zeta), shapers.ei(f, zeta)
        for s in (zv, zvd, ei):
            assert s.amplitudes.sum() == pytest.approx(1.0, abs=1e-15)
            assert s.times_s[0] == 0.0 and np.all(np.diff(s.times_s) > 0)
        assert zv.residual(f, zeta) < 1e-12 and zvd.residual(f, zeta) < 1e-12
        # ZVD: zero derivative, by central differences of V
        h = 1e-4 * f
        slope = (zvd.residual(f + h, zeta) - zvd.residual(f - h, zeta)) / (2 * h)
        assert abs(slope) < 1e-6
        band = np.linspace(0.8 * f, 1.2 * f, 201)
        assert ei.residual(band, zeta).max() <= 0.051
        assert zv.residual(band, zeta).max() > 0.25            # the ZV is not robust
    # undamped ZVD at +-10 %: 2.45 % (cos^2 of pi/2 (1 +- 0.1))^2 ... closed form
    assert shapers.zvd(10.0).residual(11.0) == pytest.approx(math.cos(math.pi / 2 * 1.1) ** 2,
                                                             rel=1e-12)


def test_convolved_shaper_multiplies_the_residuals():
    a, b = shapers.zvd(4.0, 0.02), shapers.ei(11.0, 0.01)
    both = shapers.convolve(a, b)
    f = np.linspace(1.0, 20.0, 50)
    assert_allclose(both.residual(f, 0.02), a.residual(f, 0.02) * b.residual(f, 0.02),
                    rtol=1e-10, atol=1e-10)      # times rounded to 1e-12 s
    assert both.amplitudes.sum() == pytest.approx(1.0)
    pairs = both.pairs()
    assert_allclose(pairs[0::2], both.times_s) and assert_allclose(pairs[1::2], both.amplitudes)
    # equal impulse times merge: ZV(10) * ZV(10) is the ZVD
    assert_allclose(shapers.convolve(shapers.zv(10.0), shapers.zv(10.0)).amplitudes,
                    shapers.zvd(10.0).amplitudes, rtol=1e-12)


@pytest.mark.parametrize('kind, offsets, limit', [('zvd', (0.0,), 0.05),
                                                  ('zvd', (-0.1, 0.1), 0.10),
                                                  ('ei', (-0.2, -0.1, 0.0, 0.1, 0.2), 0.10)])
def test_newmark_step_through_the_shaper_leaves_little_residual(robot, kind, offsets, limit):
    """The shaper is designed for the predicted mode, the robot's actual mode off by up to
    +-10 % (ZVD) or +-20 % (EI): the residual vibration relative to the unshaped step's."""
    settings, system, damping, found = robot
    f, zeta, phi = lowest_mode(robot)
    unshaped = residual_amplitude(system, damping, (f, zeta, phi),
                                  shapers.Shaper(np.zeros(1), np.ones(1)))
    for offset in offsets:
        designed = shapers.design(kind, f / (1 + offset), zeta)
        ratio = residual_amplitude(system, damping, (f, zeta, phi), designed) / unshaped
        assert ratio <= limit, (kind, offset, ratio)
        # and as the closed form says (Newmark and the dt grid: within 1 % of the unshaped)
        assert ratio == pytest.approx(float(designed.residual(f, zeta)), abs=0.01)


def test_notch_biquad_gain():
    fs = 1000.0
    for f in (3.0, 25.0, 240.0):
        c = shapers.notch_biquad(f, fs)
        assert c[3] == 1.0
        gain = np.abs(shapers.biquad_response(c, [0.0, f, fs / 2], fs))
        assert gain[0] == pytest.approx(1.0, abs=1e-12)
        assert gain[1] < 1e-9
        assert gain[2] == pytest.approx(1.0, abs=1e-9)
        # the difference equation itself: a sine at f dies out, DC passes
        n = np.arange(int(40 * fs / f))
        x = np.sin(2 * math.pi * f / fs * n) + 1.0
        y = np.zeros_like(x)
        b, a = c[:3], c[3:]
        for i in range(n.size):
            y[i] = (b[0] * x[i] + b[1] * x[i - 1] * (i > 0) + b[2] * x[i - 2] * (i > 1)
                    - a[1] * y[i - 1] * (i > 0) - a[2] * y[i - 2] * (i > 1))
        tail = y[-int(2 * fs / f):]
        assert np.abs(tail - 1.0).max() < 0.02
    with pytest.raises(ValueError, match='sample rate above'):
        shapers.notch_biquad(600.0, fs)


def test_mode_table_and_shaping_of_the_paper_robot(robot):
    settings, system, damping, found = robot
    table = mode_table(system, found, damping, settings.f_max_hz)
    assert table.shape[1] == len(mode_labels(3)) == 7
    assert np.all(table[:, 0] <= settings.f_max_hz)
    assert_allclose(table[:, 1], damping.ratios(table[:, 0]))
    assert set(table[:, 3]) <= set(KIND_CODES.values())
    assert_allclose(np.linalg.norm(table[:, 4:], axis=1), 1.0)
    # directions (null vectors of the condensed dynamic stiffness) against the eigenvectors of
    # the full model, away from the centre (distinct frequencies), fem with cable DOFs
    off = settings.replace(method='fem', elements_per_cable=4,
                           initial_position_m=np.array([0.3, -0.2, 1.1]))
    off_system = build_system(off, equilibrium(off))
    shapes = modes(off_system, off.f_max_hz, shapes=True)
    rows = mode_table(off_system, shapes, damping_for(off, off_system), off.f_max_hz)
    platform = [i for i, k in enumerate(shapes.kind[:len(rows)]) if k == 'platform']
    assert len(platform) == 3
    for i in platform:
        shape = shapes.shapes[:3, i]
        assert abs(rows[i, 4:] @ shape) == pytest.approx(np.linalg.norm(shape), rel=1e-6)
    shaping = controller_shaping(found, damping, 'zvd', 2, 1000.0)
    assert_allclose(shaping.frequency_hz, found.platform_hz[:2])
    expected = shapers.convolve(*(shapers.zvd(f, z) for f, z in
                                  zip(shaping.frequency_hz, shaping.damping_ratio)))
    assert_allclose(shaping.shaper.pairs(), expected.pairs())
    assert shaping.notches.shape == (2, 6)
    # the paper's own damping overdamps every mode above 6.4 Hz: nothing to shape
    paper = load_settings().replace(method='spring')
    paper_system = build_system(paper, equilibrium(paper))
    none = controller_shaping(modes(paper_system, paper.f_max_hz), damping_for(paper),
                              'zvd', 1, 1000.0)
    assert none.shaper is None and any('overdamped' in s for s in none.skipped)
