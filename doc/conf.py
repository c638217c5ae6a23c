"""Sphinx configuration of the cdpr_dynamics documentation (MyST Markdown pages).

Build: ``sphinx-build -W --keep-going -b html doc OUT`` in the project's venv (autodoc imports
the package and its ROS message modules). ``_ext/cdpr_docs.py`` writes the generated parts.
"""
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

DOC = Path(__file__).resolve().parent
sys.path.insert(0, str(DOC / '_ext'))
sys.path.insert(0, str(DOC.parent))

_package = ET.parse(DOC.parent / 'package.xml').getroot()
project = 'cdpr_dynamics'
author = 'cdpr_dynamics maintainers'
copyright = 'cdpr_dynamics maintainers, ' + _package.findtext('license')
release = version = _package.findtext('version')

extensions = ['myst_parser', 'sphinx.ext.autodoc', 'sphinx.ext.mathjax', 'cdpr_docs']
source_suffix = {'.md': 'markdown', '.rst': 'restructuredtext'}
root_doc = 'index'
smartquotes = False          # command lines keep their -- and quotes
exclude_patterns = ['_build', 'benchmarks', '_ext']
myst_enable_extensions = ['dollarmath']
myst_heading_anchors = 3

autodoc_member_order = 'bysource'
autodoc_typehints = 'signature'
autodoc_default_options = {'undoc-members': False}

html_theme = 'alabaster'
html_title = 'cdpr_dynamics'
html_theme_options = {'description': 'Live vibration prediction for cable-driven parallel robots',
                      'fixed_sidebar': True}
suppress_warnings = ['ref.python']   # builtin type names (bytes, type) that match attributes
suppress_warnings += ['myst.header']   # a topic page's heading levels are its own affair
