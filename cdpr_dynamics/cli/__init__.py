"""Console scripts of the package; :func:`interruptible` gives them one Ctrl-C behaviour."""
from __future__ import annotations

import functools
import os
import signal
import sys

#: Exit status after Ctrl-C (128 + SIGINT), as shells report it.
INTERRUPTED_STATUS = 128 + signal.SIGINT


def interruptible(prog: str):
    """Decorate a console script's ``main(argv=None) -> int``: Ctrl-C ends it with the one line
    ``PROG: interrupted`` on stderr and status 130, never a traceback.

    The first SIGINT raises KeyboardInterrupt in the main thread, so ``finally`` blocks stop
    child processes and close files; a second SIGINT while that clean-up runs ends the process
    at once (``os._exit``), still with one line and 130. The previous handler is restored when
    ``main`` returns (in-process callers, tests)."""
    def decorate(main):
        @functools.wraps(main)
        def run(argv=None) -> int:
            said = []

            def say():
                if not said:
                    said.append(True)
                    try:
                        sys.stderr.write(f'{prog}: interrupted\n')
                        sys.stderr.flush()
                    except (OSError, ValueError):   # stderr closed: the status says it
                        pass

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
                say()
                return INTERRUPTED_STATUS
            finally:
                if not getattr(on_sigint, 'seen', False):
                    signal.signal(signal.SIGINT, previous)
        return run
    return decorate
