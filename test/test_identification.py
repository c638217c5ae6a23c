"""cdpr_calibrate identify: synthetic free decays of the package's own model, through MCAP.

A decay is the package's Newmark time history of the platform (spring model of the rigid
robot, cables softened so its six modes lie at 2-15 Hz, below the 50 Hz Nyquist frequency of a
100 Hz record) from an initial displacement, with Rayleigh damping; the truth is the
eigensolution of the same K and M and the damping's modal ratios.
"""
import numpy as np
import pytest

from cdpr_dynamics.analysis.config import read_params_file, settings_from_params
from cdpr_dynamics.analysis.identification import (Options, identify_record, noise_level, refine,
                                                   ssi_poles, stable_poles)
from cdpr_dynamics.analysis.modes_table import read_modes_table
from cdpr_dynamics.analysis.synthetic import free_decay, pose_rows
from cdpr_dynamics.cli.calibrate import main
from cdpr_dynamics.recording.writer import RecordingWriter
from msg_adapters.pose import pose_message
from msg_adapters.validation import ns_to_stamp

from test_calibration import PAPER, RIGID

POSE = 'geometry_msgs/msg/PoseStamped'
T0_NS = 1_700_000_000 * 10**9
U0 = np.array([0.004, -0.003, 0.005, 0.012, -0.010, 0.015])


def soft_robot():
    flat = read_params_file(RIGID)
    flat.update({'model.method': 'spring', 'cable.youngs_modulus_pa': 2.01e8})
    return settings_from_params(flat)


def decay(settings, position, u0=U0, duration_s=15.0):
    """(t, u, v, acc, frequencies, damping ratios, mode shapes) of the free decay from ``u0``:
    2 % Rayleigh damping at the lowest and highest mode, 100 Hz."""
    d = free_decay(settings, position, u0, duration_s)
    return d.t_s, d.u, d.v, d.acc, d.frequency_hz, d.damping_ratio, d.shapes


def write_poses(path, t_s, poses, topic='/measured_pose'):
    with RecordingWriter(path) as writer:
        writer.add_topic(topic, POSE)
        for t, row in zip(t_s, poses):
            ns = T0_NS + int(round(t * 1e9))
            writer.write(topic, pose_message(row[:3], row[3:], 'world', ns_to_stamp(ns)), ns)


def mac(a, b):
    return float(a @ b) ** 2 / float(a @ a) / float(b @ b)


def check_modes(modes, f_true, zeta_true, phi=None, count=5):
    """Every true mode among the ``count`` lowest found within 0.5 % in frequency and 20 % in
    damping (and its direction where ``phi``), nothing else."""
    found = np.array([m.frequency_hz for m in modes])
    assert found.size >= count and found.size <= len(f_true), found
    for j in range(count):
        i = int(np.argmin(np.abs(found - f_true[j])))
        mode = modes[i]
        assert abs(mode.frequency_hz / f_true[j] - 1) < 0.005, (mode, f_true[j])
        assert abs(mode.damping_ratio / zeta_true[j] - 1) < 0.2, (mode, zeta_true[j])
        assert 0 < mode.std_hz < 0.01 * mode.frequency_hz
        assert abs(mode.frequency_hz - f_true[j]) < 5 * mode.std_hz + 1e-4 * f_true[j]
        if phi is not None:
            assert mac(mode.direction, phi[:, j]) > 0.9


@pytest.mark.slow
def test_free_decay_in_mcap_identified(tmp_path, capsys):
    settings = soft_robot()
    position = np.array([0.1, -0.05, 1.3])
    t, u, _, _, f, zeta, phi = decay(settings, position)
    rng = np.random.default_rng(0)
    path = tmp_path / 'decay.mcap'
    write_poses(path, t, pose_rows(position, u, 1e-4, rng))
    out = tmp_path / 'modes.csv'
    assert main(['identify', str(path), '--output', str(out), '--f-min', '1']) == 0
    table = read_modes_table(out)
    assert set(table.pose_id.tolist()) == {0}
    assert np.abs(table.pose[0, :3] - position).max() < 1e-3
    result = identify_record(t, pose_rows(position, u, 1e-4, np.random.default_rng(0)),
                             options=Options(f_min_hz=1.0))
    (stretch,) = result.stretches
    assert np.allclose(table.frequency_hz, [m.frequency_hz for m in stretch.modes], rtol=1e-8)
    check_modes(stretch.modes, f, zeta, phi)


@pytest.mark.slow
def test_messy_record_motion_gaps_and_large_oscillation():
    """Starts mid-motion, drops 3 % of its samples and 0.4 s at once, moves to a second pose;
    the first decay starts larger than --max-amplitude."""
    settings = soft_robot()
    rng = np.random.default_rng(5)
    a, b = np.array([0.0, 0.0, 1.25]), np.array([0.15, 0.1, 1.2])
    t1, u1, _, _, f1, z1, _ = decay(settings, a, U0 * [25, 25, 25, 1, 1, 1], duration_s=15.0)
    t2, u2, _, _, f2, z2, _ = decay(settings, b, U0, duration_s=12.0)
    ramp_t = np.arange(0, 1.5, 0.01)
    start = a - np.array([0.3, 0.0, 0.0])
    ramp = start + (a - start) * np.sin(0.5 * np.pi * (ramp_t + 0.5) / 2.0)[:, None] ** 2
    move_t = np.arange(0, 2.0, 0.01)
    move = a + (b - a) * (0.5 - 0.5 * np.cos(np.pi * move_t / 2.0))[:, None]
    still = np.tile([0.0, 0.0, 0.0, 1.0], (len(ramp_t), 1))
    parts = [(ramp_t, np.hstack([ramp, still])),
             (t1, pose_rows(a, u1, 1e-4, rng)),
             (move_t, np.hstack([move, np.tile([0.0, 0.0, 0.0, 1.0], (len(move_t), 1))])),
             (t2, pose_rows(b, u2, 1e-4, rng))]
    times, rows, offset = [], [], 0.0
    for t, r in parts:
        times.append(t + offset)
        rows.append(r)
        offset += t[-1] + 0.01
    t, rows = np.concatenate(times), np.concatenate(rows)
    keep = rng.random(t.size) > 0.03
    keep[(t > 11.0) & (t < 11.4)] = False
    result = identify_record(t[keep], rows[keep], options=Options(f_min_hz=1.0))
    reasons = ' | '.join(r for _, _, r in result.skipped)
    assert 'moving' in reasons and 'gap of 0.4' in reasons and 'larger than 0.1 m' in reasons
    assert result.filled_samples > 0.02 * t.size
    assert len(result.stretches) == 3          # the first decay split at the gap
    # after the gap (8 s into the decay) the modes above 9 Hz have died out
    expected = ((a, f1, z1, 4), (a, f1, z1, 3), (b, f2, z2, 4))
    for stretch, (where, f, z, count) in zip(result.stretches, expected):
        assert np.abs(stretch.pose[:3] - where).max() < 2e-3
        check_modes(stretch.modes, f, z, count=count)
    assert result.stretches[0].start_s > 1.5       # not in the motion it started in


@pytest.mark.slow
def test_imu_record_identified():
    """Angular velocity and acceleration of the same decay: same modes, directions too."""
    settings = soft_robot()
    position = np.array([0.1, -0.05, 1.3])
    t, _, v, acc, f, zeta, phi = decay(settings, position)
    rng = np.random.default_rng(2)
    samples = np.hstack([v[:, 3:], acc[:, :3]])
    samples += 0.01 * np.abs(samples).max(axis=0) * rng.standard_normal(samples.shape)
    poses = np.tile(np.concatenate([position, [0.0, 0.0, 0.0, 1.0]]), (t.size, 1))
    result = identify_record(t, samples, 'imu', Options(f_min_hz=1.0), poses)
    (stretch,) = result.stretches
    assert np.allclose(stretch.pose[:3], position)
    check_modes(stretch.modes, f, zeta, phi)


@pytest.mark.parametrize('args, message', [
    (['--topic', '/nothing'], 'no topic /nothing'),
    (['--f-min', '-1'], '--f-min must be positive'),
])
def test_identify_errors_are_one_line(tmp_path, capsys, args, message):
    path = tmp_path / 'short.mcap'
    write_poses(path, np.arange(5) * 0.01, np.tile([0, 0, 1.25, 0, 0, 0, 1.0], (5, 1)))
    code = main(['identify', str(path), '--output', str(tmp_path / 'm.csv')] + args)
    err = capsys.readouterr().err
    assert code == 1 and message in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.slow
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_a_noisy_decay_gives_right_modes_or_none(seed):
    """1 mm and 1 mrad of noise on a decay of a few mm: what is reported is right (within
    0.5 % and 20 %, the frequency within 4 of its standard uncertainties), the lowest mode is
    found, and nothing made of noise is reported."""
    settings = soft_robot()
    position = np.array([0.1, -0.05, 1.3])
    t, u, _, _, f, zeta, _ = decay(settings, position, duration_s=20.0)
    rows = pose_rows(position, u, 1e-3, np.random.default_rng(seed))
    (stretch,) = identify_record(t, rows, options=Options(f_min_hz=1.0)).stretches
    found = [m.frequency_hz for m in stretch.modes]
    assert abs(found[0] / f[0] - 1) < 0.005
    for mode in stretch.modes:
        j = int(np.argmin(np.abs(f - mode.frequency_hz)))
        assert abs(mode.frequency_hz / f[j] - 1) < 0.005
        assert abs(mode.frequency_hz - f[j]) < 4 * mode.std_hz
        assert abs(mode.damping_ratio / zeta[j] - 1) < 0.2


@pytest.mark.slow
def test_taps_at_one_pose_are_separate_decays():
    """Quiet at the pose for 4 s, a tap (the decay from U0), a second, larger tap 9 s later:
    two decays, each starting at its tap, the quiet time before the first said so."""
    settings = soft_robot()
    position = np.array([0.1, -0.05, 1.3])
    t1, u1, _, _, f, zeta, _ = decay(settings, position, duration_s=9.0)
    t2, u2, *_ = decay(settings, position, U0 * 2, duration_s=12.0)
    quiet = np.zeros((400, 6))
    u = np.concatenate([quiet, u1, u2 + u1[-1]])
    t = np.arange(u.shape[0]) * 0.01
    rows = pose_rows(position, u, 1e-4, np.random.default_rng(4))
    result = identify_record(t, rows, options=Options(f_min_hz=1.0))
    assert len(result.stretches) == 2
    starts = [s.start_s for s in result.stretches]
    assert abs(starts[0] - 4.0) < 0.6 and abs(starts[1] - (4.0 + t1[-1] + 0.01)) < 0.6, starts
    assert any('before an excitation' in reason for *_, reason in result.skipped)
    for stretch in result.stretches:
        check_modes(stretch.modes, f, zeta, count=4)


def test_refinement_from_two_equal_poles_does_not_fail():
    """Two starting poles alike make the amplitudes' normal equations singular: the
    refinement falls back to least-norm amplitudes (no LinAlgError) and keeps the mode."""
    t = np.arange(1500) * 0.01
    pole = complex(-0.02 * 2 * np.pi * 3.0, 2 * np.pi * 3.0)
    y = np.real(np.outer(np.exp(pole * t), [1.0, 0.5 - 0.2j]))
    y += 1e-4 * np.random.default_rng(0).standard_normal(y.shape)
    fit = refine(t, y, [pole, pole])
    best = fit.poles[int(np.argmax(fit.snr))]
    assert abs(best.imag / pole.imag - 1) < 1e-3 and abs(best.real / pole.real - 1) < 0.05


def close_triple(ratio, duration_s):
    """The paper's point mass, softened: three modes within 1.5 % (3.27-3.32 Hz) in three
    different directions, each released with 3-5 mm, Rayleigh damping ``ratio``."""
    flat = read_params_file(PAPER)
    flat.update({'model.method': 'spring', 'cable.youngs_modulus_pa': 2.01e8})
    settings = settings_from_params(flat)
    position = settings.initial_position_m + [0.2, 0.1, 0.1]
    return position, free_decay(settings, position, U0[:3], duration_s, ratio)


@pytest.mark.slow
@pytest.mark.parametrize('ratio, seed, still',
                         [(0.002, 0, False), (0.005, 1, False), (0.005, 2, True)])
def test_three_close_modes_at_low_damping_identified(ratio, seed, still):
    """0.1 mm of noise (and 0.1 mrad on the rotations, or none: ``still``, channels without
    motion), 3 % of the samples dropped: the three modes and nothing else, each frequency
    within 0.5 % and 4 of its standard uncertainties, its damping ratio within 20 % or 4 of
    its uncertainties, its direction the model's (MAC above 0.9)."""
    position, d = close_triple(ratio, 40.0)
    rng = np.random.default_rng(seed)
    rows = pose_rows(position, d.u, 1e-4, rng)
    if still:
        rows[:, 3:] = [0.0, 0.0, 0.0, 1.0]
    keep = rng.random(d.t_s.size) > 0.03
    result = identify_record(d.t_s[keep], rows[keep], options=Options(f_min_hz=1.0))
    assert result.filled_samples > 0.02 * d.t_s.size
    (stretch,) = result.stretches
    assert len(stretch.modes) == 3, stretch.modes
    for mode, f, zeta, shape in zip(stretch.modes, d.frequency_hz, d.damping_ratio, d.shapes.T):
        assert abs(mode.frequency_hz / f - 1) < 0.005, (mode, f)
        assert abs(mode.frequency_hz - f) < 4 * mode.std_hz, (mode, f)
        assert (abs(mode.damping_ratio / zeta - 1) < 0.2
                or abs(mode.damping_ratio - zeta) < 4 * mode.damping_ratio_std), (mode, zeta)
        assert mac(mode.direction[:3], shape) > 0.9, (mode, shape)


def damped_sum(t, poles, shapes):
    """sum_r Re(shape_r e^{s_r t}) (n, c) of complex shapes (m, c)."""
    return np.real(np.exp(np.outer(t, poles)) @ shapes)


def test_subspace_poles_of_an_exact_decay():
    """Three modes 0.5 % apart in three directions, no noise: the subspace step at the
    model's order returns the poles it was built from, and their shapes."""
    poles = 2 * np.pi * np.array([3.0, 3.015, 3.03]) * (-0.005 + 1j)
    shapes = np.array([[1.0, 0.2, 0.1], [0.1 + 0.3j, 1.0, -0.2], [0.3, -0.4j, 1.0]])
    t = np.arange(2000) * 0.01
    ((found, found_shapes),) = ssi_poles(damped_sum(t, poles, shapes), 0.01, [6], 30)
    upper = np.argsort(np.where(found.imag > 0, found.imag, np.inf))[:3]
    assert np.allclose(found[upper], poles, rtol=1e-8)
    for k, j in enumerate(upper):
        # a shape up to a complex factor
        ratio = found_shapes[:, j] / shapes[k]
        assert np.allclose(ratio, ratio[0], rtol=1e-6)


def test_stable_poles_keeps_close_modes_apart_and_drops_noise():
    """Over 12 orders: three poles 0.5 % apart, each with a shape of its own, drifting 0.02 %
    from order to order, and 4 poles of noise at random; every order lists them shuffled.
    The three come back (medians of their tracks), though each lies within the 1 % that
    pairs a pole with the next order's; nothing of the noise does. Without shapes, the
    assignment on pole distance alone still tells them apart."""
    rng = np.random.default_rng(3)
    poles = 2 * np.pi * np.array([3.0, 3.015, 3.03]) * (-0.005 + 1j)
    shapes = np.eye(3, dtype=complex)
    per_order, per_order_bare = [], []
    for _ in range(12):
        drift = poles * (1 + 2e-4 * rng.standard_normal(3))
        noise = 2 * np.pi * rng.uniform(1.0, 20.0, 4) * (-rng.uniform(0.01, 0.2, 4) + 1j)
        found = np.concatenate([drift, noise])
        found_shapes = np.hstack([shapes, rng.standard_normal((3, 4))])
        order = rng.permutation(found.size)
        per_order.append((found[order], found_shapes[:, order]))
        per_order_bare.append((found[order], None))
    for listing in (per_order, per_order_bare):
        stable = np.array(stable_poles(listing, 1.0, 25.0, 0.3))
        assert stable.size == 3 and np.allclose(stable, poles, rtol=5e-4), stable


def test_noise_level_of_white_noise_beside_a_mode():
    """White noise of 0.1 and 1 (two channels) under a 2 Hz decay of amplitude 50 at 100 Hz:
    each channel's noise standard deviation within 10 % (20 % from the band above 45 Hz
    where the band asked for, above the Nyquist frequency, holds nothing)."""
    rng = np.random.default_rng(0)
    t = np.arange(4000) * 0.01
    y = 50 * np.exp(-0.5 * t)[:, None] * np.sin(4 * np.pi * t)[:, None] * [1.0, 0.3]
    y = y + rng.standard_normal(y.shape) * [0.1, 1.0]
    assert np.allclose(noise_level(y, 0.01, 40.0), [0.1, 1.0], rtol=0.1)
    assert np.allclose(noise_level(y, 0.01, 50.0), [0.1, 1.0], rtol=0.2)   # from 45 Hz


@pytest.mark.slow
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_a_frequency_drifting_with_the_amplitude_is_one_mode(seed):
    """A mode in x and y at 2 % damping whose frequency rises 2 % as it decays (a softening
    suspension), beside a 7 Hz rotation: two modes, the drifting one once, between its first
    and last frequency."""
    t = np.arange(3000) * 0.01
    amplitude = np.exp(-0.02 * 2 * np.pi * 3.0 * t)
    phase = 2 * np.pi * 3.0 * np.cumsum(1 + 0.02 * (1 - amplitude)) * 0.01
    u = np.zeros((t.size, 6))
    u[:, :2] = np.outer(amplitude * np.cos(phase), [0.005, 0.002])
    u[:, 3] = 0.01 * np.exp(-0.01 * 2 * np.pi * 7.0 * t) * np.cos(2 * np.pi * 7.0 * t)
    rows = pose_rows([0.0, 0.0, 1.0], u, 1e-4, np.random.default_rng(seed))
    result = identify_record(t, rows, options=Options(f_min_hz=1.0))
    found = [m.frequency_hz for s in result.stretches for m in s.modes]
    assert len(found) == 2 and 3.0 < found[0] < 3.06 and abs(found[1] - 7.0) < 0.01, found


@pytest.mark.slow
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_white_noise_gives_no_mode(seed):
    """20 s of white noise (0.1 mm, 0.1 mrad) at a rest pose: no mode reported."""
    rows = pose_rows([0.1, -0.05, 1.3], np.zeros((2001, 6)), 1e-4, np.random.default_rng(seed))
    result = identify_record(np.arange(2001) * 0.01, rows, options=Options(f_min_hz=1.0))
    assert not [m for s in result.stretches for m in s.modes]


CLOSE_TRIPLE = '''
import json
import numpy as np
from cdpr_dynamics.analysis.identification import Options, identify_record
from cdpr_dynamics.analysis.synthetic import pose_rows
from test_identification import close_triple
position, decay = close_triple(0.02, 20.0)
rows = pose_rows(position, decay.u, 1e-4, np.random.default_rng(2))
result = identify_record(decay.t_s, rows, options=Options(f_min_hz=1.0))
print(json.dumps({'found': [[m.frequency_hz, m.damping_ratio] for s in result.stretches
                            for m in s.modes],
                  'true': decay.frequency_hz.tolist(), 'zeta': decay.damping_ratio.tolist()}))
'''


@pytest.mark.slow
def test_three_close_modes_at_two_percent_damping_without_a_singular_step():
    """Three modes within 1.5 % at 2 % damping decay before they beat through a period of
    their difference: at least two of them are told apart, each reported mode lies on a
    different true one (0.5 %, 20 %). Run with one BLAS thread, as cdpr_calibrate runs (a
    Levenberg-Marquardt step whose pole's amplitude vanishes is regularised, not a
    LinAlgError)."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path
    here = str(Path(__file__).resolve().parent)
    env = dict(os.environ, OPENBLAS_NUM_THREADS='1', OMP_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join([here, os.environ.get('PYTHONPATH', '')]))
    out = subprocess.run([sys.executable, '-c', CLOSE_TRIPLE], env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    true, zeta = np.array(result['true']), np.array(result['zeta'])
    assert len(result['found']) >= 2
    matched = set()
    for f, z in result['found']:
        j = int(np.argmin(np.abs(f / true - 1)))
        assert abs(f / true[j] - 1) < 0.005 and abs(z / zeta[j] - 1) < 0.2, (f, z, true)
        assert j not in matched
        matched.add(j)
