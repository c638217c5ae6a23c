"""Sphinx extension of the cdpr_dynamics docs: the pages' generated parts.

A page marks where a generated part goes with an HTML comment on a line of its own, e.g.
``<!-- cdpr:parameters -->``; when Sphinx reads the page the comment is replaced by Markdown made
from the code or from committed data, so the text can never drift from what it describes:

- ``cdpr:parameters`` / ``cdpr:node-parameters``: the parameter tables, from
  ``cdpr_dynamics.analysis.config.PARAMETERS`` and ``NODE_PARAMETERS``;
- ``cdpr:benchmarks``: the tables of every ``doc/benchmarks/*.json`` written by
  ``cdpr_bench --json``; ``cdpr:tradeoff``: of every ``doc/benchmarks/tradeoff_*.csv`` written by
  ``cdpr_tradeoff --csv``;
- ``cdpr:estimates``: ``auto``'s estimated against measured errors, from
  ``doc/estimates/table.json`` written by ``cdpr_estimate_table --json``;
- ``cdpr:tests``: each test module and the first paragraph of its docstring;
- ``cdpr:api``: an ``automodule`` per module of the packages ``cdpr_dynamics`` and
  ``msg_adapters``, grouped by layer;
- ``cdpr:other-pages``: a toctree of every page of ``doc/`` that no other toctree of the page
  names, so a topic page added to ``doc/`` is linked (and the build stays free of warnings).

Docstrings are written for ``help()`` as much as for Sphinx: one whose reStructuredText does not
parse cleanly is shown as a literal block instead of failing the warnings-as-errors build.
"""
from __future__ import annotations

import ast
import csv
import io
import importlib
import json
import math
import pkgutil
import re
from pathlib import Path

from docutils.frontend import get_default_settings
from docutils.parsers.rst import Parser
from docutils.transforms.references import Substitutions
from docutils.utils import SystemMessage, new_document

DOC = Path(__file__).resolve().parent.parent
ROOT = DOC.parent
MARKER = re.compile(r'^<!-- cdpr:([\w-]+) -->$', re.M)

#: the package's layers, low to high, with what each holds (the API page's sections)
LAYERS = (
    ('cdpr_dynamics.models', 'Cable models: one interface, one module per model, a registry.'),
    ('cdpr_dynamics.mechanics', 'Robot geometry, tensions, feasibility, statics, underactuated.'),
    ('cdpr_dynamics.dynamics', 'Assembly, damping, FRF, Newmark, modes, slack, shapers.'),
    ('cdpr_dynamics.selection', 'Closed forms, error estimates, the reference, ``auto``.'),
    ('cdpr_dynamics.analysis', 'The parameter table, the pipeline, the live core, maps, '
     'calibration, figures.'),
    ('msg_adapters', 'The only place that converts ROS messages.'),
    ('cdpr_dynamics.recording', 'MCAP writer, reader, recorder, recovery, replay.'),
    ('cdpr_dynamics.ros', 'The node and its processes.'),
    ('cdpr_dynamics.cli', 'The console scripts.'),
)


def _cell(text: str) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def _number(value) -> str:
    return f'{value:g}' if isinstance(value, float) else str(value)


def _range(param) -> str:
    if param.choices:
        return ', '.join(param.choices)
    if param.length == 0:
        return '3 per cable'
    if param.length:
        return f'{param.length} values'
    if param.low is not None:
        return f'{_number(param.low)} .. {_number(param.high)}'
    return ''


def _default(param) -> str:
    if param.required:
        return '**required**'
    if param.default == []:
        return '`[]`'
    return f'`{param.default}`'


def parameter_table(params) -> str:
    """Markdown table of ``params``: name, default, range, meaning."""
    rows = ['| name | default | range | meaning |', '|---|---|---|---|']
    rows += [f'| `{p.name}` | {_default(p)} | {_cell(_range(p))} | {_cell(p.description)} |'
             for p in params]
    return '\n'.join(rows)


def _is_timing(value) -> bool:
    return isinstance(value, dict) and isinstance(value.get('p50_s'), float)


def _value(value) -> str:
    """One table cell: a timing as p50 / p99 in ms, a number to 4 digits, a dict inline."""
    if _is_timing(value):
        return f"{value['p50_s'] * 1e3:.3g} / {value['p99_s'] * 1e3:.3g}"
    if isinstance(value, dict):
        return '; '.join(f'{k} {_value(v)}' for k, v in value.items())
    if isinstance(value, float):
        return f'{value:.4g}' if math.isfinite(value) else str(value)
    if isinstance(value, list):
        return f'{len(value)} values' if len(value) > 6 else ', '.join(map(_value, value))
    return _cell(value)


def _rows_table(rows: list[dict]) -> list[str]:
    columns = list(dict.fromkeys(key for row in rows for key in row))
    out = ['| ' + ' | '.join(c.replace('_', ' ') for c in columns) + ' |',
           '|' + '---|' * len(columns)]
    out += ['| ' + ' | '.join(_value(row.get(c, '')) for c in columns) + ' |' for row in rows]
    return out


def benchmark_section(key: str, value) -> list[str]:
    """The table of one top-level entry of a ``cdpr_bench --json`` file."""
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        rows = value
    elif (isinstance(value, dict) and not _is_timing(value) and value
          and all(isinstance(v, dict) for v in value.values())):
        rows = [{'case': name, **(item if not _is_timing(item) else {'time': item})}
                for name, item in value.items()]
    elif isinstance(value, dict):
        rows = [value if not _is_timing(value) else {'time': value}]
    else:
        return [f'- `{key}`: {_value(value)}']
    return [f'### {key}', ''] + _rows_table(rows) + ['']


def benchmark_tables() -> str:
    """A section per ``doc/benchmarks/*.json``, a table per top-level entry of the file."""
    out = []
    for path in sorted((DOC / 'benchmarks').glob('*.json')):
        data = json.loads(path.read_text())
        out += [f'## `{path.name}`', '']
        for key, value in data.items():
            out += benchmark_section(key, value)
        out.append('')
    return '\n'.join(out) if out else 'No benchmark file in `doc/benchmarks/`.'


def tradeoff_tables() -> str:
    """A table per ``doc/benchmarks/tradeoff_*.csv`` written by ``cdpr_tradeoff --csv``."""
    out = []
    for path in sorted((DOC / 'benchmarks').glob('tradeoff_*.csv')):
        with path.open(newline='') as stream:
            rows = list(csv.DictReader(stream))
        out += [f'`{path.name}`:', '',
                '| method | n | DOFs | freq error % | FRF error % | time ms '
                '| estimated freq / FRF error % | note |',
                '|---|---:|---:|---:|---:|---:|---|---|']
        for row in rows:
            out.append(
                f"| {row['method']} | {row['elements_per_cable']} | {row['dofs']} | "
                f"{float(row['freq_error_pct']):.3g} | {float(row['frf_error_pct']):.3g} | "
                f"{float(row['time_s']) * 1e3:.3g} | "
                f"{float(row['estimated_freq_error_pct']):.3g} / "
                f"{float(row['estimated_frf_error_pct']):.3g} | {_cell(row['note'])} |")
        out.append('')
    return '\n'.join(out) if out else 'No trade-off file in `doc/benchmarks/`.'


def _first_paragraph(text: str) -> str:
    return ' '.join(text.strip().split('\n\n')[0].split())


def test_list() -> str:
    """Table of the test modules with the first paragraph of each module's docstring."""
    rows = ['| test module | what it checks |', '|---|---|']
    for path in sorted((ROOT / 'test').glob('test_*.py')):
        doc = ast.get_docstring(ast.parse(path.read_text())) or ''
        rows.append(f'| `{path.name}` | {_cell(_first_paragraph(doc))} |')
    return '\n'.join(rows)


def _modules(package: str) -> list[str]:
    module = importlib.import_module(package)
    names = [package]
    if hasattr(module, '__path__'):
        found = pkgutil.walk_packages(module.__path__, package + '.')
        names += sorted(info.name for info in found if not info.name.endswith('__main__'))
    return names


def api_reference() -> str:
    """An ``automodule`` per module, a section per layer."""
    out = ['## `cdpr_dynamics`\n', '```{eval-rst}', '.. automodule:: cdpr_dynamics', '```', '']
    for package, what in LAYERS:
        out.append(f'## `{package}`\n\n{what}\n')
        for name in _modules(package):
            out += [f'### `{name}`\n', '```{eval-rst}', f'.. automodule:: {name}',
                    '   :members:', '   :show-inheritance:', '```', '']
    return '\n'.join(out)


_TOCTREE = re.compile(r'```\{toctree\}\n(.*?)```', re.S)


def other_pages(text: str) -> str:
    """A toctree of the pages of ``doc/`` that the toctrees in ``text`` do not name."""
    named = {line.strip() for block in _TOCTREE.findall(text) for line in block.splitlines()
             if line.strip() and not line.startswith(':')}
    pages = sorted(str(p.relative_to(DOC).with_suffix('')) for suffix in ('*.md', '*.rst')
                   for p in DOC.rglob(suffix)
                   if p.relative_to(DOC).parts[0] not in ('_ext', 'benchmarks', '_build'))
    rest = [page for page in pages if page not in named | {'index'}]
    if not rest:
        return ''
    return '\n'.join(['```{toctree}', ':maxdepth: 1', ':caption: Topics', ''] + rest + ['```'])


def estimate_table() -> str:
    """The estimator's table from the committed ``doc/estimates/table.json``."""
    from cdpr_dynamics.cli import estimate_table as tool
    return tool.markdown(tool.read_json(DOC / 'estimates' / 'table.json'))


def generated(kind: str, text: str = '') -> str:
    """The Markdown for marker ``kind`` of a page whose source is ``text``."""
    from cdpr_dynamics.analysis import config
    makers = {
        'parameters': lambda: parameter_table(config.PARAMETERS),
        'node-parameters': lambda: parameter_table(config.NODE_PARAMETERS),
        'benchmarks': benchmark_tables,
        'tradeoff': tradeoff_tables,
        'estimates': estimate_table,
        'tests': test_list,
        'api': api_reference,
        'other-pages': lambda: other_pages(text),
    }
    if kind not in makers:
        raise ValueError(f'unknown generated part <!-- cdpr:{kind} -->')
    return makers[kind]()


def _source_read(app, docname, source):
    source[0] = MARKER.sub(lambda m: generated(m[1], source[0]), source[0])


_ROLE = re.compile(r':[\w:.-]+:`')


_SETTINGS = None


def rst_is_clean(text: str) -> bool:
    """Whether ``text`` parses as reStructuredText without a warning (Sphinx roles as literals)."""
    global _SETTINGS
    if _SETTINGS is None:
        _SETTINGS = get_default_settings(Parser)
        _SETTINGS.report_level = 2
        _SETTINGS.halt_level = 5
    stream = io.StringIO()
    _SETTINGS.warning_stream = stream
    document = new_document('<docstring>', _SETTINGS)
    try:
        Parser().parse(_ROLE.sub('`', text), document)
        document.transformer.add_transform(Substitutions)
        document.transformer.apply_transforms()
    except (SystemMessage, AttributeError):     # e.g. a Sphinx directive that needs its env
        return False
    return not stream.getvalue() and not any(document.findall(
        lambda node: node.tagname in ('system_message', 'problematic')))


def _process_docstring(app, what, name, obj, options, lines):
    """Keep a clean docstring; escape the bars of norms like ``|x|``; else show it verbatim."""
    text = '\n'.join(lines)
    if not lines or rst_is_clean(text):
        return
    escaped = text.replace('|', '\\|')
    if rst_is_clean(escaped):
        lines[:] = escaped.split('\n')
    else:
        lines[:] = ['::', ''] + ['   ' + line for line in lines] + ['']


def setup(app):
    """Register the hooks."""
    app.connect('source-read', _source_read)
    app.connect('autodoc-process-docstring', _process_docstring)
    return {'version': '1', 'parallel_read_safe': True, 'parallel_write_safe': True}
