"""``cdpr_record``: record the node's topics (and FRF service events) to one MCAP file.

    cdpr_record --output run.mcap [--topics pose wrench ...] [--force] [--ros-args ...]
    cdpr_record --recover IN OUT [--force]

Records until SIGINT (Ctrl-C) or SIGTERM, then finishes the file (summary and index), prints
one line with where it is and how many messages it holds, and exits 0: the normal stop. Chunks
are closed at least every second, so even a recorder killed outright leaves a file whose
messages up to about a second before the kill can be read
(``cdpr_dynamics.recording.reader.read_messages(..., allow_incomplete=True)``, or ``--recover``).

When writing fails (a full disk, a file-size limit), recording stops, the file is finished with
every whole chunk written before (summary and footer: every MCAP reader opens it) and the tool
exits 1 with one line naming the cause and what the file keeps.

``--recover IN OUT`` writes every message of every whole chunk of IN (a killed or cut
recording) to a new, complete file OUT; IN is only read and an existing OUT is never replaced.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time

from msg_adapters.mcap_schema import service_event_topic

#: The recorder takes what waits on its subscriptions this often, in batches, instead of one
#: executor wake-up per message: at 3000 messages/s (a 1 kHz controller and the node's answers)
#: the wake-ups took more of a core than the node beside it. The queues (QOS_DEPTH = 1000 per
#: topic) hold 200 times this period at 1 kHz.
POLL_S = 0.005
#: ... and spins its node's executor once every this many polls (0.1 s): one spin_once costs
#: 0.3-0.8 ms here, the node's wait set rebuilt each time.
SPIN_EVERY = 20

# doc/node_interface.md: the node's inputs and outputs, and its FRF service (introspection events).
DEFAULT_TOPICS = {
    'pose': 'geometry_msgs/msg/PoseStamped',
    'wrench': 'geometry_msgs/msg/WrenchStamped',
    'predicted_displacement': 'geometry_msgs/msg/Vector3Stamped',
    'cable_tensions': 'sensor_msgs/msg/JointState',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
    service_event_topic('frequency_response'): 'rcl_interfaces/srv/GetParameters_Event',
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cdpr_record',
        description='Record cdpr_dynamics topics to a rosbag2-compatible MCAP file '
                    'until SIGINT or SIGTERM (exit 0); a failing write (a full disk) '
                    'finishes the file of its whole chunks and exits 1; --recover completes '
                    'a killed recording.')
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument('--output', '-o', metavar='PATH',
                      help='MCAP file to write (refused if it exists, unless --force)')
    mode.add_argument('--recover', nargs=2, metavar=('IN', 'OUT'),
                      help='write every whole chunk of the killed or cut recording IN to a new, '
                           'complete file OUT, then exit (IN is only read; OUT must not exist)')
    parser.add_argument('--topics', nargs='+', metavar='T',
                        help='topics to record (default: ' + ', '.join(DEFAULT_TOPICS) +
                             '); the type is taken from the publishers unless it is one of '
                             'the defaults')
    parser.add_argument('--force', action='store_true',
                        help='replace an existing output file (not with --recover)')
    parser.add_argument('--chunk-size', type=int, default=None, metavar='BYTES',
                        help='close a chunk when it holds this many bytes (default 786432; '
                             'the first closes at 16384 and each next one at twice the '
                             "previous one's size, up to this)")
    parser.add_argument('--compression', choices=('none', 'zstd', 'lz4'), default='none',
                        help='chunk compression (default none, as rosbag2)')
    return parser


def _fail(message: str, code: int = 1) -> int:
    print(f'cdpr_record: error: {message}', file=sys.stderr, flush=True)
    return code


def _drain(recorder, budget_s: float = 0.5) -> None:
    """Take what the middleware already holds before closing (bounded, stops when idle)."""
    deadline = time.monotonic() + budget_s
    idle = 0
    while idle < 3 and time.monotonic() < deadline:
        before = recorder.message_count
        recorder.poll()
        idle = idle + 1 if recorder.message_count == before else 0
        time.sleep(0.01)      # the polling period of the subscriptions, not a synchronisation


def _recover(source: str, destination: str) -> int:
    """``--recover IN OUT``: one line with the counts (and a line per kind of damage met), or
    one line with the error."""
    from cdpr_dynamics.recording.base import RecordingError
    from cdpr_dynamics.recording.reader import recording_info, Salvage
    from cdpr_dynamics.recording.recovery import recover_recording

    def on_term(signum, frame):   # as Ctrl-C: the partial output is removed
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    salvage = Salvage()
    try:
        before = recording_info(source)
        kept = recover_recording(source, destination, salvage=salvage)
        after = recording_info(destination)
    except RecordingError as err:
        return _fail(str(err))
    except KeyboardInterrupt:
        return _fail('interrupted; no output written', 130)
    except OSError as err:
        return _fail(f'{getattr(err, "filename", "") or ""} {err.strerror or err}'.strip())
    topics = ', '.join(f'{name} {t.message_count}' for name, t in sorted(after.topics.items()))
    state = ('was complete' if before.complete and not salvage else
             'was damaged' if salvage.lost_chunks or before.complete else 'was cut short')
    print(f'cdpr_record: recovered {kept} messages from {salvage.chunks_read} whole chunks of '
          f'{before.path} ({state}) into {after.path.resolve()}: {topics or "no topics"}',
          flush=True)
    for line in salvage.lines():
        print(f'cdpr_record: {before.path}: {line}', flush=True)
    return 0


def main(argv=None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rclpy.utilities import remove_ros_args

    from cdpr_dynamics.recording.base import DEFAULT_CHUNK_SIZE, RecordingError
    from cdpr_dynamics.recording.recorder import Recorder

    argv = sys.argv if argv is None else ['cdpr_record', *argv]
    args = _parser().parse_args(remove_ros_args(argv)[1:])
    if args.recover:
        if args.force:
            return _fail('--recover never replaces a file: remove OUT first, or name another')
        return _recover(*args.recover)
    if args.chunk_size is not None and args.chunk_size < 1:
        return _fail(f'--chunk-size must be a positive number of bytes, got {args.chunk_size}')
    if args.topics:
        topics = {name: DEFAULT_TOPICS.get(name) for name in args.topics}
    else:
        topics = dict(DEFAULT_TOPICS)

    if os.path.lexists(args.output) and not args.force:
        return _fail(f'{args.output} exists; not overwriting it (use --force to replace it)')

    # Our own handlers: a signal only sets a flag, so no exception lands mid-write.
    stop = threading.Event()
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node = recorder = executor = None
    status = 0
    try:
        node = rclpy.create_node('cdpr_record')

        def on_signal(signum, frame):
            stop.set()

        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
        recorder = Recorder(node, args.output, topics, force=args.force,
                            chunk_size=args.chunk_size or DEFAULT_CHUNK_SIZE,
                            compression=args.compression, log_failure=False)
        print(f'cdpr_record: recording {", ".join(sorted(recorder.topic_counts))} '
              f'to {recorder.path.resolve()} (Ctrl-C or SIGTERM to stop)', flush=True)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        polls = 0
        while not stop.is_set() and rclpy.ok() and recorder.error is None:
            recorder.poll()                       # every topic's waiting messages, in batches
            polls += 1
            if polls % SPIN_EVERY == 0:           # what else is ready (parameter services)
                executor.spin_once(timeout_sec=0.0)
            stop.wait(POLL_S)
        if recorder.error is None:
            _drain(recorder)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RecordingError as err:
        status = _fail(str(err))
    except OSError as err:
        status = _fail(f'{getattr(err, "filename", "") or ""} {err.strerror or err}'.strip())
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)   # a second Ctrl-C must not cut the close
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if recorder is not None:
            summary = recorder.close()
            seen = ', '.join(f'{name} {count}' for name, count in sorted(summary.topics.items()))
            kept = (f'{summary.message_count} messages ({summary.bytes} bytes, '
                    f'{summary.chunk_count} chunks)')
            if summary.error is None:
                print(f'cdpr_record: wrote {kept} to {summary.path.resolve()}: {seen}',
                      flush=True)
            else:
                ending = ('finished with its summary' if summary.complete else
                          'cut at the last whole chunk, no summary: use --recover')
                status = _fail(f'{summary.error}; recording stopped, the file keeps {kept}, '
                               f'{ending}: {seen}')
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
