"""The documentation site: Sphinx builds ``doc/`` with warnings as errors, every page is built,
and the generated parts say what the code and the committed data say."""
import ast
import html
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cdpr_dynamics.analysis.config import NODE_PARAMETERS, PARAMETERS

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / 'doc'
sys.path.insert(0, str(DOC / '_ext'))
import cdpr_docs  # noqa: E402  (the extension, from doc/_ext)

#: pages Sphinx writes besides the sources
SPECIAL = {'genindex', 'search', 'py-modindex'}


def source_pages() -> set[str]:
    """Every Markdown or reStructuredText page of the site, as Sphinx names it."""
    skip = ('_ext', 'benchmarks', '_build')
    return {str(p.relative_to(DOC).with_suffix('')) for suffix in ('*.md', '*.rst')
            for p in DOC.rglob(suffix) if not p.relative_to(DOC).parts[0] in skip}


@pytest.fixture(scope='module')
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp('site')
    run = subprocess.run([sys.executable, '-m', 'sphinx', '-W', '--keep-going', '-q', '-b',
                          'html', '-d', str(out / 'doctrees'), str(DOC), str(out / 'html')],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-6000:]
    assert run.stderr == '', run.stderr[-6000:]     # -W: no warning at all
    return out / 'html'


def built_pages(site: Path) -> set[str]:
    return {str(p.relative_to(site).with_suffix('')) for p in site.rglob('*.html')
            if not p.relative_to(site).parts[0].startswith('_')} - SPECIAL


def text_of(site: Path, page: str) -> str:
    page_html = (site / f'{page}.html').read_text()
    return html.unescape(re.sub(r'<[^>]+>', '', page_html))


@pytest.mark.slow
def test_every_page_is_built_and_linked(site):
    pages = source_pages()
    assert built_pages(site) == pages
    assert len(pages) >= 15
    index = (site / 'index.html').read_text()
    for page in pages - {'index'}:        # each page is in a toctree of the front page
        assert f'href="{page}.html' in index, page


@pytest.mark.slow
def test_every_parameter_is_in_the_generated_tables(site):
    text = (site / 'configuration.html').read_text()
    for param in PARAMETERS + NODE_PARAMETERS:
        assert re.search(rf'<span class="pre">{re.escape(param.name)}</span>', text), param.name


def test_parameter_table_rows():
    """One row per parameter, in the table's order, required ones marked, defaults shown."""
    rows = cdpr_docs.parameter_table(PARAMETERS).splitlines()[2:]
    assert len(rows) == len(PARAMETERS)
    for row, param in zip(rows, PARAMETERS):
        cells = [c.strip() for c in re.split(r'(?<!\\)\|', row)[1:-1]]
        assert cells[0] == f'`{param.name}`'
        assert (cells[1] == '**required**') == param.required, param.name
        if param.default not in (None, []):
            assert cells[1] == f'`{param.default}`', param.name
        if param.choices:
            assert cells[2] == ', '.join(param.choices)


@pytest.mark.slow
def test_benchmark_tables_show_the_committed_json(site):
    files = sorted((DOC / 'benchmarks').glob('*.json'))
    assert files, 'no cdpr_bench --json output committed in doc/benchmarks'
    text = text_of(site, 'benchmarks')
    for path in files:
        data = json.loads(path.read_text())
        assert path.name in text
        for key in data:
            if isinstance(data[key], (dict, list)):
                assert key in text, key
        warm = data['qp']['warm']          # one number, rendered as the table does
        assert f"{warm['p50_s'] * 1e3:.3g} / {warm['p99_s'] * 1e3:.3g}" in text


@pytest.mark.slow
def test_tradeoff_table_shows_the_committed_csv(site):
    text = text_of(site, 'tools/cdpr_tradeoff')
    csv_text = (DOC / 'benchmarks' / 'tradeoff_paper_cdpr.csv').read_text().splitlines()
    assert len(csv_text) > 10
    for line in csv_text[1:]:
        method, _, dofs, freq, frf, *_ = line.split(',')
        assert re.search(rf'{method}\s+\d+\s+{dofs}\s+{float(freq):.3g}\s+{float(frf):.3g}',
                         text), line


@pytest.mark.slow
def test_api_reference_documents_every_module(site):
    text = (site / 'api.html').read_text()
    for folder in ('cdpr_dynamics', 'msg_adapters'):
        for path in sorted((ROOT / folder).rglob('*.py')):
            name = '.'.join(path.relative_to(ROOT).with_suffix('').parts)
            name = name.removesuffix('.__init__')
            if name.endswith('__main__'):
                continue
            assert f'id="module-{name}"' in text, name


@pytest.mark.slow
def test_validation_lists_every_test_module(site):
    text = text_of(site, 'validation')
    for path in sorted((ROOT / 'test').glob('test_*.py')):
        assert path.name in text, path.name
        doc = ast.get_docstring(ast.parse(path.read_text())) or ''
        first = ' '.join(doc.split('\n\n')[0].split())
        assert first[:30].replace('``', '') in text.replace('\n', ' '), path.name


def test_a_docstring_that_is_not_clean_rst_is_shown_verbatim():
    assert cdpr_docs.rst_is_clean('The FRF of ``x`` per :func:`f`.')
    assert not cdpr_docs.rst_is_clean('The FRF |H| per newton.')     # an undefined substitution
    assert not cdpr_docs.rst_is_clean('a\n  b\n c')                    # unexpected unindent
    lines = ['Bad *emphasis', '', 'text']
    cdpr_docs._process_docstring(None, 'function', 'f', None, {}, lines)
    assert lines[:2] == ['::', ''] and lines[2] == '   Bad *emphasis'
    lines = ['The norm |x| of x.']
    cdpr_docs._process_docstring(None, 'function', 'f', None, {}, lines)
    assert lines == ['The norm \\|x\\| of x.']


def test_a_page_no_toctree_names_is_linked_from_the_front_page():
    index = (DOC / 'index.md').read_text()
    listed = cdpr_docs.other_pages(index).splitlines()[4:-1]
    named = cdpr_docs.other_pages('').splitlines()[4:-1]         # nothing named: every page
    assert set(named) == source_pages() - {'index'}
    assert 'getting_started' not in listed and set(listed) <= set(named)
    assert cdpr_docs.other_pages('```{toctree}\n:maxdepth: 1\n\n' + '\n'.join(named) + '\n```') \
        == ''
