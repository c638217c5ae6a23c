"""``--help`` of every console tool: plain text, no reStructuredText markup of docstrings."""
import importlib
import re

import pytest

from cdpr_dynamics import cli
from cdpr_dynamics.cli import plain
from conftest import REPO

#: console scripts of setup.py (name -> entry attribute of cdpr_dynamics.cli); the node's
#: --help is its own
TOOLS = dict(re.findall(r"'(cdpr_\w+) = cdpr_dynamics\.cli:(\w+)'",
                        (REPO / 'setup.py').read_text()))
#: tools with subcommands: each subcommand's --help too
SUBCOMMANDS = {'cdpr_calibrate': ('identify', 'fit')}
MARKUP = re.compile(r'``|:(func|mod|class|meth|data|attr|ref):|`[^`\s][^`]*`|\*\*')


def test_plain_drops_roles_literals_and_bold():
    assert plain('see :func:`~cdpr_dynamics.dynamics.system.time_history`, ``frf.force_n`` '
                 'and **not** :data:`MAX_DOFS` or `x`') == \
        'see time_history, frf.force_n and not MAX_DOFS or x'


@pytest.mark.parametrize('name, sub', [(name, sub) for name in sorted(TOOLS)
                                       for sub in (None,) + SUBCOMMANDS.get(name, ())])
def test_help_has_no_rst_markup(name, sub, capsys):
    module = getattr(cli, TOOLS[name]).module
    main = importlib.import_module(module).main
    with pytest.raises(SystemExit) as done:
        main([sub, '--help'] if sub else ['--help'])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert f'usage: {name}' in text.replace('\n', ' ')
    assert not MARKUP.search(text), MARKUP.search(text).group(0)
