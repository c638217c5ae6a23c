"""The node's ``/diagnostics``: the health of each input (counters, the last rejection, the
worst level since the last report, throttled log lines) and the statuses of one report (model,
pose input, wrench input, frequency_response).
"""
from __future__ import annotations

import collections
import time

import numpy as np

from cdpr_dynamics.analysis.pipeline import equilibrium_summary
from msg_adapters import diagnostics as diag

LOG_PERIOD_S = 1.0        # a kind of rejection or warning is logged at most this often


class InputHealth:
    """Counters and the last rejection of one input; the worst level since the last report."""

    def __init__(self, logger, bad_level: int):
        self.logger = logger
        self.bad_level = bad_level
        self.accepted = 0
        self.rejected = collections.Counter()
        self.last_reason = ''
        self.last_reason_time = 0.0
        self.level = diag.OK           # of the latest input
        self.worst = diag.OK           # since the last report
        self.worst_reason = ''
        self._logged: dict[str, float] = {}
        self._suppressed = collections.Counter()
        self._children = {}
        self.notes = collections.Counter()
        self.last_note = ''
        self.late = 0                  # taken out of stamp order with the other input
        self.late_max_ms = 0.0

    def accept(self, late_by_ns: int | None = None) -> bool:
        """Count a good input (``late_by_ns``: it came out of stamp order with the other
        input by that much, :attr:`msg_adapters.inputs.InputHandler.late_by_ns`); True when the
        level changed."""
        self.accepted += 1
        if late_by_ns is not None:
            self.late += 1
            self.late_max_ms = max(self.late_max_ms, late_by_ns * 1e-6)
        changed = self.level != diag.OK
        self.level = diag.OK
        return changed

    def reject(self, kind: str, reason: str) -> bool:
        """Count a rejection, log it (at most once a second per kind); True when it is news."""
        now = time.monotonic()
        self.rejected[kind] += 1
        news = self.level != self.bad_level or reason != self.last_reason
        self.last_reason, self.last_reason_time = reason, now
        self.level = self.bad_level
        if self.worst < self.bad_level:
            self.worst, self.worst_reason = self.bad_level, reason
        if now - self._logged.get(kind, -np.inf) >= LOG_PERIOD_S:
            more = self._suppressed.pop(kind, 0)
            text = reason + (f' ({more} more since the last log)' if more else '')
            if kind not in self._children:
                self._children[kind] = self.logger.get_child(kind)
            logger = self._children[kind]
            # throttled above (once a second per kind, counting what was held back)
            if self.bad_level >= diag.ERROR:
                logger.error(text)
            else:
                logger.warning(text)
            self._logged[kind] = now
        else:
            self._suppressed[kind] += 1
        return news

    def warn(self, kind: str, text: str) -> bool:
        """An accepted input that is worth a warning (a clock jump, a skipped interval): log it
        (throttled as rejections are), count it and raise this report to WARN; True (news)."""
        self.notes[kind] += 1
        self.last_note = text
        if self.worst < diag.WARN:
            self.worst, self.worst_reason = diag.WARN, text
        now = time.monotonic()
        key = 'note_' + kind
        if now - self._logged.get(key, -np.inf) >= LOG_PERIOD_S:
            more = self._suppressed.pop(key, 0)
            self.logger.warning(text + (f' ({more} more since the last log)' if more else ''))
            self._logged[key] = now
        else:
            self._suppressed[key] += 1
        return True

    def report(self):
        """(level, reason) for this report: the worst since the last one; then reset."""
        level, reason = max(self.level, self.worst), self.worst_reason or (
            self.last_reason if self.level else '')
        self.worst, self.worst_reason = diag.OK, ''
        return level, reason

    def values(self) -> dict:
        age = time.monotonic() - self.last_reason_time if self.last_reason else None
        values = {'accepted': self.accepted, 'rejected': sum(self.rejected.values()),
                  'late': self.late, 'late_max_ms': round(self.late_max_ms, 3)}
        values.update({f'rejected_{k}': v for k, v in sorted(self.rejected.items())})
        values['last_rejection'] = self.last_reason or 'none'
        if self.notes:
            values['warnings'] = sum(self.notes.values())
            values['last_warning'] = self.last_note
        if age is not None:
            values['last_rejection_age_s'] = round(age, 3)
        return values


class Timings:
    """Samples (seconds) the diagnostics report as percentiles: the model's rebuilds, each
    wrench's computation (check, integration, message) and publication, the wrenches' arrival
    times, and (``node.rebuild: worker``) a moved pose's wait for its model."""

    def __init__(self):
        self.rebuild_s = collections.deque(maxlen=512)
        self.compute_s = collections.deque(maxlen=4096)
        self.publish_s = collections.deque(maxlen=4096)
        self.wrench_times = collections.deque(maxlen=8192)
        self.swap_s = collections.deque(maxlen=512)

    def wrench_values(self) -> dict:
        """compute/publish ms p50 and p99 and the wrench rate of the last second (Hz)."""
        values = {}
        for key, samples in (('compute', self.compute_s), ('publish', self.publish_s)):
            if samples:
                ms = np.array(samples) * 1e3
                values[f'{key}_ms_p50'] = float(np.percentile(ms, 50))
                values[f'{key}_ms_p99'] = float(np.percentile(ms, 99))
        times = np.array(self.wrench_times)
        recent = times[times > time.perf_counter() - 1.0]
        values['rate_hz'] = float(recent.size)
        return values

    def model_values(self) -> dict:
        """The rebuilds' ms p50 and p99 and the pose-to-model swap's ms p50 and max."""
        values = {}
        if self.swap_s:
            swap = np.array(self.swap_s) * 1e3
            values['swap_ms_p50'] = float(np.percentile(swap, 50))
            values['swap_ms_max'] = float(swap.max())
        if self.rebuild_s:
            rebuild = np.array(self.rebuild_s) * 1e3
            values['update_ms_p50'] = float(np.percentile(rebuild, 50))
            values['update_ms_p99'] = float(np.percentile(rebuild, 99))
        return values


def input_status(name: str, title: str, health: InputHealth, extra: dict, hw: str) -> tuple:
    """The status of one input for this report (resets its worst level)."""
    level, reason = health.report()
    message = reason or f'{health.accepted} accepted'
    return f'{name}: {title}', level, message, {**health.values(), **extra}, hw


def model_status(name: str, hw: str, predictor, modal: dict, extra: dict) -> tuple:
    """The model's status: its method, size, pose, tensions, modes (``modal``: lowest_hz,
    platform_hz, warnings), equilibrium and ``extra`` values; WARN with the first warning."""
    update = predictor.last_update
    warnings = list(update.warnings) + list(modal['warnings'])
    platform_hz = modal['platform_hz']
    values = {
        'method': update.method, 'configured_method': predictor.settings.method,
        'elements_per_cable': predictor.settings.elements_per_cable, 'dofs': update.dofs,
        'position_m': np.round(predictor.position_m, 5).tolist(),
        'qp_status': predictor.eq.tensions.status,
        'qp_iterations': predictor.eq.tensions.iterations,
        'tension_min_n': float(predictor.eq.tensions.tension_n.min()),
        'tension_max_n': float(predictor.eq.tensions.tension_n.max()),
        'lowest_natural_frequency_hz': modal['lowest_hz'],
        'lowest_platform_mode_hz': (float(platform_hz[0]) if platform_hz.size
                                    else float('nan')),
        'platform_modes_hz': np.round(platform_hz, 4).tolist(),
        'sag_parameter': np.round(update.sag_parameter, 4).tolist(),
        **equilibrium_values(predictor.settings, predictor.eq),
        **extra,
    }
    for stage, seconds in update.timings_s.items():
        values[f'last_update_{stage}_ms'] = seconds * 1e3
    values['warnings'] = warnings or 'none'
    level = diag.WARN if warnings else diag.OK
    message = (f'{update.method}, {update.dofs} DOFs' + (f': {warnings[0]}' if warnings
                                                         else ''))
    return f'{name}: model', level, message, values, hw


def equilibrium_values(settings, eq) -> dict:
    """Diagnostics of the static state: statics kind, residual, iterations, per-cable end force
    (N, 3 values per cable) and unstretched length (m)."""
    summary = equilibrium_summary(settings, eq)
    return {'statics': summary['statics'],
            'equilibrium_residual_n': summary['residual_n'],
            'equilibrium_residual_nm': summary['residual_nm'],
            'equilibrium_relative_residual': summary['relative_residual'],
            'statics_iterations': summary['iterations'],
            'end_force_n': np.round(eq.end_force_n, 4).ravel().tolist(),
            'unstretched_length_m': np.round(eq.unstretched_length_m, 6).tolist()}
