"""The package's layers: no module imports from a layer above its own.

From the bottom up: the cable models, the robot's mechanics (geometry, tensions, statics), the
dynamics (assembly, FRF, modes, time histories), model selection, analysis (configuration,
pipeline, live prediction, workspace, figures), ``msg_adapters`` (the only place that converts
messages), recording (MCAP, replay), the ROS node, and the console scripts.
"""
import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LAYERS = ('models', 'mechanics', 'dynamics', 'selection', 'analysis', 'msg_adapters',
          'recording', 'ros', 'cli')


def layer_of(module: str) -> str | None:
    """The layer of a dotted module name of this repository, None for anything else."""
    parts = module.split('.')
    if parts[0] == 'msg_adapters':
        return 'msg_adapters'
    if parts[0] == 'cdpr_dynamics' and len(parts) > 1:
        return parts[1] if parts[1] in LAYERS else '?'
    return None


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of this repository's packages in ``path``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            if node.module == 'cdpr_dynamics':     # from cdpr_dynamics import models
                found += [(node.lineno, f'cdpr_dynamics.{a.name}') for a in node.names]
            else:
                found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
    return [(line, name) for line, name in found if layer_of(name)]


def sources() -> list[Path]:
    return sorted([*(REPO / 'cdpr_dynamics').rglob('*.py'),
                   *(REPO / 'msg_adapters').rglob('*.py')])


def test_every_module_belongs_to_a_layer():
    loose = [str(p.relative_to(REPO)) for p in sources()
             if layer_of('.'.join(p.relative_to(REPO).with_suffix('').parts)) in (None, '?')
             and p.name != '__init__.py']
    assert loose == []


@pytest.mark.parametrize('path', sources(), ids=lambda p: str(p.relative_to(REPO)))
def test_no_module_imports_a_layer_above_its_own(path):
    own = layer_of('.'.join(path.relative_to(REPO).with_suffix('').parts))
    if own in (None, '?'):
        return
    upward = [f'line {line}: {name} ({layer_of(name)})' for line, name in imported_modules(path)
              if layer_of(name) != '?' and LAYERS.index(layer_of(name)) > LAYERS.index(own)]
    assert upward == [], f'{path.name} ({own}) imports from above'


def test_the_check_sees_an_upward_import(tmp_path):
    """The checker itself: an upward import is found."""
    module = tmp_path / 'robot.py'
    module.write_text('from cdpr_dynamics.analysis.config import Settings\n'
                      'import numpy as np\n')
    assert imported_modules(module) == [(1, 'cdpr_dynamics.analysis.config')]
    assert LAYERS.index(layer_of('cdpr_dynamics.analysis.config')) > LAYERS.index('mechanics')
