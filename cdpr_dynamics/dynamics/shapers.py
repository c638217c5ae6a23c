"""Input shapers (ZV, ZVD, EI) and notch biquads for predicted modes.

A shaper is a train of impulses, times t_i (s) and amplitudes A_i summing to 1; a command
convolved with it leaves a mode (frequency f, damping ratio zeta, w = 2 pi f,
w_d = w sqrt(1 - zeta^2)) the residual vibration

    V(f, zeta) = exp(-zeta w t_N) |sum_i A_i exp(zeta w t_i) exp(j w_d t_i)|

of the unshaped command's (Singer and Seering 1990). With K = exp(-zeta pi / sqrt(1 - zeta^2))
and the damped half period T = pi / w_d:

* ZV: A = (1, K) / (1 + K) at (0, T): V = 0 at f.
* ZVD: A = (1, 2K, K^2) / (1 + K)^2 at (0, T, 2T): V = 0 and dV/df = 0 at f.
* EI (extra insensitive, tolerance V_tol = 5 %): the undamped EI weights
  ((1 + V_tol)/4, (1 - V_tol)/2, (1 + V_tol)/4) times (1, K, K^2), normalised, at (0, T, 2T):
  V = V_tol at f (exactly for zeta = 0) and zero on either side, so V <= V_tol over about
  +-20 % of f.

Shapers for several modes are convolved (times added, amplitudes multiplied): the residual of
each mode is at most its own shaper's. A notch is the biquad of the RBJ audio-EQ cookbook at a
sample rate fs, w0 = 2 pi f / fs, alpha = sin(w0) / (2 Q):
b = (1, -2 cos w0, 1) / a0, a = (1 + alpha, -2 cos w0, 1 - alpha) / a0 with a0 = 1 + alpha:
gain 1 at DC and at Nyquist, 0 at f, -3 dB at f (1 +- 1/(2 Q)) roughly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

KINDS = ('zv', 'zvd', 'ei')
EI_TOLERANCE = 0.05
NOTCH_Q = 2.5       # -3 dB band about +-20 % of the notch frequency
TIME_DECIMALS = 12  # impulse times closer than 1e-12 s merge when shapers are convolved


@dataclass(frozen=True, eq=False)
class Shaper:
    """Impulse ``times_s`` (ascending, the first 0) and ``amplitudes`` (summing to 1)."""

    times_s: np.ndarray
    amplitudes: np.ndarray

    def pairs(self) -> np.ndarray:
        """t0, a0, t1, a1, ... (the ``input_shaper`` message's data)."""
        return np.column_stack([self.times_s, self.amplitudes]).reshape(-1)

    @property
    def duration_s(self) -> float:
        """The time of the last impulse (s): the delay the shaper adds."""
        return float(self.times_s[-1])

    def residual(self, frequency_hz, damping_ratio=0.0) -> np.ndarray:
        """V: the residual vibration of a mode, relative to the unshaped command's."""
        f = np.asarray(frequency_hz, dtype=float)[..., None]
        zeta = np.asarray(damping_ratio, dtype=float)[..., None]
        w = 2.0 * math.pi * f
        w_d = w * np.sqrt(np.clip(1.0 - zeta ** 2, 0.0, None))
        t = self.times_s
        total = np.sum(self.amplitudes * np.exp(zeta * w * (t - t[-1]) + 1j * w_d * t), axis=-1)
        return np.abs(total)

    def shaped(self, t_s, command) -> np.ndarray:
        """The command (a function of time, vectorised) convolved with the impulses, at
        ``t_s``: sum_i A_i command(t - t_i)."""
        t_s = np.asarray(t_s, dtype=float)
        return sum(a * command(t_s - ti) for ti, a in zip(self.times_s, self.amplitudes))


def _damped(frequency_hz: float, damping_ratio: float) -> tuple[float, float]:
    """(K, T): the decay over a half period and the damped half period (s)."""
    if not (frequency_hz > 0 and 0.0 <= damping_ratio < 1.0):
        raise ValueError(f'a shaper needs an underdamped mode (f > 0, 0 <= zeta < 1), not '
                         f'f = {frequency_hz:g} Hz, zeta = {damping_ratio:g}')
    root = math.sqrt(1.0 - damping_ratio ** 2)
    return (math.exp(-damping_ratio * math.pi / root),
            1.0 / (2.0 * frequency_hz * root))


def _train(weights, half_period_s: float) -> Shaper:
    weights = np.asarray(weights, dtype=float)
    return Shaper(half_period_s * np.arange(weights.size), weights / weights.sum())


def zv(frequency_hz: float, damping_ratio: float = 0.0) -> Shaper:
    """Zero vibration: two impulses half a damped period apart."""
    k, half = _damped(frequency_hz, damping_ratio)
    return _train([1.0, k], half)


def zvd(frequency_hz: float, damping_ratio: float = 0.0) -> Shaper:
    """Zero vibration and derivative: three impulses, a damped period long."""
    k, half = _damped(frequency_hz, damping_ratio)
    return _train([1.0, 2.0 * k, k * k], half)


def ei(frequency_hz: float, damping_ratio: float = 0.0,
       tolerance: float = EI_TOLERANCE) -> Shaper:
    """Extra insensitive: V = ``tolerance`` at the mode, zero on either side."""
    k, half = _damped(frequency_hz, damping_ratio)
    return _train([(1.0 + tolerance) / 4.0, (1.0 - tolerance) / 2.0 * k,
                   (1.0 + tolerance) / 4.0 * k * k], half)


def design(kind: str, frequency_hz, damping_ratio) -> Shaper:
    """The ``kind`` shaper (zv, zvd, ei) for each mode, convolved (:func:`convolve`)."""
    make = {'zv': zv, 'zvd': zvd, 'ei': ei}.get(kind)
    if make is None:
        raise ValueError(f'unknown shaper {kind!r} (one of {", ".join(KINDS)})')
    return convolve(*(make(float(f), float(z)) for f, z in
                      zip(np.atleast_1d(frequency_hz), np.atleast_1d(damping_ratio))))


def convolve(*shapers: Shaper) -> Shaper:
    """One shaper doing what ``shapers`` do one after another (impulses at equal times
    merged)."""
    times, amplitudes = np.zeros(1), np.ones(1)
    for shaper in shapers:
        times = (times[:, None] + shaper.times_s[None, :]).reshape(-1)
        amplitudes = (amplitudes[:, None] * shaper.amplitudes[None, :]).reshape(-1)
    keys, inverse = np.unique(np.round(times, TIME_DECIMALS), return_inverse=True)
    merged = np.zeros(keys.size)
    np.add.at(merged, inverse, amplitudes)
    return Shaper(keys, merged)


def notch_biquad(frequency_hz: float, sample_rate_hz: float, q: float = NOTCH_Q) -> np.ndarray:
    """(b0, b1, b2, a0, a1, a2), a0 = 1: the notch at ``frequency_hz`` (module docstring).
    Raises ``ValueError`` at or above Nyquist."""
    if not 0.0 < frequency_hz < sample_rate_hz / 2.0:
        raise ValueError(f'a notch at {frequency_hz:g} Hz needs a sample rate above '
                         f'{2 * frequency_hz:g} Hz (got {sample_rate_hz:g} Hz)')
    w0 = 2.0 * math.pi * frequency_hz / sample_rate_hz
    alpha = math.sin(w0) / (2.0 * q)
    c = -2.0 * math.cos(w0)
    a0 = 1.0 + alpha
    return np.array([1.0, c, 1.0, a0, c, 1.0 - alpha]) / a0


def biquad_response(coefficients, frequency_hz, sample_rate_hz: float) -> np.ndarray:
    """Complex gain H(e^{j w}) of (b0, b1, b2, a0, a1, a2) at ``frequency_hz``."""
    b, a = np.asarray(coefficients[:3]), np.asarray(coefficients[3:6])
    z = np.exp(-1j * 2.0 * math.pi * np.asarray(frequency_hz, dtype=float) / sample_rate_hz)
    powers = np.stack([np.ones_like(z), z, z * z], axis=-1)
    return (powers @ b) / (powers @ a)
