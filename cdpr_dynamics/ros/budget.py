"""What the node can sustain: the cost of one wrench on a model against the wrenches' period,
and the time budgets of its background jobs.

A setting is within the node's means when one wrench costs less than the interval between
wrenches; otherwise the node predicts only about period / cost of them (the rest wait in the
subscription's queue until the oldest are dropped). The cost is measured, not modelled: a copy
of the predictor advances a few wrenches at the period (Newmark steps, or the closed form of a
held load where the predictor takes it), and the fastest of them counts, so a busy machine
does not make a setting look dearer than it is.
"""
from __future__ import annotations

import copy
import time

import numpy as np

NOMINAL_PERIOD_S = 1e-3      # the wrench period assumed until wrenches arrive (a 1 kHz loop)
MEASURE_WRENCHES = 5         # wrenches advanced on the copy (the fastest counts)
MODES_BUDGET_S = 60.0        # a modes refresh running longer is cancelled
FRF_BUDGET_S = 120.0         # a frequency_response computation running longer is cancelled


def wrench_period_s(arrivals) -> tuple[float, bool]:
    """(period s, measured?): the median interval of the wrenches that arrived in the last
    two seconds (``arrivals``: time.perf_counter() values), or :data:`NOMINAL_PERIOD_S`."""
    times = np.asarray(arrivals, dtype=float)
    recent = times[times > time.perf_counter() - 2.0]
    if recent.size >= 20:
        return float(np.median(np.diff(recent))), True
    return NOMINAL_PERIOD_S, False


def wrench_cost_s(predictor, period_s: float) -> float:
    """Seconds one wrench costs ``predictor``'s model when wrenches come every ``period_s``:
    the fastest of :data:`MEASURE_WRENCHES` advanced on a copy (the predictor is untouched)."""
    trial = copy.deepcopy(predictor)
    trial.reset_time()
    step_ns = max(1, round(period_s * 1e9))
    force = np.zeros(3)
    trial.advance(0, force)
    best = np.inf
    for k in range(1, MEASURE_WRENCHES + 1):
        start = time.perf_counter()
        trial.advance(k * step_ns, force)
        best = min(best, time.perf_counter() - start)
    return float(best)


def over_budget(cost_s: float, period_s: float, measured: bool) -> str:
    """Why ``cost_s`` a wrench is more than the node can sustain at ``period_s`` ('' if it
    is not): the estimate and the share of wrenches it would drop."""
    if cost_s <= period_s:
        return ''
    source = 'measured' if measured else 'nominal, until wrenches arrive'
    dropped = 100.0 * (1.0 - period_s / cost_s)
    return (f'a wrench would cost {cost_s * 1e3:.3g} ms on this model against a wrench '
            f'period of {period_s * 1e3:.3g} ms ({source}): about {dropped:.0f} % of the '
            'wrenches would be dropped')
