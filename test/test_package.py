"""The package builds in a real Jazzy workspace: package.xml, setup.py, launch file, imports."""
import ast
import py_compile
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: import name -> rosdep key declared in package.xml
IMPORT_KEYS = {
    'rclpy': 'rclpy', 'geometry_msgs': 'geometry_msgs', 'sensor_msgs': 'sensor_msgs',
    'diagnostic_msgs': 'diagnostic_msgs', 'rcl_interfaces': 'rcl_interfaces',
    'builtin_interfaces': 'builtin_interfaces', 'std_msgs': 'std_msgs',
    'service_msgs': 'service_msgs', 'ament_index_python': 'ament_index_python',
    'rosidl_parser': 'rosidl_parser',
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm', 'mcap': 'python3-mcap-pip',
    'mcap_ros2': 'python3-mcap-ros2-support-pip', 'qpsolvers': 'python3-qpsolvers-pip',
    'proxsuite': 'proxsuite', 'launch': 'launch', 'launch_ros': 'launch_ros',
    'pytest': 'python3-pytest', 'rosbags': 'python3-rosbags-pip',
}
OWN = {'cdpr_dynamics', 'msg_adapters'}


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


def test_every_imported_module_is_declared():
    root = package_xml()
    run = {e.text for e in root.findall('exec_depend')} | {e.text for e in root.findall('depend')}
    test = {e.text for e in root.findall('test_depend')}
    for module in sorted(imported_modules(['cdpr_dynamics', 'msg_adapters', 'launch'])):
        assert module in IMPORT_KEYS, f'{module}: no rosdep key known; add it to IMPORT_KEYS'
        assert IMPORT_KEYS[module] in run, f'{module} ({IMPORT_KEYS[module]}) not exec_depend'
    for module in sorted(imported_modules(['test']) - {'setuptools'}):
        assert module in IMPORT_KEYS, f'{module}: no rosdep key known'
        assert IMPORT_KEYS[module] in run | test, f'{module} not declared for tests'


def test_setup_installs_the_share_folder_and_every_executable():
    text = (ROOT / 'setup.py').read_text()
    for data in ("'resource/' + package_name", "['package.xml']", "glob('config/*.yaml')",
                 "glob('launch/*.py')"):
        assert data in text
    scripts = set(re.findall(r"'(\w+) = (cdpr_dynamics[\w.]*):main'", text))
    names = {name for name, _ in scripts}
    assert {'dynamics_node', 'cdpr_analyze', 'cdpr_tradeoff', 'cdpr_record', 'cdpr_replay',
            'cdpr_demo', 'cdpr_bench'} <= names
    for _, module in scripts:     # each entry point's module exists and has main()
        source = ROOT / (module.replace('.', '/') + '.py')
        assert 'def main(' in source.read_text(), module
    assert (ROOT / 'resource' / 'cdpr_dynamics').exists()
    assert 'script_dir=$base/lib/cdpr_dynamics' in (ROOT / 'setup.cfg').read_text()


def test_launch_file_compiles(tmp_path):
    for path in (ROOT / 'launch').glob('*.py'):
        py_compile.compile(str(path), cfile=str(tmp_path / 'x.pyc'), doraise=True)
