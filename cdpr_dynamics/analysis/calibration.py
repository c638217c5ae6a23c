"""Fit parameters of the configuration table to measured natural frequencies (``fit``).

The model of a measured mode is a platform mode of the configured cable model at the table's
pose: eig(K, M) with K the platform stiffness with every cable DOF statically condensed
(:meth:`~cdpr_dynamics.dynamics.system.PlatformSystem.static_stiffness`) and M the platform's
mass matrix, the same modes ``damping.modal_ratio`` is fitted on. Measured and model modes
are paired per pose by :func:`pair_modes`. The residual of a pair is its relative frequency
error divided by its relative standard uncertainty; :func:`fit` minimises their squares with
bounds (scipy's trust-region reflective least squares).

The Jacobian takes each fitted parameter's finite difference of the assembled K and M (one
statics and assembly per pose and parameter, no eigensolve) into the eigenvalue sensitivity
d(lam)/dp = phi^T (dK/dp - lam dM/dp) phi (phi mass-normalised; for a repeated eigenvalue the
eigenvalues of the projected derivative). Parameter combinations the data cannot tell apart,
small singular values of the Jacobian in relative parameter changes, are named and left
unfitted. Damping parameters are fitted linearly to the measured damping ratios.
"""
from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import yaml
from scipy.optimize import least_squares, linear_sum_assignment, lsq_linear

from cdpr_dynamics.analysis.config import (PARAMETER_BY_NAME, ConfigError, Settings, check_names,
                                           check_value, key_matches, settings_from_params)
from cdpr_dynamics.analysis.modes_table import ModesTable
from cdpr_dynamics.analysis.pipeline import AnalysisError, build_system, equilibrium
from cdpr_dynamics.dynamics.system import rayleigh_from_modal_ratio
from cdpr_dynamics.mechanics.robot import quaternion_to_matrix
from cdpr_dynamics.selection.auto import choose_model

#: Damping parameters: fitted linearly to the measured damping ratios, not to frequencies.
DAMPING_PARAMETERS = ('damping.modal_ratio', 'damping.mass_factor', 'damping.stiffness_factor')
#: A combination whose singular value of the scaled Jacobian is below this times the largest
#: is called unidentifiable: its uncertainty is that many times the best-determined one's.
MIN_SINGULAR_RATIO = 1e-3
#: Vector parameters whose components cannot be negative (lengths).
NON_NEGATIVE = ('robot.pulley_radii_m', 'cable.winch_side_lengths_m')
#: Relative step of a parameter in the finite differences of K and M.
STEP = 1e-6
#: Residual of every mode where a trial parameter set makes no model (a refused pose or a
#: configuration error): the trust region shrinks away from it.
PENALTY = 1e3
#: Scale of a length parameter whose given value is zero (m): its relative changes are per
#: 10 cm.
ZERO_LENGTH_SCALE_M = 0.1
#: Parameters the statics (tensions, sag) do not depend on: a change of them reuses it.
STATICS_FREE = ('robot.inertia_kg_m2',)
#: Largest |ln(f_model / f_measured)| of a pair (a factor 1.28): a measured mode farther from
#: every model mode is left out of the fit and counted in the report.
MAX_PAIR_LOG = 0.25
#: Eigenvalues closer than this (relative) are one repeated eigenvalue in the sensitivities.
REPEATED = 1e-6
_TARGET = re.compile(r'([A-Za-z_][A-Za-z0-9_.]*)(?:\[(\d+|\*)\])?')
#: The index of a target that is one value shared by every component of a vector (``name[*]``).
SHARED = '*'


class CalibrationError(ValueError):
    """A fit that cannot be done (a bad target name, no usable pose); one line."""


@dataclass(frozen=True)
class Target:
    """One fitted number: parameter ``parameter``, component ``index`` (None: a scalar;
    :data:`SHARED`: one value for every component of a vector)."""

    parameter: str
    index: int | str | None

    @property
    def name(self) -> str:
        return self.parameter if self.index is None else f'{self.parameter}[{self.index}]'


def parse_targets(names, flat: dict) -> tuple[Target, ...]:
    """The numbers ``--fit`` names: whole parameters (every component of a vector), single
    components ``name[i]``, or one value shared by every component ``name[*]`` (the pulley
    radius of a robot whose pulleys are all alike); each a numeric parameter of the
    configuration table."""
    targets = []
    for text in names:
        match = _TARGET.fullmatch(str(text).strip())
        if not match:
            raise CalibrationError(f'--fit {text!r}: write a parameter name, name[i] for a '
                                   f'component, or name[*] for one value shared by all')
        name, index = match.group(1), match.group(2)
        check_names([name])
        param = PARAMETER_BY_NAME.get(name)
        if param is None or param.value_type not in (float, list):
            raise CalibrationError(f'--fit {name}: not a real-valued parameter of the robot '
                                   f'(only float and float-array parameters can be fitted)')
        value = current_value(flat, name)
        if param.value_type is float:
            if index is not None:
                raise CalibrationError(f'--fit {text}: {name} is a single number')
            found = [Target(name, None)]
        elif index is None:
            found = [Target(name, i) for i in range(value.size)]
        elif index == SHARED:
            if value.size == 0:
                raise CalibrationError(f'--fit {text}: {name} has no values')
            found = [Target(name, SHARED)]
        elif int(index) >= value.size:
            raise CalibrationError(f'--fit {text}: {name} has {value.size} values')
        else:
            found = [Target(name, int(index))]
        for target in found:
            if target in targets:
                raise CalibrationError(f'--fit names {target.name} twice')
            shared = {t.parameter for t in targets if t.index == SHARED}
            if target.parameter in shared or (target.index == SHARED and any(
                    t.parameter == target.parameter for t in targets)):
                raise CalibrationError(f'--fit names {target.parameter} both shared ([*]) and '
                                       'by component')
            targets.append(target)
    return tuple(targets)


def current_value(flat: dict, name: str):
    """The value of parameter ``name`` in ``flat`` (its default where absent), as read."""
    param = PARAMETER_BY_NAME[name]
    if name not in flat and param.required:
        if name == 'robot.inertia_kg_m2':
            raise CalibrationError('robot.inertia_kg_m2 is not given: a point-mass platform '
                                   'has no inertia to fit')
        raise CalibrationError(f'{name} is not given')
    value = check_value(name, flat.get(name, param.default))
    return np.array(value, dtype=float) if param.value_type is list else float(value)


def target_values(flat: dict, targets) -> np.ndarray:
    """The current values of ``targets`` in ``flat`` (a shared one: the components' mean)."""
    out = []
    for t in targets:
        value = current_value(flat, t.parameter)
        out.append(value if t.index is None else np.mean(value) if t.index == SHARED
                   else value[t.index])
    return np.array(out, dtype=float)


def with_values(flat: dict, targets, values) -> dict:
    """A copy of ``flat`` with ``targets`` set to ``values``."""
    out = dict(flat)
    arrays = {}
    for target, value in zip(targets, values):
        if target.index is None:
            out[target.parameter] = float(value)
            continue
        if target.parameter not in arrays:
            arrays[target.parameter] = current_value(flat, target.parameter).copy()
        if target.index == SHARED:
            arrays[target.parameter][:] = value
        else:
            arrays[target.parameter][target.index] = value
    out.update({name: array.tolist() for name, array in arrays.items()})
    return out


def _scale(flat: dict, target: Target, value: float) -> float:
    """The size of a relative change of ``target``: |value|, else a typical size."""
    if value != 0.0:
        return abs(value)
    if target.index is not None and target.index != SHARED:
        whole = np.abs(current_value(flat, target.parameter))
        if whole.max() > 0:
            return float(whole.max())
    return ZERO_LENGTH_SCALE_M if target.parameter.endswith('_m') else 1.0


def _bounds(target: Target) -> tuple[float, float]:
    """Bounds of a fitted number: the table's range; a positive inertia diagonal; pulley
    radii and winch-side lengths not negative."""
    param = PARAMETER_BY_NAME[target.parameter]
    if target.parameter == 'robot.inertia_kg_m2' and target.index in (0, 1, 2):
        return 0.0, np.inf
    if target.parameter in NON_NEGATIVE:
        return 0.0, np.inf
    if param.low is not None:
        return param.low, param.high
    return -np.inf, np.inf


# --------------------------------------------------------------------------- the model

@dataclass(frozen=True)
class PoseModel:
    """The platform modes at one pose: K, M (ndof, ndof), lam (ndof,), phi mass-normalised."""

    stiffness: np.ndarray
    mass: np.ndarray
    eigenvalues: np.ndarray
    shapes: np.ndarray

    @property
    def frequency_hz(self) -> np.ndarray:
        return np.sqrt(np.clip(self.eigenvalues, 0.0, None)) / (2.0 * np.pi)


def pose_rotation(pose) -> np.ndarray:
    return quaternion_to_matrix(np.asarray(pose, dtype=float)[3:7])


def pose_matrices(settings: Settings, pose, method: tuple | None = None, eq=None):
    """(K, M, statics) of the platform at ``pose`` (x y z qx qy qz qw): the statics (``eq``
    where given), the cable model ``method`` = (name, elements) (default the configured one),
    every cable DOF condensed."""
    pose = np.asarray(pose, dtype=float)
    name, elements = method or (settings.method, settings.elements_per_cable)
    if eq is None:
        eq = equilibrium(settings, pose[:3], pose_rotation(pose), method=name)
    system = build_system(settings, eq, name, elements)
    return system.static_stiffness(), system.platform_mass, eq


def pose_model(settings: Settings, pose, method: tuple | None = None) -> PoseModel:
    """The platform modes at ``pose`` (:func:`pose_matrices`)."""
    k, m, _ = pose_matrices(settings, pose, method)
    lam, phi = scipy.linalg.eigh(k, m)
    return PoseModel(k, m, lam, phi)


def resolved_method(settings: Settings, pose) -> tuple[str, int]:
    """The cable model of ``pose``: the configured one, or the one ``auto`` picks there (kept
    through the fit, so the model does not switch between steps)."""
    if settings.method != 'auto':
        return settings.method, settings.elements_per_cable
    pose = np.asarray(pose, dtype=float)
    eq = equilibrium(settings, pose[:3], pose_rotation(pose))
    choice = choose_model(settings, eq)
    return choice.method, choice.elements_per_cable


def eigenvalue_derivatives(model: PoseModel, d_stiffness, d_mass) -> np.ndarray:
    """d(lam)/dp of every mode from dK/dp, dM/dp: phi^T (dK - lam dM) phi; a repeated
    eigenvalue takes the ascending eigenvalues of its modes' projected derivative."""
    lam, phi = model.eigenvalues, model.shapes
    out = np.einsum('ij,ik,kj->j', phi, d_stiffness, phi) - \
        lam * np.einsum('ij,ik,kj->j', phi, d_mass, phi)
    start = 0
    while start < lam.size:
        end = start + 1
        while end < lam.size and lam[end] - lam[start] <= REPEATED * abs(lam[end]):
            end += 1
        if end - start > 1:
            group = phi[:, start:end]
            mean = lam[start:end].mean()
            projected = group.T @ (d_stiffness - mean * d_mass) @ group
            out[start:end] = np.linalg.eigvalsh(0.5 * (projected + projected.T))
        start = end
    return out


def _mac(a: np.ndarray, b: np.ndarray) -> float:
    """Modal assurance criterion |a.b|^2 / (|a|^2 |b|^2) (0 where either is zero)."""
    den = float(a @ a) * float(b @ b)
    return float(a @ b) ** 2 / den if den > 0 else 0.0


def pair_modes(model_hz, model_shapes, measured_hz, directions) -> np.ndarray:
    """For each measured mode of a pose the index of its model mode (-1: none left).

    Cost of a pair: |ln(f_model / f_measured)| plus, where the measured direction is known
    (``directions`` (m, 6), NaN where not), 1 - MAC of the direction and the model mode's
    platform DOFs; the assignment of least total cost (linear_sum_assignment). A pair farther
    apart than :data:`MAX_PAIR_LOG` is none (a cable mode in the table, say)."""
    model_hz = np.asarray(model_hz, dtype=float)
    measured_hz = np.asarray(measured_hz, dtype=float)
    ndof = model_shapes.shape[0]
    cost = np.abs(np.log(np.maximum(model_hz[None, :], 1e-12) / measured_hz[:, None]))
    for i, direction in enumerate(np.asarray(directions, dtype=float)[:, :ndof]):
        known = np.isfinite(direction)
        if known.any() and np.any(direction[known]):
            cost[i] += [1.0 - _mac(direction[known], model_shapes[known, j])
                        for j in range(model_hz.size)]
    rows, cols = linear_sum_assignment(cost)
    out = np.full(measured_hz.size, -1)
    near = np.abs(np.log(np.maximum(model_hz[cols], 1e-12) / measured_hz[rows])) <= MAX_PAIR_LOG
    out[rows[near]] = cols[near]
    return out


# --------------------------------------------------------------------------- the problem

@dataclass
class _State:
    """The model at one parameter vector: settings, per pose its model (None: refused)."""

    x: np.ndarray
    settings: Settings | None
    models: list
    pairs: list
    residuals: np.ndarray
    predicted_hz: np.ndarray


class FitProblem:
    """Residuals and Jacobian of the frequencies of ``rows`` of ``table`` over ``targets``."""

    def __init__(self, flat: dict, targets, table: ModesTable, pose_ids, methods: dict):
        self.flat, self.targets, self.table = flat, tuple(targets), table
        self.pose_ids = list(pose_ids)
        self.methods = methods
        self.rows = [table.rows_of(pid) for pid in self.pose_ids]
        self.p0 = target_values(flat, self.targets)
        self.scale = np.array([_scale(flat, t, v) for t, v in zip(self.targets, self.p0)])
        self.sigma = relative_sigma(table)
        self._last: _State | None = None
        self._statics: dict = {}
        self.evaluations = 0

    @property
    def n_residuals(self) -> int:
        return int(sum(r.size for r in self.rows))

    def parameters(self, x) -> np.ndarray:
        return np.asarray(x, dtype=float) * self.scale

    def settings(self, x) -> Settings:
        return settings_from_params(with_values(self.flat, self.targets, self.parameters(x)))

    def matrices(self, settings: Settings, x, pose_index: int):
        """(K, M) at pose ``pose_index``; the statics are shared by parameter sets that differ
        only in :data:`STATICS_FREE` parameters (the last few kept)."""
        key = tuple(float(v) for t, v in zip(self.targets, x) if t.parameter not in STATICS_FREE)
        cached = self._statics.setdefault(key, {})
        if len(self._statics) > 4:
            del self._statics[next(iter(self._statics))]
        pid = self.pose_ids[pose_index]
        k, m, eq = pose_matrices(settings, self.table.pose[self.rows[pose_index][0]],
                                 self.methods[pid], cached.get(pid))
        cached[pid] = eq
        return k, m

    def state(self, x) -> _State:
        x = np.asarray(x, dtype=float)
        if self._last is not None and np.array_equal(self._last.x, x):
            return self._last
        self.evaluations += 1
        try:
            settings = self.settings(x)
        except (ConfigError, ValueError):
            settings = None
        models, pairs, res, pred = [], [], [], []
        for index, rows in enumerate(self.rows):
            model = None
            if settings is not None:
                try:
                    k, m = self.matrices(settings, x, index)
                    model = PoseModel(k, m, *scipy.linalg.eigh(k, m))
                except (AnalysisError, ValueError, np.linalg.LinAlgError):
                    model = None
            models.append(model)
            if model is None:
                pairs.append(np.full(rows.size, -1))
                res.append(np.full(rows.size, PENALTY))
                pred.append(np.full(rows.size, np.nan))
                continue
            pair = pair_modes(model.frequency_hz, model.shapes, self.table.frequency_hz[rows],
                              self.table.direction[rows])
            pairs.append(pair)
            f = np.where(pair >= 0, model.frequency_hz[np.maximum(pair, 0)], np.nan)
            pred.append(f)
            r = (f / self.table.frequency_hz[rows] - 1.0) / self.sigma[rows]
            res.append(np.where(pair >= 0, r, 0.0))
        self._last = _State(x.copy(), settings, models, pairs, np.concatenate(res),
                            np.concatenate(pred))
        return self._last

    def residuals(self, x) -> np.ndarray:
        return self.state(x).residuals

    def jacobian(self, x) -> np.ndarray:
        """d(residuals)/dx (x: parameters over their scale) by eigenvalue sensitivities."""
        state = self.state(x)
        jac = np.zeros((self.n_residuals, len(self.targets)))
        if state.settings is None:
            return jac
        for k in range(len(self.targets)):
            bound = _bounds(self.targets[k])
            step = STEP * max(abs(x[k]), 1.0)
            if (x[k] + step) * self.scale[k] > bound[1]:
                step = -step
            xk = np.array(x, dtype=float)
            xk[k] += step
            try:
                settings = self.settings(xk)
            except (ConfigError, ValueError):
                continue
            start = 0
            for index, (rows, model, pair) in enumerate(zip(self.rows, state.models,
                                                            state.pairs)):
                span = slice(start, start + rows.size)
                start += rows.size
                if model is None:
                    continue
                try:
                    k2, m2 = self.matrices(settings, xk, index)
                except (AnalysisError, ValueError):
                    continue
                dlam = eigenvalue_derivatives(model, (k2 - model.stiffness) / step,
                                              (m2 - model.mass) / step)
                f = model.frequency_hz
                used = pair >= 0
                j = pair[used]
                df = dlam[j] / (8.0 * np.pi ** 2 * np.maximum(f[j], 1e-12))
                col = np.zeros(rows.size)
                col[used] = df / (self.table.frequency_hz[rows][used] * self.sigma[rows][used])
                jac[span, k] = col
        return jac


def relative_sigma(table: ModesTable) -> np.ndarray:
    """Relative standard uncertainty of each measured frequency: std_hz / f where given, else
    the median of the given ones, else 1 (then the fit's scatter sets the uncertainty)."""
    rel = table.std_hz / table.frequency_hz
    known = np.isfinite(rel) & (rel > 0)
    fill = float(np.median(rel[known])) if known.any() else 1.0
    return np.where(known, rel, fill)


# --------------------------------------------------------------------------- identifiability

def unidentifiable(jac: np.ndarray, names, ratio: float = MIN_SINGULAR_RATIO):
    """Combinations of the columns of ``jac`` the data cannot tell apart.

    Returns (kept column indices, [(combination {name: coefficient}, singular value / largest,
    the name left unfitted)]): while the smallest singular value of the kept columns is below
    ``ratio`` times the largest, the column carrying most of its right singular vector (the
    later named on a tie) is left unfitted."""
    kept = list(range(jac.shape[1]))
    dropped = []
    while kept:
        sub = jac[:, kept]
        if not np.any(sub):
            break
        _, sing, vt = np.linalg.svd(sub, full_matrices=False)
        if sing[-1] >= ratio * sing[0]:
            break
        vector = vt[-1] * np.sign(vt[-1][np.argmax(np.abs(vt[-1]))])
        weights = np.abs(vector) * (1.0 + 1e-6 * np.arange(vector.size))
        worst = int(np.argmax(weights))
        combination = {names[kept[i]]: round(float(c), 4) for i, c in enumerate(vector)
                       if abs(c) >= 0.01}
        dropped.append((combination, float(sing[-1] / sing[0]), names[kept[worst]]))
        del kept[worst]
    return kept, dropped


def combination_text(combination: dict) -> str:
    """``+0.707 cable.area_m2 -0.707 cable.youngs_modulus_pa`` (relative changes)."""
    return ' '.join(f'{c:+.3g} {name}' for name, c in combination.items())


# --------------------------------------------------------------------------- damping

def fit_damping(table: ModesTable, rows, targets, flat: dict) -> dict:
    """Damping parameters fitted to the measured damping ratios of ``rows``.

    ``damping.modal_ratio``: the weighted mean ratio. ``damping.mass_factor`` and
    ``damping.stiffness_factor``: zeta = dM / (2 w) + dK w / 2 at the measured frequencies,
    linear least squares with dM, dK >= 0 (a factor not fitted keeps its given value).
    Returns {name: (value, standard uncertainty)}; weights 1 / damping_ratio_std where given.
    """
    rows = np.asarray(rows, dtype=int)
    zeta = table.damping_ratio[rows]
    ok = np.isfinite(zeta)
    if not ok.any():
        raise CalibrationError('the modes table has no damping_ratio to fit '
                               f'{", ".join(t.name for t in targets)} to')
    zeta = zeta[ok]
    w = 2.0 * np.pi * table.frequency_hz[rows][ok]
    std = table.damping_ratio_std[rows][ok]
    known = np.isfinite(std) & (std > 0)
    sigma = np.where(known, std, np.median(std[known]) if known.any() else 1.0)
    names = [t.parameter for t in targets]
    if 'damping.modal_ratio' in names:
        if len(names) > 1:
            raise CalibrationError('fit damping.modal_ratio or the Rayleigh factors '
                                   'damping.mass_factor and damping.stiffness_factor, not both')
        weight = 1.0 / sigma ** 2
        mean = float(np.sum(weight * zeta) / np.sum(weight))
        chi2 = float(np.sum(weight * (zeta - mean) ** 2)) / max(zeta.size - 1, 1)
        scale = chi2 if not known.any() else max(chi2, 1.0)
        return {'damping.modal_ratio': (mean, math.sqrt(scale / np.sum(weight)))}
    basis = {'damping.mass_factor': 1.0 / (2.0 * w), 'damping.stiffness_factor': w / 2.0}
    fixed = np.zeros_like(zeta)
    for name, column in basis.items():
        if name not in names:
            fixed += float(current_value(flat, name)) * column
    a = np.stack([basis[n] for n in names], axis=1) / sigma[:, None]
    b = (zeta - fixed) / sigma
    colscale = np.linalg.norm(a, axis=0)
    solution = lsq_linear(a / colscale, b, bounds=(0.0, np.inf))
    values = solution.x / colscale
    dof = max(zeta.size - len(names), 1)
    chi2 = float(np.sum((a @ values - b) ** 2)) / dof
    scale = chi2 if not known.any() else max(chi2, 1.0)
    cov = np.linalg.pinv(a.T @ a) * scale
    return {n: (float(v), float(math.sqrt(max(cov[i, i], 0.0))))
            for i, (n, v) in enumerate(zip(names, values))}


def configured_ratios(settings: Settings, frequency_hz, model_hz) -> np.ndarray:
    """The damping ratios the settings give modes at ``frequency_hz`` (a modal ratio fitted
    as the package fits it, on the pose's platform modes ``model_hz``)."""
    f = np.asarray(frequency_hz, dtype=float)
    if settings.damping_modal_ratio <= 0:
        from cdpr_dynamics.dynamics.system import Damping
        return Damping(settings.damping_mass_factor, settings.damping_stiffness_factor).ratios(f)
    model_hz = np.asarray(model_hz, dtype=float)
    band = model_hz[(model_hz > 0) & (model_hz <= settings.f_max_hz)]
    high = band[-1] if band.size else model_hz[0]
    return rayleigh_from_modal_ratio(settings.damping_modal_ratio, model_hz[0], high).ratios(f)


# --------------------------------------------------------------------------- the fit

@dataclass(frozen=True)
class FitResult:
    """What :func:`fit` found; ``report`` is the JSON report."""

    flat: dict                      # the input parameters with the fitted values
    values: dict                    # {parameter: (value, std per component or None)}
    report: dict


def split_holdout(pose_ids, fraction: float, seed: int = 0):
    """(fit ids, held-out ids): ``fraction`` of the poses drawn at random (seeded), at least
    one of each where ``fraction`` > 0."""
    pose_ids = list(pose_ids)
    if not 0.0 <= fraction < 1.0:
        raise CalibrationError(f'--holdout {fraction} must be in [0, 1)')
    count = int(round(fraction * len(pose_ids)))
    if fraction > 0:
        count = min(max(count, 1), len(pose_ids) - 1)
    if count == 0:
        return pose_ids, []
    held = set(np.random.default_rng(seed).choice(len(pose_ids), count, replace=False).tolist())
    return ([p for i, p in enumerate(pose_ids) if i not in held],
            [p for i, p in enumerate(pose_ids) if i in held])


def _rms_pct(predicted, measured) -> float | None:
    ok = np.isfinite(predicted)
    if not ok.any():
        return None
    return float(100.0 * np.sqrt(np.mean((predicted[ok] / measured[ok] - 1.0) ** 2)))


def fit(flat: dict, table: ModesTable, names, holdout: float = 0.0, seed: int = 0,
        min_singular_ratio: float = MIN_SINGULAR_RATIO) -> FitResult:
    """Fit the parameters ``names`` (``--fit``) of the configuration ``flat`` to ``table``."""
    started = time.perf_counter()
    targets = parse_targets(names, flat)
    damping_targets = [t for t in targets if t.parameter in DAMPING_PARAMETERS]
    targets = [t for t in targets if t.parameter not in DAMPING_PARAMETERS]
    try:
        settings0 = settings_from_params(flat)
    except ConfigError as exc:
        raise CalibrationError(str(exc)) from None
    skipped, methods, usable = [], {}, []
    for pid in table.poses:
        pose = table.pose[table.rows_of(pid)[0]]
        try:
            methods[pid] = resolved_method(settings0, pose)
            pose_model(settings0, pose, methods[pid])
            usable.append(pid)
        except (AnalysisError, ValueError) as exc:
            skipped.append({'pose_id': int(pid), 'reason': str(exc).splitlines()[0]})
    if not usable:
        raise CalibrationError('no pose of the modes table has a model: '
                               f'{skipped[0]["reason"] if skipped else "the table is empty"}')
    fit_ids, held_ids = split_holdout(usable, holdout, seed)
    report = {'targets': [t.name for t in targets + damping_targets], 'skipped_poses': skipped,
              'fit_poses': [int(p) for p in fit_ids], 'holdout_poses': [int(p) for p in held_ids],
              'model': {str(int(p)): f'{m[0]} ({m[1]} elements)' if m[0] in ('fem', 'fem_sag')
                        else m[0] for p, m in methods.items()}}
    values, new_flat, parameters = {}, dict(flat), []
    problem_all = FitProblem(flat, targets, table, usable, methods)
    before = problem_all.state(problem_all.p0 / problem_all.scale)
    fit_started = time.perf_counter()
    if targets:
        problem = FitProblem(flat, targets, table, fit_ids, methods)
        x0 = problem.p0 / problem.scale
        if any(m is None for m in problem.state(x0).models):
            raise CalibrationError('a pose of the modes table has no model at the given '
                                   'parameters')
        jac0 = problem.jacobian(x0)
        kept, dropped = unidentifiable(jac0, [t.name for t in targets], min_singular_ratio)
        report['unidentifiable'] = [
            {'combination': combo, 'combination_text': combination_text(combo),
             'singular_value_ratio': ratio, 'left_unfitted': name}
            for combo, ratio, name in dropped]
        active = [targets[i] for i in kept]
        if not active:
            raise CalibrationError('the measured frequencies do not depend on '
                                   f'{", ".join(t.name for t in targets)}')
        sub = FitProblem(flat, active, table, fit_ids, methods)
        lb, ub = zip(*(_bounds(t) for t in active))
        lower, upper = np.array(lb) / sub.scale, np.array(ub) / sub.scale
        xs = np.clip(sub.p0 / sub.scale, lower, upper)
        solution = least_squares(sub.residuals, xs, jac=sub.jacobian, bounds=(lower, upper),
                                 method='trf', x_scale=1.0, max_nfev=100)
        jac = sub.jacobian(solution.x)
        dof = max(sub.n_residuals - len(active), 1)
        chi2 = float(np.sum(solution.fun ** 2)) / dof
        known_std = np.isfinite(table.std_hz).any()
        s2 = max(chi2, 1.0) if known_std else chi2
        u, sing, vt = np.linalg.svd(jac, full_matrices=False)
        inv = np.where(sing > 1e-12 * sing[0], 1.0 / np.maximum(sing, 1e-300) ** 2, 0.0)
        cov_x = (vt.T * inv) @ vt * s2
        std = np.sqrt(np.clip(np.diag(cov_x), 0.0, None)) * sub.scale
        fitted = sub.parameters(solution.x)
        new_flat = with_values(flat, active, fitted)
        for t, p0, p, s in zip(active, sub.p0, fitted, std):
            parameters.append({'name': t.name, 'initial': float(p0), 'fitted': float(p),
                               'std': float(s), 'relative_std': float(s / abs(p)) if p else None})
        for t in targets:
            if t not in active:
                parameters.append({'name': t.name, 'initial': float(target_values(flat, [t])[0]),
                                   'fitted': None, 'std': None,
                                   'note': 'left unfitted: not identifiable from these modes'})
        corr = cov_x / np.sqrt(np.outer(np.diag(cov_x), np.diag(cov_x)) + 1e-300)
        pairs = [(abs(corr[i, j]), i, j) for i in range(len(active))
                 for j in range(i + 1, len(active))]
        report['correlations'] = [{'a': active[i].name, 'b': active[j].name,
                                   'correlation': float(corr[i, j])}
                                  for _, i, j in sorted(pairs, reverse=True)[:5]]
        report['chi2_reduced'] = chi2
        report['uncertainty_scale'] = math.sqrt(s2)
        report['iterations'] = int(solution.nfev)
        report['optimizer'] = solution.message
        for t, p, s in zip(active, fitted, std):
            values.setdefault(t.parameter, {})[t.index] = (float(p), float(s))
    else:
        report['unidentifiable'] = []
    fit_seconds = time.perf_counter() - fit_started
    problem_after = FitProblem(new_flat, targets, table, usable, methods)
    after = problem_after.state(problem_after.p0 / problem_after.scale)
    rows_all = np.concatenate(problem_all.rows)
    measured = table.frequency_hz[rows_all]
    pose_of_row = table.pose_id[rows_all]
    is_held = np.isin(pose_of_row, held_ids)
    report['rms_error_pct'] = {
        part: {'before': _rms_pct(before.predicted_hz[mask], measured[mask]),
               'after': _rms_pct(after.predicted_hz[mask], measured[mask]),
               'modes': int(mask.sum())}
        for part, mask in (('fit', ~is_held), ('holdout', is_held)) if mask.any()}
    report['unpaired_modes'] = {'before': int(np.isnan(before.predicted_hz).sum()),
                                'after': int(np.isnan(after.predicted_hz).sum())}
    report['modes'] = [{'pose_id': int(p), 'measured_hz': float(m), 'before_hz': _num(b),
                        'after_hz': _num(a), 'holdout': bool(h)}
                       for p, m, b, a, h in zip(pose_of_row, measured, before.predicted_hz,
                                                after.predicted_hz, is_held)]
    if damping_targets:
        fit_rows = np.concatenate([table.rows_of(p) for p in fit_ids])
        fitted_damping = fit_damping(table, fit_rows, damping_targets, flat)
        for name, (value, s) in fitted_damping.items():
            values.setdefault(name, {})[None] = (value, s)
            parameters.append({'name': name, 'initial': float(current_value(flat, name)),
                               'fitted': value, 'std': s,
                               'relative_std': s / value if value else None})
        new_flat = with_values(new_flat, [Target(n, None) for n in fitted_damping],
                               [v for v, _ in fitted_damping.values()])
        # a modal ratio and Rayleigh factors exclude each other: the other kind is set to 0
        others = (('damping.mass_factor', 'damping.stiffness_factor')
                  if 'damping.modal_ratio' in fitted_damping else ('damping.modal_ratio',))
        new_flat.update({name: 0.0 for name in others})
        report['damping'] = _damping_summary(table, flat, new_flat, problem_all, before,
                                             after, rows_all, is_held)
    report['parameters'] = parameters
    report['timings_s'] = {'fit': fit_seconds, 'total': time.perf_counter() - started,
                           'model_evaluations': problem_all.evaluations}
    try:
        settings_from_params(new_flat)
    except ConfigError as exc:
        raise CalibrationError(f'the fitted parameters make no valid robot: {exc}') from None
    return FitResult(new_flat, values, report)


def _num(value) -> float | None:
    return float(value) if np.isfinite(value) else None


def _damping_summary(table, flat, new_flat, problem, before, after, rows_all, is_held) -> dict:
    """RMS relative error of the damping ratios the settings give, before and after."""
    out = {}
    for label, parameters, state in (('before', flat, before), ('after', new_flat, after)):
        settings = settings_from_params(parameters)
        predicted = np.full(rows_all.size, np.nan)
        start = 0
        for rows, model in zip(problem.rows, state.models):
            if model is not None:
                predicted[start:start + rows.size] = configured_ratios(
                    settings, table.frequency_hz[rows], model.frequency_hz)
            start += rows.size
        measured = table.damping_ratio[rows_all]
        for part, mask in (('fit', ~is_held), ('holdout', is_held)):
            ok = mask & np.isfinite(measured) & np.isfinite(predicted)
            if ok.any():
                out.setdefault(part, {})[label + '_rms_error_pct'] = float(
                    100 * np.sqrt(np.mean((predicted[ok] / measured[ok] - 1.0) ** 2)))
    return out


# --------------------------------------------------------------------------- the YAML

def _flow(value) -> str:
    if isinstance(value, (list, tuple, np.ndarray)):
        return '[' + ', '.join(f'{float(v):.10g}' for v in value) + ']'
    return f'{float(value):.10g}'


def _uncertainty_comment(parameter: str, fitted: dict) -> str:
    """``calibrated, standard uncertainty 1.2e+08`` or per component ``[0] 0.01, [2] 0.02``."""
    if list(fitted) == [None]:
        return f'calibrated, standard uncertainty {fitted[None][1]:.3g}'
    if list(fitted) == [SHARED]:
        return f'calibrated (one value for all), standard uncertainty {fitted[SHARED][1]:.3g}'
    parts = ', '.join(f'[{i}] {s:.3g}' for i, (_, s) in sorted(fitted.items()))
    return f'calibrated, standard uncertainty {parts}'


def _find_value_nodes(node, prefix: str, found: dict, mappings: dict) -> None:
    """Dotted name -> value node of a ros__parameters tree; dotted prefix -> mapping node."""
    mappings[prefix.rstrip('.')] = node
    for key_node, value_node in node.value:
        name = prefix + str(key_node.value)
        if isinstance(value_node, yaml.MappingNode):
            _find_value_nodes(value_node, name + '.', found, mappings)
        else:
            found[name] = (key_node, value_node)


def calibrated_yaml(text: str, new_values: dict, fitted: dict) -> str:
    """The params-file ``text`` with parameters ``new_values`` {name: value} replaced in place
    (a comment from ``fitted`` {name: {index: (value, std)}} after each fitted one) and the
    ones it does not set added to their section; everything else as written."""
    if not text.endswith('\n'):
        text += '\n'
    root = yaml.compose(text, Loader=yaml.SafeLoader)
    edits = []          # (start, end, new text)
    remaining = dict(new_values)
    sections = []
    for key_node, section in root.value:
        if not key_matches(key_node.value, 'cdpr_dynamics'):
            continue
        for inner_key, params in section.value:
            if inner_key.value == 'ros__parameters':
                found, mappings = {}, {}
                _find_value_nodes(params, '', found, mappings)
                sections.append((found, mappings))
                for name in list(remaining):
                    if name in found:
                        _, node = found[name]
                        comment = (f'  # {_uncertainty_comment(name, fitted[name])}'
                                   if name in fitted else '')
                        edits.append((node.start_mark.index, node.end_mark.index,
                                      _flow(remaining.pop(name)) + comment))
    if remaining and sections:
        _, mappings = sections[0]
        for name, value in remaining.items():
            parts = name.split('.')
            depth = max(d for d in range(len(parts)) if '.'.join(parts[:d]) in mappings)
            mapping = mappings['.'.join(parts[:depth])]
            first_key = mapping.value[0][0]
            indent = ' ' * first_key.start_mark.column
            end = mapping.value[-1][1].end_mark.index
            line_end = text.find('\n', end)
            at = len(text) if line_end < 0 else line_end + 1
            comment = (f'  # {_uncertainty_comment(name, fitted[name])}' if name in fitted
                       else '')
            edits.append((at, at, f'{indent}{".".join(parts[depth:])}: {_flow(value)}'
                                  f'{comment}\n'))
    for start, end, new in sorted(edits, key=lambda e: e[0], reverse=True):
        text = text[:start] + new + text[end:]
    return text
