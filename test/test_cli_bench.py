"""cdpr_bench --quick runs every stage (no timing is asserted: this machine is shared)."""
import json
import subprocess

import pytest

from conftest import installed


@pytest.mark.slow
def test_bench_quick_reports_every_stage(tmp_path):
    out = subprocess.run([installed('cdpr_bench'), '--quick', '--json', str(tmp_path / 'b.json')],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    result = json.loads((tmp_path / 'b.json').read_text())
    assert result['qp']['warm']['p50_s'] > 0
    rows = {(r['method'], r['elements_per_cable']): r for r in result['models']}
    assert not [r for r in rows.values() if 'error' in r]
    assert {'spring', 'fem', 'catenary', 'catenary_exact', 'fem_sag', 'dsm'} <= \
        {m for m, _ in rows}
    assert all(r['frf_391']['p50_s'] > 0 and r['build']['p50_s'] > 0 for r in rows.values())
    assert rows[('fem', 64)]['dofs'] == 1515
    sizes = result['frf_sizes']        # quick mode: n = 16 and 64, interleaved
    assert set(sizes['p50_s']) == {'16', '64'} and sizes['largest_over_smallest'] > 0
    assert set(result['node_pose_update']) >= {'spring', 'catenary', 'fem_n16', 'catenary_exact',
                                               'fem_sag_n16', 'fem_sag_n16_chord_statics'}
    assert result['node_compute_per_wrench']['p99_ms'] > 0
    slack = result['node_slack_per_wrench']     # the paper demo's load slackens cables
    assert set(slack) == {'spring', 'fem_n16'}
    assert all(row['slack_fraction'] > 0.5 and row['aware_slack']['p50_ms'] > 0
               for row in slack.values())
    modes = result['modes'][0]         # quick mode: fem 16, counted and by the eigensolver
    assert modes['modes'] == 27 and modes['platform_modes'] == 3
    assert modes['counted']['p50_s'] > 0 and modes['eigensolver']['p50_s'] > 0
    replay = {r['method']: r for r in result['replay']}
    assert set(replay) == {'spring', 'fem'} and all(r['inputs'] > 0 for r in replay.values())
    heavy = result['heavy_sag']        # quick mode: n = 16 only
    assert [row['elements_per_cable'] for row in heavy['sizes']] == [16]
    assert heavy['sizes'][0]['fem_sag_frf_p50_s'] > 0 and heavy['sizes'][0]['fem_modes_p50_s'] > 0
    assert heavy['sizes'][0]['frf_sag_end_stiffness_share'] > 0
    assert heavy['pose_update_fem_sag_n16']['dofs'] == 366
    under = result['underactuated']
    assert under['statics_at_equilibrium']['p50_s'] > 0 and under['geometrico_static']['p50_s'] > 0
    assert 'geometrico-static solve' in out.stdout


def test_compute_per_wrench_scales_its_load_to_what_the_cables_hold():
    """The rigid 6-DOF robot holds less than 1000 N along z: the bench's wrench load halves
    until both signs are feasible instead of failing on the first rejected wrench."""
    from pathlib import Path

    from cdpr_dynamics.cli.bench_node import compute_per_wrench
    from cdpr_dynamics.analysis.config import load_settings
    from cdpr_dynamics.analysis.live import LivePredictor
    settings = load_settings(Path(__file__).parent / 'data' / 'rigid_cdpr.yaml')
    result = compute_per_wrench(settings, n=300)
    amplitude = result['amplitude_n']
    assert amplitude < 1000.0 and result['p50_ms'] > 0
    predictor = LivePredictor(settings)
    held = [not predictor.wrench_reason((0.0, 0.0, sign * scale * amplitude))
            for scale in (1.0, 2.0) for sign in (1.0, -1.0)]
    assert held[:2] == [True, True] and not all(held[2:])   # twice as much is not held


@pytest.mark.ros
def test_slack_rate_accounts_for_every_wrench_of_the_demo_load(ros_env):
    """cdpr_bench --dds's slack row: the paper's 1500 N at 5 Hz slackens cables in the node's
    slack-aware prediction, and every wrench sent is predicted, rejected or counted lost."""
    from cdpr_dynamics.analysis.config import default_config_path
    from cdpr_dynamics.cli.bench_node import slack_rate
    row = slack_rate(str(default_config_path()), 1000.0, 1.0, {'model.method': 'spring'})
    assert row['slack'] == 'aware' and row['method'] == 'spring' and row['force_n'] == 1500.0
    assert row['sent'] == 1000 and row['predicted'] > 0, json.dumps(row)
    assert row['predicted'] + row['rejected'] + row['lost'] == row['sent'] and row['lost'] >= 0
    assert 0.0 < row['slack_time_s'] <= 1.0


@pytest.mark.slow
def test_bench_calibration_quick_fits_and_identifies(tmp_path):
    """cdpr_bench --calibration --quick: the fit row fits its 9 parameters to the noise level,
    the identify row reads its MCAP record back and finds the decay's modes."""
    out = subprocess.run([installed('cdpr_bench'), '--calibration', '--quick', '--json',
                          str(tmp_path / 'c.json')], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    result = json.loads((tmp_path / 'c.json').read_text())
    fit = result['fit']
    assert fit['parameters'] == fit['fitted'] == 9 and fit['poses'] == 10
    assert fit['rms_error_pct_after'] < 1.5 and fit['seconds'] > 0      # 1 % noise
    identify = result['identify']
    assert identify['samples'] == 2001 and identify['read_p50_s'] > 0
    assert 4 <= identify['modes_found'] <= identify['true_modes'] == 6
    assert 'cdpr_calibrate fit: 9 parameters' in out.stdout
