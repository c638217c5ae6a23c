"""workspace_maps: one colour scale per quantity over every variant, white cells explained."""
from types import SimpleNamespace

import matplotlib
import numpy as np
import pyarrow as pa
import pytest

from cdpr_dynamics.analysis import workspace_maps
from cdpr_dynamics.analysis.config import load_settings

matplotlib.use('Agg')


def _run_and_table():
    """Two variants of a 3 x 2 x 1 grid: the second's values twice the first's; one pose not
    ok (no values), one feasible pose without a platform mode (no lowest_platform_hz)."""
    grid = (np.array([-0.5, 0.0, 0.5]), np.array([-0.5, 0.5]), np.array([1.25]))
    shape = (3, 2, 1)
    n = 6
    hz = np.linspace(10.0, 15.0, n)
    peak = np.linspace(1e-7, 6e-7, n)
    margin = np.linspace(-50.0, 200.0, n)
    columns = {'status': [], 'lowest_platform_hz': [], 'peak_receptance_m_per_n': [],
               'tension_margin_n': []}
    for factor in (1.0, 2.0):
        for i in range(n):
            bad = i == 0
            columns['status'].append('infeasible' if bad else 'ok')
            columns['lowest_platform_hz'].append(None if bad or i == 3 else factor * hz[i])
            columns['peak_receptance_m_per_n'].append(None if bad else factor * peak[i])
            columns['tension_margin_n'].append(factor * margin[i])
    run = SimpleNamespace(grid=grid, shape=shape, poses=np.zeros((n, 7)),
                          settings=load_settings(None), variant_list=[{}, {}])
    return run, pa.table(columns), n


def test_one_colour_scale_per_quantity_across_variants_and_white_cells_explained():
    import matplotlib.pyplot as plt
    run, table, n = _run_and_table()
    limits = workspace_maps.colour_limits(table)
    assert limits['lowest_platform_hz'] == pytest.approx((11.0, 30.0))     # both variants
    assert limits['peak_receptance_m_per_n'] == pytest.approx(
        (np.log10(2e-7), np.log10(1.2e-6)))
    assert limits['tension_margin_n'] == pytest.approx((-100.0, 400.0))
    status = np.asarray(table.column('status').to_pylist())
    for v in range(2):
        rows = slice(v * n, (v + 1) * n)
        values = {name: workspace_maps._column(table, name)[rows].reshape(run.shape)
                  for name, *_ in workspace_maps.QUANTITIES}
        bad = (status[rows] != 'ok').reshape(run.shape)
        fig = workspace_maps.map_figure(plt, run, values, bad, 2, limits)
        panels = fig.axes[:len(workspace_maps.QUANTITIES)]      # one slice: a panel per row
        meshes = [ax.collections[0] for ax in panels]
        for mesh, (name, *_) in zip(meshes, workspace_maps.QUANTITIES):
            assert (mesh.norm.vmin, mesh.norm.vmax) == pytest.approx(limits[name]), name
        notes = [t.get_text() for t in fig.legends[0].get_texts()]
        assert any(t.startswith('hatched: status != ok') and 'white' in t for t in notes)
        assert any(t.startswith('white, not hatched: no value at a feasible pose')
                   for t in notes)
        plt.close(fig)
