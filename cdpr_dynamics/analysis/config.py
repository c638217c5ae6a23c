"""Settings of a CDPR analysis: one table of parameters, read from ROS 2 YAML or a flat dict.

The parameter names are the ROS parameter names of doc/configuration.md (dotted, flat arrays where
ROS needs them). :data:`PARAMETERS` is the single source of names, defaults, units, ranges and
descriptions: the node declares its ROS parameters from it and the offline tools parse YAML
files through it, so both read the same file the same way.

Configuration is strict (doc/configuration.md): a name not in the table is an error naming the
closest known name; the robot's physical description (parameters whose default is ``None``) has no
defaults; numerical settings keep theirs. Files are read defensively (:func:`read_params_file`):
at most :data:`MAX_CONFIG_BYTES`, strict UTF-8, no YAML anchors or aliases, nesting at most
:data:`MAX_CONFIG_DEPTH`, at most :data:`MAX_CONFIG_SCALARS` values, no duplicate keys; every
problem is one line naming the cause.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from cdpr_dynamics.mechanics.robot import Robot, quaternion_to_matrix


class ConfigError(ValueError):
    """A configuration that cannot describe a robot; the message names the parameter."""


@dataclass(frozen=True)
class Param:
    """One parameter: default value, description and, for numbers, an allowed range.

    ``default=None`` marks the robot's physical description: no default, ``kind`` (float,
    int, str or list) gives the type; otherwise the type is the default's."""

    name: str
    default: object
    description: str
    low: float | None = None
    high: float | None = None
    length: int | None = None  # fixed array length; 0 = any multiple of 3
    choices: tuple[str, ...] = ()
    kind: type | None = None

    @property
    def value_type(self) -> type:
        """float, int, str or list."""
        if self.kind is not None:
            return self.kind
        return list if isinstance(self.default, list) else type(self.default)

    @property
    def required(self) -> bool:
        return self.default is None


METHODS = ('spring', 'fem', 'catenary', 'catenary_exact', 'fem_sag', 'dsm', 'auto')

PARAMETERS: tuple[Param, ...] = (
    Param('robot.frame_id', 'world', 'frame of anchors, poses and outputs (REP-103)'),
    Param('robot.anchors', None, 'anchor points a_i on the frame, x y z per cable (m)', length=0,
          kind=list),
    Param('robot.attachments', [], 'attachment points b_i in the platform frame, x y z per '
          'cable (m); all zero for a point-mass end-effector', length=0),
    Param('robot.mass_kg', None, 'end-effector mass (kg)', 1e-9, 1e9, kind=float),
    Param('robot.inertia_kg_m2', None, 'inertia about the centre of mass in the platform '
          'frame: Ixx Iyy Izz Ixy Ixz Iyz (kg m^2); required for a rigid platform', length=6,
          kind=list),
    Param('robot.center_of_mass_m', [0.0, 0.0, 0.0], 'centre of mass in the platform frame '
          '(m); the frame origin is the reference point of poses and outputs', length=3),
    Param('robot.pulley_axes', [], 'per cable the swivel axis k_i of its pulley, x y z, along '
          'the cable from the winch into the pulley; zero: a fixed eyelet (empty: no pulleys)',
          length=0),
    Param('robot.pulley_radii_m', [], 'per cable the pulley radius r_i (m); the anchor is then '
          'where the cable from the winch meets the groove (empty: no pulleys)', kind=list),
    Param('robot.gravity', [0.0, 0.0, -9.81], 'gravity vector in robot.frame_id (m/s^2)',
          length=3),
    Param('robot.initial_position', None, 'platform position of offline analyses and '
          'of the node before its first pose (m)', length=3, kind=list),
    Param('robot.initial_orientation', [0.0, 0.0, 0.0, 1.0], 'platform orientation qx qy qz qw',
          length=4),
    Param('load.external_force_n', [0.0, 0.0, 0.0], 'static external force on top of gravity '
          '(N)', length=3),
    Param('load.external_moment_nm', [0.0, 0.0, 0.0], 'static external moment about the '
          'centroid (N m)', length=3),
    Param('cable.area_m2', None, 'cable cross-section (m^2)', 1e-12, 1.0, kind=float),
    Param('cable.youngs_modulus_pa', None, "cable Young's modulus (Pa)", 1.0, 1e13, kind=float),
    Param('cable.weight_per_length_n_per_m', None, 'cable weight per unstrained length (N/m)',
          0.0, 1e6, kind=float),
    Param('cable.winch_side_lengths_m', [], 'per cable the length between drum and anchor (m), '
          'in series with the free span (empty: zero)', kind=list),
    Param('tension.min_n', None, 'lowest admissible cable tension (N)', 0.0, 1e9, kind=float),
    Param('tension.max_n', None, 'highest admissible cable tension (N)', 0.0, 1e9, kind=float),
    Param('model.method', 'fem', 'cable model: ' + ', '.join(METHODS), choices=METHODS),
    Param('model.elements_per_cable', 16, 'truss elements per cable (fem, fem_sag)', 1, 4096),
    Param('model.tolerance', 0.01, 'relative error allowed to method auto', 1e-9, 1.0),
    Param('model.max_dofs', 600, 'compute budget of method auto: the largest DOF count it may '
          'pick', 3, 1000000),
    Param('damping.mass_factor', 0.0, 'Rayleigh factor delta_M of C = dM M + dK K (1/s); '
          'used where damping.modal_ratio is 0', 0.0, 1e6),
    Param('damping.stiffness_factor', 0.0, 'Rayleigh factor delta_K of C = dM M + dK K (s); '
          'used where damping.modal_ratio is 0', 0.0, 1e3),
    Param('damping.modal_ratio', 0.02, 'modal damping ratio: Rayleigh factors fitted to it at '
          'the lowest and highest platform modes (2 %: light damping as of steel wire rope or '
          'fibre cables); 0 to give damping.mass_factor and damping.stiffness_factor instead',
          0.0, 10.0),
    Param('frf.f_min_hz', 1.0, 'lowest frequency of the sweep (Hz)', 0.0, 1e6),
    Param('frf.f_max_hz', 40.0, 'highest frequency of the sweep (Hz)', 1e-6, 1e6),
    Param('frf.n_points', 391, 'frequencies in the sweep', 1, 1000000),
    Param('frf.force_n', [0.0, 0.0, 1.0], 'harmonic force amplitude on the platform (N); a '
          'unit force gives the FRF per newton', length=3),
    Param('frf.moment_nm', [0.0, 0.0, 0.0], 'harmonic moment amplitude on the platform (N m)',
          length=3),
    Param('frf.point_m', [0.0, 0.0, 0.0], 'point whose FRF and time history are reported '
          '(m, platform frame; zero: the centroid)', length=3),
    Param('newmark.alpha', 0.5, 'Newmark alpha (gamma in most texts)', 0.0, 10.0),
    Param('newmark.beta', 0.25, 'Newmark beta', 0.0, 10.0),
    Param('newmark.dt_s', 0.001, 'Newmark time step (s)', 1e-9, 10.0),
)
PARAMETER_BY_NAME = {p.name: p for p in PARAMETERS}

#: Parameters of the node (and of cdpr_replay, which accepts inputs as the node does).
NODE_PARAMETERS: tuple[Param, ...] = (
    Param('node.pose_tolerance_m', 1e-4, 'a pose closer than this to the current one does not '
          'rebuild the model (m)', 0.0, 1.0),
    Param('node.angle_tolerance_rad', 1e-4, 'an orientation closer than this to the current one '
          'does not rebuild the model (rad)', 0.0, 3.2),
    Param('node.quaternion_tolerance', 1e-3, 'largest | |q| - 1 | accepted in a pose (then '
          'normalised)', 0.0, 0.5),
    Param('node.diagnostics_period_s', 1.0, 'period of /diagnostics when nothing changes (s); '
          'changes are published within 0.1 s', 0.1, 60.0),
    Param('node.wrench_queue_depth', 1000, 'depth of the best-effort wrench subscription: how '
          'many wrenches wait while the node is busy before the oldest are dropped', 1, 10000),
    Param('node.pose_queue_depth', 50, 'depth of the best-effort pose subscription: how many '
          'poses wait while the node is busy before the oldest are dropped (50: 1 s of a 50 Hz '
          'pose stream, as the wrench queue holds 1 s of 1 kHz wrenches)', 1, 10000),
    Param('node.rebuild', 'inline', 'where a moved pose is solved: inline (before the next '
          'wrench, as cdpr_replay does) or worker (the tensions and sag-consistent statics in a '
          'process of their own while the old model keeps predicting, then a swap)',
          choices=('inline', 'worker')),
    Param('node.frf_max_points', 20000, 'largest n_points a frequency_response call may ask '
          'for (the worker process computes it: a large one takes seconds)', 1, 1000000),
    Param('node.frf_cache_size', 8, 'frequency responses kept per state (0: no cache)',
          0, 1000),
    Param('node.service_introspection', 'contents', 'service events on '
          'frequency_response/_service_event: off, metadata or contents',
          choices=('off', 'metadata', 'contents')),
    Param('node.frf_max_values', 400000, 'largest frequency_response reply: distinct arrays '
          'asked for x points (8 bytes each); larger calls are refused with the numbers',
          1, 100000000),
    Param('node.frf_queue_depth', 100, 'frequency_response calls that may wait while one is '
          'computed (service QoS depth)', 1, 10000),
    Param('node.max_steps_per_wrench', 1000, 'most Newmark steps one wrench may cost; a longer '
          'interval steps the held wrench this often and skips the rest, keeping the state',
          1, 10000000),
    Param('node.max_stamp_ahead_s', 1.0, 'an input stamped further than this ahead of the '
          "node's clock is rejected (s)", 0.0, 1e9),
    Param('node.clock_jump_back_s', 1.0, 'an input older than the last one by more than this '
          'means its clock jumped back: the stream restarts with a warning; by less: out of '
          'order, rejected (s)', 0.0, 1e9),
    Param('node.zero_stamp', 'reject', 'unstamped inputs (stamp 0): reject, or time them by '
          'their arrival', choices=('reject', 'arrival')),
    Param('node.output_point_m', [0.0, 0.0, 0.0], 'point whose predicted displacement and '
          'pose are published (m, platform frame; zero: the centroid)', length=3),
    Param('node.slack', 'aware', 'where a cable would go slack: aware (the compression-free '
          'model of cdpr_analyze --slack-aware takes over until every cable is taut again) or '
          'linear (the linear prediction, a warning)', choices=('aware', 'linear')),
    Param('node.shaper', 'none', 'input shaper and notch filters published for the lowest '
          'platform modes after each rebuild: none, zv, zvd or ei',
          choices=('none', 'zv', 'zvd', 'ei')),
    Param('node.shaper_modes', 1, 'how many of the lowest platform modes the shaper '
          '(convolved) and the notch filters cover', 1, 6),
    Param('node.notch_sample_rate_hz', 1000.0, 'sample rate of the notch_filter biquads (Hz); '
          'a mode at or above half of it gets no notch', 1e-3, 1e9),
    Param('node.unique_name', 'warn', 'another node of this name and namespace in the graph: '
          'warn (both nodes), or refuse (a newcomer exits 1)', choices=('warn', 'refuse')),
    Param('node.marker_scale', 100.0, 'exaggeration of the predicted-displacement arrow of '
          'cdpr_markers (arrow length / displacement)', 0.0, 1e9),
)
NODE_PARAMETER_BY_NAME = {p.name: p for p in NODE_PARAMETERS}
#: Parameters every rclpy node has; a params file may set them.
ROS_NODE_PARAMETERS = ('use_sim_time', 'start_type_description_service')
KNOWN_NAMES = tuple(PARAMETER_BY_NAME) + tuple(NODE_PARAMETER_BY_NAME) + ROS_NODE_PARAMETERS


@dataclass(frozen=True)
class CableProperties:
    """Material of every cable: EA (N), weight per length gamma (N/m), mass per length (kg/m)."""

    area_m2: float
    youngs_modulus_pa: float
    weight_per_length_n_per_m: float
    g_m_s2: float

    @property
    def ea_n(self) -> float:
        return self.area_m2 * self.youngs_modulus_pa

    @property
    def mass_per_length_kg_m(self) -> float:
        """mu = gamma / g (kg/m), as in the paper's Eq. 17."""
        return self.weight_per_length_n_per_m / self.g_m_s2


@dataclass(frozen=True)
class Settings:
    """Everything an analysis needs, SI units; built by :func:`settings_from_params`."""

    robot: Robot
    cable: CableProperties
    initial_position_m: np.ndarray
    initial_rotation: np.ndarray          # 3x3
    external_force_n: np.ndarray
    external_moment_nm: np.ndarray
    tension_min_n: float
    tension_max_n: float
    method: str
    elements_per_cable: int
    tolerance: float
    max_dofs: int
    damping_mass_factor: float
    damping_stiffness_factor: float
    damping_modal_ratio: float
    f_min_hz: float
    f_max_hz: float
    n_points: int
    frf_force_n: np.ndarray
    newmark_alpha: float
    newmark_beta: float
    dt_s: float
    frf_moment_nm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    frf_point_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    @property
    def frequencies_hz(self) -> np.ndarray:
        return np.linspace(self.f_min_hz, self.f_max_hz, self.n_points)

    def replace(self, **changes) -> 'Settings':
        """A copy with some fields changed (e.g. ``method='spring'``), validated again."""
        new = dataclasses.replace(self, **changes)
        _check_settings(new)
        return new


def default_config_path() -> Path:
    """The installed ``share/cdpr_dynamics/config/paper_cdpr.yaml`` (or the source tree's)."""
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory('cdpr_dynamics')) / 'config')
    except Exception:  # no ament index (plain venv without AMENT_PREFIX_PATH): look on
        pass
    candidates.append(Path(sys.prefix) / 'share' / 'cdpr_dynamics' / 'config')
    here = Path(__file__).resolve()
    # installed as <prefix>/lib/pythonX.Y/site-packages/cdpr_dynamics/analysis/config.py (a colcon
    # workspace, /opt/ros, a venv): <prefix>/share, found without the ament index as well
    if here.parents[2].name == 'site-packages' and len(here.parents) > 5:
        candidates.append(here.parents[5] / 'share' / 'cdpr_dynamics' / 'config')
    candidates.append(here.parents[2] / 'config')     # the source tree
    for folder in candidates:
        if (folder / 'paper_cdpr.yaml').is_file():
            return folder / 'paper_cdpr.yaml'
    raise ConfigError('cannot find config/paper_cdpr.yaml: is cdpr_dynamics installed?')


#: Largest config file read (bytes): a robot of a few hundred cables fits in a few kB.
MAX_CONFIG_BYTES = 1 << 20
#: Deepest nesting of mappings and lists in a config file (a params file needs 5).
MAX_CONFIG_DEPTH = 16
#: Most scalars (keys and values) in a config file: a robot at the cable limit needs about 500;
#: the bound keeps any file within the byte limit to a fraction of a second of parsing.
MAX_CONFIG_SCALARS = 20000
_SHOWN_CHARS = 60

#: libyaml's parser where PyYAML has it (SafeLoader's semantics, 5x faster on a 1 MiB file).
_SafeBase = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)


def _shown(value, limit: int = _SHOWN_CHARS) -> str:
    """``repr(value)`` cut to ``limit`` characters, for one-line messages."""
    text = value if isinstance(value, str) else repr(value)
    return text if len(text) <= limit else text[:limit - 3] + '...'


class _Refused(yaml.YAMLError):
    """A YAML construct a config file may not use; ``line`` is 1-based."""

    def __init__(self, problem: str, line: int, note: str = ''):
        super().__init__(problem)
        self.text = f'{problem} at line {line}{note}'


class StrictLoader(_SafeBase):
    """A safe loader that refuses duplicate keys and merge keys (``<<``).

    Anchors, aliases and the nesting depth are checked on the event stream first
    (:func:`_check_events`), so nothing is composed from an alias bomb or a deep file."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, _ in node.value:
                line = key_node.start_mark.line + 1
                if key_node.tag == 'tag:yaml.org,2002:merge':
                    raise _Refused('merge keys (<<) are not allowed', line)
                key = self.construct_object(key_node, deep=True)
                try:
                    if key in seen:
                        raise _Refused(f'duplicate key {_shown(str(key))!r}', line,
                                       f' (first at line {seen[key]})')
                    seen[key] = line
                except TypeError:   # unhashable: the base class says so
                    pass
        return super().construct_mapping(node, deep)


def _check_events(text: str) -> None:
    """Refuse anchors, aliases, nesting deeper than MAX_CONFIG_DEPTH and more than
    MAX_CONFIG_SCALARS scalars (one pass over the events, nothing composed)."""
    loader = _SafeBase(text)
    depth = scalars = 0
    try:
        while loader.check_event():
            event = loader.get_event()
            line = event.start_mark.line + 1
            if isinstance(event, yaml.ScalarEvent):
                scalars += 1
                if scalars > MAX_CONFIG_SCALARS:
                    raise _Refused(f'more than {MAX_CONFIG_SCALARS} values', line)
            if isinstance(event, yaml.AliasEvent):
                raise _Refused(f'YAML aliases are not allowed (*{_shown(event.anchor)})', line)
            if getattr(event, 'anchor', None) is not None:
                raise _Refused(f'YAML anchors are not allowed (&{_shown(event.anchor)})', line)
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_CONFIG_DEPTH:
                    raise _Refused(f'nesting deeper than {MAX_CONFIG_DEPTH} levels', line)
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
    finally:
        loader.dispose()


def _read_text(path) -> str:
    """The file's text: at most MAX_CONFIG_BYTES, strict UTF-8 (a BOM is allowed)."""
    limit = f'the {MAX_CONFIG_BYTES >> 20} MiB limit of a config file'
    try:
        with open(path, 'rb') as stream:
            size = os.fstat(stream.fileno()).st_size
            if size > MAX_CONFIG_BYTES:
                raise ConfigError(f'config {path} is {size} bytes, more than {limit}')
            data = stream.read(MAX_CONFIG_BYTES + 1)   # bounded for pipes and devices too
    except OSError as exc:
        raise ConfigError(f'cannot read config {path}: {exc.strerror}') from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f'config {path} is more than {limit}')
    try:
        text = data.decode('utf-8')
    except UnicodeDecodeError as exc:
        line = data.count(b'\n', 0, exc.start) + 1
        column = exc.start - data.rfind(b'\n', 0, exc.start)
        raise ConfigError(f'config {path} is not UTF-8: byte 0x{data[exc.start]:02x} at line '
                          f'{line}, column {column} (byte {exc.start} of the file)') from None
    return text.removeprefix('\ufeff')


def load_yaml(path) -> object:
    """The YAML document of a config file, read as :func:`read_params_file` says."""
    text = _read_text(path)
    try:
        _check_events(text)
        return yaml.load(text, Loader=StrictLoader)
    except _Refused as exc:
        raise ConfigError(f'config {path}: {exc.text}') from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        where = f' at line {mark.line + 1}' if mark else ''
        problem = getattr(exc, 'problem', None) or str(exc)
        raise ConfigError(f'config {path} is not valid YAML{where}: '
                          f'{_shown(" ".join(str(problem).split()), 120)}') from None


def _flatten(tree: dict, prefix: str = '') -> dict:
    """``{'robot': {'mass_kg': 30}}`` -> ``{'robot.mass_kg': 30}`` (ROS's dotted names)."""
    flat = {}
    for key, value in tree.items():
        name = f'{prefix}{key}'
        items = _flatten(value, name + '.') if isinstance(value, dict) else {name: value}
        for dotted, item in items.items():
            if dotted in flat:
                raise ConfigError(f'parameter {_shown(dotted)} is given twice')
            flat[dotted] = item
    return flat


def key_matches(key: str, node_name: str, namespace: str | None = None) -> bool:
    """Whether a params-file node key applies to node ``namespace/node_name``, as rcl matches:
    ``*`` is one name token, ``**`` any number, a key without a leading ``/`` is absolute
    (``cdpr_dynamics`` = ``/cdpr_dynamics``). ``namespace=None``: any namespace (offline)."""
    pattern = [t for t in str(key).split('/') if t]
    if not pattern or len(pattern) > 64:
        return False
    if namespace is None:
        return pattern[-1] in (node_name, '*', '**')
    target = [t for t in namespace.split('/') if t] + [node_name]

    def match(p: int, t: int) -> bool:
        if p == len(pattern):
            return t == len(target)
        if pattern[p] == '**':
            return any(match(p + 1, u) for u in range(t, len(target) + 1))
        return t < len(target) and pattern[p] in ('*', target[t]) and match(p + 1, t + 1)
    return match(0, 0)


def read_params_file(path: str | os.PathLike, node_name: str = 'cdpr_dynamics',
                     namespace: str | None = None) -> dict:
    """Flat ``{dotted name: value}`` from a ROS 2 parameter YAML file.

    Takes the ``ros__parameters`` of every section whose key applies to the node
    (:func:`key_matches`: ``/**``, ``cdpr_dynamics``, ``/ns/cdpr_dynamics``, ...), in file order;
    a parameter set by two of them, two keys naming the same node, or no matching key at all
    (the message lists the keys found) is an error. Names are not checked here
    (:func:`check_names`). Raises :class:`ConfigError` with a one-line reason on any problem.
    """
    doc = load_yaml(path)
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(f'config {path} has no node sections: a ROS 2 params file maps node '
                          f'names (e.g. /**) to ros__parameters')
    fqn = node_name if namespace is None else f'{namespace.rstrip("/")}/{node_name}'
    where = 'the node in any namespace' if namespace is None else f'node {fqn}'
    sections = [key for key in doc if key_matches(key, node_name, namespace)]
    if not sections:
        found = ', '.join(_shown(str(k), 40) for k in list(doc)[:8])
        raise ConfigError(f'config {path} has no section for {node_name} ({where}); keys found: '
                          f'{found}; key it /**: or {fqn}:')
    flat, origin, spelled = {}, {}, {}
    for key in sections:
        canonical = '/' + '/'.join(t for t in str(key).split('/') if t)
        if canonical in spelled:
            raise ConfigError(f'config {path}: sections {spelled[canonical]!r} and {key!r} are '
                              f'the same node')
        spelled[canonical] = key
        section = doc[key]
        if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'),
                                                           dict):
            raise ConfigError(f'config {path}: section {_shown(str(key), 40)!r} lacks a '
                              f'ros__parameters mapping')
        extra = [k for k in section if k != 'ros__parameters']
        if extra:
            raise ConfigError(f'config {path}: section {_shown(str(key), 40)!r} has '
                              f'{_shown(str(extra[0]), 40)!r} beside ros__parameters')
        for name, value in _flatten(section['ros__parameters']).items():
            if name in flat:
                raise ConfigError(f'config {path}: {_shown(name)} is set in both sections '
                                  f'{origin[name]!r} and {key!r}')
            flat[name], origin[name] = value, key
    return flat


def check_names(names) -> None:
    """Every name is a parameter of the table (or one rclpy gives every node); otherwise a
    :class:`ConfigError` naming it and the closest known name."""
    for name in names:
        name = str(name)
        if name in PARAMETER_BY_NAME or name in NODE_PARAMETER_BY_NAME \
                or name in ROS_NODE_PARAMETERS or name.startswith('qos_overrides.'):
            continue
        closest = difflib.get_close_matches(name, KNOWN_NAMES, n=1, cutoff=0.0)
        raise ConfigError(f'unknown parameter {_shown(name)} (did you mean {closest[0]}?)')


def check_params(flat: dict) -> None:
    """The names and each given value of a (possibly partial) flat dict, as the tools read
    them; completeness is :func:`settings_from_params`'s."""
    check_names(flat)
    for name in flat:
        if name in PARAMETER_BY_NAME or name in NODE_PARAMETER_BY_NAME:
            _value(flat, name)


def _missing(name: str) -> ConfigError:
    param = PARAMETER_BY_NAME.get(name) or NODE_PARAMETER_BY_NAME[name]
    return ConfigError(f'missing parameter {name}, {param.description}: the robot\'s physical '
                       f'description has no defaults')


def check_value(name: str, value):
    """``value`` of parameter ``name`` validated and converted (float, int, str or a float
    array) as every tool and the node read it; :class:`ConfigError` with one line otherwise."""
    return _value({name: value}, name)


def _value(flat: dict, name: str):
    param = PARAMETER_BY_NAME.get(name) or NODE_PARAMETER_BY_NAME[name]
    if name not in flat and param.required:
        raise _missing(name)
    value = flat.get(name, param.default)
    kind = param.value_type
    if kind is list:
        if isinstance(value, (str, bytes, dict)):
            raise ConfigError(f'{name} must be a list of numbers, got {_shown(value)}')
        try:
            arr = np.asarray(value, dtype=float).reshape(-1)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f'{name} must be a list of numbers, got {_shown(value)}') from None
        if not np.all(np.isfinite(arr)):
            raise ConfigError(f'{name} has a value that is not finite')
        if param.length == 0 and arr.size % 3:
            raise ConfigError(f'{name} needs 3 values per cable, got {arr.size} values')
        if param.length and arr.size != param.length:
            raise ConfigError(f'{name} needs {param.length} values, got {arr.size}')
        return arr
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(f'{name} must be a string, got {_shown(value)}')
        if param.choices and value not in param.choices:
            raise ConfigError(f'{name} must be one of {", ".join(param.choices)}; got '
                              f'{_shown(repr(value))}')
        return value
    if isinstance(value, str):  # PyYAML reads 2.01e10 as a string; ROS reads it as a double
        try:
            value = float(value)
        except ValueError:
            raise ConfigError(f'{name} must be a number, got {_shown(repr(value))}') from None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise ConfigError(f'{name} must be a number, got {_shown(value)}')
    try:
        finite = math.isfinite(value)
    except OverflowError:   # an integer beyond any float
        finite = False
    if not finite:
        raise ConfigError(f'{name} must be finite, got {_shown(value)}')
    if kind is int and not float(value).is_integer():
        raise ConfigError(f'{name} must be an integer, got {_shown(value)}')
    value = int(value) if kind is int else float(value)
    if param.low is not None and not param.low <= value <= param.high:
        raise ConfigError(f'{name} = {value} is outside [{param.low:g}, {param.high:g}]')
    return value


#: Settings fields that are plain numbers -> the parameter whose range they obey.
FIELD_PARAMETERS = {
    'tension_min_n': 'tension.min_n', 'tension_max_n': 'tension.max_n',
    'elements_per_cable': 'model.elements_per_cable', 'tolerance': 'model.tolerance',
    'max_dofs': 'model.max_dofs',
    'damping_mass_factor': 'damping.mass_factor',
    'damping_stiffness_factor': 'damping.stiffness_factor',
    'damping_modal_ratio': 'damping.modal_ratio', 'f_min_hz': 'frf.f_min_hz',
    'f_max_hz': 'frf.f_max_hz', 'n_points': 'frf.n_points', 'newmark_alpha': 'newmark.alpha',
    'newmark_beta': 'newmark.beta', 'dt_s': 'newmark.dt_s',
}


def _check_settings(s: Settings) -> None:
    for field_name, name in FIELD_PARAMETERS.items():   # Settings.replace comes here too
        _value({name: getattr(s, field_name)}, name)
    if s.tension_min_n > s.tension_max_n:
        raise ConfigError(f'tension.min_n = {s.tension_min_n} exceeds tension.max_n = '
                          f'{s.tension_max_n}')
    if s.f_min_hz > s.f_max_hz:
        raise ConfigError(f'frf.f_min_hz = {s.f_min_hz} exceeds frf.f_max_hz = {s.f_max_hz}')
    rayleigh = s.damping_mass_factor > 0 or s.damping_stiffness_factor > 0
    if s.damping_modal_ratio > 0 and rayleigh:
        raise ConfigError(f'damping.modal_ratio = {s.damping_modal_ratio:g} and Rayleigh factors '
                          f'both given: set damping.modal_ratio to 0 to use '
                          f'damping.mass_factor and damping.stiffness_factor')
    if s.method not in METHODS:
        raise ConfigError(f'model.method must be one of {", ".join(METHODS)}; got {s.method!r}')
    if s.elements_per_cable < 1:
        raise ConfigError('model.elements_per_cable must be at least 1')


def settings_from_params(flat: dict) -> Settings:
    """Validated :class:`Settings` from flat dotted parameters.

    Strict (doc/configuration.md): an unknown name is an error (:func:`check_names`); the robot's
    physical description must be given (``robot.inertia_kg_m2`` only for a rigid platform);
    numerical settings missing take their defaults. Checked in table order."""
    check_names(flat)
    v = {p.name: None if p.name == 'robot.inertia_kg_m2' and p.name not in flat
         else _value(flat, p.name) for p in PARAMETERS}
    anchors = v['robot.anchors'].reshape(-1, 3)
    if anchors.shape[0] < 1:
        raise ConfigError('robot.anchors is empty: give 3 values per cable')
    attachments = v['robot.attachments']
    if attachments.size == 0:
        attachments = np.zeros_like(anchors)
    attachments = attachments.reshape(-1, 3)
    if attachments.shape != anchors.shape:
        raise ConfigError(f'robot.attachments has {attachments.shape[0]} points but '
                          f'robot.anchors has {anchors.shape[0]}')
    rigid = np.any(attachments) or np.any(v['robot.center_of_mass_m'])
    if v['robot.inertia_kg_m2'] is None:
        if rigid:
            raise _missing('robot.inertia_kg_m2')
        v['robot.inertia_kg_m2'] = np.zeros(6)     # a point mass has no rotational inertia
    ixx, iyy, izz, ixy, ixz, iyz = v['robot.inertia_kg_m2']
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    if rigid and np.any(np.linalg.eigvalsh(inertia) <= 0.0):
        raise ConfigError('robot.inertia_kg_m2 must be positive definite for a rigid platform '
                          '(robot.attachments or robot.center_of_mass_m not all zero)')
    gravity = v['robot.gravity']
    g = float(np.linalg.norm(gravity))
    if g <= 0.0 and v['cable.weight_per_length_n_per_m'] > 0.0:
        raise ConfigError('robot.gravity is zero but cables have weight: cannot get their mass')
    q = v['robot.initial_orientation']
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise ConfigError(f'robot.initial_orientation is not a unit quaternion (norm '
                          f'{np.linalg.norm(q):.4f})')
    robot = Robot(frame_id=v['robot.frame_id'], anchors_m=anchors, attachments_m=attachments,
                  mass_kg=v['robot.mass_kg'], inertia_kg_m2=inertia, gravity_m_s2=gravity,
                  **_real_robot(v, anchors.shape[0]))
    settings = Settings(
        robot=robot,
        cable=CableProperties(v['cable.area_m2'], v['cable.youngs_modulus_pa'],
                              v['cable.weight_per_length_n_per_m'], g if g > 0 else 9.81),
        initial_position_m=v['robot.initial_position'],
        initial_rotation=quaternion_to_matrix(q),
        external_force_n=v['load.external_force_n'],
        external_moment_nm=v['load.external_moment_nm'],
        tension_min_n=v['tension.min_n'], tension_max_n=v['tension.max_n'],
        method=v['model.method'], elements_per_cable=v['model.elements_per_cable'],
        tolerance=v['model.tolerance'], max_dofs=v['model.max_dofs'],
        damping_mass_factor=v['damping.mass_factor'],
        damping_stiffness_factor=v['damping.stiffness_factor'],
        damping_modal_ratio=v['damping.modal_ratio'],
        f_min_hz=v['frf.f_min_hz'], f_max_hz=v['frf.f_max_hz'], n_points=v['frf.n_points'],
        frf_force_n=v['frf.force_n'], frf_moment_nm=v['frf.moment_nm'],
        frf_point_m=v['frf.point_m'],
        newmark_alpha=v['newmark.alpha'], newmark_beta=v['newmark.beta'], dt_s=v['newmark.dt_s'],
    )
    _check_settings(settings)
    check_problem_size(settings)
    return settings


def _per_cable(v: dict, name: str, n: int, per: int = 1) -> np.ndarray:
    """``v[name]`` as (n, per) or (n,) (per = 1), zeros where empty; a count that does not
    match the cables is a :class:`ConfigError`."""
    values = v[name]
    if values.size == 0:
        values = np.zeros(n * per)
    if values.size != n * per:
        raise ConfigError(f'{name} has {values.size} values but robot.anchors has {n} cables '
                          f'({n * per} values)')
    return values.reshape(n, per) if per > 1 else values


def _real_robot(v: dict, n: int) -> dict:
    """The optional real-robot description as :class:`Robot` arguments."""
    axes = _per_cable(v, 'robot.pulley_axes', n, 3)
    radii = _per_cable(v, 'robot.pulley_radii_m', n)
    winch = _per_cable(v, 'cable.winch_side_lengths_m', n)
    for name, values in (('robot.pulley_radii_m', radii), ('cable.winch_side_lengths_m', winch)):
        if values.min(initial=0.0) < 0.0:
            raise ConfigError(f'{name} has a negative length: {values.min():g} m')
    eyelet = (radii > 0) & ~np.any(axes, axis=1)
    if eyelet.any():
        i = int(np.flatnonzero(eyelet)[0])
        raise ConfigError(f'robot.pulley_radii_m gives cable {i} a pulley of {radii[i]:g} m but '
                          f'robot.pulley_axes gives it no swivel axis (zero: an eyelet)')
    return {'pulley_axes': axes, 'pulley_radii_m': radii, 'winch_side_lengths_m': winch,
            'center_of_mass_m': v['robot.center_of_mass_m']}


def node_options(flat: dict) -> dict:
    """Validated ``node.*`` parameters (defaults where absent), keyed by full name."""
    return {p.name: _value(flat, p.name) for p in NODE_PARAMETERS}


def load_settings(path: str | os.PathLike | None = None) -> Settings:
    """Settings from a ROS 2 parameter file (default: the installed paper config)."""
    return settings_from_params(read_params_file(path or default_config_path()))


#: Largest problem the package takes on (node and tools): beyond these a config is refused up
#: front instead of hanging the tools (a 1000-cable fem config meant a 45 003-DOF eigen solve).
MAX_CABLES = 64
MAX_DOFS = 25000
_INTERIOR_METHODS = ('fem', 'fem_sag')   # models with interior cable DOFs


def model_dofs(settings: Settings, method: str | None = None,
               elements_per_cable: int | None = None) -> int:
    """DOFs of the model: platform (3 or 6) plus 3 (n - 1) per cable for fem and fem_sag."""
    method = settings.method if method is None else method
    n = settings.elements_per_cable if elements_per_cable is None else elements_per_cable
    robot = settings.robot
    interior = 3 * (n - 1) * robot.n_cables if method in _INTERIOR_METHODS else 0
    return robot.platform_dofs + interior


def check_problem_size(settings: Settings, method: str | None = None,
                       elements_per_cable: int | None = None) -> None:
    """Raise :class:`ConfigError` with the numbers when the robot has more than
    :data:`MAX_CABLES` cables or the configured model more than :data:`MAX_DOFS` DOFs."""
    cables = settings.robot.n_cables
    if cables > MAX_CABLES:
        raise ConfigError(f'robot.anchors describes {cables} cables, more than the {MAX_CABLES} '
                          f'this package handles (MAX_CABLES)')
    dofs = model_dofs(settings, method, elements_per_cable)
    if dofs > MAX_DOFS:
        method = settings.method if method is None else method
        n = settings.elements_per_cable if elements_per_cable is None else elements_per_cable
        raise ConfigError(f'model {method} with {n} elements on {cables} cables has {dofs} '
                          f'DOFs, more than the {MAX_DOFS} this package handles (MAX_DOFS); '
                          f'lower model.elements_per_cable to at most '
                          f'{(MAX_DOFS - settings.robot.platform_dofs) // (3 * cables) + 1}')
