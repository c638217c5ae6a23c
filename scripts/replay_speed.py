"""Replay speed of cdpr_replay offline (input messages per second) for spring and fem n = 16.

    python scripts/replay_speed.py [--duration S] [--repeat N]

Input: the ``trajectory_harmonic`` scenario stretched to ``--duration`` seconds (20 Hz poses,
each one moving the platform, so every pose re-solves the tensions and rebuilds the model;
200 Hz wrenches, each 5 Newmark steps of 1 ms). Everything is timed: reading, checks, models,
writing the output file. Best of ``--repeat`` runs; the paper config otherwise.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from cdpr_dynamics import scenarios
from cdpr_dynamics.replay import load_replay_config, replay_offline

CASES = (('spring', 16), ('fem', 16), ('fem', 4))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--duration', type=float, default=20.0)
    parser.add_argument('--repeat', type=int, default=3)
    args = parser.parse_args()
    settings, options, _ = load_replay_config()
    with tempfile.TemporaryDirectory() as folder:
        source = Path(folder) / 'input.mcap'
        written = scenarios.write_scenario('trajectory_harmonic', source,
                                           duration_s=args.duration)
        print(f'input: {written.message_count} messages ({args.duration:g} s: 20 Hz poses, '
              f'200 Hz wrenches), {written.bytes} bytes')
        for method, elements in CASES:
            best = None
            for k in range(args.repeat):
                out = Path(folder) / f'{method}{elements}_{k}.mcap'
                start = time.perf_counter()
                summary = replay_offline(source, out, settings, method,
                                         elements_per_cable=elements, options=options)
                elapsed = time.perf_counter() - start
                best = elapsed if best is None else min(best, elapsed)
                out.unlink()
            rate = summary.inputs / best
            print(f'{method:6s} n={elements:2d} ({summary.dofs:3d} DOFs): {summary.inputs} inputs '
                  f'in {best:.2f} s = {rate:.0f} messages/s ({summary.rebuilds} rebuilds, '
                  f'{summary.wrenches_accepted} predictions; {summary.inputs / args.duration:.0f}'
                  f' messages/s in the recording: {rate * args.duration / summary.inputs:.0f}x '
                  'real time)')


if __name__ == '__main__':
    main()
