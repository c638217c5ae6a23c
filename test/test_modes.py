"""Mode classification (cdpr_dynamics.dynamics.modes): energy fractions, kinds, cables, effective
mass."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cdpr_dynamics.analysis.pipeline import build_system, equilibrium
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.system import DynamicsError, platform_frequencies
from cdpr_dynamics.dynamics.modes import (CABLE_SHARE, PLATFORM_SHARE, classify, modes,
                                          natural_frequencies)

REPO = Path(__file__).resolve().parents[1]
PAPER = load_settings(REPO / 'config' / 'paper_cdpr.yaml')
RIGID = load_settings(REPO / 'test' / 'data' / 'rigid_cdpr.yaml')
OFF_CENTRE = np.array([0.35, -0.2, 1.0])


@pytest.mark.parametrize('settings, method, n', [(PAPER, 'fem', 4), (PAPER, 'fem_sag', 3),
                                                 (RIGID, 'fem', 3), (RIGID, 'spring', 1)])
def test_effective_masses_sum_to_the_platform_diagonal(settings, method, n):
    eq = equilibrium(settings, OFF_CENTRE)
    system = build_system(settings, eq, method, n)
    found = modes(system, count=system.dofs)                  # every mode
    assert found.frequency_hz.size == system.dofs
    _, mass = system.matrices(dense=True)
    diagonal = np.diag(mass)[:system.platform_dofs]
    np.testing.assert_allclose(found.effective_mass.sum(axis=0), diagonal, rtol=1e-9)
    # the platform diagonal is the platform's own mass and inertia plus the end-node share
    own = np.diag(settings.robot.platform_mass_matrix(eq.geometry.rotation))
    assert np.all(diagonal >= own - 1e-12)
    assert (np.all(diagonal > own) if method != 'spring' else np.allclose(diagonal, own))


def test_massless_models_have_only_platform_modes():
    eq = equilibrium(PAPER, OFF_CENTRE)
    system = build_system(PAPER, eq, 'spring')
    found = modes(system, PAPER.f_max_hz)
    assert found.kind == ('platform',) * 3 and np.all(found.cable == -1)
    np.testing.assert_allclose(found.platform_fraction, 1.0)
    # the platform mass on the springs: eig(K_static, M_platform), an independent solve
    np.testing.assert_allclose(found.frequency_hz, platform_frequencies(system), rtol=1e-10)
    np.testing.assert_allclose(found.effective_mass.sum(axis=0), PAPER.robot.mass_kg)


def test_paper_robot_fem16_platform_triple_and_cable_modes():
    eq = equilibrium(PAPER)
    system = build_system(PAPER, eq, 'fem', 16)
    found = modes(system, PAPER.f_max_hz)
    assert found.frequency_hz.size >= 12 and found.frequency_hz[-1] <= PAPER.f_max_hz
    np.testing.assert_allclose(found.frequency_hz, natural_frequencies(system, found.frequency_hz
                                                                       .size), rtol=1e-9)
    platform = found.platform_hz
    assert platform.size == 3                               # the 32.4 Hz triple of the paper
    np.testing.assert_allclose(platform, 32.40, atol=0.01)
    spring = platform_frequencies(build_system(PAPER, eq, 'spring'))
    np.testing.assert_allclose(platform, spring, rtol=2e-3)  # cables' inertia: a little lower
    # everything else is a cable mode that barely moves the platform
    cable = np.array([k == 'cable' for k in found.kind])
    assert np.all(found.platform_fraction[cable] < 1e-2)
    assert np.all(found.cable[cable] >= 0)
    assert np.all(found.platform_fraction[~cable] > 0.98)


def test_cable_modes_name_the_cable_that_vibrates():
    """Off-centre, every cable has its own length and tension: the lowest mode attributed to
    cable i is its taut-string fundamental f = sqrt(T/mu) / (2 L) (a closed form)."""
    eq = equilibrium(PAPER, OFF_CENTRE)
    system = build_system(PAPER, eq, 'fem', 16)
    found = modes(system, 60.0)
    mu = PAPER.cable.mass_per_length_kg_m
    string = np.sqrt(eq.tensions.tension_n / mu) / (2 * eq.geometry.length_m)
    for i in range(PAPER.robot.n_cables):
        named = found.frequency_hz[(found.cable == i) & (np.array(found.kind) == 'cable')]
        assert named.size >= 2, f'cable {i} has no mode of its own below 60 Hz'
        np.testing.assert_allclose(named.min(), string[i], rtol=0.02, err_msg=f'cable {i}')


def test_classify_thresholds():
    assert classify([1.0, PLATFORM_SHARE, 0.3, CABLE_SHARE, 0.0]) == (
        'platform', 'platform', 'mixed', 'cable', 'cable')


def test_hint_changes_cost_not_modes():
    eq = equilibrium(PAPER, OFF_CENTRE)
    system = build_system(PAPER, eq, 'fem', 8)
    cold, warm = modes(system, PAPER.f_max_hz), modes(system, PAPER.f_max_hz, hint=60)
    np.testing.assert_allclose(cold.frequency_hz, warm.frequency_hz, rtol=1e-9)
    assert cold.kind == warm.kind


def test_dsm_has_no_mode_shapes():
    system = build_system(PAPER, equilibrium(PAPER), 'dsm')
    assert modes(system).shapes is None                        # classified by counting
    with pytest.raises(DynamicsError, match='no finite matrices'):
        modes(system, shapes=True)
