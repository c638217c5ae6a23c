"""What the node can sustain (cdpr_dynamics.ros.budget): the measured cost of a wrench, the
wrench period, the refusal text; and one name, one node."""
import time

import numpy as np
import pytest

from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.ros import budget
from conftest import PAPER_CONFIG


def test_the_period_is_the_median_interval_of_recent_wrenches_or_the_nominal_one():
    now = time.perf_counter()
    arrivals = now - 0.5 + np.arange(100) * 2e-3          # 500 Hz over the last 0.2 s
    period, measured = budget.wrench_period_s(arrivals)
    assert measured and period == pytest.approx(2e-3)
    assert budget.wrench_period_s(arrivals[:5]) == (budget.NOMINAL_PERIOD_S, False)
    assert budget.wrench_period_s(arrivals - 10.0) == (budget.NOMINAL_PERIOD_S, False)


def test_over_budget_says_the_estimate_and_the_share_dropped():
    assert budget.over_budget(0.9e-3, 1e-3, True) == ''
    text = budget.over_budget(4e-3, 1e-3, False)
    assert text == ('a wrench would cost 4 ms on this model against a wrench period of 1 ms '
                    '(nominal, until wrenches arrive): about 75 % of the wrenches would be '
                    'dropped')


def test_measuring_the_cost_leaves_the_predictor_as_it_was():
    predictor = LivePredictor(load_settings(PAPER_CONFIG).replace(method='fem',
                                                                  elements_per_cable=4))
    predictor.advance(0, [0.0, 0.0, 30.0])
    predictor.advance(5_000_000, [0.0, 0.0, 30.0])
    state = predictor.integrator._state.copy()
    before = predictor.prediction().displacement_m
    cost = budget.wrench_cost_s(predictor, 1e-3)
    assert 0.0 < cost < np.inf
    np.testing.assert_array_equal(predictor.integrator._state, state)
    np.testing.assert_array_equal(predictor.prediction().displacement_m, before)
    predictor.advance(6_000_000, [0.0, 0.0, 30.0])      # its clock was not moved either
