"""flake8 on the package, its tests and the launch file, as the ROS templates run it.

With ``ament_flake8`` (a ROS install, or the ``ros-jazzy-ament-flake8`` wheel) as ros2/demos'
``test_flake8.py`` calls it, otherwise with plain ``flake8`` from PyPI; both read this
repository's ``setup.cfg`` [flake8] (not ament's own configuration: see the comment there), so
both report the same errors.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / 'setup.cfg'
PATHS = ['cdpr_dynamics', 'msg_adapters', 'launch', 'test', 'doc', 'setup.py']


def flake8_errors(paths) -> list[str]:
    """flake8's findings (``file:line:col: code message``) for ``paths`` under ROOT."""
    try:
        from ament_flake8.main import main_with_errors
    except ImportError:     # no ROS lint tools: flake8 itself
        run = subprocess.run([sys.executable, '-m', 'flake8', '--config', str(CONFIG),
                              *paths], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert run.returncode in (0, 1), f'flake8 did not run: {run.stderr.strip()}'
        return run.stdout.splitlines()
    cwd = os.getcwd()
    os.chdir(ROOT)          # ament_flake8 walks the working folder for AMENT_IGNORE markers
    try:
        rc, errors = main_with_errors(argv=['--config', str(CONFIG), *paths])
    finally:
        os.chdir(cwd)
    assert (rc == 0) == (not errors)
    return errors


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    errors = flake8_errors(PATHS)
    assert not errors, f'Found {len(errors)} code style errors / warnings:\n' + '\n'.join(errors)


def test_flake8_finds_what_it_should(tmp_path):
    """The check is live: a file with an unused import and a 100-column line fails it."""
    bad = tmp_path / 'probe.py'
    bad.write_text('"""Probe."""\nimport os\n\nX = 1' + ' ' * 92 + '# 100 columns\n')
    errors = flake8_errors([str(bad)])
    assert len(errors) == 2, errors
    assert any('F401' in e for e in errors) and any('E501' in e for e in errors), errors
