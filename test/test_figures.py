"""cdpr_dynamics.analysis.figures: the PNGs of cdpr_analyze and cdpr_tradeoff, checked on the data
the
figures draw (read back from the artists), not on pixels."""
import json
import struct
from argparse import Namespace

import numpy as np
import pytest
from matplotlib.text import Annotation
from numpy.testing import assert_allclose

from cdpr_dynamics.analysis import figures
from cdpr_dynamics.analysis.pipeline import build_system, equilibrium, equilibrium_for
from cdpr_dynamics.cli import analyze as analyze_cli
from cdpr_dynamics.analysis.config import load_settings
from cdpr_dynamics.dynamics.modes import modes
from conftest import REPO, analyze

RIGID = REPO / 'test' / 'data' / 'rigid_cdpr.yaml'
HEAVY = REPO / 'config' / 'heavy_sag_6dof.yaml'


def documents(config=None, methods=('fem', 'spring'), elements=4, slack_aware=False,
              excitation=(5.0,), duration=0.3):
    args = analyze_cli.parse_args(
        (['--config', str(config)] if config else [])
        + ['--method', *methods, '--elements', str(elements), '--duration', str(duration),
           '--excitation-hz', *map(str, excitation)] + (['--slack-aware'] if slack_aware else []))
    result = analyze_cli.run(args)
    return result.get('methods', [result])


@pytest.fixture(scope='module')
def paper_docs():
    """The paper robot, fem n = 4 and spring, 5 Hz for 0.4 s with the slack-aware run."""
    return documents(slack_aware=True, duration=0.4)


@pytest.fixture(scope='module')
def rigid_docs():
    return documents(RIGID, methods=('fem',))


def lines(ax, gid):
    return [line for line in ax.get_lines() if line.get_gid() == gid]


@pytest.mark.slow
def test_frf_is_amplitude_per_newton_with_the_jsons_platform_modes_marked(paper_docs, tmp_path):
    force_n = load_settings().frf_force_n                       # the config's 1500 N along z
    fig = figures.frf_figure(paper_docs, tmp_path / 'frf.png', 'z')
    ax, ax_phase = fig.axes[:2]
    assert ax.get_xscale() == 'log' and ax.get_yscale() == 'log'
    for i, doc in enumerate(paper_docs):
        (line,) = lines(ax, f'frf-{i}')
        assert_allclose(line.get_xdata(), doc['frf']['frequency_hz'])
        assert_allclose(line.get_ydata(),
                        np.array(doc['frf']['amplitude_m'])[:, 2] / np.linalg.norm(force_n),
                        rtol=1e-12)
        (phase,) = lines(ax_phase, f'phase-{i}')
        assert_allclose(phase.get_ydata(), np.degrees(np.array(doc['frf']['phase_rad'])[:, 2]))
    # marked modes: exactly the first document's, by kind, within the sweep (1-40 Hz)
    first = paper_docs[0]
    marked = sorted(line.get_xdata()[0] for line in lines(ax, 'mode-platform'))
    assert marked == sorted(first['platform_natural_frequencies_hz']) and len(marked) == 3
    cable = sorted(line.get_xdata()[0] for line in lines(ax, 'mode-cable'))
    assert cable == sorted(m['frequency_hz'] for m in first['modes'] if m['kind'] == 'cable'
                           and 1.0 <= m['frequency_hz'] <= 40.0)
    assert ax.get_ylabel() == '|u_z / F| (m/N)' and '1500 N along +z' in ax.get_title()
    # fem and spring coincide: the legend says within how much, computed here from the data
    h = [np.array(d['frf']['amplitude_m'])[:, 2] for d in paper_docs]
    spread = 100 * np.max(np.abs(h[0] - h[1]) / h[1])
    assert 0 < spread < figures.COINCIDE_PCT
    notes = [t.get_text() for t in ax.get_legend().get_texts() if 'coincide' in t.get_text()]
    assert notes == [f'fem n=4, spring coincide within {figures.percent_text(spread)}']
    assert lines(ax, 'frf-0')[0].get_linestyle() != lines(ax, 'frf-1')[0].get_linestyle()


def test_rotation_direction_is_the_direct_receptance_and_refused_for_a_point_mass(
        rigid_docs, paper_docs, tmp_path):
    doc = rigid_docs[0]
    fig = figures.frf_figure(rigid_docs, tmp_path / 'frf.png', 'ry')
    (line,) = lines(fig.axes[0], 'frf-0')
    rec = doc['frf']['receptance']
    h = np.array(rec['real'])[:, 4, 4] + 1j * np.array(rec['imag'])[:, 4, 4]
    assert_allclose(line.get_ydata(), np.abs(h), rtol=1e-12)
    assert 'rad/(N m)' in fig.axes[0].get_ylabel()
    with pytest.raises(figures.FigureError, match='needs a 6-DOF platform'):
        figures.receptance_curve(paper_docs[0], 'rx')


def test_cli_refuses_a_rotation_plot_direction_for_a_point_mass_in_one_line(tmp_path):
    out = analyze('--plot-direction', 'rx', '--plot-dir', tmp_path / 'p')
    assert out.returncode == 1
    assert out.stderr.strip().splitlines() == [
        "cdpr_analyze: error: --plot-direction rx needs a 6-DOF platform: this robot's "
        'platform is a point mass (x, y, z only)']
    assert not (tmp_path / 'p').exists()


def png_size(path):
    data = path.read_bytes()
    assert data[:8] == b'\x89PNG\r\n\x1a\n' and data[12:16] == b'IHDR'
    return struct.unpack('>II', data[16:24])


@pytest.mark.slow
def test_cli_writes_the_four_figures_and_the_json_additions(tmp_path):
    out = analyze('--config', RIGID, '--method', 'fem', '--elements', '4', '--duration', '0.2',
                  '--plot-direction', 'ry', '--json', tmp_path / 'a.json',
                  '--plot-dir', tmp_path / 'p')
    assert out.returncode == 0, out.stderr
    for name in ('frf', 'time_history', 'geometry', 'modes'):
        path = tmp_path / 'p' / f'{name}.png'
        assert f'wrote {path}' in out.stdout
        width, height = png_size(path)
        assert 700 <= width <= 2000 and 500 <= height <= 2000, (name, width, height)
        assert path.stat().st_size > 30000
    doc = json.loads((tmp_path / 'a.json').read_text())
    settings = load_settings(RIGID)
    assert_allclose(doc['frf']['force_n'], settings.frf_force_n)
    assert_allclose(doc['frf']['moment_nm'], settings.frf_moment_nm)
    h = doc['time_history'][0]
    assert len(h['lowest_tension_n']) == len(h['t_s']) == len(h['force_n'])
    assert min(h['lowest_tension_n']) == pytest.approx(h['min_tension_n'])


@pytest.mark.parametrize('config,method', [(None, 'fem'), (RIGID, 'fem'), (HEAVY, 'fem_sag'),
                                           (HEAVY, 'fem')])
def test_geometry_cables_end_at_anchor_and_attachment_coloured_by_tension(
        config, method, tmp_path):
    settings = load_settings(config)
    eq = equilibrium_for(settings, equilibrium(settings), method)
    fig = figures.geometry_figure(figures.scene(settings, eq), tmp_path / 'g.png')
    ax, bar = fig.axes
    robot = settings.robot
    p, rotation = settings.initial_position_m, settings.initial_rotation
    attachments = p + robot.attachments_m @ rotation.T         # p + R b_i
    tension = eq.tensions.tension_n
    assert_allclose(bar.get_ylim(), (tension.min(), tension.max()))
    colours = figures.ScalarMappable(figures.Normalize(tension.min(), tension.max()), 'viridis')
    sag = []
    for i in range(robot.n_cables):
        (line,) = lines(ax, f'cable-{i}')
        points = np.array(line.get_data_3d()).T
        assert_allclose(points[0], attachments[i], atol=1e-9)
        assert_allclose(points[-1], robot.anchors_m[i], atol=1e-9)
        assert_allclose(line.get_color(), colours.to_rgba(tension[i]))
        chord = robot.anchors_m[i] - attachments[i]
        off = points - attachments[i]
        off -= np.outer(off @ chord / (chord @ chord), chord)
        sag.append(np.linalg.norm(off, axis=1).max())
    if method == 'fem_sag':                 # sagged where the model sags: cable 0 by ~1.08 m
        assert 1.0 < sag[0] < 1.2
    else:
        assert max(sag) < 1e-9
    (platform,) = lines(ax, 'platform')
    drawn = np.array(platform.get_data_3d()).T
    drawn = drawn[np.all(np.isfinite(drawn), axis=1)]
    expected = attachments if not robot.point_mass else p[None, :]
    assert {tuple(np.round(x, 9)) for x in drawn} == {tuple(np.round(x, 9)) for x in expected}
    assert ax.get_zlabel() == 'z (m)' and png_size(tmp_path / 'g.png')[0] > 700


@pytest.mark.slow
@pytest.mark.parametrize('config,n', [(None, 4), (RIGID, 4), (None, 1)])
def test_mode_panels_draw_the_mode_shape_times_the_scale(config, n, tmp_path):
    settings = load_settings(config)
    eq = equilibrium(settings)
    system = build_system(settings, eq, 'fem', n)
    found = modes(system, settings.f_max_hz, shapes=True)
    picked = figures.pick_modes(found.kind, found.platform_fraction)
    kinds = [found.kind[k] for k in picked]
    assert kinds[:3] == ['platform'] * 3
    if n > 1:
        assert kinds[3:] == ['cable'] * 3 and len(picked) == 6
    shapes = figures.mode_shapes(settings, eq, system, found, picked)
    fig = figures.modes_figure(shapes, settings.robot.anchors_m, tmp_path / 'm.png')
    size = np.ptp(settings.robot.anchors_m, axis=0).max()
    p, rotation = settings.initial_position_m, settings.initial_rotation
    anchors = settings.robot.anchors_m
    attachments = p + settings.robot.attachments_m @ rotation.T
    for ax, k, mode in zip(fig.axes, picked, shapes):
        scale = figures.mode_scale(mode, size)
        phi = found.shapes[:, k]
        u, theta = phi[:3], (phi[3:6] if system.platform_dofs == 6 else np.zeros(3))
        moved = attachments + scale * (u + np.cross(theta, attachments - p))   # u + theta x r
        (platform,) = lines(ax, 'platform-deformed')
        drawn = np.array(platform.get_data_3d()).T
        drawn = drawn[np.all(np.isfinite(drawn), axis=1)]
        expected = moved if system.platform_dofs == 6 else (p + scale * u)[None, :]
        assert {tuple(np.round(x, 9)) for x in drawn} == \
            {tuple(np.round(x, 9)) for x in expected}
        biggest = 0.0
        for c in range(len(anchors)):
            (line,) = lines(ax, f'mode-cable-{c}')
            pts = np.array(line.get_data_3d()).T
            assert_allclose(pts[0], moved[c], atol=1e-9)           # moves with the platform
            assert_allclose(pts[-1], anchors[c], atol=1e-9)        # the anchor stays
            if n > 1:       # interior node j (from the anchor) at (j + 1)/n of the chord
                j = 0
                rows = system.platform_dofs + 3 * (c * (n - 1) + j) + np.arange(3)
                node = anchors[c] + (j + 1) / n * (attachments[c] - anchors[c])
                assert_allclose(pts[n - 1 - j], node + scale * phi[rows], atol=1e-9)
            biggest = max(biggest, np.linalg.norm(pts - np.array(
                [attachments[c] + (anchors[c] - attachments[c]) * t
                 for t in np.linspace(0, 1, len(pts))]), axis=1).max())
        # a cable mode's largest drawn displacement is the stated fraction of the frame size;
        # a platform mode's platform moves by it, its cables by at most the cap
        platform = np.linalg.norm(scale * (u + np.cross(theta, attachments - p)), axis=1).max()
        if found.kind[k] == 'cable':
            assert biggest == pytest.approx(figures.MODE_SCALE_FRACTION * size, rel=1e-9)
        elif biggest < figures.MODE_CABLE_CAP_FRACTION * size * (1 - 1e-9):
            assert platform == pytest.approx(figures.MODE_SCALE_FRACTION * size, rel=1e-9)
        else:
            assert biggest == pytest.approx(figures.MODE_CABLE_CAP_FRACTION * size, rel=1e-9)
            assert platform < figures.MODE_SCALE_FRACTION * size
        assert f'{found.frequency_hz[k]:.2f} Hz, {found.kind[k]}' in ax.get_title()


def test_time_history_shades_the_slack_spans_under_load_and_lowest_tension(paper_docs,
                                                                           tmp_path):
    settings = load_settings()
    fig = figures.time_history_figure(paper_docs, tmp_path / 'th.png', 2, settings.tension_min_n)
    ax_u, ax_f, ax_t = fig.axes[:3]
    doc = paper_docs[0]
    h = doc['time_history'][0]
    t, u = np.array(h['t_s']), np.array(h['u_m'])
    # lowest tension: T_i - (EA/L_i) u_i . u (straight cables), independent of the JSON's
    p = settings.initial_position_m
    chord = settings.robot.anchors_m - p
    length = np.linalg.norm(chord, axis=1)
    lowest = np.min(np.array(doc['tensions_n'])
                    - settings.cable.ea_n / length * ((chord / length[:, None]) @ u.T).T,
                    axis=1)
    assert_allclose(h['lowest_tension_n'], lowest, rtol=1e-9, atol=1e-6)
    assert_allclose(ax_t.get_lines()[0].get_ydata(), lowest, rtol=1e-9, atol=1e-6)
    assert_allclose(ax_f.get_lines()[0].get_ydata(), 1500.0 * np.sin(2 * np.pi * 5.0 * t),
                    atol=1e-9)

    def runs(flags):
        edges = np.flatnonzero(np.diff(np.r_[0, flags.astype(int), 0]))
        return [(t[s], t[e - 1]) for s, e in zip(edges[::2], edges[1::2])]

    def spans(ax, gid):
        return [(patch.get_x(), patch.get_x() + patch.get_width()) for patch in ax.patches
                if patch.get_gid() == gid]
    slack = runs(lowest <= 0)
    assert len(slack) >= 1          # the paper's 1500 N slackens the lower cables
    aware = np.array(h['slack_aware']['lowest_tension_n'])
    assert aware.min() == 0.0 and np.all(aware >= 0)
    for ax in (ax_u, ax_f, ax_t):
        assert_allclose(spans(ax, 'slack'), slack)
        assert_allclose(spans(ax, 'slack-aware'), runs(aware <= 0))
    assert png_size(tmp_path / 'th.png')[1] > 500


@pytest.mark.slow
def test_tradeoff_labels_do_not_overlap_and_the_legend_names_the_families(tmp_path):
    from cdpr_dynamics.cli import tradeoff
    rows = [{'method': m, 'elements_per_cable': n, 'time_s': t * 1e-3, 'freq_error_pct': f,
             'frf_error_pct': e, 'auto': (m, n) == ('fem_sag', 16)}
            for m, n, t, f, e in [
                ('spring', 1, 1.1, 100, 0.93), ('fem', 1, 1.1, 100, 0.92),
                ('fem', 2, 1.4, 100, 0.92), ('catenary', 1, 1.5, 100, 0.72),
                ('catenary_exact', 1, 1.9, 100, 0.62), ('fem', 4, 5.6, 10.3, 0.92),
                ('fem', 8, 10.3, 2.66, 0.92), ('fem', 16, 14.7, 0.72, 0.92),
                ('fem', 32, 23.7, 0.70, 0.92), ('fem_sag', 4, 8.0, 10.3, 0.059),
                ('fem_sag', 8, 12.4, 2.59, 0.015), ('fem_sag', 16, 18.8, 0.64, 0.0037),
                ('fem_sag', 15, 18.1, 0.73, 0.0042), ('dsm', 0, 14.1, 0.74, 0.92),
                ('fem_sag', 64, 50.0, 0.04, 0.00023)]]
    reference = Namespace(f_max_hz=40.0, label='fem_sag n=128/256 Richardson')
    fig = tradeoff.plot(rows, reference, tmp_path / 't.png', 'paper', 0.01)
    renderer = fig.canvas.get_renderer()
    for ax, key in zip(fig.axes, ('freq_error_pct', 'frf_error_pct')):
        notes = [t for t in ax.texts if isinstance(t, Annotation)]
        boxes = [n.get_window_extent(renderer) for n in notes]
        for i in range(len(boxes)):
            for j in range(i):
                assert not boxes[i].overlaps(boxes[j]), (notes[i].get_text(),
                                                         notes[j].get_text())
        errors = np.clip([r[key] for r in rows], figures.FLOOR_PCT, figures.CAP_PCT)
        front = figures.pareto([r['time_s'] for r in rows], errors)
        labelled = {n.get_text() for n in notes}
        assert {figures.row_label(rows[i]) for i in front} <= labelled
        assert 'fem_sag 16' in labelled                         # auto's pick
        legend = {t.get_text() for t in ax.get_legend().get_texts()}
        assert {'spring', 'fem (straight)', 'catenary', 'catenary_exact', 'fem_sag', 'dsm',
                'Pareto front', 'auto at 1 %'} <= legend
    assert png_size(tmp_path / 't.png')[0] > 1000


def test_modes_of_little_platform_energy_never_stand_in_for_platform_modes():
    """Where the band has fewer platform modes than panels, the modes of the largest platform
    energy fill in, but none below PLATFORM_MIN_FRACTION (0.1 %): a cable mode with 0.001 %
    is no platform mode."""
    kinds = ['cable', 'mixed', 'cable', 'cable', 'cable']
    fractions = [2e-5, 0.3, 5e-3, 9e-4, 1e-3]
    assert figures.pick_modes(kinds, fractions, platform=3, cable=0) == [1, 2, 4]
    assert figures.pick_modes(kinds, fractions, platform=5, cable=0) == [1, 2, 4]
    assert figures.pick_modes(kinds, fractions, platform=3, cable=2) == [1, 2, 4, 0, 3]


def test_platform_mode_labels_do_not_overlap():
    """Platform modes close on the log axis (the rigid robot's 18.2 and 26.4 Hz were drawn
    over each other) are labelled in rows; coincident ones once, with the multiplicity. The
    rows are laid out when drawn: a narrower figure afterwards (tight_layout, another size)
    stacks them again, still without overlap."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    freqs = [1.5, 18.2, 26.4, 27.0, 27.0, 31.0, 34.5, 38.0, 39.5]
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.set_xscale('log')
    ax.set_xlim(1.0, 40.0)
    figures.mark_modes(ax, [{'frequency_hz': f, 'kind': 'platform'} for f in freqs],
                       1.0, 40.0)
    notes = [t for t in ax.texts if isinstance(t, Annotation)]
    assert sorted(n.get_text() for n in notes) == sorted(
        ['1.5 Hz', '18.2 Hz', '26.4 Hz', '27.0 Hz (x2)', '31.0 Hz', '34.5 Hz', '38.0 Hz',
         '39.5 Hz'])
    rows = {}
    for width_in in (6.0, 3.0, 9.0):
        fig.set_size_inches(width_in, 3.0)
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        boxes = [n.get_window_extent(renderer) for n in notes]
        for i in range(len(boxes)):
            for j in range(i):
                assert not boxes[i].overlaps(boxes[j]), (width_in, notes[i].get_text(),
                                                         notes[j].get_text())
        rows[width_in] = len({n.xyann[1] for n in notes})
    assert rows[3.0] > rows[6.0] >= rows[9.0] >= 1       # narrower: more rows
    plt.close(fig)
