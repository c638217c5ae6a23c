"""Console scripts of the package; :func:`interruptible` gives them one Ctrl-C behaviour.

The console scripts' entry points are the small functions at the end of this module (this
module imports nothing heavy): each installs its SIGINT handler first and only then imports
its tool, so a Ctrl-C during the imports (seconds on a busy machine: numpy, scipy, rclpy)
also ends the tool with one line and status 130 instead of Python's traceback.
"""
from __future__ import annotations

import functools
import importlib
import os
import re
import signal
import sys

_ROLE = re.compile(r':[a-z]+:`~?(?:[\w.]+\.)?([^`]+)`')     # :func:`~a.b.name` -> name
_LITERAL = re.compile(r'``([^`]+)``|`([^`]+)`|\*\*([^*]+)\*\*')


def plain(text: str) -> str:
    """``text`` (a docstring's line) without reStructuredText markup, for ``--help``:
    roles give their target's last name, literals and bold their text."""
    text = _ROLE.sub(r'\1', text)
    return _LITERAL.sub(lambda m: next(g for g in m.groups() if g is not None), text)


#: Exit status after Ctrl-C (128 + SIGINT), as shells report it.
INTERRUPTED_STATUS = 128 + signal.SIGINT


def _say_interrupted(prog: str) -> None:
    try:
        sys.stderr.write(f'{prog}: interrupted\n')
        sys.stderr.flush()
    except (OSError, ValueError):   # stderr closed: the status says it
        pass


def _stop_children() -> None:
    """Stop the children started in sessions of their own (a node) that the interrupted code
    did not stop (cdpr_dynamics.ros.process.start_child: only if it was ever imported)."""
    process = sys.modules.get('cdpr_dynamics.ros.process')
    if process is not None:
        process.stop_started()


def interruptible(prog: str):
    """Decorate a console script's ``main(argv=None) -> int``: Ctrl-C ends it with the one line
    ``PROG: interrupted`` on stderr and status 130, never a traceback.

    The first SIGINT raises KeyboardInterrupt in the main thread, so ``finally`` blocks stop
    child processes and close files (and children of
    :func:`cdpr_dynamics.ros.process.start_child` the interrupted code had not stopped are
    stopped after them); a second SIGINT while that clean-up runs ends the process
    at once (``os._exit``), still with one line and 130. The previous handler is restored when
    ``main`` returns (in-process callers, tests)."""
    def decorate(main):
        @functools.wraps(main)
        def run(argv=None) -> int:
            said = []

            def say():
                if not said:
                    said.append(True)
                    _say_interrupted(prog)

            def on_sigint(signum, frame):
                if getattr(on_sigint, 'seen', False):
                    say()
                    os._exit(INTERRUPTED_STATUS)
                on_sigint.seen = True
                raise KeyboardInterrupt

            previous = signal.signal(signal.SIGINT, on_sigint)
            try:
                return main(argv)
            except KeyboardInterrupt:
                _stop_children()
                say()
                return INTERRUPTED_STATUS
            finally:
                if not getattr(on_sigint, 'seen', False):
                    signal.signal(signal.SIGINT, previous)
        return run
    return decorate


def entry_point(prog: str, module: str):
    """A console script's entry: Ctrl-C ends it at once with ``PROG: interrupted`` and status
    130 until ``module`` is imported (nothing to clean up yet), then ``module.main()`` runs
    (with its own handler, :func:`interruptible`)."""
    def on_sigint(signum, frame):
        _say_interrupted(prog)
        os._exit(INTERRUPTED_STATUS)

    def run() -> int:
        signal.signal(signal.SIGINT, on_sigint)
        return importlib.import_module(module).main()
    run.__name__ = run.__qualname__ = prog
    run.module = module
    return run


cdpr_analyze = entry_point('cdpr_analyze', 'cdpr_dynamics.cli.analyze')
cdpr_bench = entry_point('cdpr_bench', 'cdpr_dynamics.cli.bench')
cdpr_record = entry_point('cdpr_record', 'cdpr_dynamics.cli.record')
cdpr_demo = entry_point('cdpr_demo', 'cdpr_dynamics.cli.demo')
cdpr_tradeoff = entry_point('cdpr_tradeoff', 'cdpr_dynamics.cli.tradeoff')
cdpr_estimate_table = entry_point('cdpr_estimate_table', 'cdpr_dynamics.cli.estimate_table')
cdpr_replay = entry_point('cdpr_replay', 'cdpr_dynamics.cli.replay')
cdpr_workspace = entry_point('cdpr_workspace', 'cdpr_dynamics.cli.workspace')
cdpr_calibrate = entry_point('cdpr_calibrate', 'cdpr_dynamics.cli.calibrate')
