"""The node's parameters: the command line checked before rcl reads it, their declaration as
ROS parameters (descriptors from the one parameter table of
:mod:`cdpr_dynamics.analysis.config`), and a runtime change validated as a whole.

Strict as the tools: a name not in the table, or a value the tools refuse, is a one-line
:class:`ConfigError`; a value of another type (30 for 30.0, '2.01e10') is converted as the
tools convert it.
"""
from __future__ import annotations

import numpy as np
import yaml
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.parameter import Parameter

from cdpr_dynamics.analysis.config import (NODE_PARAMETERS, PARAMETER_BY_NAME, PARAMETERS,
                                           ROS_NODE_PARAMETERS, ConfigError, Param, check_names,
                                           check_params, check_value, node_options,
                                           read_params_file, settings_from_params)
from cdpr_dynamics.ros.rclpy_compat import parameter_overrides
from msg_adapters.inputs import first_line

NODE_NAME = 'cdpr_dynamics'
IO_SUFFIX = '_io'         # the companion node of pose and wrench: '<name>_io', same namespace

#: Fixed for the life of the node: the robot itself and what is set up once.
READ_ONLY = {'robot.frame_id', 'robot.anchors', 'robot.attachments', 'robot.initial_position',
             'robot.initial_orientation', 'node.diagnostics_period_s',
             'node.wrench_queue_depth', 'node.pose_queue_depth', 'node.service_introspection',
             # limits protect the node: a client must not raise them at runtime
             'node.frf_max_points', 'node.frf_max_values', 'node.frf_queue_depth',
             'node.frf_cache_size', 'node.max_steps_per_wrench', 'node.rebuild',
             'node.unique_name'}

_TYPE_ONLY = {float: Parameter.Type.DOUBLE, int: Parameter.Type.INTEGER,
              str: Parameter.Type.STRING, list: Parameter.Type.DOUBLE_ARRAY}


def descriptor(param: Param) -> ParameterDescriptor:
    """The ROS descriptor of a table entry: type, description, range, choices, read-only."""
    value_type = param.value_type
    if value_type is str:
        kind = ParameterType.PARAMETER_STRING
    elif value_type is list:
        kind = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif value_type is int:
        kind = ParameterType.PARAMETER_INTEGER
    else:
        kind = ParameterType.PARAMETER_DOUBLE
    described = ParameterDescriptor(name=param.name, type=kind, description=param.description,
                                    read_only=param.name in READ_ONLY)
    if param.choices:
        described.additional_constraints = 'one of: ' + ', '.join(param.choices)
    elif param.length:
        described.additional_constraints = f'{param.length} values'
    elif param.length == 0:
        described.additional_constraints = '3 values per cable'
    if param.low is not None and kind == ParameterType.PARAMETER_INTEGER:
        described.integer_range = [IntegerRange(from_value=int(param.low),
                                                to_value=int(param.high), step=0)]
    elif param.low is not None and kind == ParameterType.PARAMETER_DOUBLE:
        described.floating_point_range = [FloatingPointRange(
            from_value=float(param.low), to_value=float(param.high), step=0.0)]
    return described


def declare_parameters(node) -> dict:
    """Declare the table's parameters on ``node``; their values (flat, dotted) as the tools
    read them.

    A name given to the node (params file or ``-p``) that is not in the table is a
    :class:`ConfigError` naming the closest one; parameters without a default are declared by
    type only and left out of the result when not given, so :func:`settings_from_params`
    names the missing one."""
    check_names(parameter_overrides(node))
    flat = {}
    for param in PARAMETERS + NODE_PARAMETERS:
        described = descriptor(param)
        default = param.default
        if default is None or (isinstance(default, list) and not default):
            default = _TYPE_ONLY[param.value_type]   # no default: must come from the file
        try:
            value = node.declare_parameter(param.name, default, described).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            value = _declare_widened(node, param, described, exc)
        if value is not None:
            flat[param.name] = plain(value)
        elif param.default is not None:
            flat[param.name] = param.default
    return flat


def _declare_widened(node, param: Param, described, exc):
    """A value ROS refuses (another type: 30 for 30.0, '2.01e10'; out of range) converted and
    checked as the offline tools do (:func:`check_value`): declared with the converted value,
    or the tools' one-line reason; never rclpy's multi-line text."""
    override = parameter_overrides(node).get(param.name)
    if override is None:
        raise ConfigError(f'parameter {param.name}: {first_line(exc)}') from None
    value = check_value(param.name, plain(override.value))
    value = value.tolist() if isinstance(value, np.ndarray) else value
    try:
        return node.declare_parameter(param.name, value, described,
                                      ignore_override=True).value
    except (InvalidParameterTypeException, InvalidParameterValueException) as err:
        raise ConfigError(f'parameter {param.name}: {first_line(err)}') from None


def changed(flat: dict, params) -> tuple[dict, object, bool]:
    """(flat values, settings, analysis changed) after the runtime change ``params`` (those of
    this package), checked as a whole as the tools check a configuration; raises the tools'
    errors."""
    new = dict(flat)
    new.update({p.name: plain(p.value) for p in params})
    settings = settings_from_params(new)
    node_options(new)
    return new, settings, any(p.name in PARAMETER_BY_NAME for p in params)


def plain(value):
    """A parameter value as plain Python (array.array -> list)."""
    if hasattr(value, 'tolist') and not isinstance(value, (str, bytes)):
        return value.tolist()
    return list(value) if isinstance(value, (list, tuple)) else value


# ------------------------------------------------------------------------ the command line

def _ros_override(rule: str) -> str:
    """A ``-p NAME:=VALUE`` rule checked as the tools check a config (name, value) and written
    with the parameter's ROS type (``frf.n_points:=400.0`` -> ``400``, ``robot.mass_kg:=40`` ->
    ``40.0``): rcl silently drops some overrides whose type differs from the params file's."""
    name, sep, text = rule.partition(':=')
    if not sep or name in ROS_NODE_PARAMETERS or name.startswith('qos_overrides.'):
        return rule                      # rcl's own rules (and its one-line error)
    check_names([name])
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        raise ConfigError(f'-p {rule[:80]}: the value is not YAML') from None
    value = check_value(name, value)
    if isinstance(value, np.ndarray):
        return f'{name}:=[{", ".join(repr(float(x)) for x in value)}]'
    if isinstance(value, float):
        return f'{name}:={value!r}'
    return rule if isinstance(value, str) else f'{name}:={value}'


def check_command_line(argv) -> tuple[bool, list]:
    """(help asked, the arguments for rclpy). For ``-h``/``--help``: (True, argv). Otherwise
    every ``--params-file`` is read strictly, as the tools read a config (size, UTF-8,
    aliases, depth, duplicates, the node key for this node's name and namespace, names and
    values), and every ``-p`` rule checked and typed (:func:`_ros_override`), so a bad
    configuration gets the tools' one line before rcl parses it (:class:`ConfigError`).
    Arguments outside ``--ros-args`` are refused."""
    user, files, name, namespace, ros = [], [], NODE_NAME, '/', False
    out = list(argv[:1])
    args = iter(argv[1:])
    for arg in args:
        out.append(arg)
        if arg == '--ros-args':
            ros = True
        elif not ros or arg == '--':
            ros = False
            if arg != '--':
                user.append(arg)
        elif arg == '--params-file':
            files.append(next(args, None))
            out.append(files[-1])
        elif arg in ('-p', '--param'):
            rule = next(args, None)
            out.append(rule if rule is None else _ros_override(rule))
        elif arg in ('-r', '--remap'):
            out.append(next(args, ''))
            node, key, value = split_rule(out[-1])
            if node in ('', NODE_NAME) and key == '__ns':
                namespace = value
            elif node in ('', NODE_NAME) and key in ('__node', '__name'):
                name = value
        elif arg in ('-e', '--enclave', '--log-level', '--log-file-name', '--log-config-file'):
            out.append(next(args, None))
    if '-h' in user or '--help' in user:
        return True, list(argv)
    if user:
        raise ConfigError(f'unknown argument {user[0][:60]!r} (see dynamics_node --help)')
    for path in files:
        if path is None:
            raise ConfigError('--params-file needs a file name')
        check_params(read_params_file(path, name, namespace))
    return False, [a for a in out if a is not None]


def io_arguments(argv) -> list:
    """ROS arguments for the companion pose and wrench node: the remap rules of ``argv`` that
    concern it (global ones but a node rename, and those addressed to this node's name,
    without the name), in the same namespace; no parameters (it declares none)."""
    rules, args = [], iter(argv[1:])
    for arg in args:
        if arg in ('-r', '--remap'):
            rules.append(split_rule(next(args, '')))
    name = next((value for node, key, value in reversed(rules)
                 if node in ('', NODE_NAME) and key in ('__node', '__name')), NODE_NAME)
    out = []
    for node, key, value in rules:
        if key not in ('__node', '__name') and node in ('', NODE_NAME, name):
            out += ['-r', f'{key}:={value}']
    return ['--ros-args'] + out if out else []


def split_rule(rule: str) -> tuple[str, str, str]:
    """A remap rule ``[node:]key:=value`` as (node or '', key, value)."""
    target, _, value = rule.partition(':=')
    node, _, key = target.rpartition(':')
    return node, key, value
