"""Subprocesses of a test (recorders, publishers, replays, nodes), logged to its output folder
and all stopped at the end, and what the recording tests read while a file is written."""
from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

from cdpr_dynamics.recording.base import RecordingError
from cdpr_dynamics.recording.reader import recording_info


class Processes:
    """Subprocesses of one test, logged to its output folder, all stopped at the end."""

    def __init__(self, env: dict, folder: Path):
        self.env, self.folder, self.procs = env, folder, []

    def start(self, name: str, args: list, stdin=None, **popen) -> subprocess.Popen:
        """Start ``args`` in a session of its own; ``proc.logs`` are its stdout and stderr."""
        out = open(self.folder / f'{name}.out', 'w')
        err = open(self.folder / f'{name}.err', 'w')
        proc = subprocess.Popen([str(a) for a in args], env=self.env, stdout=out, stderr=err,
                                stdin=stdin, cwd=self.folder, start_new_session=True, **popen)
        proc.logs = (self.folder / f'{name}.out', self.folder / f'{name}.err')
        self.procs.append(proc)
        return proc

    def stop_all(self):
        """End what still runs by SIGINT (its stdin closed, if it is fed on it); killed (its
        whole session) if it has not ended within 10 s."""
        for proc in self.procs:
            if proc.poll() is None:
                if proc.stdin:
                    proc.stdin.close()
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=5)


def finish(proc: subprocess.Popen, sig=signal.SIGINT, timeout: float = 30.0) -> str:
    """Stop ``proc`` with ``sig`` (if it still runs) and return its stdout; it must exit 0
    without a traceback."""
    if proc.poll() is None:
        proc.send_signal(sig)
    proc.wait(timeout=timeout)
    out, err = (p.read_text() for p in proc.logs)
    assert proc.returncode == 0, f'{proc.args[:3]} exited {proc.returncode}: {err}'
    assert 'Traceback' not in err, err
    return out


def counts_so_far(path: Path) -> dict:
    """Messages per topic in a file being written (what its closed chunks hold)."""
    if not path.exists():
        return {}
    try:
        return {k: t.message_count for k, t in recording_info(path).topics.items()}
    except RecordingError:
        return {}
