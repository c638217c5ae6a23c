"""Docstring conventions (pydocstyle) on the package, its tests and the launch file.

As ros2/demos' ``test_pep257.py``: ``ament_pep257`` where installed, otherwise ``pydocstyle``
from PyPI (what ament_pep257 runs); both with the error codes of ``setup.cfg`` [pydocstyle]
(ament's convention less the departures listed there), so both report the same errors.
"""
import configparser
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PATHS = ['cdpr_dynamics', 'msg_adapters', 'launch', 'test', 'doc', 'setup.py']


def ignored_codes() -> list[str]:
    """The codes setup.cfg [pydocstyle] ignores."""
    config = configparser.ConfigParser()
    config.read(ROOT / 'setup.cfg')
    return [c.strip() for c in config['pydocstyle']['ignore'].split(',') if c.strip()]


def pep257_errors(paths) -> tuple[int, str]:
    """(exit status, report) of the docstring check of ``paths`` (relative to ROOT)."""
    try:
        import ament_pep257.main  # noqa: F401  (only whether it is installed)
    except ImportError:     # no ROS lint tools: pydocstyle itself
        command = [sys.executable, '-m', 'pydocstyle', '--ignore=' + ','.join(ignored_codes())]
    else:
        command = [sys.executable, '-m', 'ament_pep257.main', '--ignore', *ignored_codes(),
                   '--']
    run = subprocess.run(command + [str(p) for p in paths], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode in (0, 1), f'{command[2]} did not run: {run.stderr.strip()}'
    return run.returncode, run.stdout + run.stderr


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    status, report = pep257_errors(PATHS)
    assert status == 0, 'Found code style errors / warnings:\n' + report


def test_pep257_finds_what_it_should(tmp_path):
    """The check is live: a single-quoted docstring and a blank line after one fail it."""
    bad = tmp_path / 'probe.py'
    bad.write_text("'''Probe.'''\n\n\ndef f():\n    \"\"\"Return 1.\"\"\"\n\n    return 1\n")
    status, report = pep257_errors([bad])
    assert status == 1 and 'D300' in report and 'D202' in report, report
