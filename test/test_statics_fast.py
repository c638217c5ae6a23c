"""The sag statics' fast path against its general one (the regression guard of both).

The SQP of ``statics.sag_equilibrium`` takes each solve's tension sensitivity from the solve's
own last evaluation (``catenary.solve_with_sensitivity``) and starts its trial solves from the
first-order prediction alone (``warm_only``). The general path is ``catenary.solve`` (the
parabola start beside the warm start) followed by ``catenary.tension_sensitivity`` of the lifted
forces. Both must give the same tensions, end forces and unstrained lengths to rounding, the same
SQP iteration counts, warnings and refusals, along pose sequences that include the lifted lower
bounds (existence probes, step halving) of the low-tension robot.
"""
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from cdpr_dynamics.mechanics import statics
from cdpr_dynamics.analysis.pipeline import AnalysisError, equilibrium
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.models import catenary
from cdpr_dynamics.models.base import CableSet

REPO = Path(__file__).resolve().parents[1]
CONFIGS = {'paper': REPO / 'config' / 'paper_cdpr.yaml',
           'heavy': REPO / 'config' / 'heavy_sag_6dof.yaml',
           'low_tension': REPO / 'config' / 'low_tension_cdpr.yaml',
           'rigid': REPO / 'test' / 'data' / 'rigid_cdpr.yaml'}

CASES = {'paper': ('paper', None), 'heavy': ('heavy', None), 'rigid': ('rigid', None),
         'low_tension': ('low_tension', None), 'low_tension_lifted': ('low_tension', 0.5),
         'heavy_lifted': ('heavy', 0.5)}


def general_solve_with_sensitivity(cables, start=None, warm_only=False):
    """The general path: solve (both starts), then the sensitivity of the lifted forces."""
    state = catenary.solve(cables, start=start)
    return (state, *catenary.tension_sensitivity(state, cables))


def rotation(v):
    """Rotation matrix of the rotation vector v (Rodrigues)."""
    angle = np.linalg.norm(v)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]) / angle
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def pose_sequence(settings, n=24, seed=5):
    """A 5 cm circle of 12 poses, then a random walk of 3 cm steps with small rotations."""
    rng = np.random.default_rng(seed)
    start = np.asarray(settings.initial_position_m, dtype=float)
    poses = [(start + 0.05 * np.array([np.cos(a), np.sin(a), 0.0]), np.eye(3))
             for a in np.linspace(0.0, 2 * np.pi, n // 2, endpoint=False)]
    position = start
    for _ in range(n - n // 2):
        position = position + rng.normal(0.0, 0.03, 3)
        poses.append((position, rotation(rng.normal(0.0, 0.02, 3))))
    return poses


def sag_sequence(settings, poses):
    """(tensions, end forces, L0, iterations, warnings) or the refusal's text, per pose, each
    pose warm-started from the previous answer (as the live predictor does)."""
    out, previous = [], None
    for position, rot in poses:
        try:
            eq = equilibrium(settings, position, rot, method='catenary_exact', start=previous)
        except AnalysisError as exc:
            out.append(str(exc))
            previous = None
            continue
        out.append((eq.tensions.tension_n, eq.end_force_n, eq.unstretched_length_m,
                    eq.iterations, eq.warnings))
        previous = eq
    return out


@pytest.mark.parametrize('case', sorted(CASES))
def test_fast_sag_statics_equal_the_general_path(case, monkeypatch):
    name, t_min = CASES[case]
    settings = load_settings(str(CONFIGS[name])).replace(method='catenary_exact')
    if t_min is not None:
        settings = settings.replace(tension_min_n=t_min)
    poses = pose_sequence(settings)
    fast = sag_sequence(settings, poses)
    monkeypatch.setattr(catenary, 'solve_with_sensitivity', general_solve_with_sensitivity)
    general = sag_sequence(settings, poses)
    t_max = settings.tension_max_n
    solved = 0
    for mine, ref in zip(fast, general):
        assert type(mine) is type(ref)
        if isinstance(ref, str):
            assert mine == ref                      # the same refusal, word for word
            continue
        solved += 1
        tension, force, l0, iterations, warnings = mine
        assert iterations == ref[3] and warnings == ref[4]
        assert_allclose(tension, ref[0], rtol=0, atol=1e-9 * t_max)
        assert_allclose(tension, ref[0], rtol=1e-11)
        assert_allclose(force, ref[1], rtol=0, atol=1e-11 * np.abs(ref[1]).max())
        assert_allclose(l0, ref[2], rtol=1e-11)
    assert solved >= len(poses) // 2


def test_lifted_sequences_exercise_the_probes_and_the_halvings(monkeypatch):
    """The lifted cases above go through lowest_tension's probes and halved SQP steps."""
    calls = {'lowest': 0, 'halved': 0}
    lowest, solve = statics.lowest_tension, catenary.solve_with_sensitivity

    def count_lowest(*args, **kwargs):
        calls['lowest'] += 1
        return lowest(*args, **kwargs)

    def count_trials(cables, start=None, warm_only=False):
        calls['halved'] += warm_only
        return solve(cables, start=start, warm_only=warm_only)

    monkeypatch.setattr(statics, 'lowest_tension', count_lowest)
    monkeypatch.setattr(catenary, 'solve_with_sensitivity', count_trials)
    settings = load_settings(str(CONFIGS['heavy']))
    settings = settings.replace(method='catenary_exact', tension_min_n=0.5)
    iterations = 0
    for item in sag_sequence(settings, pose_sequence(settings, n=6)):
        iterations += 0 if isinstance(item, str) else item[3] - 1
    assert calls['lowest'] > 0
    assert calls['halved'] > iterations           # more trial solves than accepted steps


@pytest.mark.parametrize('seed', range(4))
def test_solve_with_sensitivity_equals_solve_then_tension_sensitivity(seed):
    rng = np.random.default_rng(seed)
    for _ in range(25):
        n = int(rng.integers(1, 9))
        chord = rng.normal(size=(n, 3)) * rng.uniform(0.1, 5.0, (n, 1))
        gamma = float(rng.choice([0.0, 0.5, 5.0]))
        tension = (gamma + 1.0) * np.linalg.norm(chord, axis=1) * rng.uniform(-0.2, 4.0, n)
        cables = CableSet(chord, tension, float(rng.choice([1e4, 1e6])), gamma, (0, 0, -9.81))
        start = catenary.solve(cables)
        moved = cables.with_tension(tension * (1.0 + rng.normal(0.0, 0.01, n)))
        for warm_only in (False, True):
            state, d_force, d_length = catenary.solve_with_sensitivity(moved, start, warm_only)
            ref = catenary.solve(moved, start=start)
            ref_force, ref_length = catenary.tension_sensitivity(ref, moved)
            assert np.array_equal(state.valid, ref.valid) and state.reasons == ref.reasons
            ok = ref.valid
            assert_allclose(state.force_n[ok], ref.force_n[ok], rtol=1e-12,
                            atol=1e-12 * np.abs(moved.tension_n).max())
            assert_allclose(state.unstrained_length_m, ref.unstrained_length_m, rtol=1e-12)
            assert np.array_equal(np.isnan(d_length), np.isnan(ref_length))
            fin = ~np.isnan(ref_length)     # rounding of the lift and back, where d.w cancels
            assert_allclose(d_length[fin], ref_length[fin], rtol=1e-8,
                            atol=1e-8 * np.abs(ref_length[fin]).max(initial=0.0))
            assert_allclose(d_force[fin], ref_force[fin], rtol=1e-8,
                            atol=1e-8 * np.abs(ref_force[fin]).max(initial=0.0))
            if not warm_only:       # the same solve: the very same catenaries
                assert np.array_equal(state.force_n, ref.force_n)
