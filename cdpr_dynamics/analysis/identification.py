"""Modal identification of free decays at rest poses (``identify``), arrays in, arrays out.

A record is a time series of the platform's pose (or of an IMU's angular velocity and linear
acceleration). :func:`identify_record`:

1. splits it at gaps longer than ``max_gap_s`` and resamples each piece on a uniform grid
   (shorter gaps, dropped samples, are filled by linear interpolation and counted);
2. finds the rest stretches: where the pose low-passed well below the modes (zero-phase
   Butterworth at ``f_min_hz / 2``) moves slower than ``rest_speed_m_s`` (and
   ``rest_speed_rad_s``); the motion between them, a stretch that starts mid-motion
   included, is skipped and reported; the part of a stretch where the oscillation exceeds
   ``max_amplitude_m`` is skipped too (beyond the linear model); each excitation within a
   stretch starts a decay of its own (:func:`decay_spans`), used if at least
   ``min_duration_s`` long;
3. identifies each decay's modes (its first ``max_window_s``) by the eigensystem realisation
   algorithm (ERA: the block Hankel matrix of the free decay, its SVD, poles from the shifted
   Hankel matrix) over a range of model orders, keeps the poles that are stable over the
   orders, and refines them by a variable-projection Levenberg-Marquardt fit of the decay
   sum_r Re(a_r e^{s_r t}) to the samples, whose Jacobian gives the standard uncertainty of
   each frequency and damping ratio.

The mode's direction is its residue vector over the platform DOFs (x y z, rotation vector),
phase-aligned and normalised; an IMU's angular velocity and acceleration residues are divided
by s and s^2 first (displacement-like).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.signal
from scipy.spatial.transform import Rotation

#: Record kinds: a pose (x y z qx qy qz qw per sample) or an IMU (wx wy wz ax ay az).
KINDS = ('pose', 'imu')


class IdentificationError(ValueError):
    """A record that cannot be identified; the message is one line."""


@dataclass(frozen=True)
class Options:
    """Settings of :func:`identify_record` (SI units)."""

    f_min_hz: float = 0.5
    f_max_hz: float | None = None          # default 0.4 x the sample rate
    max_gap_s: float = 0.1
    min_duration_s: float = 3.0
    rest_speed_m_s: float = 0.005
    rest_speed_rad_s: float = 0.01
    max_amplitude_m: float = 0.1
    max_damping_ratio: float = 0.3
    max_modes: int = 12
    max_window_s: float = 30.0
    min_snr: float = 8.0
    max_damping_rel_std: float = 0.5


@dataclass(frozen=True)
class Mode:
    """One identified mode: frequency and damping ratio with standard uncertainties, and its
    direction (6,) over x y z rx ry rz (NaN where the record has no such DOF)."""

    frequency_hz: float
    std_hz: float
    damping_ratio: float
    damping_ratio_std: float
    direction: np.ndarray


@dataclass(frozen=True)
class Stretch:
    """A free decay at rest: its time span (s), mean pose (7,) (NaN for an IMU) and modes."""

    start_s: float
    end_s: float
    pose: np.ndarray
    modes: tuple[Mode, ...]


@dataclass
class RecordResult:
    """Every stretch identified, and what was skipped and why ((start, end, reason))."""

    stretches: list[Stretch] = field(default_factory=list)
    skipped: list[tuple[float, float, str]] = field(default_factory=list)
    filled_samples: int = 0


# --------------------------------------------------------------------------- signals

def pose_dofs(position_m, quaternion) -> np.ndarray:
    """(n, 6): the position and the rotation vector (world frame) of each orientation relative
    to the mean orientation."""
    rotations = Rotation.from_quat(np.asarray(quaternion, dtype=float))
    mean = rotations.mean()
    return np.hstack([np.asarray(position_m, dtype=float),
                      (rotations * mean.inv()).as_rotvec()])


def mean_pose(position_m, quaternion) -> np.ndarray:
    """(7,): the mean position and the mean orientation (qx qy qz qw, qw >= 0)."""
    q = Rotation.from_quat(np.asarray(quaternion, dtype=float)).mean().as_quat()
    return np.concatenate([np.mean(position_m, axis=0), q if q[3] >= 0 else -q])


def uniform_pieces(t_s, values, max_gap_s: float):
    """Split at gaps longer than ``max_gap_s``; resample each piece on a uniform grid of the
    median sample interval. Returns ([(t, values)], sample interval, filled sample count,
    [(start, end) of each gap split at])."""
    t = np.asarray(t_s, dtype=float)
    order = np.argsort(t, kind='stable')
    t, values = t[order], np.asarray(values, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, values = t[keep], values[keep]
    if t.size < 3:
        raise IdentificationError(f'the record has {t.size} samples')
    dt = float(np.median(np.diff(t)))
    cuts = np.flatnonzero(np.diff(t) > max(max_gap_s, 1.5 * dt)) + 1
    pieces, filled, gaps = [], 0, []
    for start, end in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [t.size]])):
        if start > 0:
            gaps.append((float(t[start - 1]), float(t[start])))
        ts = t[start:end]
        if ts.size < 2:
            continue
        grid = ts[0] + dt * np.arange(int(math.floor((ts[-1] - ts[0]) / dt + 1e-9)) + 1)
        filled += grid.size - ts.size if grid.size > ts.size else 0
        resampled = np.stack([np.interp(grid, ts, column) for column in values[start:end].T],
                             axis=1)
        pieces.append((grid, resampled))
    return pieces, dt, filled, gaps


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index ranges where ``mask`` is true."""
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def slow_part(t: np.ndarray, y: np.ndarray, f_min_hz: float) -> np.ndarray:
    """``y`` low-passed at ``f_min_hz / 2`` (zero-phase 4th-order Butterworth); its mean where
    the record is too short or the cutoff above Nyquist."""
    dt = t[1] - t[0]
    cutoff = 0.5 * f_min_hz
    if t.size < 30 or cutoff >= 0.5 / dt:
        return np.broadcast_to(y.mean(axis=0), y.shape)
    sos = scipy.signal.butter(4, cutoff, fs=1.0 / dt, output='sos')
    padlen = min(t.size - 1, int(3.0 / (cutoff * dt)))
    return scipy.signal.sosfiltfilt(sos, y, axis=0, padlen=padlen)


def rest_mask(t: np.ndarray, slow: np.ndarray, options: Options) -> np.ndarray:
    """Samples where the slow part of the pose moves slower than the rest speeds."""
    if t.size < 30:
        return np.zeros(t.size, dtype=bool)
    speed = np.gradient(slow, t[1] - t[0], axis=0)
    linear = np.linalg.norm(speed[:, :3], axis=1) < options.rest_speed_m_s
    angular = np.linalg.norm(speed[:, 3:], axis=1) < options.rest_speed_rad_s
    return linear & angular


def decay_spans(fast: np.ndarray, dt: float, f_min_hz: float) -> list[tuple[int, int]]:
    """(start, end) of the free decays in the oscillating part ``fast`` (n, c) of a rest
    stretch: each starts at the peak of its envelope (moving mean over 1 / f_min of the
    energy, channels at unit variance) and ends where the envelope grows to 4 times its least
    value since the peak (a new excitation: a tap, a release)."""
    n = fast.shape[0]
    width = max(int(round(1.0 / (f_min_hz * dt))), 5)
    scale = fast.std(axis=0)
    scale[scale == 0] = 1.0
    energy = np.sum((fast / scale) ** 2, axis=1)
    envelope = np.convolve(energy, np.ones(width) / width, mode='same')
    spans, start = [], 0
    while n - start > width:
        ahead = envelope[start:]
        fallen = np.flatnonzero(ahead < 0.5 * np.maximum.accumulate(ahead))
        if fallen.size == 0:
            break
        peak = start + int(np.argmax(ahead[:fallen[0]]))
        after = envelope[peak:]
        least = np.minimum.accumulate(after)
        grown = np.flatnonzero(after > 4.0 * least)
        end = n if grown.size == 0 else peak + int(np.argmin(after[:grown[0]]))
        spans.append((max(peak - width // 2, start), end))
        start = max(end, peak + 1)
    return spans


# --------------------------------------------------------------------------- ERA

def era_poles(y: np.ndarray, dt: float, orders, block_rows: int):
    """Continuous-time poles and mode shapes (per order) of the free decay ``y`` (n, c) by
    ERA: H0 = U S V^T (block Hankel, ``block_rows`` blocks), A = S^-1/2 U^T H1 V S^-1/2,
    from the small products H0 H0^T = U S^2 U^T and H1 H0^T (V = H0^T U S^-1)."""
    n, c = y.shape
    cols = n - block_rows
    idx = np.arange(block_rows)[:, None] + np.arange(cols + 1)[None, :]
    big = y[idx].transpose(0, 2, 1).reshape(block_rows * c, cols + 1)    # (i c, j + 1)
    h0, h1 = big[:, :-1], big[:, 1:]
    s2, u = np.linalg.eigh(h0 @ h0.T)
    s2, u = s2[::-1], u[:, ::-1]
    s = np.sqrt(np.clip(s2, 0.0, None))
    cross = h1 @ h0.T
    out = []
    for order in orders:
        if order > s.size or s[order - 1] <= 1e-10 * s[0]:
            continue
        root = 1.0 / np.sqrt(s[:order])
        a = (root[:, None] * (u[:, :order].T @ cross @ u[:, :order]) / s[:order]) * root[None, :]
        mu, psi = np.linalg.eig(a)
        with np.errstate(divide='ignore', invalid='ignore'):
            poles = np.log(mu.astype(complex)) / dt
        shapes = (u[:c, :order] * np.sqrt(s[:order])) @ psi
        out.append((poles, shapes))
    return out


def stable_poles(per_order, f_min: float, f_max: float, max_zeta: float,
                 tolerance: float = 0.01) -> list[complex]:
    """Poles (upper half plane) found at matching frequency in at least half of the orders:
    the median pole of each such cluster."""
    found = []
    for poles, _ in per_order:
        ok = np.isfinite(poles) & (poles.imag > 0)
        p = poles[ok]
        f = p.imag / (2 * np.pi)
        zeta = -p.real / np.abs(p)
        keep = (f >= f_min) & (f <= f_max) & (zeta > 0) & (zeta < max_zeta)
        found.extend(p[keep].tolist())
    if not found:
        return []
    found = np.array(sorted(found, key=lambda z: z.imag))
    clusters, current = [], [found[0]]
    for pole in found[1:]:
        if pole.imag - current[-1].imag <= tolerance * current[-1].imag:
            current.append(pole)
        else:
            clusters.append(current)
            current = [pole]
    clusters.append(current)
    need = max(2, len(per_order) // 2)
    out = []
    for cluster in clusters:
        if len(cluster) >= need:
            cluster = np.array(cluster)
            out.append(complex(np.median(cluster.real), np.median(cluster.imag)))
    return out


# --------------------------------------------------------------------------- refinement

def _basis(t: np.ndarray, poles: np.ndarray) -> np.ndarray:
    """(n, 2m) real basis e^{sigma t} cos(w t), e^{sigma t} sin(w t) per pole."""
    e = np.exp(np.outer(t, poles.real))
    wt = np.outer(t, poles.imag)
    return np.concatenate([e * np.cos(wt), e * np.sin(wt)], axis=1)


def refine(t: np.ndarray, y: np.ndarray, poles: list[complex], steps: int = 20):
    """Least-squares poles of y(t) = sum_r Re(a_r e^{s_r t}) + offset (variable projection:
    the amplitudes a_r, complex per channel, solved linearly for each trial pole set), by
    at most ``steps`` Levenberg-Marquardt steps from the ERA poles.

    Returns (poles, covariance of (sigma_1..m, omega_1..m), residues (m, c) complex,
    per pole the ratio of its signal's RMS to the residual's)."""
    t = t - t[0]
    n, c = y.shape
    m = len(poles)
    scale = np.maximum(np.std(y, axis=0), 1e-300)
    ys = y / scale

    def solve(x):
        p = x[:m] + 1j * x[m:]
        a = np.concatenate([_basis(t, p), np.ones((n, 1))], axis=1)
        norm = np.linalg.norm(a, axis=0)
        an = a / norm                        # normal equations of unit columns: (2m+1)^2
        try:
            coef = np.linalg.solve(an.T @ an, an.T @ ys) / norm[:, None]
        except np.linalg.LinAlgError:        # two trial poles alike: least norm amplitudes
            coef = np.linalg.lstsq(an, ys, rcond=None)[0] / norm[:, None]
        return (a @ coef - ys).ravel(), a, coef

    def jacobian(x, r):
        step = 1e-7 * np.abs(x[m:]).repeat(2).reshape(2, m).ravel()
        columns = []
        for k in range(2 * m):
            xk = x.copy()
            xk[k] += step[k]
            columns.append((solve(xk)[0] - r) / step[k])
        return np.stack(columns, axis=1)

    x = np.concatenate([np.real(poles), np.imag(poles)])
    r, a, coef = solve(x)
    jac = jacobian(x, r)
    mu = 1e-3
    with np.errstate(over='ignore', invalid='ignore'):   # a growing trial: refused
        for _ in range(steps):          # Levenberg-Marquardt
            normal = jac.T @ jac
            # a pole whose amplitude has vanished has a zero column: damped by the mean scale
            scale_diag = np.diag(normal) + 1e-9 * np.trace(normal) / normal.shape[0]
            try:
                dx = np.linalg.solve(normal + mu * np.diag(scale_diag), -jac.T @ r)
            except np.linalg.LinAlgError:
                break
            r_new, a_new, coef_new = solve(x + dx)
            if r_new @ r_new < r @ r:
                done = r @ r - r_new @ r_new < 1e-10 * (r @ r)
                x, r, a, coef = x + dx, r_new, a_new, coef_new
                jac = jacobian(x, r)
                mu = max(mu / 3.0, 1e-9)
                if done:
                    break
            else:
                mu *= 4.0
    dof = max(r.size - 2 * m - (2 * m + 1) * c, 1)
    s2 = float(r @ r) / dof
    cov = np.linalg.pinv(jac.T @ jac) * s2
    signal = np.array([np.sqrt(np.mean((a[:, [k, m + k]] @ coef[[k, m + k]]) ** 2))
                       for k in range(m)])
    snr = signal * math.sqrt(n) / max(math.sqrt(s2), 1e-300)
    coef = coef * scale
    residues = coef[:m] - 1j * coef[m:2 * m]        # Re(a e^{st}) = Re(a) cos - Im(a) sin
    return x[:m] + 1j * x[m:], cov, residues, snr


def _frequency_damping(pole: complex, var_sigma: float, var_omega: float, covar: float):
    """f, std f, zeta, std zeta of a pole s = sigma + i omega_d (first-order propagation)."""
    sigma, omega = pole.real, pole.imag
    r = math.hypot(sigma, omega)
    f = r / (2 * math.pi)
    zeta = -sigma / r
    # gradients of |s| and -sigma/|s| in (sigma, omega)
    g_r = np.array([sigma / r, omega / r])
    g_z = np.array([-1.0 / r + sigma * sigma / r ** 3, sigma * omega / r ** 3])
    cov = np.array([[var_sigma, covar], [covar, var_omega]])
    std_f = math.sqrt(max(g_r @ cov @ g_r, 0.0)) / (2 * math.pi)
    std_z = math.sqrt(max(g_z @ cov @ g_z, 0.0))
    return f, std_f, zeta, std_z


def direction(residue: np.ndarray, pole: complex, kind: str) -> np.ndarray:
    """A mode's unit vector (6,) over x y z rx ry rz from its residues on the channels."""
    residue = np.asarray(residue, dtype=complex).copy()
    if kind == 'imu':       # (angular velocity, acceleration) -> (rotation, translation)
        residue = np.concatenate([residue[3:] / pole ** 2, residue[:3] / pole])
    k = int(np.argmax(np.abs(residue)))
    aligned = (residue * np.exp(-1j * np.angle(residue[k]))).real
    norm = np.linalg.norm(aligned)
    return aligned / norm if norm > 0 else aligned


def identify_decay(t: np.ndarray, y: np.ndarray, kind: str, options: Options,
                   f_max_hz: float) -> list[Mode]:
    """The modes of one free decay ``y`` (n, 6) sampled uniformly at ``t``."""
    dt = t[1] - t[0]
    y = y - y.mean(axis=0)
    scale = np.std(y, axis=0)
    used = scale > 1e-12 * max(scale.max(), 1e-300)
    if not used.any():
        return []
    ys = y[:, used] / scale[used]
    c = ys.shape[1]
    top = min(2 * options.max_modes + 10, 60)
    period_rows = int(math.ceil(0.125 / (options.f_min_hz * dt)))   # 1/8 of the longest period
    block_rows = max(int(math.ceil(1.2 * top / c)) + 2, period_rows)
    block_rows = min(block_rows, ys.shape[0] // 3)
    orders = list(range(max(4, top // 3) + (max(4, top // 3) % 2), top + 1, 2))
    per_order = era_poles(ys, dt, orders, block_rows)
    poles = stable_poles(per_order, options.f_min_hz, f_max_hz, options.max_damping_ratio)
    if not poles:
        return []
    poles = poles[:options.max_modes]
    refined, cov, residues, snr = refine(t, y[:, used], poles)
    m = len(poles)
    modes = []
    for r in range(m):
        pole = refined[r]
        if not (pole.imag > 0 and pole.real < 0 and snr[r] >= options.min_snr):
            continue
        f, sf, z, sz = _frequency_damping(pole, cov[r, r], cov[m + r, m + r], cov[r, m + r])
        if not (options.f_min_hz <= f <= f_max_hz and z < options.max_damping_ratio
                and sz <= options.max_damping_rel_std * z):
            continue
        full = np.zeros(6, dtype=complex)
        full[used] = residues[r]
        modes.append(Mode(f, sf, z, sz, direction(full, pole, kind)))
    modes.sort(key=lambda mode: mode.frequency_hz)
    return modes


# --------------------------------------------------------------------------- a record

def _envelope_start(y: np.ndarray, limit: float) -> int:
    """First sample after which the translation's distance from its mean stays below
    ``limit``."""
    distance = np.linalg.norm(y[:, :3] - y[:, :3].mean(axis=0), axis=1)
    over = np.flatnonzero(distance > limit)
    return 0 if over.size == 0 else int(over[-1]) + 1


def _identify_span(result: RecordResult, t, y, values, first: int, end: int, kind: str,
                   options: Options, f_max: float, posed: bool, method) -> None:
    """Identify samples [first, end) of a piece as one free decay, or say why not."""
    dt = t[1] - t[0]
    span = (float(t[first]), float(t[end - 1]))
    if (end - first) * dt < options.min_duration_s:
        result.skipped.append(span + (f'free decay of {(end - first) * dt:.3g} s, less than '
                                      f'{options.min_duration_s:g} s',))
        return
    last = min(end, first + int(round(options.max_window_s / dt)) + 1)
    modes = method(t[first:last], y[first:last], kind, options, f_max)
    if not modes:
        result.skipped.append(span + ('no mode stands out of the noise',))
        return
    pose = (mean_pose(values[first:end, :3], values[first:end, 3:7]) if posed
            else np.full(7, np.nan))
    result.stretches.append(Stretch(span[0], span[1], pose, tuple(modes)))


def identify_record(t_s, samples, kind: str = 'pose', options: Options = Options(),
                    poses=None, method=identify_decay) -> RecordResult:
    """Identify every free decay at rest in a record.

    ``samples``: (n, 7) poses (x y z qx qy qz qw) for ``kind='pose'``, (n, 6) angular velocity
    and linear acceleration for ``kind='imu'`` (then ``poses``: (n, 7) the platform pose at
    each sample, or None). ``method`` identifies one decay (the signature of
    :func:`identify_decay`; another algorithm can be compared on the same stretches)."""
    if kind not in KINDS:
        raise IdentificationError(f'record kind {kind!r} is not one of {", ".join(KINDS)}')
    samples = np.asarray(samples, dtype=float)
    t_s = np.asarray(t_s, dtype=float)
    if samples.ndim != 2 or samples.shape[0] != t_s.size:
        raise IdentificationError('the record has no samples of the expected shape')
    finite = np.all(np.isfinite(samples), axis=1) & np.isfinite(t_s)
    result = RecordResult()
    if not finite.all():
        result.skipped.append((float(t_s[~finite][0]), float(t_s[~finite][-1]),
                               f'{int((~finite).sum())} samples not finite (dropped)'))
    t_s, samples = t_s[finite], samples[finite]
    if kind == 'pose':
        channels = pose_dofs(samples[:, :3], samples[:, 3:7])
        pose_samples = samples
    else:
        channels = samples
        pose_samples = None if poses is None else np.asarray(poses, dtype=float)[finite]
    if pose_samples is not None:
        pose_channels = np.concatenate([pose_samples, channels], axis=1)
    else:
        pose_channels = channels
    pieces, dt, result.filled_samples, gaps = uniform_pieces(t_s, pose_channels,
                                                             options.max_gap_s)
    for start, end in gaps:
        result.skipped.append((start, end, f'gap of {end - start:.3g} s in the samples '
                               f'(longer than {options.max_gap_s:g} s)'))
    f_max = options.f_max_hz or 0.4 / dt
    f_max = min(f_max, 0.45 / dt)
    for t, values in pieces:
        offset = 0 if pose_samples is None else 7
        y = values[:, offset:]
        if pose_samples is not None and kind == 'pose':
            y = pose_dofs(values[:, :3], values[:, 3:7])
        slow = slow_part(t, y, options.f_min_hz) if kind == 'pose' else \
            np.broadcast_to(y.mean(axis=0), y.shape)
        rest = rest_mask(t, slow, options) if kind == 'pose' else np.ones(t.size, bool)
        position = 0
        for start, end in _runs(rest):
            if start > position:
                result.skipped.append((float(t[position]), float(t[start - 1]),
                                       'moving (not at a rest pose)'))
            position = end
            first = start
            if kind == 'pose':
                first = start + _envelope_start(y[start:end], options.max_amplitude_m)
                if first > start:
                    result.skipped.append((float(t[start]), float(t[first - 1]),
                                           f'oscillation larger than {options.max_amplitude_m:g}'
                                           ' m (beyond the linear model)'))
            done = first
            for a, b in decay_spans(y[first:end] - slow[first:end], dt, options.f_min_hz) \
                    or [(0, end - first)]:
                if (first + a - done) * dt >= 1.0:
                    result.skipped.append((float(t[done]), float(t[first + a - 1]),
                                           'at rest before an excitation (no free decay)'))
                _identify_span(result, t, y, values, first + a, first + b, kind, options,
                               f_max, pose_samples is not None, method)
                done = first + b
        if position < t.size:
            result.skipped.append((float(t[position]), float(t[-1]),
                                   'moving (not at a rest pose)'))
    return result
