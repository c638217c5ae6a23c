"""Settings of a CDPR analysis: one table of parameters, read from ROS 2 YAML or a flat dict.

The parameter names are the ROS parameter names of SPEC section 3 (dotted, flat arrays where
ROS needs them). :data:`PARAMETERS` is the single source of names, defaults, units, ranges and
descriptions: the node declares its ROS parameters from it and the offline tools parse YAML
files through it, so both read the same file the same way.
"""
from __future__ import annotations

import dataclasses
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from cdpr_dynamics.robot import Robot, quaternion_to_matrix


class ConfigError(ValueError):
    """A configuration that cannot describe a robot; the message names the parameter."""


@dataclass(frozen=True)
class Param:
    """One parameter: default value, description and, for numbers, an allowed range."""

    name: str
    default: object
    description: str
    low: float | None = None
    high: float | None = None
    length: int | None = None  # fixed array length; 0 = any multiple of 3
    choices: tuple[str, ...] = ()


METHODS = ('spring', 'fem', 'catenary', 'catenary_exact', 'fem_sag', 'dsm', 'auto')

PARAMETERS: tuple[Param, ...] = (
    Param('robot.frame_id', 'world', 'frame of anchors, poses and outputs (REP-103)'),
    Param('robot.anchors', [], 'anchor points a_i on the frame, x y z per cable (m)', length=0),
    Param('robot.attachments', [], 'attachment points b_i in the platform frame, x y z per '
          'cable (m); all zero for a point-mass end-effector', length=0),
    Param('robot.mass_kg', 30.0, 'end-effector mass (kg)', 1e-9, 1e9),
    Param('robot.inertia_kg_m2', [0.0] * 6, 'inertia about the centroid in the platform frame: '
          'Ixx Iyy Izz Ixy Ixz Iyz (kg m^2)', length=6),
    Param('robot.gravity', [0.0, 0.0, -9.81], 'gravity vector in robot.frame_id (m/s^2)',
          length=3),
    Param('robot.initial_position', [0.0, 0.0, 0.0], 'platform position of offline analyses and '
          'of the node before its first pose (m)', length=3),
    Param('robot.initial_orientation', [0.0, 0.0, 0.0, 1.0], 'platform orientation qx qy qz qw',
          length=4),
    Param('load.external_force_n', [0.0, 0.0, 0.0], 'static external force on top of gravity '
          '(N)', length=3),
    Param('load.external_moment_nm', [0.0, 0.0, 0.0], 'static external moment about the '
          'centroid (N m)', length=3),
    Param('cable.area_m2', 50.265e-6, 'cable cross-section (m^2)', 1e-12, 1.0),
    Param('cable.youngs_modulus_pa', 2.01e10, "cable Young's modulus (Pa)", 1.0, 1e13),
    Param('cable.weight_per_length_n_per_m', 0.251, 'cable weight per unstrained length (N/m)',
          0.0, 1e6),
    Param('tension.min_n', 100.0, 'lowest admissible cable tension (N)', 0.0, 1e9),
    Param('tension.max_n', 1000.0, 'highest admissible cable tension (N)', 0.0, 1e9),
    Param('model.method', 'fem', 'cable model: ' + ', '.join(METHODS), choices=METHODS),
    Param('model.elements_per_cable', 16, 'truss elements per cable (fem, fem_sag)', 1, 4096),
    Param('model.tolerance', 0.01, 'relative error allowed to method auto', 1e-9, 1.0),
    Param('damping.mass_factor', 0.05, 'Rayleigh factor delta_M of C = dM M + dK K (1/s)',
          0.0, 1e6),
    Param('damping.stiffness_factor', 0.05, 'Rayleigh factor delta_K of C = dM M + dK K (s)',
          0.0, 1e3),
    Param('damping.modal_ratio', 0.0, 'if > 0: Rayleigh factors fitted to this modal damping '
          'ratio at the lowest and highest platform modes, overriding the factors', 0.0, 10.0),
    Param('frf.f_min_hz', 1.0, 'lowest frequency of the sweep (Hz)', 0.0, 1e6),
    Param('frf.f_max_hz', 40.0, 'highest frequency of the sweep (Hz)', 1e-6, 1e6),
    Param('frf.n_points', 391, 'frequencies in the sweep', 1, 1000000),
    Param('frf.force_n', [0.0, 0.0, 1500.0], 'harmonic force amplitude on the platform (N)',
          length=3),
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
    Param('node.wrench_queue_depth', 50, 'depth of the best-effort wrench subscription: how '
          'many wrenches wait while the node is busy before the oldest are dropped', 1, 10000),
    Param('node.frf_max_points', 20000, 'largest n_points a frequency_response call may ask '
          'for (one call blocks the node for its duration)', 1, 1000000),
    Param('node.frf_cache_size', 8, 'frequency responses kept per state (0: no cache)',
          0, 1000),
    Param('node.service_introspection', 'contents', 'service events on '
          'frequency_response/_service_event: off, metadata or contents',
          choices=('off', 'metadata', 'contents')),
)
NODE_PARAMETER_BY_NAME = {p.name: p for p in NODE_PARAMETERS}
#: Parameters every rclpy node has; a params file may set them.
ROS_NODE_PARAMETERS = ('use_sim_time', 'start_type_description_service')


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
    candidates.append(Path(__file__).resolve().parent.parent / 'config')
    for folder in candidates:
        if (folder / 'paper_cdpr.yaml').is_file():
            return folder / 'paper_cdpr.yaml'
    raise ConfigError('cannot find config/paper_cdpr.yaml: is cdpr_dynamics installed?')


def _flatten(tree: dict, prefix: str = '') -> dict:
    flat = {}
    for key, value in tree.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            flat.update(_flatten(value, name + '.'))
        else:
            flat[name] = value
    return flat


def read_params_file(path: str | os.PathLike, node_name: str = 'cdpr_dynamics') -> dict:
    """Flat ``{dotted name: value}`` from a ROS 2 parameter YAML file.

    Takes the ``ros__parameters`` of ``node_name`` (or of ``/**``, or of the only node in the
    file). Raises :class:`ConfigError` with a one-line reason on any problem.
    """
    try:
        with open(path, encoding='utf-8') as stream:
            doc = yaml.safe_load(stream)
    except OSError as exc:
        raise ConfigError(f'cannot read config {path}: {exc.strerror}') from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        where = f' at line {mark.line + 1}' if mark else ''
        raise ConfigError(f'config {path} is not valid YAML{where}') from None
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(f'config {path} has no node section with ros__parameters')
    section = None
    for key in (node_name, '/' + node_name, '/**'):
        if key in doc:
            section = doc[key]
            break
    if section is None:
        if len(doc) != 1:
            raise ConfigError(f'config {path} has no section for node {node_name!r}')
        section = next(iter(doc.values()))
    if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'), dict):
        raise ConfigError(f'config {path}: node section lacks a ros__parameters mapping')
    return _flatten(section['ros__parameters'])


def _value(flat: dict, name: str):
    param = PARAMETER_BY_NAME.get(name) or NODE_PARAMETER_BY_NAME[name]
    value = flat.get(name, param.default)
    if isinstance(param.default, list):
        try:
            arr = np.asarray(value, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ConfigError(f'{name} must be a list of numbers, got {value!r}') from None
        if not np.all(np.isfinite(arr)):
            raise ConfigError(f'{name} has a value that is not finite')
        if param.length == 0 and arr.size % 3:
            raise ConfigError(f'{name} needs 3 values per cable, got {arr.size} values')
        if param.length and arr.size != param.length:
            raise ConfigError(f'{name} needs {param.length} values, got {arr.size}')
        return arr
    if isinstance(param.default, str):
        if not isinstance(value, str):
            raise ConfigError(f'{name} must be a string, got {value!r}')
        if param.choices and value not in param.choices:
            raise ConfigError(f'{name} must be one of {", ".join(param.choices)}; got {value!r}')
        return value
    if isinstance(value, str):  # PyYAML reads 2.01e10 as a string; ROS reads it as a double
        try:
            value = float(value)
        except ValueError:
            raise ConfigError(f'{name} must be a number, got {value!r}') from None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f'{name} must be a number, got {value!r}')
    if isinstance(param.default, int) and not float(value).is_integer():
        raise ConfigError(f'{name} must be an integer, got {value!r}')
    value = int(value) if isinstance(param.default, int) else float(value)
    if not math.isfinite(value):
        raise ConfigError(f'{name} must be finite, got {value!r}')
    if param.low is not None and not param.low <= value <= param.high:
        raise ConfigError(f'{name} = {value} is outside [{param.low:g}, {param.high:g}]')
    return value


#: Settings fields that are plain numbers -> the parameter whose range they obey.
FIELD_PARAMETERS = {
    'tension_min_n': 'tension.min_n', 'tension_max_n': 'tension.max_n',
    'elements_per_cable': 'model.elements_per_cable', 'tolerance': 'model.tolerance',
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
    if s.method not in METHODS:
        raise ConfigError(f'model.method must be one of {", ".join(METHODS)}; got {s.method!r}')
    if s.elements_per_cable < 1:
        raise ConfigError('model.elements_per_cable must be at least 1')


def settings_from_params(flat: dict) -> Settings:
    """Validated :class:`Settings` from flat dotted parameters (missing names take defaults)."""
    unknown = sorted(k for k in flat if k not in PARAMETER_BY_NAME
                     and k not in NODE_PARAMETER_BY_NAME and k not in ROS_NODE_PARAMETERS
                     and not k.startswith('qos_overrides.'))
    if unknown:
        raise ConfigError(f'unknown parameter {unknown[0]}')
    v = {p.name: _value(flat, p.name) for p in PARAMETERS}
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
    ixx, iyy, izz, ixy, ixz, iyz = v['robot.inertia_kg_m2']
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    if np.any(attachments) and np.any(np.linalg.eigvalsh(inertia) <= 0.0):
        raise ConfigError('robot.inertia_kg_m2 must be positive definite for a rigid platform '
                          '(robot.attachments not all zero)')
    gravity = v['robot.gravity']
    g = float(np.linalg.norm(gravity))
    if g <= 0.0 and v['cable.weight_per_length_n_per_m'] > 0.0:
        raise ConfigError('robot.gravity is zero but cables have weight: cannot get their mass')
    q = v['robot.initial_orientation']
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise ConfigError(f'robot.initial_orientation is not a unit quaternion (norm '
                          f'{np.linalg.norm(q):.4f})')
    robot = Robot(frame_id=v['robot.frame_id'], anchors_m=anchors, attachments_m=attachments,
                  mass_kg=v['robot.mass_kg'], inertia_kg_m2=inertia, gravity_m_s2=gravity)
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
        tolerance=v['model.tolerance'],
        damping_mass_factor=v['damping.mass_factor'],
        damping_stiffness_factor=v['damping.stiffness_factor'],
        damping_modal_ratio=v['damping.modal_ratio'],
        f_min_hz=v['frf.f_min_hz'], f_max_hz=v['frf.f_max_hz'], n_points=v['frf.n_points'],
        frf_force_n=v['frf.force_n'],
        newmark_alpha=v['newmark.alpha'], newmark_beta=v['newmark.beta'], dt_s=v['newmark.dt_s'],
    )
    _check_settings(settings)
    return settings


def node_options(flat: dict) -> dict:
    """Validated ``node.*`` parameters (defaults where absent), keyed by full name."""
    return {p.name: _value(flat, p.name) for p in NODE_PARAMETERS}


def load_settings(path: str | os.PathLike | None = None) -> Settings:
    """Settings from a ROS 2 parameter file (default: the installed paper config)."""
    return settings_from_params(read_params_file(path or default_config_path()))
