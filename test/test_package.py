"""The package builds in a real Jazzy workspace: package.xml, setup.py, launch file, imports."""
import ast
import configparser
import importlib
import py_compile
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: import name -> rosdep key declared in package.xml
IMPORT_KEYS = {
    'rclpy': 'rclpy', 'geometry_msgs': 'geometry_msgs', 'sensor_msgs': 'sensor_msgs',
    'diagnostic_msgs': 'diagnostic_msgs', 'rcl_interfaces': 'rcl_interfaces',
    'builtin_interfaces': 'builtin_interfaces', 'std_msgs': 'std_msgs',
    'service_msgs': 'service_msgs', 'ament_index_python': 'ament_index_python',
    'rosidl_parser': 'rosidl_parser', 'visualization_msgs': 'visualization_msgs',
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'mpl_toolkits': 'python3-matplotlib',   # its 3D axes
    'tqdm': 'python3-tqdm',
    'mcap': 'mcap-ros2-support',        # no key of its own: a pip dependency of mcap-ros2-support
    'mcap_ros2': 'mcap-ros2-support', 'qpsolvers': 'python3-qpsolvers-pip',
    'proxsuite': 'proxsuite', 'launch': 'launch', 'launch_ros': 'launch_ros',
    'pytest': 'python3-pytest', 'rosbags': 'python3-rosbags-pip',
    'ament_flake8': 'ament_flake8', 'ament_pep257': 'ament_pep257',
}
OWN = {'cdpr_dynamics', 'msg_adapters', 'cdpr_docs'}   # cdpr_docs: doc/_ext, the docs' extension
#: modules with no rosdep key (rosdistro's rosdep/python.yaml has no rule for dask, distributed,
#: cloudpickle or pyarrow) -> the PyPI name to pip-install: not in package.xml (an undefined
#: key makes `rosdep install` fail), optional (imported where used: the workspace tool) and
#: documented. cloudpickle (imported by test_workspace) comes with dask[distributed].
PIP_ONLY = {'dask': 'dask[distributed]', 'distributed': 'dask[distributed]',
            'cloudpickle': 'dask[distributed]', 'pyarrow': 'pyarrow'}
#: every package.xml key -> how rosdep resolves it on Ubuntu 24.04 / Jazzy: 'ros' (a package
#: of jazzy/distribution.yaml, apt ros-jazzy-*), 'apt' or the PyPI name ('pip:NAME'), as
#: rosdistro's rosdep/python.yaml says (checked by hand; doc/getting_started.md lists the same)
ROSDEP = {
    'rclpy': 'ros', 'geometry_msgs': 'ros', 'sensor_msgs': 'ros', 'diagnostic_msgs': 'ros',
    'std_msgs': 'ros', 'rcl_interfaces': 'ros', 'builtin_interfaces': 'ros',
    'service_msgs': 'ros', 'ament_index_python': 'ros', 'rosidl_parser': 'ros',
    'launch': 'ros', 'launch_ros': 'ros', 'proxsuite': 'ros', 'ament_flake8': 'ros',
    'ament_pep257': 'ros', 'visualization_msgs': 'ros',
    'python3-numpy': 'apt', 'python3-scipy': 'apt', 'python3-yaml': 'apt',
    'python3-matplotlib': 'apt', 'python3-tqdm': 'apt', 'python3-pytest': 'apt',
    'mcap-ros2-support': 'pip:mcap-ros2-support', 'python3-qpsolvers-pip': 'pip:qpsolvers',
    'python3-rosbags-pip': 'pip:rosbags', 'python3-sphinx': 'apt', 'python3-myst-parser': 'apt',
}


def package_xml():
    return ET.parse(ROOT / 'package.xml').getroot()


def imported_modules(folders):
    names = set()
    for folder in folders:
        for path in (ROOT / folder).rglob('*.py'):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names |= {a.name.split('.')[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names.add(node.module.split('.')[0])
    local = {path.stem for folder in folders for path in (ROOT / folder).glob('*.py')}
    return names - OWN - local - set(sys.stdlib_module_names)


def test_package_xml_is_format_3_ament_python():
    root = package_xml()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'cdpr_dynamics'
    assert root.find('export/build_type').text == 'ament_python'


@pytest.mark.slow
def test_every_imported_module_is_declared():
    root = package_xml()
    run = {e.text for e in root.findall('exec_depend')} | {e.text for e in root.findall('depend')}
    test = {e.text for e in root.findall('test_depend')}
    for module in sorted(imported_modules(['cdpr_dynamics', 'msg_adapters', 'launch'])
                         - set(PIP_ONLY)):
        assert module in IMPORT_KEYS, f'{module}: no rosdep key known; add it to IMPORT_KEYS'
        assert IMPORT_KEYS[module] in run, f'{module} ({IMPORT_KEYS[module]}) not exec_depend'
    for module in sorted(imported_modules(['test']) - {'setuptools'} - set(PIP_ONLY)):
        assert module in IMPORT_KEYS, f'{module}: no rosdep key known'
        assert IMPORT_KEYS[module] in run | test, f'{module} not declared for tests'


def test_modules_without_a_rosdep_key_are_optional_and_documented():
    """A module with no rosdep rule is imported only inside the functions that use it (the
    package imports and runs without it), is in requirements.txt, and the colcon steps of
    doc/getting_started.md say how to pip-install it."""
    readme = (ROOT / 'doc' / 'getting_started.md').read_text()
    section = readme[readme.index('## Run it in a ROS 2 Jazzy workspace (colcon)'):]
    requirements = (ROOT / 'requirements.txt').read_text()
    for module, name in PIP_ONLY.items():
        assert re.search(rf'^{re.escape(name)}(?![\w\[-])', requirements, re.M), name
        assert re.search(rf'pip install [^\n]*{re.escape(name)}', section), name
    for folder in ('cdpr_dynamics', 'msg_adapters', 'launch'):
        for path in (ROOT / folder).rglob('*.py'):
            for node in ast.parse(path.read_text()).body:      # module level only
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ''] if isinstance(node, ast.ImportFrom) else [])
                for imported in names:
                    assert imported.split('.')[0] not in PIP_ONLY, (
                        f'{path.relative_to(ROOT)} imports {imported} at module level')


def test_setup_installs_the_share_folder_and_every_executable():
    text = (ROOT / 'setup.py').read_text()
    for data in ("'resource/' + package_name", "['package.xml']", "glob('config/*.yaml')",
                 "glob('launch/*.py')"):
        assert data in text
    scripts = set(re.findall(r"'(\w+) = (cdpr_dynamics[\w.]*):(\w+)'", text))
    names = {name for name, _, _ in scripts}
    assert {'dynamics_node', 'cdpr_analyze', 'cdpr_tradeoff', 'cdpr_record', 'cdpr_replay',
            'cdpr_demo', 'cdpr_bench'} <= names
    for name, module, attribute in scripts:   # each entry point exists; a tool's has main()
        entry = getattr(importlib.import_module(module), attribute)
        assert callable(entry), name
        tool = getattr(entry, 'module', module)
        source = ROOT / (tool.replace('.', '/') + '.py')
        assert 'def main(' in source.read_text(), (name, tool)
    assert (ROOT / 'resource' / 'cdpr_dynamics').exists()
    assert 'script_dir=$base/lib/cdpr_dynamics' in (ROOT / 'setup.cfg').read_text()


def test_launch_file_compiles(tmp_path):
    for path in (ROOT / 'launch').glob('*.py'):
        py_compile.compile(str(path), cfile=str(tmp_path / 'x.pyc'), doraise=True)


def test_every_key_resolves_and_the_readme_installs_the_pip_ones():
    """Each declared key is one whose rosdep rule was checked (no made-up ``-pip`` keys); the
    colcon steps of doc/getting_started.md skip exactly the pip keys in rosdep and pip-install
    their packages."""
    root = package_xml()
    declared = [e.text for tag in ('depend', 'exec_depend', 'test_depend', 'doc_depend')
                for e in root.findall(tag)]
    assert len(declared) == len(set(declared)), 'a key declared twice'
    assert set(declared) == set(ROSDEP), set(declared) ^ set(ROSDEP)
    pip_keys = {k: v.split(':', 1)[1] for k, v in ROSDEP.items() if v.startswith('pip:')}
    readme = (ROOT / 'doc' / 'getting_started.md').read_text()
    section = readme[readme.index('## Run it in a ROS 2 Jazzy workspace (colcon)'):]
    skipped = re.search(r'--skip-keys "([^"]+)"', section)
    assert skipped and set(skipped[1].split()) == set(pip_keys), skipped
    installed = re.search(r'\npip install ([^\n]+)', section)
    assert installed and set(installed[1].split()) == set(pip_keys.values()), installed
    requirements = (ROOT / 'requirements.txt').read_text()
    for name in pip_keys.values():
        assert re.search(rf'^{re.escape(name)}\b', requirements, re.M), name


def test_console_scripts_use_the_python_on_path():
    """setup.cfg gives the installed scripts ``#!/usr/bin/env python3`` (a venv's Python when
    active), and installs them where ``ros2 run`` looks (lib/cdpr_dynamics)."""
    config = configparser.ConfigParser()
    config.read(ROOT / 'setup.cfg')
    assert config['build_scripts']['executable'] == '/usr/bin/env python3'
    assert config['install']['install_scripts'] == '$base/lib/cdpr_dynamics'


def test_installed_share_holds_the_package_files():
    """The package's share directory found through the ament index (as the node, the tools and
    the launch file find it: a colcon install/, /opt/ros, or the venv of scripts/setup.sh) holds
    package.xml, every config and the launch file, the same as the source tree's."""
    from ament_index_python.packages import get_package_share_directory
    share = Path(get_package_share_directory('cdpr_dynamics'))
    files = ['package.xml'] + [str(p.relative_to(ROOT)) for p in sorted(ROOT.glob('config/*.yaml'))
                               + sorted(ROOT.glob('launch/*.py'))]
    assert len(files) >= 3
    for name in files:
        assert (share / name).is_file(), f'{name} not installed under {share}'
        assert (share / name).read_bytes() == (ROOT / name).read_bytes(), name
