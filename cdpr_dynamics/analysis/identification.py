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
3. identifies each decay's modes (its first ``max_window_s``): each channel divided by its
   noise level (:func:`noise_level`), covariance-driven stochastic subspace identification
   over a range of model orders (:func:`ssi_poles`), the poles that are stable over the
   orders, tracked from order to order by frequency, damping and shape
   (:func:`stable_poles`), refined by a variable-projection Levenberg-Marquardt fit of the
   decay sum_r Re(a_r e^{s_r t}) to the samples, whose Jacobian gives the standard
   uncertainty of each frequency and damping ratio; of two reported poles within 2 % that
   move alike the weaker is dropped (:func:`merge_alike`); poles the subspace missed are
   looked for in the fit's residual (:func:`add_missed_poles`).

The mode's direction is its residue vector over the platform DOFs (x y z, rotation vector),
phase-aligned and normalised; an IMU's angular velocity and acceleration residues are divided
by s and s^2 first (displacement-like).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import scipy.signal
import scipy.stats
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


# --------------------------------------------------------------------------- subspace

def noise_level(y: np.ndarray, dt: float, f_above_hz: float) -> np.ndarray:
    """(c,): each channel's white-noise standard deviation, from its periodogram above
    ``f_above_hz`` (no mode there; at most 0.45 x the sample rate): the median bin over ln 2
    (the median of a chi-square of two degrees of freedom over two)."""
    spectrum = np.abs(np.fft.rfft(y, axis=0)) ** 2 / y.shape[0]
    band = np.fft.rfftfreq(y.shape[0], dt) >= min(f_above_hz, 0.45 / dt)
    return np.sqrt(np.median(spectrum[band], axis=0) / math.log(2.0))


def ssi_poles(y: np.ndarray, dt: float, orders, block_rows: int):
    """Continuous-time poles and mode shapes (per order) of the free decay ``y`` (n, c) by
    covariance-driven stochastic subspace identification: T = Y_f Y_p^T / j (the future block
    rows of the block Hankel matrix times the past ones; white noise, independent between
    them, leaves no floor in T) = U S V^T, observability O = U S^1/2, A from
    O[without the last block] A = O[without the first], shapes C psi (C: O's first block)."""
    n, c = y.shape
    cols = n - 2 * block_rows + 1
    idx = np.arange(2 * block_rows)[:, None] + np.arange(cols)[None, :]
    big = y[idx].transpose(0, 2, 1).reshape(2 * block_rows * c, cols)     # (2 i c, j)
    past, future = big[:block_rows * c], big[block_rows * c:]
    u, s, _ = np.linalg.svd(future @ past.T / cols)
    out = []
    for order in orders:
        if order > s.size or s[order - 1] <= 1e-10 * s[0]:
            continue
        o = u[:, :order] * np.sqrt(s[:order])
        a = np.linalg.lstsq(o[:-c], o[c:], rcond=None)[0]
        mu, psi = np.linalg.eig(a)
        with np.errstate(divide='ignore', invalid='ignore'):
            poles = np.log(mu.astype(complex)) / dt
        out.append((poles, o[:c] @ psi))
    return out


def _physical(poles, shapes, f_min, f_max, max_zeta):
    """The poles (upper half plane) in the band and damping range, with their shapes."""
    ok = np.isfinite(poles) & (poles.imag > 0)
    f = np.where(ok, poles.imag, 0.0) / (2 * np.pi)
    with np.errstate(invalid='ignore', divide='ignore'):
        zeta = -poles.real / np.abs(poles)
    keep = ok & (f >= f_min) & (f <= f_max) & (zeta > 0) & (zeta < max_zeta)
    return poles[keep], None if shapes is None else shapes[:, keep]


def _mac(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Modal assurance criterion |a_i^H b_j|^2 / (|a_i|^2 |b_j|^2) of the columns (p, q)."""
    num = np.abs(a.conj().T @ b) ** 2
    den = np.outer(np.sum(np.abs(a) ** 2, axis=0), np.sum(np.abs(b) ** 2, axis=0))
    return num / np.maximum(den, 1e-300)


def stable_poles(per_order, f_min: float, f_max: float, max_zeta: float,
                 tolerance: float = 0.01, min_mac: float = 0.9) -> list[complex]:
    """Poles (upper half plane) stable over the model orders: each order's poles continue the
    tracks of the lower orders, one pole per track and order, paired by an assignment on the
    pole's relative distance |s - s'| / |s'| (below ``tolerance``) and, where shapes are given,
    the shapes' MAC (above ``min_mac``); a track with a pole in at least half of the orders is
    a mode, its pole the median of the track's. Close modes stay apart as long as each order
    holds them apart."""
    tracks = []          # [list of poles, last shape]
    big = 1e6
    for poles, shapes in per_order:
        poles, shapes = _physical(np.asarray(poles), shapes, f_min, f_max, max_zeta)
        if poles.size == 0:
            continue
        matched = np.zeros(poles.size, bool)
        if tracks:
            last = np.array([track[0][-1] for track in tracks])
            distance = np.abs(poles[None, :] - last[:, None]) / np.abs(last)[:, None]
            cost = distance.copy()
            gate = distance < tolerance
            if shapes is not None:
                mac = _mac(np.stack([track[1] for track in tracks], axis=1), shapes)
                gate &= mac > min_mac
                cost = cost + tolerance * (1.0 - mac)
            rows, cols = scipy.optimize.linear_sum_assignment(np.where(gate, cost, big))
            for i, j in zip(rows, cols):
                if gate[i, j]:
                    tracks[i][0].append(poles[j])
                    tracks[i][1] = None if shapes is None else shapes[:, j]
                    matched[j] = True
        for j in np.flatnonzero(~matched):
            tracks.append([[poles[j]], None if shapes is None else shapes[:, j]])
    need = max(2, len(per_order) // 2)
    out = [complex(np.median(np.real(track)), np.median(np.imag(track)))
           for track, _ in tracks if len(track) >= need]
    return sorted(out, key=lambda pole: pole.imag)


# --------------------------------------------------------------------------- refinement

def _basis(t: np.ndarray, poles: np.ndarray) -> np.ndarray:
    """(n, 2m) real basis e^{sigma t} cos(w t), e^{sigma t} sin(w t) per pole."""
    e = np.exp(np.outer(t, poles))
    return np.concatenate([e.real, e.imag], axis=1)


@dataclass(frozen=True)
class Fit:
    """A refined decay model: poles (m,), covariance of (sigma_1..m, omega_1..m), residues
    (m, c) complex, per pole the ratio of its signal's RMS to the residual's (times
    sqrt(samples)), and the residual (n, c) in units of the weights."""

    poles: np.ndarray
    cov: np.ndarray
    residues: np.ndarray
    snr: np.ndarray
    residual: np.ndarray


def refine(t: np.ndarray, y: np.ndarray, poles: list[complex], weights=None,
           steps: int = 20) -> Fit:
    """Least-squares poles of y(t) = sum_r Re(a_r e^{s_r t}) + offset, each channel divided by
    its ``weights`` (c,) (default: its standard deviation; its noise level makes it the
    maximum-likelihood fit), by variable projection (the amplitudes a_r, complex per channel,
    solved linearly for each trial pole set) and at most ``steps`` Levenberg-Marquardt steps
    from ``poles``."""
    t = t - t[0]
    n, c = y.shape
    m = len(poles)
    scale = np.maximum(np.std(y, axis=0) if weights is None else np.asarray(weights, float),
                       1e-300)
    ys = y / scale

    def solve(x, a=None):
        if a is None:
            a = np.concatenate([_basis(t, x[:m] + 1j * x[m:]), np.ones((n, 1))], axis=1)
        norm = np.linalg.norm(a, axis=0)
        an = a / norm                        # normal equations of unit columns: (2m+1)^2
        try:
            coef = np.linalg.solve(an.T @ an, an.T @ ys) / norm[:, None]
        except np.linalg.LinAlgError:        # two trial poles alike: least norm amplitudes
            coef = np.linalg.lstsq(an, ys, rcond=None)[0] / norm[:, None]
        return (a @ coef - ys).ravel(), a, coef

    def jacobian(x, r, a):
        """Forward differences; a step of pole k changes the basis' columns k and m + k."""
        step = 1e-7 * np.abs(x[m:]).repeat(2).reshape(2, m).ravel()
        columns = []
        for k in range(2 * m):
            xk = x.copy()
            xk[k] += step[k]
            ak = a.copy()
            ak[:, [k % m, m + k % m]] = _basis(t, xk[[k % m]] + 1j * xk[[m + k % m]])
            columns.append((solve(xk, ak)[0] - r) / step[k])
        return np.stack(columns, axis=1)

    x = np.concatenate([np.real(poles), np.imag(poles)])
    r, a, coef = solve(x)
    jac = jacobian(x, r, a)
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
                jac = jacobian(x, r, a)
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
    return Fit(x[:m] + 1j * x[m:], cov, residues, snr, r.reshape(n, c))


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


def _modes(fit: Fit, used: np.ndarray, kind: str, options: Options,
           f_max_hz: float) -> list[tuple[int, Mode]]:
    """(index of the pole, mode) of each pole of ``fit`` that stands out of the noise
    (``min_snr``) in the band with a damping ratio known to ``max_damping_rel_std``."""
    m = fit.poles.size
    out = []
    for r, pole in enumerate(fit.poles):
        if not (pole.imag > 0 and pole.real < 0 and fit.snr[r] >= options.min_snr):
            continue
        f, sf, z, sz = _frequency_damping(pole, fit.cov[r, r], fit.cov[m + r, m + r],
                                          fit.cov[r, m + r])
        if not (options.f_min_hz <= f <= f_max_hz and z < options.max_damping_ratio
                and sz <= options.max_damping_rel_std * z):
            continue
        full = np.zeros(6, dtype=complex)
        full[used] = fit.residues[r]
        out.append((r, Mode(f, sf, z, sz, direction(full, pole, kind))))
    return out


def _alike(fit: Fit, kept: list[int], weights: np.ndarray, tolerance: float = 0.02,
           max_mac: float = 0.9):
    """Two of the kept poles (indices into ``fit.poles``) within ``tolerance`` of each other in
    frequency that move alike (MAC of their residues, channels in units of ``weights``, above
    ``max_mac``): one mode fitted by two poles (a frequency drifting with the amplitude);
    None if there are none."""
    f = np.abs(fit.poles[kept])
    shapes = (fit.residues[kept] / weights).T
    near = np.abs(f[:, None] - f[None, :]) < tolerance * f[:, None]
    np.fill_diagonal(near, False)
    pairs = np.argwhere(near & (_mac(shapes, shapes) > max_mac))
    return None if pairs.size == 0 else (kept[pairs[0][0]], kept[pairs[0][1]])


def merge_alike(t, y, weights, fit: Fit, valid, options: Options, f_max_hz: float,
                kind: str, used: np.ndarray):
    """Refit without the weaker of two reported poles that move alike (:func:`_alike`) until
    no such pair is left. ``y`` (n, c) and ``weights`` (c,) are the ``used`` channels.

    Returns (fit, [(pole index, mode)])."""
    while (pair := _alike(fit, [r for r, _ in valid], weights)) is not None:
        weaker = min(pair, key=lambda r: fit.snr[r])
        fit = refine(t, y, [p for r, p in enumerate(fit.poles) if r != weaker], weights)
        valid = _modes(fit, used, kind, options, f_max_hz)
    return fit, valid


def _residual_peak(fit: Fit, dt: float, f_min: float, f_max: float) -> float:
    """The frequency (Hz) of the highest peak of the residual's spectrum in the band."""
    spectrum = np.sum(np.abs(np.fft.rfft(fit.residual, axis=0)) ** 2, axis=1)
    freq = np.fft.rfftfreq(fit.residual.shape[0], dt)
    band = (freq >= f_min) & (freq <= f_max)
    return float(freq[band][np.argmax(spectrum[band])]) if band.any() else math.nan


def add_missed_poles(t, y, weights, fit: Fit, valid, options: Options, f_max_hz: float,
                     kind: str, used: np.ndarray, tries: int = 3):
    """Poles the subspace step missed (a mode too weak for its noise), looked for in the
    refined model's residual: a pole at the residual spectrum's highest peak (with the
    damping ratio of the nearest pole) joins the model if the refit leaves significantly less
    residual (F test at 1e-6), reports more modes, and no two of them within 2 % move alike
    (:func:`_alike`); at most ``tries`` poles. ``y`` (n, c) and ``weights`` (c,) are the
    ``used`` channels.

    Returns (fit, [(pole index, mode)])."""
    n, c = fit.residual.shape
    for _ in range(tries):
        if len(valid) >= options.max_modes:
            break
        f_peak = _residual_peak(fit, t[1] - t[0], options.f_min_hz, f_max_hz)
        if not math.isfinite(f_peak):
            break
        near = fit.poles[int(np.argmin(np.abs(fit.poles.imag / (2 * np.pi) - f_peak)))]
        zeta = min(max(-near.real / abs(near), 1e-3), 0.1)
        omega = 2 * np.pi * f_peak
        trial = refine(t, y, list(fit.poles) + [complex(-zeta * omega, omega)], weights)
        rss, rss_trial = float(np.sum(fit.residual ** 2)), float(np.sum(trial.residual ** 2))
        m = trial.poles.size
        dof = max(n * c - 2 * m - (2 * m + 1) * c, 1)
        added = 2 + 2 * c
        significant = ((rss - rss_trial) / added) / (rss_trial / dof) > \
            scipy.stats.f.isf(1e-6, added, dof)
        found = _modes(trial, used, kind, options, f_max_hz)
        if not (significant and len(found) > len(valid)
                and _alike(trial, [r for r, _ in found], weights) is None):
            break
        fit, valid = trial, found
    return fit, valid


def identify_decay(t: np.ndarray, y: np.ndarray, kind: str, options: Options,
                   f_max_hz: float) -> list[Mode]:
    """The modes of one free decay ``y`` (n, 6) sampled uniformly at ``t``."""
    dt = t[1] - t[0]
    y = y - y.mean(axis=0)
    scale = np.std(y, axis=0)
    used = scale > 1e-12 * max(scale.max(), 1e-300)
    if not used.any():
        return []
    weights = np.zeros(6)
    weights[used] = np.maximum(noise_level(y[:, used], dt, max(f_max_hz, 0.4 / dt)),
                               1e-3 * scale[used])
    ys = y[:, used] / weights[used]
    top = min(2 * options.max_modes + 10, 60)
    c = ys.shape[1]
    # lags over 0.3 of the longest period, at most 360 Hankel rows, enough for the top order
    block_rows = max(min(int(math.ceil(0.3 / (options.f_min_hz * dt))), 360 // c),
                     int(math.ceil(top / c)) + 2)
    block_rows = min(block_rows, ys.shape[0] // 4)
    orders = list(range(max(4, top // 3) + (max(4, top // 3) % 2), top + 1, 2))
    per_order = ssi_poles(ys, dt, orders, block_rows)
    poles = stable_poles(per_order, options.f_min_hz, f_max_hz, options.max_damping_ratio)
    if not poles:
        return []
    fit = refine(t, y[:, used], poles[:options.max_modes], weights[used])
    valid = _modes(fit, used, kind, options, f_max_hz)
    fit, valid = merge_alike(t, y[:, used], weights[used], fit, valid, options, f_max_hz, kind,
                             used)
    fit, valid = add_missed_poles(t, y[:, used], weights[used], fit, valid, options, f_max_hz,
                                  kind, used)
    return sorted((mode for _, mode in valid), key=lambda mode: mode.frequency_hz)


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
