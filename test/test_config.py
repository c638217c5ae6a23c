"""Strict configuration, hostile config files and clean Ctrl-C of the tools.

Library level: names, missing physical parameters, defaults of the numerical settings, node
keys, every hostile-file guard. Subprocess level: ``cdpr_analyze`` (and the other tools) and
``dynamics_node`` answer each mistake with the same single line and status 1; the node's key
matching and ``-p`` typing are checked against rclpy itself; SIGINT to a busy tool ends it
with one line and status 130.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdpr_dynamics.analysis.config import (MAX_CONFIG_BYTES, MAX_CONFIG_DEPTH, MAX_CONFIG_SCALARS,
                                           NODE_PARAMETERS, PARAMETER_BY_NAME, PARAMETERS,
                                           ConfigError, check_names, key_matches, load_settings,
                                           read_params_file, settings_from_params)
from cdpr_dynamics.analysis.pipeline import build_system, equilibrium
from cdpr_dynamics.dynamics.system import configured_damping, platform_frequencies
from cdpr_dynamics.ros.parameters import check_command_line as _check_command_line
from conftest import PAPER_CONFIG, REPO, cpu_seconds, installed, wait_until, write_config

RIGID_CONFIG = REPO / 'test' / 'data' / 'rigid_cdpr.yaml'
PHYSICAL = ('robot.anchors', 'robot.mass_kg', 'robot.initial_position', 'cable.area_m2',
            'cable.youngs_modulus_pa', 'cable.weight_per_length_n_per_m', 'tension.min_n',
            'tension.max_n')
NUMERICAL_SECTIONS = ('model', 'damping', 'frf', 'newmark')


def paper_text() -> str:
    return PAPER_CONFIG.read_text()


def write(tmp_path, text: str, name: str = 'bad.yaml') -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ------------------------------------------------------------------------- names and defaults


def test_shipped_configs_are_keyed_for_any_namespace():
    for path in sorted((REPO / 'config').glob('*.yaml')) + sorted(
            (REPO / 'test' / 'data').glob('*.yaml')):
        assert list(yaml.safe_load(path.read_text())) == ['/**'], path
        load_settings(path)


@pytest.mark.parametrize('typo,closest', [
    ('robot.mass_kgg', 'robot.mass_kg'), ('model.methd', 'model.method'),
    ('cable.youngs_modulus', 'cable.youngs_modulus_pa'), ('frf.npoints', 'frf.n_points'),
    ('node.frf_max_point', 'node.frf_max_points'), ('model.max_dof', 'model.max_dofs'),
])
def test_unknown_name_is_an_error_naming_the_closest(tmp_path, typo, closest):
    config = write_config(tmp_path, **{typo: 1})
    message = f'unknown parameter {typo} (did you mean {closest}?)'
    with pytest.raises(ConfigError) as err:
        load_settings(config)
    assert str(err.value) == message
    with pytest.raises(ConfigError) as err:
        check_names([typo])
    assert str(err.value) == message


@pytest.mark.parametrize('name', PHYSICAL)
def test_physical_description_has_no_defaults(tmp_path, name):
    with pytest.raises(ConfigError, match=f'^missing parameter {name}, .*has no defaults$'):
        load_settings(write_config(tmp_path, **{name: None}))


def test_inertia_is_required_for_a_rigid_platform_only(tmp_path):
    with pytest.raises(ConfigError, match='^missing parameter robot.inertia_kg_m2'):
        load_settings(write_config(tmp_path, base=RIGID_CONFIG,
                                   **{'robot.inertia_kg_m2': None}))
    point = load_settings(write_config(tmp_path, **{'robot.inertia_kg_m2': None,
                                                    'robot.attachments': None}))
    assert point.robot.point_mass and point.robot.n_cables == 8   # attachments out: point mass
    assert np.array_equal(point.robot.inertia_kg_m2, np.zeros((3, 3)))


def test_numerical_settings_keep_their_documented_defaults(tmp_path):
    """A robot that sets no numerical section gets light damping (a 2 % modal ratio, no
    Rayleigh factors of its own) and a unit FRF force; the paper's heavy damping and 1500 N
    load are in its file only, the sweep and Newmark settings are the paper's."""
    doc = yaml.safe_load(paper_text())
    params = doc['/**']['ros__parameters']
    for section in NUMERICAL_SECTIONS:
        del params[section]
    config = write(tmp_path, yaml.safe_dump(doc))
    s = load_settings(config)
    paper = load_settings(PAPER_CONFIG)
    for field in ('method', 'elements_per_cable', 'f_min_hz', 'f_max_hz', 'n_points',
                  'newmark_alpha', 'newmark_beta', 'dt_s'):
        assert getattr(s, field) == getattr(paper, field), field
    assert (s.damping_modal_ratio, s.damping_mass_factor, s.damping_stiffness_factor) == \
        (0.02, 0.0, 0.0)
    assert (paper.damping_modal_ratio, paper.damping_mass_factor,
            paper.damping_stiffness_factor) == (0.0, 0.05, 0.05)
    assert s.tolerance == 0.01
    assert np.array_equal(s.frf_force_n, [0.0, 0.0, 1.0])
    assert np.array_equal(paper.frf_force_n, [0.0, 0.0, 1500.0])
    assert s.max_dofs == 600
    for param in PARAMETERS + NODE_PARAMETERS:
        section = param.name.split('.')[0]
        assert param.required == (param.name in PHYSICAL + ('robot.inertia_kg_m2',)), param
        if section in NUMERICAL_SECTIONS + ('node',):
            assert param.default is not None, param


def test_max_dofs_range():
    assert PARAMETER_BY_NAME['model.max_dofs'].default == 600
    flat = read_params_file(PAPER_CONFIG)
    assert settings_from_params({**flat, 'model.max_dofs': 3}).max_dofs == 3
    for bad, words in ((2, r'outside \[3, 1e\+06\]'), (10 ** 6 + 1, 'outside'),
                       (12.5, 'must be an integer'), ('many', 'must be a number')):
        with pytest.raises(ConfigError, match=f'^model.max_dofs.*{words}'):
            settings_from_params({**flat, 'model.max_dofs': bad})
    with pytest.raises(ConfigError, match='model.max_dofs'):
        load_settings(PAPER_CONFIG).replace(max_dofs=1)


# ------------------------------------------------------------------------------ node keys


def test_node_key_that_matches_nothing_lists_the_keys(tmp_path):
    config = write(tmp_path, paper_text().replace('/**:', 'cdpr_dynamic:'))
    with pytest.raises(ConfigError) as err:
        load_settings(config)
    assert str(err.value) == (f'config {config} has no section for cdpr_dynamics (the node in '
                              f'any namespace); keys found: cdpr_dynamic; key it /**: or '
                              f'cdpr_dynamics:')


@pytest.mark.parametrize('key', ['/**', 'cdpr_dynamics', '/cdpr_dynamics',
                                 '/**/cdpr_dynamics', '/robot1/cdpr_dynamics', '/*'])
def test_tools_take_the_section_for_the_node_in_any_namespace(tmp_path, key):
    config = write(tmp_path, paper_text().replace('/**:', f'{key!r}:'))
    assert load_settings(config).robot.mass_kg == 30.0


def test_sections_merge_but_never_silently_override(tmp_path):
    common = textwrap.dedent('''\
        /**:
          ros__parameters:
            use_sim_time: false
        ''')
    merged = write(tmp_path, paper_text().replace('/**:', 'cdpr_dynamics:') + common)
    assert read_params_file(merged)['use_sim_time'] is False
    twice = write(tmp_path, paper_text() + '/cdpr_dynamics:\n  ros__parameters:\n'
                  '    robot:\n      mass_kg: 3.0\n')
    with pytest.raises(ConfigError, match=r"robot.mass_kg is set in both sections '/\*\*' and "
                                          r"'/cdpr_dynamics'$"):
        read_params_file(twice)
    same = write(tmp_path, paper_text().replace('/**:', 'cdpr_dynamics:')
                 + '/cdpr_dynamics:\n  ros__parameters:\n    model:\n      method: spring\n')
    with pytest.raises(ConfigError, match="sections 'cdpr_dynamics' and '/cdpr_dynamics' are "
                                          "the same node$"):
        read_params_file(same)
    dotted = write(tmp_path, paper_text().replace('    load:\n',
                                                  '    robot.mass_kg: 4.0\n    load:\n'))
    with pytest.raises(ConfigError, match='^parameter robot.mass_kg is given twice$'):
        read_params_file(dotted)


KEYS = ['/**', '/*', 'cdpr_dynamics', '/cdpr_dynamics', '/**/cdpr_dynamics',
        '/ns/cdpr_dynamics', '/*/cdpr_dynamics', '/ns/*', '/**/ns/cdpr_dynamics', '/ns/**',
        'ns/cdpr_dynamics', '/a/**/cdpr_dynamics', '/other/cdpr_dynamics', '/cdpr']
NAMESPACES = ['/', '/ns', '/a/ns']

RCLPY_PROBE = r'''
import json, sys, rclpy
from rclpy.node import Node
from cdpr_dynamics.ros.parameters import check_command_line as _check_command_line
keys, namespaces, rules, params = json.loads(sys.argv[1])
matches = {}
for ns in namespaces:
    for key in keys:
        with open(params, 'w') as f:
            f.write(f'"{key}":\n  ros__parameters:\n    use_sim_time: true\n')
        context = rclpy.Context()
        rclpy.init(args=['x', '--ros-args', '--params-file', params], context=context)
        node = Node('cdpr_dynamics', namespace=ns, context=context)
        matches[ns + ' ' + key] = 'use_sim_time' in node._parameter_overrides
        node.destroy_node()
        rclpy.shutdown(context=context)
typed = {}
for rule in rules:
    argv = ['x', '--ros-args', '--params-file', sys.argv[2], '-p', rule]
    context = rclpy.Context()
    rclpy.init(args=_check_command_line(argv)[1], context=context)
    node = Node('cdpr_dynamics', context=context)
    override = node._parameter_overrides[rule.split(':=')[0]]
    typed[rule] = [override.type_.name, list(override.value) if override.type_.name.endswith(
        'ARRAY') else override.value]
    node.destroy_node()
    rclpy.shutdown(context=context)
print(json.dumps([matches, typed]))
'''


def test_key_matching_and_p_typing_agree_with_rclpy(ros_env, tmp_path):
    """rclpy decides which params-file sections reach a node, and silently drops some ``-p``
    overrides whose type differs from the file's (``frf.n_points:=400.0``): compare."""
    rules = ['frf.n_points:=400.0', 'robot.mass_kg:=40', 'robot.initial_position:=[0, 1, 1]',
             'model.method:=spring', 'cable.youngs_modulus_pa:=2e11']
    run = subprocess.run([sys.executable, '-c', RCLPY_PROBE,
                          json.dumps([KEYS, NAMESPACES, rules, str(tmp_path / 'p.yaml')]),
                          str(PAPER_CONFIG)], env=ros_env, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    matches, typed = json.loads(run.stdout.strip().splitlines()[-1])
    for ns in NAMESPACES:
        for key in KEYS:
            assert key_matches(key, 'cdpr_dynamics', ns) == matches[f'{ns} {key}'], (ns, key)
    assert sum(matches.values()) >= 10      # the probe saw matches at all
    assert typed == {'frf.n_points:=400.0': ['INTEGER', 400],
                     'robot.mass_kg:=40': ['DOUBLE', 40.0],
                     'robot.initial_position:=[0, 1, 1]': ['DOUBLE_ARRAY', [0.0, 1.0, 1.0]],
                     'model.method:=spring': ['STRING', 'spring'],
                     'cable.youngs_modulus_pa:=2e11': ['DOUBLE', 2e11]}


def test_command_line_checks():
    assert _check_command_line(['x', '--help'])[0] and _check_command_line(['x', '-h'])[0]
    assert _check_command_line(['x', '--ros-args', '-r', '__ns:=/a', '--', '-h'])[0]
    help_asked, args = _check_command_line(['x', '--ros-args', '--params-file',
                                            str(PAPER_CONFIG), '-p', 'model.method:=spring'])
    assert not help_asked and args[-2:] == ['-p', 'model.method:=spring']
    for argv, message in (
            (['x', '--ros-args', '-p', 'model.methd:=spring'],
             'unknown parameter model.methd (did you mean model.method?)'),
            (['x', '--ros-args', '-p', 'robot.mass_kg:=heavy'],
             "robot.mass_kg must be a number, got 'heavy'"),
            (['x', '--bogus'], "unknown argument '--bogus' (see dynamics_node --help)")):
        with pytest.raises(ConfigError) as err:
            _check_command_line(argv)
        assert str(err.value) == message


# -------------------------------------------------------------------------- hostile files


def billion_laughs() -> str:
    lines = ['/**:', '  ros__parameters:', '    robot:',
             '      a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 10):
        lines.append(f'      a{i}: &a{i} [' + ', '.join([f'*a{i - 1}'] * 9) + ']')
    return '\n'.join(lines) + '\n'


def nested(depth: int) -> str:
    return ('/**:\n  ros__parameters:\n    robot:\n      anchors: ' + '[' * depth + '1.0'
            + ']' * depth + '\n')


def hostile_files(tmp_path) -> dict[str, tuple[Path, str]]:
    """name -> (file, the exact message after 'config FILE')."""
    files = {}

    def add(name, text, message):
        files[name] = (write(tmp_path, text, f'{name}.yaml'), message)
    add('alias_bomb', billion_laughs(), ': YAML anchors are not allowed (&a0) at line 4')
    add('alias', paper_text().replace('mass_kg: 30.0', 'mass_kg: *m'),
        ': YAML aliases are not allowed (*m) at line 21')
    add('depth_1000', nested(1000), ' is not valid YAML at line 4: exceeded maximum nesting '
        'depth')
    add('depth_20', nested(20), f': nesting deeper than {MAX_CONFIG_DEPTH} levels at line 4')
    add('duplicate_key', paper_text().replace('mass_kg: 30.0', 'mass_kg: 30.0\n'
                                              '      mass_kg: 3.0'),
        ": duplicate key 'mass_kg' at line 22 (first at line 21)")
    add('duplicate_section', paper_text() + '/**:\n  ros__parameters:\n    robot:\n'
        '      mass_kg: 3.0\n', f": duplicate key '/**' at line "
        f"{len(paper_text().splitlines()) + 1} (first at line 5)")
    add('many_values', '/**:\n  ros__parameters:\n    robot:\n      anchors: ['
        + ', '.join(['1.0'] * (3 * MAX_CONFIG_SCALARS)) + ']\n',
        f': more than {MAX_CONFIG_SCALARS} values at line 4')
    add('merge_key', '/**:\n  ros__parameters:\n    <<: {robot: {mass_kg: 1.0}}\n',
        ': merge keys (<<) are not allowed at line 3')
    big = tmp_path / 'big_100MB.yaml'
    with open(big, 'wb') as stream:            # sparse: instant to make, 100 MB long
        stream.write(paper_text().encode())
        stream.truncate(100 * 2 ** 20)
    files['big_100MB'] = (big, f' is {100 * 2 ** 20} bytes, more than the 1 MiB limit of a '
                          f'config file')
    latin = tmp_path / 'non_utf8.yaml'
    latin.write_bytes(paper_text().replace('frame_id: world', 'frame_id: w\xf6rld')
                      .encode('latin-1'))
    files['non_utf8'] = (latin, ' is not UTF-8: byte 0xf6 at line 8, column 18 (byte 396 of '
                         'the file)')
    return files


def test_hostile_files_get_one_line_reasons(tmp_path):
    for name, (path, message) in hostile_files(tmp_path).items():
        with pytest.raises(ConfigError) as err:
            load_settings(path)
        assert str(err.value) == f'config {path}{message}', name


def test_size_limit_holds_for_files_that_do_not_say_their_size(tmp_path):
    fifo = tmp_path / 'pipe.yaml'
    os.mkfifo(fifo)
    writer = subprocess.Popen(['sh', '-c', f'head -c {MAX_CONFIG_BYTES + 10} /dev/zero > {fifo}'])
    try:
        with pytest.raises(ConfigError, match='is more than the 1 MiB limit'):
            load_settings(fifo)
    finally:
        writer.kill()
        writer.wait()


def test_values_in_messages_are_cut_short(tmp_path):
    config = write_config(tmp_path, **{'model.method': 'x' * 100000})
    with pytest.raises(ConfigError) as err:
        load_settings(config)
    assert len(str(err.value)) < 200 and str(err.value).startswith('model.method must be one')


def one_line(run: subprocess.CompletedProcess, prog: str) -> str:
    assert run.returncode == 1, (run.returncode, run.stderr[-2000:])
    assert 'Traceback' not in run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'{prog}: error: '), lines
    return lines[0][len(f'{prog}: error: '):]


def node(ros_env, *args, timeout=60) -> subprocess.CompletedProcess:
    return subprocess.run([installed('dynamics_node'), *map(str, args)], env=ros_env,
                          capture_output=True, text=True, timeout=timeout)


def side_by_side(ros_env, tool_args, node_args):
    """``cdpr_analyze tool_args`` and ``dynamics_node node_args`` run at the same time; their
    CompletedProcess and wall times (s)."""
    commands = [[installed('cdpr_analyze'), *map(str, tool_args)],
                [installed('dynamics_node'), *map(str, node_args)]]
    start = time.monotonic()
    procs = [subprocess.Popen(c, env={**ros_env, 'OMP_NUM_THREADS': '1'}, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for c in commands]
    runs, seconds = [], []
    for command, proc in zip(commands, procs):
        out, err = proc.communicate(timeout=120)
        seconds.append(round(time.monotonic() - start, 2))
        runs.append(subprocess.CompletedProcess(command, proc.returncode, out, err))
    return runs, seconds


def test_hostile_files_in_the_node_and_cdpr_analyze(ros_env, tmp_path):
    timings = {}
    for name, (path, message) in hostile_files(tmp_path).items():
        (tool, ros_node), timings[name] = side_by_side(
            ros_env, ['--config', path], ['--ros-args', '--params-file', path])
        assert one_line(tool, 'cdpr_analyze') == f'config {path}{message}', name
        assert one_line(ros_node, 'dynamics_node') == f'config {path}{message}', name
    print('seconds to the answer (cdpr_analyze, dynamics_node, side by side):', timings)


@pytest.mark.slow
@pytest.mark.parametrize('tool', ['cdpr_tradeoff', 'cdpr_bench', 'cdpr_demo'])
def test_hostile_file_in_the_other_tools(tmp_path, tool):
    bomb = write(tmp_path, billion_laughs())
    args = ['--config', bomb] + (['--csv', tmp_path / 'a.csv', '--plot', tmp_path / 'a.png']
                                 if tool == 'cdpr_tradeoff' else [])
    run = subprocess.run([installed(tool), *map(str, args)], capture_output=True, text=True,
                         timeout=120)
    assert one_line(run, tool) == f'config {bomb}: YAML anchors are not allowed (&a0) at line 4'


# ----------------------------------------------------- the node and cdpr_analyze, same line


CONFIG_MISTAKES = {   # name -> (file text, -p rules, message)
    'mass_kgg': (lambda t: t.replace('mass_kg:', 'mass_kgg:'), [],
                 'unknown parameter robot.mass_kgg (did you mean robot.mass_kg?)'),
    'missing_mass': (lambda t: t.replace('      mass_kg: 30.0\n', ''), [],
                     "missing parameter robot.mass_kg, end-effector mass (kg): the robot's "
                     "physical description has no defaults"),
    'string_for_mass': (lambda t: t.replace('mass_kg: 30.0', 'mass_kg: heavy'), [],
                        "robot.mass_kg must be a number, got 'heavy'"),
    'array_for_mass': (lambda t: t.replace('mass_kg: 30.0', 'mass_kg: [30.0]'), [],
                       'robot.mass_kg must be a number, got [30.0]'),
    'out_of_range': (lambda t: t.replace('mass_kg: 30.0', 'mass_kg: -30.0'), [],
                     'robot.mass_kg = -30.0 is outside [1e-09, 1e+09]'),
    'p_methd': (lambda t: t, ['-p', 'model.methd:=spring'],
                'unknown parameter model.methd (did you mean model.method?)'),
    'p_string_for_mass': (lambda t: t, ['-p', 'robot.mass_kg:=heavy'],
                          "robot.mass_kg must be a number, got 'heavy'"),
}


@pytest.mark.parametrize('mistake', sorted(CONFIG_MISTAKES))
def test_config_mistakes_get_the_same_line_in_node_and_tool(ros_env, tmp_path, mistake):
    edit, rules, message = CONFIG_MISTAKES[mistake]
    config = write(tmp_path, edit(paper_text()))
    (tool, ros_node), _ = side_by_side(ros_env, ['--config', config],
                                       ['--ros-args', '--params-file', config, *rules])
    assert one_line(ros_node, 'dynamics_node') == message
    if not rules:
        assert one_line(tool, 'cdpr_analyze') == message


def test_wrong_node_key_in_the_node(ros_env, tmp_path):
    config = write(tmp_path, paper_text().replace('/**:', 'cdpr_dynamic:'))
    assert one_line(node(ros_env, '--ros-args', '--params-file', config), 'dynamics_node') == (
        f'config {config} has no section for cdpr_dynamics (node /cdpr_dynamics); keys found: '
        f'cdpr_dynamic; key it /**: or /cdpr_dynamics:')
    keyed = write(tmp_path, paper_text().replace('/**:', '/robot1/cdpr_dynamics:'), 'ns.yaml')
    assert one_line(node(ros_env, '--ros-args', '--params-file', keyed, '-r', '__ns:=/robot2'),
                    'dynamics_node') == (f'config {keyed} has no section for cdpr_dynamics '
                                         f'(node /robot2/cdpr_dynamics); keys found: '
                                         f'/robot1/cdpr_dynamics; key it /**: or '
                                         f'/robot2/cdpr_dynamics:')


def test_node_without_a_params_file_names_the_first_missing_parameter(ros_env):
    assert one_line(node(ros_env), 'dynamics_node').startswith(
        'missing parameter robot.anchors, ')


@pytest.mark.parametrize('flag', ['--help', '-h'])
def test_node_help(ros_env, flag):
    run = node(ros_env, flag)   # no params file: it must not try to build a robot
    assert run.returncode == 0 and run.stderr == ''
    assert run.stdout.startswith('usage: dynamics_node')
    for words in ('--params-file', 'paper_cdpr.yaml', "'/**:'", 'doc/configuration.md'):
        assert words in run.stdout, words


def test_shipped_config_works_in_a_namespace(ros_env, tmp_path):
    """The launch file's ``namespace:=`` is ``-r __ns:=``: the ``/**`` keyed paper config still
    reaches the node, with a ``-p`` override typed for rcl."""
    log = open(tmp_path / 'node.log', 'w+')
    proc = subprocess.Popen([installed('dynamics_node'), '--ros-args', '--params-file',
                             str(PAPER_CONFIG), '-r', '__ns:=/robot1', '-p',
                             'model.method:=spring'], env=ros_env, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)

    def up():
        text = (tmp_path / 'node.log').read_text()
        return text if 'waiting for pose' in text or proc.poll() is not None else ''
    try:
        text = wait_until(up, 60, 'the namespaced node to come up')
        assert '[robot1.cdpr_dynamics]: spring model, 3 DOFs' in text, text
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
        log.close()


# ---------------------------------------------------------------------------------- Ctrl-C


def interrupt_when_busy(command, env, busy):
    """Start ``command`` in a session of its own, wait until ``busy(proc, out_path)`` holds,
    send SIGINT to its process group (what Ctrl-C in a terminal does) and collect it.

    Returns the CompletedProcess and the pids of its child processes at the interrupt (some run
    in sessions of their own, e.g. cdpr_bench --dds's node: the tool must stop them itself)."""
    out_path = Path(env['ROS_LOG_DIR']) / 'stdout.txt'
    with open(out_path, 'w') as out:
        proc = subprocess.Popen([str(c) for c in command], env=env, stdout=out,
                                stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            wait_until(lambda: proc.poll() is not None or busy(proc, out_path), 120,
                       f'{command[0]} to get busy')
            assert proc.poll() is None, (proc.returncode, proc.stderr.read())
            kids = children(proc.pid)
            os.killpg(proc.pid, signal.SIGINT)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return (subprocess.CompletedProcess(command, proc.returncode, out_path.read_text(), err),
            [int(k) for k in kids])


def alive(pid: int) -> bool:
    """True while process ``pid`` runs (a zombie counts as gone)."""
    try:
        return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False


def described(pid: int) -> str:
    """``PID NAME: COMMAND LINE`` of a running process (which child outlived an interrupt)."""
    try:
        name = Path(f'/proc/{pid}/comm').read_text().strip()
        command = Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ').decode(
            errors='replace').strip()
    except OSError:
        return f'{pid} (gone)'
    return f'{pid} {name}: {command}'


def children(pid: int) -> list[str]:
    """Child processes of ``pid`` (cdpr_bench --dds: its dynamics_node is up)."""
    try:
        return Path(f'/proc/{pid}/task/{pid}/children').read_text().split()
    except OSError:
        return []


def computing(seconds: float):
    """Busy: more than ``seconds`` of CPU (imports and config reading take about 1 s)."""
    return lambda proc, out_path: cpu_seconds(proc.pid) > seconds


# Each run is long enough to be busy well after 2.5 s of CPU: cdpr_analyze 7 s, cdpr_tradeoff
# 10 s at --repeat 30 (3 s at its default), cdpr_bench 18 s in its full run (--quick: 2.6 s)
@pytest.mark.parametrize('tool,args,busy', [
    ('cdpr_analyze', ['--method', 'fem', '--elements', '48', '--duration', '60'],
     computing(2.5)),
    ('cdpr_tradeoff', ['--csv', 'out.csv', '--plot', 'out.png', '--repeat', '30'],
     computing(2.5)),
    ('cdpr_bench', [], computing(2.5)),
    ('cdpr_bench', ['--quick', '--dds'], lambda proc, out_path: children(proc.pid)),
    ('cdpr_demo', ['--output', 'demo.png', '--no-record', '--duration', '30'],
     lambda proc, out_path: 'node up' in out_path.read_text()),
], ids=['cdpr_analyze', 'cdpr_tradeoff', 'cdpr_bench', 'cdpr_bench_dds', 'cdpr_demo'])
def test_ctrl_c_ends_a_busy_tool_with_one_line(ros_env, tmp_path, tool, args, busy):
    env = {**ros_env, 'OMP_NUM_THREADS': '1'}
    args = [str(tmp_path / a) if a.startswith(('out.', 'demo.')) else a for a in args]
    run, kids = interrupt_when_busy([installed(tool), *args], env, busy)
    assert run.returncode == 130, (run.returncode, run.stderr[-3000:])
    assert 'Traceback' not in run.stderr
    assert run.stderr.strip().splitlines() == [f'{tool}: interrupted'], run.stderr[-3000:]
    # nothing left running: the children it had at the interrupt are stopped too
    try:
        try:
            wait_until(lambda: not any(alive(k) for k in kids), 15, f'{tool} children to stop')
        except AssertionError as timed_out:
            left = [described(k) for k in kids if alive(k)]
            raise AssertionError(f'{timed_out}; still running: {left}') from None
    finally:
        for k in kids:
            if alive(k):
                os.kill(k, signal.SIGKILL)


def entered(stderr_lines: list) -> bool:
    """True once the console script's entry has run: ``-X importtime`` prints an import's
    line when it completes, so a line after ``cdpr_dynamics.cli``'s (one of the tool module's
    own imports) means the entry installed its handler and began importing the tool."""
    names = [line.rsplit('|', 1)[-1].strip() for line in stderr_lines
             if line.startswith('import time:')]
    return 'cdpr_dynamics.cli' in names and names[-1] != 'cdpr_dynamics.cli'


@pytest.mark.parametrize('tool,args', [
    ('cdpr_analyze', ['--method', 'fem', '--elements', '48', '--duration', '60']),
    ('cdpr_tradeoff', ['--csv', 'out.csv', '--plot', 'out.png']),
])
@pytest.mark.parametrize('delay_s', [0.0, 0.1, 0.4, 1.0])
def test_ctrl_c_during_the_imports_ends_a_tool_with_one_line(ros_env, tmp_path, tool, args,
                                                             delay_s):
    """SIGINT at several delays after the entry began importing the tool (0: at once; the
    heavy imports take about a second): one line, status 130, no traceback."""
    env = {**ros_env, 'OMP_NUM_THREADS': '1', 'PYTHONPROFILEIMPORTTIME': '1'}
    args = [str(tmp_path / a) if a.startswith('out.') else a for a in args]
    proc = subprocess.Popen([installed(tool), *args], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    lines = []
    try:
        for line in proc.stderr:
            lines.append(line.rstrip('\n'))
            if entered(lines):
                break
        assert proc.poll() is None, lines[-5:]
        time.sleep(delay_s)            # a delay to land at different moments, not a wait
        os.killpg(proc.pid, signal.SIGINT)
        lines += proc.communicate(timeout=60)[1].splitlines()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    said = [line for line in lines if not line.startswith('import time:')]
    assert proc.returncode == 130, (proc.returncode, said[-20:])
    assert said == [f'{tool}: interrupted'], said[-20:]


def test_a_modal_ratio_beside_rayleigh_factors_is_a_one_line_error(tmp_path):
    """Both damping forms given (e.g. factors set on top of the default 2 % ratio) would let
    one silently win: it is an error that says how to choose."""
    with pytest.raises(ConfigError, match=r'^damping.modal_ratio = 0.02 and Rayleigh factors '
                                          r'both given: set damping.modal_ratio to 0') as err:
        load_settings(write_config(tmp_path, **{'damping.modal_ratio': 0.02,
                                                'damping.mass_factor': 0.0,
                                                'damping.stiffness_factor': 0.01}))
    assert '\n' not in str(err.value)
    paper = load_settings(PAPER_CONFIG)
    with pytest.raises(ConfigError, match='damping.modal_ratio = 0.03'):
        paper.replace(damping_modal_ratio=0.03)


def test_the_default_damping_is_two_percent_at_the_lowest_and_highest_platform_modes(tmp_path):
    """The default fits Rayleigh factors to zeta = 2 % at the lowest and highest platform mode
    of the band: zeta(w) = dM / (2 w) + dK w / 2 there, less in between."""
    s = load_settings(write_config(tmp_path, **{'damping.modal_ratio': None,
                                                'damping.mass_factor': None,
                                                'damping.stiffness_factor': None,
                                                'model.method': 'spring'}))
    system = build_system(s, equilibrium(s))
    damping = configured_damping(s, system)
    freqs = platform_frequencies(system)
    band = freqs[(freqs > 0) & (freqs <= s.f_max_hz)]
    w = 2 * np.pi * np.array([band[0], band[-1]])
    np.testing.assert_allclose(damping.mass_factor / (2 * w) + damping.stiffness_factor * w / 2,
                               0.02, rtol=1e-12)
    assert damping.mass_factor > 0 and damping.stiffness_factor > 0
