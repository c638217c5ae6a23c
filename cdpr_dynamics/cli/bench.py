"""``cdpr_bench``: how long each stage takes, as JSON (timings belong here, not in tests).

    cdpr_bench [--config PATH] [--quick] [--dds] [--json PATH]
    cdpr_bench --workspace [--config PATH] [--quick] [--json PATH]
    cdpr_bench --calibration [--config PATH] [--quick] [--json PATH]

Stages: tension QP (cold, warm), model build per method and size, a 391-point FRF, a 1000-step
Newmark time history, an underactuated robot's statics (at an equilibrium, and the
geometrico-static solve), and the node's own work (pose update: tensions + model + factorisation;
one wrench: message check, feasibility, Newmark step, prediction message), cdpr_replay offline
and, with
``--dds``, the live node as a child process (wrench -> prediction latency, its own compute,
the sustained input rate, and ``cdpr_record`` beside it under a wrench flood). ``--quick``
runs every stage with few repetitions (CI runs it to prove the command works; its numbers are
not meant to be read).
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np

from cdpr_dynamics.analysis.pipeline import (AnalysisError, build_system, damping_for, equilibrium,
                                             new_tension_solver)
from cdpr_dynamics.cli import bench_node, interruptible, plain
from cdpr_dynamics.analysis.config import ConfigError, Settings, default_config_path, load_settings
from cdpr_dynamics.dynamics.system import DynamicsError, frequency_response, time_history
from cdpr_dynamics.mechanics.robot import geometry, required_wrench

NODE_METHODS = (('spring', 1), ('catenary', 1), ('fem', 16), ('catenary_exact', 1),
                ('fem_sag', 16))
SIZES = [('spring', 1), ('fem', 1), ('fem', 4), ('fem', 16), ('fem', 64), ('fem', 256),
         ('catenary', 1), ('catenary_exact', 1), ('fem_sag', 16), ('fem_sag', 64), ('dsm', 1)]
# the controller's 1000 N at 5 Hz slackens the heavy-sag robot's cables and throws its
# compression-free rigid platform out of the small-rotation range (Newton then fails wrench
# after wrench): the pose-update rows predict linearly
HEAVY_SAG_MODEL = {'model.method': 'fem_sag', 'model.elements_per_cable': 16,
                   'node.slack': 'linear'}
MODE_SIZES = [('fem', 16), ('fem', 64), ('fem_sag', 16), ('fem_sag', 64), ('dsm', 1)]


def timed(call, repeat: int) -> dict:
    """Run ``call`` once to warm up, then ``repeat`` times: p50, p99 and min in seconds."""
    call()
    samples = []
    for _ in range(repeat):
        start = time.perf_counter()
        call()
        samples.append(time.perf_counter() - start)
    samples = np.array(samples)
    return {'p50_s': float(np.median(samples)), 'p99_s': float(np.percentile(samples, 99)),
            'min_s': float(samples.min()), 'repeat': repeat}


def bench_qp(settings: Settings, repeat: int) -> dict:
    robot = settings.robot
    wrench = required_wrench(robot, settings.external_force_n, settings.external_moment_nm)
    poses = settings.initial_position_m + 0.01 * np.stack(
        [np.cos(np.linspace(0, 6, 64)), np.sin(np.linspace(0, 6, 64)), np.zeros(64)], axis=1)
    matrices = [geometry(robot, p).structure_matrix for p in poses]
    solver = new_tension_solver(settings)
    index = iter(range(10 ** 9))

    def warm():
        solver.solve(matrices[next(index) % len(matrices)], wrench)

    def cold():
        new_tension_solver(settings).solve(matrices[next(index) % len(matrices)], wrench)
    return {'warm': timed(warm, 20 * repeat), 'cold': timed(cold, 2 * repeat)}


def settle_heap() -> None:
    """Put the allocator where a long-running process is: glibc raises its mmap and trim
    thresholds the first time a large block (here 8 MB) is freed, after which arrays of ~100 kB
    (an FRF's temporaries) are reused instead of being returned to the OS and faulted in again
    on every call (2-3x slower on this VM). Every model row is then measured in the same state,
    whatever ran before it."""
    block = np.ones(1 << 20)
    del block


def bench_models(settings: Settings, repeat: int, quick: bool) -> list[dict]:
    """Per method and size: build, the 391-point FRF and a Newmark time history."""
    settle_heap()
    eq = equilibrium(settings)
    freqs = settings.frequencies_hz
    rows = []
    for method, n in SIZES:
        if quick and n > 64:
            continue
        try:
            system = build_system(settings, eq, method, n)
        except (AnalysisError, DynamicsError, ValueError) as exc:
            rows.append({'method': method, 'elements_per_cable': n, 'error': str(exc)})
            continue
        try:
            damping = damping_for(settings, system)
        except (AnalysisError, DynamicsError) as exc:
            rows.append({'method': method, 'elements_per_cable': n, 'error': str(exc)})
            continue
        row = {'method': method, 'elements_per_cable': n, 'dofs': system.dofs,
               'build': timed(lambda: build_system(settings, eq, method, n), repeat),
               'frf_391': timed(lambda: frequency_response(system, freqs, settings.frf_force_n,
                                                           damping=damping), repeat)}
        if system.assembly.blocks is not None:
            steps = 100 if quick else 1000
            row[f'time_history_{steps}_steps'] = timed(
                lambda: time_history(system, settings.frf_force_n, 5.0, steps * settings.dt_s,
                                     damping, settings.dt_s, settings.newmark_alpha,
                                     settings.newmark_beta), max(1, repeat // 10))
        rows.append(row)
    return rows


def bench_frf_sizes(settings: Settings, repeat: int, sizes=(16, 64, 256)) -> dict:
    """The 391-point fem FRF at each of ``sizes`` elements per cable, calls interleaved (one
    of each size per round): the cost against n. Each model row's own p50 moves 0.6-2x with
    the allocator's state left by the rows before it (measured here: the n = 256 / n = 16
    ratio of those rows from 0.6 to 2.1 in four runs), interleaving shares that state."""
    settle_heap()
    eq = equilibrium(settings)
    freqs = settings.frequencies_hz
    calls = {}
    for n in sizes:
        system = build_system(settings, eq, 'fem', n)
        damping = damping_for(settings, system)
        calls[n] = functools.partial(frequency_response, system, freqs, settings.frf_force_n,
                                     damping=damping)
        calls[n]()
    samples = {n: [] for n in sizes}
    for _ in range(max(3, 3 * repeat)):
        for n, call in calls.items():
            start = time.perf_counter()
            call()
            samples[n].append(time.perf_counter() - start)
    p50 = {n: float(np.median(values)) for n, values in samples.items()}
    return {'p50_s': p50, 'largest_over_smallest': p50[sizes[-1]] / p50[sizes[0]]}


def bench_modes(settings: Settings, repeat: int, quick: bool) -> list[dict]:
    """Every mode below ``frf.f_max_hz`` (at least 12), classified: by Wittrick-Williams
    counting (:func:`cdpr_dynamics.dynamics.modes.modes`, the default) against the dense / Lanczos
    eigensolver with mode shapes (``shapes=True``), in the same run."""
    from cdpr_dynamics.dynamics.modes import modes
    eq = equilibrium(settings)
    rows = []
    for method, n in MODE_SIZES[:1] if quick else MODE_SIZES:
        system = build_system(settings, eq, method, n)
        found = modes(system, settings.f_max_hz)
        row = {'method': method, 'elements_per_cable': n, 'dofs': system.dofs,
               'modes': int(found.frequency_hz.size),
               'platform_modes': int(found.platform_hz.size),
               'counted': timed(lambda: modes(system, settings.f_max_hz), max(2, repeat // 3))}
        if system.assembly.blocks is not None:
            row['eigensolver'] = timed(lambda: modes(system, settings.f_max_hz, shapes=True),
                                       max(1, repeat // 10))
            row['counted_over_eigensolver'] = row['counted']['p50_s'] / \
                row['eigensolver']['p50_s']
        rows.append(row)
    return rows


def bench_replay(duration_s: float) -> list[dict]:
    """``cdpr_replay`` offline on ``duration_s`` of 1 kHz wrenches and 50 Hz poses
    (:func:`~cdpr_dynamics.recording.scenarios.long_log_messages`: a robot holding stations,
    one rebuild per 10 s), spring and fem 16 in log order, fem 16 in stamp order: input
    messages per second, reading, checks, models and writing the output file included, and
    times real time (the log's duration over the replay's wall time, and over its CPU time:
    the steadier figure on a shared host)."""
    import tempfile

    from cdpr_dynamics.recording import scenarios
    from cdpr_dynamics.recording.replay import load_replay_config, replay_offline

    settings, options, _ = load_replay_config()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        source = Path(folder) / 'input.mcap'
        scenarios.write_long_log(source, duration_s)
        for method, elements, order in (('spring', 1, 'log'), ('fem', 16, 'log'),
                                        ('fem', 16, 'stamp')):
            output = Path(folder) / f'{method}.mcap'
            start, cpu = time.perf_counter(), time.process_time()
            summary = replay_offline(source, output, settings, method,
                                     elements_per_cable=elements, options=options, order=order)
            elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
            rows.append({'method': method, 'elements_per_cable': elements, 'order': order,
                         'inputs': summary.inputs, 'seconds': elapsed, 'cpu_seconds': cpu,
                         'messages_per_s': summary.inputs / elapsed,
                         'times_real_time': duration_s / elapsed,
                         'times_real_time_cpu': duration_s / cpu})
            output.unlink()
    return rows


def bench_underactuated(repeat: int) -> dict:
    """The shipped suspended 4-cable robot (underactuated): the statics at an equilibrium pose
    (:func:`equilibrium`: balance, slack and stability checks) and the geometrico-static solve
    from poses 5 cm off it (with the same checks)."""
    settings = load_settings(Path(default_config_path()).parent / 'suspended_4cable.yaml')
    at = settings.initial_position_m
    off = [at + 0.05 * np.array([np.cos(a), np.sin(a), 0.2]) for a in np.linspace(0, 6, 16)]
    index = iter(range(10 ** 9))

    def balanced():
        equilibrium(settings, at)

    def solved():
        equilibrium(settings, off[next(index) % len(off)])
    return {'config': 'suspended_4cable.yaml',
            'statics_at_equilibrium': timed(balanced, 20 * repeat),
            'geometrico_static': timed(solved, 2 * repeat)}


def bench_heavy_sag(repeat: int, quick: bool) -> dict:
    """``config/heavy_sag_6dof.yaml``: fem_sag against fem at the same n (16 and 64; each at
    its own equilibrium, fem_sag's sag-consistent): the modes below ``frf.f_max_hz`` (counted)
    and the configured FRF, interleaved call by call, p50 and fem_sag over fem, with the part
    of fem_sag's FRF its cables' end stiffness takes (the element-by-element recursion at
    the FRF's damped frequencies); and the in-process pose update of fem_sag 16 along a 5 cm
    circle (p50/p99, stages' p50)."""
    from cdpr_dynamics.analysis.pipeline import equilibrium_for
    from cdpr_dynamics.dynamics.modes import modes
    settings = load_settings(Path(default_config_path()).parent / 'heavy_sag_6dof.yaml')
    eq = equilibrium(settings)
    eqs = {'fem': eq, 'fem_sag': equilibrium_for(settings, eq, 'fem_sag')}
    freqs = settings.frequencies_hz
    rows = []
    for n in ((16,) if quick else (16, 64)):
        calls = {}
        for method in ('fem', 'fem_sag'):
            system = build_system(settings, eqs[method], method, n)
            damping = damping_for(settings, system)
            calls[method, 'modes'] = (lambda system=system: modes(system, settings.f_max_hz))
            calls[method, 'frf'] = (lambda system=system, damping=damping: frequency_response(
                system, freqs, settings.frf_force_n, damping=damping))
            if method == 'fem_sag':
                w = 2.0 * np.pi * freqs                 # the FRF's lam (dynamic_stiffness)
                lam = (w * w - 1j * w * damping.mass_factor) / (
                    1.0 + 1j * w * damping.stiffness_factor)
                calls[method, 'end_stiffness'] = (
                    lambda system=system, lam=lam: system.assembly.end_stiffness(lam))
        samples = {key: [] for key in calls}
        for call in calls.values():
            call()
        for _ in range(max(3, repeat // 3)):
            for key, call in calls.items():
                start = time.perf_counter()
                call()
                samples[key].append(time.perf_counter() - start)
        p50 = {key: float(np.median(values)) for key, values in samples.items()}
        rows.append({'elements_per_cable': n, 'frf_points': int(freqs.size),
                     **{f'{method}_{what}_p50_s': value for (method, what), value in p50.items()},
                     'modes_sag_over_fem': p50['fem_sag', 'modes'] / p50['fem', 'modes'],
                     'frf_sag_over_fem': p50['fem_sag', 'frf'] / p50['fem', 'frf'],
                     'frf_sag_end_stiffness_share': p50['fem_sag', 'end_stiffness']
                     / p50['fem_sag', 'frf']})
    update = bench_node.pose_updates(settings, (('fem_sag', 16),), n=30 if quick else 300)
    return {'config': 'heavy_sag_6dof.yaml', 'sizes': rows,
            'pose_update_fem_sag_n16': update['fem_sag_n16']}


def run(settings: Settings, quick: bool, dds_config: str | None = None) -> dict:
    """Every stage; with ``dds_config`` also the live node over DDS (a child process)."""
    repeat = 3 if quick else 30
    result = {'quick': quick, 'qp': bench_qp(settings, repeat),
              'models': bench_models(settings, repeat, quick),
              'frf_sizes': bench_frf_sizes(settings, repeat, (16, 64) if quick else
                                           (16, 64, 256)),
              'modes': bench_modes(settings, repeat, quick),
              'node_compute_per_wrench': bench_node.compute_per_wrench(
                  settings, 2000 if quick else 20000),
              'node_slack_per_wrench': bench_node.slack_per_wrench(
                  settings, n=1000 if quick else 4000),
              'node_pose_update': bench_node.pose_updates(
                  settings, NODE_METHODS, n=30 if quick else 300),
              'replay': bench_replay(2.0 if quick else 60.0),
              'pulley_pose_update': bench_node.pulley_pose_updates(
                  Path(default_config_path()).parent / 'paper_pulleys.yaml',
                  n=30 if quick else 300),
              'underactuated': bench_underactuated(repeat),
              'heavy_sag': bench_heavy_sag(repeat, quick)}
    if dds_config:
        result['dds'] = bench_node.dds(dds_config, rates=(1000, 5000) if quick else
                                       (1000, 2000, 3000, 5000, 8000),
                                       latency_s=2.0 if quick else 5.0,
                                       frf_call_points=1000 if quick else
                                       bench_node.FRF_CALL_POINTS)
        result['recording'] = bench_node.recording_throughput(dds_config,
                                                              duration_s=1.0 if quick else 3.0)
        # the paper demo's load (frf.force_n at 5 Hz), 1 kHz, node.slack: aware
        result['slack_rate'] = {
            f'{method}_n{n}' if method == 'fem' else method: bench_node.slack_rate(
                dds_config, 1000.0, 2.0 if quick else 10.0,
                {'model.method': method, 'model.elements_per_cable': n})
            for method, n in (('spring', 1), ('fem', 16))}
        # vibration_modes: pose -> table (station to station), and while the pose moves on
        result['modes_latency'] = {
            f'{method}_n{n}' if method == 'fem' else method: bench_node.modes_latency(
                dds_config, {'model.method': method, 'model.elements_per_cable': n},
                poses=3 if quick else 20, spacing_s=spacing, moving_s=1.0 if quick else 3.0)
            for method, n, spacing in (('spring', 1, 1.0), ('fem', 16, 1.5))}
        result['controller'] = bench_node.controller_rate(dds_config,
                                                          duration_s=2.0 if quick else 10.0)
        # the heavy-sag 6-DOF robot, fem_sag 16: pose updates of milliseconds at 50 Hz, solved
        # inline (before the next wrench) and by node.rebuild: worker, in the same run
        heavy = Path(default_config_path()).parent / 'heavy_sag_6dof.yaml'
        result['controller_heavy_sag'] = {
            mode: bench_node.controller_rate(heavy, duration_s=2.0 if quick else 10.0,
                                             parameters={**HEAVY_SAG_MODEL,
                                                         'node.rebuild': mode})
            for mode in (('worker',) if quick else ('inline', 'worker'))}
    return result


def summary(result: dict) -> str:
    ms = 1e3
    lines = [f"QP warm p50 {result['qp']['warm']['p50_s'] * 1e6:.1f} us, cold p50 "
             f"{result['qp']['cold']['p50_s'] * 1e6:.1f} us"]
    for row in result['models']:
        if 'error' in row:
            lines.append(f"{row['method']} n={row['elements_per_cable']}: {row['error']}")
            continue
        th = next((v for k, v in row.items() if k.startswith('time_history')), None)
        text = (f"{row['method']:>15} n={row['elements_per_cable']:<3} dofs={row['dofs']:<5} "
                f"build {row['build']['p50_s'] * ms:7.3f} ms  FRF391 "
                f"{row['frf_391']['p50_s'] * ms:7.3f} ms")
        if th:
            text += f"  time history {th['p50_s'] * ms:8.1f} ms"
        lines.append(text)
    sizes = result['frf_sizes']
    lines.append('fem FRF391 interleaved n=' + '/'.join(str(n) for n in sizes['p50_s'])
                 + ' p50 ' + ' / '.join(f'{v * ms:.3f}' for v in sizes['p50_s'].values())
                 + f" ms (largest / smallest n x{sizes['largest_over_smallest']:.2f})")
    for row in result['modes']:
        text = (f"modes below f_max {row['method']:>8} n={row['elements_per_cable']:<3} "
                f"{row['modes']} ({row['platform_modes']} platform): counted "
                f"{row['counted']['p50_s'] * ms:7.2f} ms")
        if 'eigensolver' in row:
            text += (f", eigensolver with shapes {row['eigensolver']['p50_s'] * ms:7.1f} ms "
                     f"(x{row['counted_over_eigensolver']:.3f})")
        lines.append(text)
    wrench = result['node_compute_per_wrench']
    lines.append('node compute per wrench: ' + wrench['error'] if 'error' in wrench else
                 f"node compute per wrench ({wrench['method']}, {wrench['dofs']} DOFs, "
                 f"{wrench['amplitude_n']:g} N at 5 Hz) p50/p99 "
                 f"{wrench['p50_ms']:.3f}/{wrench['p99_ms']:.3f} ms")
    for method, row in result['node_slack_per_wrench'].items():
        if 'error' in row or not row['slack_fraction']:
            lines.append(f"node per wrench {method} under frf.force_n: "
                         + row.get('error', 'no cable slackens'))
            continue
        lines.append(f"node per wrench {method}, {row['force_n'][2]:g} N at 5 Hz: linear p50/p99 "
                     f"{row['linear']['p50_ms'] * 1e3:.0f}/{row['linear']['p99_ms'] * 1e3:.0f} us"
                     f", slack-aware while slack ({100 * row['slack_fraction']:.0f} % of "
                     f"wrenches) {row['aware_slack']['p50_ms'] * 1e3:.0f}/"
                     f"{row['aware_slack']['p99_ms'] * 1e3:.0f} us "
                     f"(x{row['aware_over_linear_p50']:.2f})")
    for method, row in result['node_pose_update'].items():
        lines.append(f"node pose update {method}: " + (row['error'] if 'error' in row else
                     f"p50/p99 {row['p50_ms']:.3f}/{row['p99_ms']:.3f} ms"))
    for method, row in result['pulley_pose_update'].items():
        lines.append(f"pose update with pulleys {method}: p50 {row['pulleys']['p50_ms']:.3f} ms, "
                     f"without {row['none']['p50_ms']:.3f} ms (x{row['pulleys_over_none']:.2f})")
    under = result['underactuated']
    lines.append(f"underactuated ({under['config']}): statics at an equilibrium p50 "
                 f"{under['statics_at_equilibrium']['p50_s'] * ms:.3f} ms, geometrico-static "
                 f"solve p50/p99 {under['geometrico_static']['p50_s'] * ms:.2f}/"
                 f"{under['geometrico_static']['p99_s'] * ms:.2f} ms")
    heavy = result['heavy_sag']
    for row in heavy['sizes']:
        ms_ = {key: value * ms for key, value in row.items() if key.endswith('_p50_s')}
        lines.append(f"heavy_sag_6dof n={row['elements_per_cable']}: modes fem_sag/fem "
                     f"{ms_['fem_sag_modes_p50_s']:.1f}/{ms_['fem_modes_p50_s']:.1f} ms "
                     f"(x{row['modes_sag_over_fem']:.1f}), {row['frf_points']}-point FRF "
                     f"{ms_['fem_sag_frf_p50_s']:.2f}/{ms_['fem_frf_p50_s']:.2f} ms "
                     f"(x{row['frf_sag_over_fem']:.1f}; fem_sag's cable end stiffness "
                     f"{100 * row['frf_sag_end_stiffness_share']:.0f} % of it)")
    update = heavy['pose_update_fem_sag_n16']
    lines.append(f"heavy_sag_6dof fem_sag n=16 pose update p50/p99 {update['p50_ms']:.2f}/"
                 f"{update['p99_ms']:.2f} ms (stages p50: " + ', '.join(
                     f'{k} {v:.2f}' for k, v in update['stages_p50_ms'].items()) + ' ms)')
    for row in result['replay']:
        lines.append(f"cdpr_replay offline {row['method']} n={row['elements_per_cable']} "
                     f"--order {row['order']}, 1 kHz wrenches + 50 Hz poses: "
                     f"{row['messages_per_s']:.0f} messages/s ({row['times_real_time']:.1f}x "
                     f"real time; CPU time {row['cpu_seconds']:.2f} s, "
                     f"{row['times_real_time_cpu']:.1f}x)")
    if 'dds' in result:
        dds = result['dds']
        echo, ratio = dds['echo_latency'], dds['latency_over_echo']
        lines.append(f"DDS wrench -> prediction latency p50/p99 {dds['latency']['p50_ms']:.2f}/"
                     f"{dds['latency']['p99_ms']:.2f} ms (an rclpy echo node {echo['p50_ms']:.2f}/"
                     f"{echo['p99_ms']:.2f} ms: x{ratio['p50_ms']:.2f}/x{ratio['p99_ms']:.2f})"
                     "; node compute p50/p99 "
                     f"{dds['node_compute']['p50_ms']:.3f}/{dds['node_compute']['p99_ms']:.3f} "
                     f"ms; sustained {dds['sustained_rate_hz']} Hz (max processed "
                     f"{dds['max_processed_hz']:.0f}/s)")
        call = dds['during_frf_call']
        lines.append(f"during a {call['points']}-point fem_sag 64 FRF call "
                     f"({call['call_s']:.2f} s): {call['sent_during_call']} wrenches, "
                     f"{call['lost_during_call']} lost, latency p50 {call['during']['p50_ms']:.2f}"
                     f" ms (x{call['p50_during_over_before']:.2f} of before), longest gap "
                     f"{call['longest_gap_ms']:.1f} ms")
        rec = result['recording']
        lines.append(f"cdpr_record beside the node under a 5 kHz wrench flood: "
                     f"{rec['topics'].get('/wrench', 0)} of {rec['wrenches_sent']} wrenches "
                     f"recorded, {rec['messages_per_s']:.0f} messages/s (all topics), "
                     f"{rec['bytes_per_message']:.0f} bytes/message (file)")
        for method, row in result['slack_rate'].items():
            lines.append(f"node.slack {row['slack']} {method}, {row['force_n']:g} N at 5 Hz, "
                         f"{row['rate_hz']:.0f} Hz for {row['duration_s']:.0f} s: "
                         f"{row['predicted']}/{row['sent']} predicted, {row['lost']} lost, "
                         f"{row['rejected']} rejected, {row['slack_time_s']:.2f} s slack; "
                         f"compute p50/p99 {row['compute_ms_p50']:.3f}/"
                         f"{row['compute_ms_p99']:.3f} ms")
        for method, row in result['modes_latency'].items():
            moving = row['moving']
            lines.append(f"vibration_modes {method}: pose -> table p50/p99 "
                         f"{row['latency']['p50_ms']:.1f}/{row['latency']['p99_ms']:.1f} ms "
                         f"({row['poses']} poses {row['spacing_s']:g} s apart, "
                         f"{row['missing']} without a table); poses at 50 Hz: "
                         f"{moving['tables']} tables for {moving['poses']} poses, age p50 "
                         f"{moving['age']['p50_ms']:.1f} ms, {moving['foreign_stamps']} "
                         "not stamped with a pose sent")
        lines.append(_controller_line('controller', result['controller']))
        for mode, ctl in result['controller_heavy_sag'].items():
            lines.append(_controller_line(f'heavy_sag_6dof, node.rebuild {mode}:', ctl))
    return '\n'.join(lines)


def _controller_line(title: str, ctl: dict) -> str:
    swap = (f", swap p50 {ctl['swap_ms_p50']:.2f} ms, {ctl['poses_superseded']} poses "
            f"superseded" if ctl.get('rebuild') == 'worker' else '')
    return (f"{title} {ctl['wrench_hz']:.0f} Hz wrenches + {ctl['pose_hz']:.0f} Hz moving "
            f"poses ({ctl['method']}) with cdpr_record, {ctl['duration_s']:.0f} s: published "
            f"{ctl['published']['wrench']}/{ctl['published']['pose']}, recorded "
            f"{ctl['recorded'].get('wrench', 0)}/{ctl['recorded'].get('pose', 0)} "
            f"(+{ctl['recorded'].get('predicted_displacement', 0)} predictions), predicted "
            f"{ctl['predicted']} ({100 * ctl['predicted_fraction']:.2f} %; with the rejected "
            f"{100 * ctl['handled_fraction']:.2f} %), poses accepted "
            f"{ctl['poses_accepted']}; pose update p50/p99 {ctl['update_ms_p50']:.2f}/"
            f"{ctl['update_ms_p99']:.2f} ms{swap}{_cpu_text(ctl)}")


def _cpu_text(ctl: dict) -> str:
    cpu = ctl.get('cpu_percent') or {}
    return ('; CPU ' + ', '.join(f'{key} {value:.0f} %' for key, value in cpu.items())
            + ' of a core' if cpu else '')


@interruptible('cdpr_bench')
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='cdpr_bench', description=plain(__doc__.split('\n')[0]))
    parser.add_argument('--config', help='ROS 2 parameter YAML (default: the paper robot)')
    parser.add_argument('--quick', action='store_true', help='few repetitions (CI smoke run)')
    parser.add_argument('--json', type=Path, help='write the results to this JSON file')
    parser.add_argument('--dds', action='store_true',
                        help='also run dynamics_node as a child process: DDS latency, '
                        'its own compute per wrench, the sustained input rate')
    parser.add_argument('--workspace', action='store_true',
                        help='instead: what a cdpr_workspace run costs (poses/s per worker, '
                        '1 -> 2 worker scaling, engine overhead per chunk size)')
    parser.add_argument('--calibration', action='store_true',
                        help='instead: cdpr_calibrate fit (9 parameters, 50 poses x 4 modes) '
                        'and identify (a 100 s record at 100 Hz) on synthetic measurements; '
                        '--config: a 6-DOF robot (default: the rigid test robot)')
    args = parser.parse_args(argv)
    try:
        if args.workspace:
            from cdpr_dynamics.cli import bench_workspace
            result = bench_workspace.run(args.config, args.quick)
        elif args.calibration:
            from cdpr_dynamics.cli import bench_calibration
            result = bench_calibration.run(args.config, args.quick)
        else:
            settings = load_settings(args.config)
            config = args.config or str(default_config_path())
            result = run(settings, args.quick, config if args.dds else None)
    except (ConfigError, AnalysisError) as exc:
        print(f'cdpr_bench: error: {exc}', file=sys.stderr)
        return 1
    if args.json:
        try:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(result, indent=1))
        except OSError as exc:
            print(f'cdpr_bench: error: cannot write {args.json}: {exc.strerror}',
                  file=sys.stderr)
            return 1
    if args.workspace:
        print(bench_workspace.summary(result))
        return 0
    if args.calibration:
        print(bench_calibration.summary(result))
        return 0
    print(summary(result))
    return 0


if __name__ == '__main__':
    sys.exit(main())
