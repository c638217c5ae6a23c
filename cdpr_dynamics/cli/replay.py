"""``cdpr_replay``: feed a recording's pose and wrench messages through the models.

    cdpr_replay INPUT --output PATH [--config PATH] [--method M] [--elements N] [--force]
                [--pose-topic T] [--wrench-topic T] [--order log|stamp] [--allow-incomplete]
                [--skip-bad] [--resume] [--no-progress]
    cdpr_replay INPUT --live [--rate R] [--subscribers N] [--wait S] [--ros-args ...]

Offline, the inputs go through the same code as ``dynamics_node`` (checks, tension QP, model,
Newmark) and a new MCAP file gets the inputs plus ``predicted_displacement``,
``cable_tensions`` and a ``/diagnostics`` message per rejected input; on a terminal a progress
bar with the time left runs on stderr (nothing on a pipe). The output appears only once
complete and an existing one is kept unless ``--force``.
Live, the recorded pose and wrench messages are republished on ``pose`` and ``wrench`` with
the recorded timing (``--rate 2``: twice as fast), once a subscriber (the node) is there.

Errors (a missing, truncated or corrupt file, missing topics, a topic of another type, a
message that does not decode, a bad config) end with one line and exit status 1;
``--skip-bad`` replays past undecodable input messages and says how many it skipped;
``--allow-incomplete`` replays every intact chunk of a cut or damaged file and names what was
lost. Ctrl-C or SIGTERM ends with one line and status 130, no output file, and the partial
output kept under its hidden temporary name (``.NAME.partial-XXXX``): ``--resume`` continues it,
a run without ``--resume`` names and removes it (as it does the leftover of a killed replay).
"""
from __future__ import annotations

from cdpr_dynamics.cli import blas_threads  # noqa: F401  (before numpy: one BLAS thread)

import argparse
import os
import signal
import sys
import threading

from cdpr_dynamics.analysis.config import METHODS
from msg_adapters.inputs import NUMERIC_ERRORS, first_line

PROG = 'cdpr_replay'


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description='Replay the pose and wrench messages of an MCAP recording '
                               'through the cdpr_dynamics models (offline, into a new MCAP '
                               'file) or to a running node (--live).')
    parser.add_argument('input', metavar='INPUT', help='MCAP file (cdpr_record, ros2 bag '
                        'record -s mcap - the file or its bag directory - or a cdpr_replay '
                        'output)')
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument('--output', '-o', metavar='PATH',
                      help='offline: MCAP file to write (refused if it exists, unless --force)')
    mode.add_argument('--live', action='store_true',
                      help='republish to a running node with the recorded timing')
    parser.add_argument('--config', metavar='PATH',
                        help='ROS 2 parameter file (default: the installed paper_cdpr.yaml)')
    parser.add_argument('--method', choices=METHODS, help='cable model (default: the config)')
    parser.add_argument('--elements', type=int, metavar='N',
                        help='elements per cable for fem / fem_sag (default: the config)')
    parser.add_argument('--force', action='store_true', help='replace an existing output')
    parser.add_argument('--pose-topic', metavar='T',
                        help='PoseStamped topic of the input (default: the one named pose)')
    parser.add_argument('--wrench-topic', metavar='T',
                        help='WrenchStamped topic of the input (default: the one named wrench)')
    parser.add_argument('--order', choices=('log', 'stamp'), default='log',
                        help='offline: process inputs by receive time (log, as the node saw '
                             'them; default) or by header stamp')
    parser.add_argument('--allow-incomplete', action='store_true',
                        help='replay what survives of a file whose recorder was killed')
    parser.add_argument('--skip-bad', action='store_true',
                        help='offline: skip input messages that do not decode and count them '
                             '(default: stop with an error naming the first)')
    parser.add_argument('--resume', action='store_true',
                        help='offline: continue the interrupted or killed replay whose partial '
                             'output (.PATH.partial-*) is beside PATH')
    parser.add_argument('--rate', type=float, default=1.0, metavar='R',
                        help='live: R times the recorded speed (default 1)')
    parser.add_argument('--subscribers', type=int, default=1, metavar='N',
                        help='live: wait for N subscriptions on pose and on wrench (default 1)')
    parser.add_argument('--wait', type=float, default=30.0, metavar='S',
                        help='live: give up after S seconds without subscribers (default 30)')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    return parser


def _fail(message: str, code: int = 1) -> int:
    print(f'{PROG}: error: {message}', file=sys.stderr, flush=True)
    return code


class _Bar:
    """tqdm on stderr, created on the first update (the total is known then)."""

    def __init__(self, enabled: bool, unit: str, desc: str):
        self.enabled, self.unit, self.desc = enabled, unit, desc
        self.bar = None
        self.last = 0

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self.bar is None:
            from tqdm import tqdm
            self.bar = tqdm(total=total, unit=self.unit, desc=self.desc, file=sys.stderr,
                            dynamic_ncols=True, mininterval=0.2, leave=False)
        if done - self.last >= 50 or done >= self.bar.total:
            self.bar.update(done - self.last)
            self.last = done

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _offline(args) -> int:
    from cdpr_dynamics.recording.base import RecordingError
    from cdpr_dynamics.recording.replay import (ReplayError, ReplayInterrupted,
                                                load_replay_config, replay_offline,
                                                summary_lines)

    def on_signal(signum, frame):
        """Ctrl-C or SIGTERM: the replay stops and keeps its partial output for --resume; a
        second one while that is written ends the process at once."""
        if getattr(on_signal, 'seen', False):
            os._exit(_fail('interrupted again: the partial output may be incomplete', 130))
        on_signal.seen = True
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, on_signal)        # replaces the console script's own
    signal.signal(signal.SIGTERM, on_signal)
    bar = _Bar(not args.no_progress and sys.stderr.isatty(), 'msg', 'replay')
    try:
        settings, options, flat = load_replay_config(args.config)
        if args.method:
            flat['model.method'] = args.method
        if args.elements is not None:
            flat['model.elements_per_cable'] = args.elements
        summary = replay_offline(
            args.input, args.output, settings, args.method, bar,
            elements_per_cable=args.elements, options=options, force=args.force,
            pose_topic=args.pose_topic, wrench_topic=args.wrench_topic, order=args.order,
            allow_incomplete=args.allow_incomplete, parameters=flat, skip_bad=args.skip_bad,
            resume=args.resume, keep_partial=True)
    except ReplayInterrupted as stop:
        bar.close()
        return _fail(f'{stop}; no output written', 130)
    except KeyboardInterrupt:
        bar.close()
        return _fail('interrupted; no output written', 130)
    except (ReplayError, RecordingError) + NUMERIC_ERRORS as exc:
        bar.close()
        return _fail(first_line(exc))
    except OSError as exc:
        bar.close()
        return _fail(f'{getattr(exc, "filename", "") or ""} {exc.strerror or exc}'.strip())
    signal.signal(signal.SIGINT, signal.SIG_IGN)    # the output is there: say so, whatever
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    bar.close()
    for line in summary_lines(summary):
        print(f'{PROG}: {line}', flush=True)
    for line in summary.warnings:
        print(f'{PROG}: warning: {line}', file=sys.stderr, flush=True)
    return 0


def _live(args, argv) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    from cdpr_dynamics.recording.base import RecordingError
    from cdpr_dynamics.recording.replay import (ReplayError, inspect_input, replay_live,
                                                resolve_input)

    try:   # a bad file fails before anything starts
        inspect_input(resolve_input(args.input), args.pose_topic, args.wrench_topic,
                      args.allow_incomplete)
    except (ReplayError, RecordingError) as exc:
        return _fail(first_line(exc))
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    node = None
    bar = _Bar(not args.no_progress and sys.stderr.isatty(), 'msg', 'live')
    try:
        node = rclpy.create_node('cdpr_replay')
        print(f'{PROG}: waiting for {args.subscribers} subscriber(s) on '
              f'{node.resolve_topic_name("pose")} and {node.resolve_topic_name("wrench")}',
              flush=True)
        summary = replay_live(node, args.input, rate=args.rate, pose_topic=args.pose_topic,
                              wrench_topic=args.wrench_topic, subscribers=args.subscribers,
                              wait_s=args.wait, stop=stop, progress=bar,
                              allow_incomplete=args.allow_incomplete)
    except (ReplayError, RecordingError) as exc:
        bar.close()
        return _fail(first_line(exc))
    except (KeyboardInterrupt, ExternalShutdownException):
        bar.close()
        return _fail('interrupted', 130)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    bar.close()
    print(f'{PROG}: published {summary.published} of {summary.total} messages on '
          f'{summary.pose_topic} and {summary.wrench_topic} in {summary.duration_s:.2f} s '
          f'({summary.recorded_span_s:.2f} s recorded, rate {args.rate:g}; latest '
          f'{summary.max_late_s * 1e3:.1f} ms behind schedule)'
          + ('; stopped early' if summary.stopped else ''), flush=True)
    return 130 if summary.stopped else 0


def main(argv=None) -> int:
    from rclpy.utilities import remove_ros_args

    argv = sys.argv if argv is None else [PROG, *argv]
    args = _parser().parse_args(remove_ros_args(argv)[1:])
    if args.live:
        if args.skip_bad or args.resume:
            return _fail(f'{"--skip-bad" if args.skip_bad else "--resume"} works offline '
                         'only (with --output)')
        if args.subscribers < 1:
            return _fail('--subscribers must be at least 1')
        if not (0.0 < args.rate < float('inf')):
            return _fail(f'--rate must be a positive number, got {args.rate:g}')
        return _live(args, argv)
    return _offline(args)


if __name__ == '__main__':
    sys.exit(main())
