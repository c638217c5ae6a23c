"""``--help`` of every console tool: plain text, no reStructuredText markup of docstrings."""
import importlib
import re

import pytest

from cdpr_dynamics.cli import plain
from conftest import REPO

#: console scripts of setup.py (name -> module, function); the node's --help is its own
TOOLS = {name: (module, function) for name, module, function in re.findall(
    r"'(cdpr_\w+) = ([\w.]+):(\w+)'", (REPO / 'setup.py').read_text())}
MARKUP = re.compile(r'``|:(func|mod|class|meth|data|attr|ref):|`[^`\s][^`]*`|\*\*')


def test_plain_drops_roles_literals_and_bold():
    assert plain('see :func:`~cdpr_dynamics.dynamics.system.time_history`, ``frf.force_n`` '
                 'and **not** :data:`MAX_DOFS` or `x`') == \
        'see time_history, frf.force_n and not MAX_DOFS or x'


@pytest.mark.parametrize('name', sorted(TOOLS))
def test_help_has_no_rst_markup(name, capsys):
    module, function = TOOLS[name]
    main = getattr(importlib.import_module(module), function)
    with pytest.raises(SystemExit) as done:
        main(['--help'])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert f'usage: {name}' in text.replace('\n', ' ')
    assert not MARKUP.search(text), MARKUP.search(text).group(0)
