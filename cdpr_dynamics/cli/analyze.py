"""``cdpr_analyze``: tensions, natural frequencies, FRF and time histories for one config.

    cdpr_analyze [--config PATH] [--method M [M ...]] [--elements N] [--json PATH]
                 [--plot-dir DIR] [--f-min HZ] [--f-max HZ] [--n-points N]
                 [--excitation-hz F [F ...]] [--duration S] [--slack-aware]
                 [--plot-direction {x,y,z,rx,ry,rz}] [--position X Y Z]
                 [--shaper {none,zv,zvd,ei} [--shaper-modes N] [--notch-sample-rate HZ]]

Writes the JSON of doc/tools/cdpr_analyze.md (for the first method; every method under
``methods``) and
PNG plots (:mod:`cdpr_dynamics.analysis.figures`): the FRF along ``--plot-direction`` (one line per
method) and the time histories of every method, the geometry and the mode shapes of the first.
Errors end with one line naming the cause and exit status 1.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from cdpr_dynamics.analysis.pipeline import (AnalysisError, Equilibrium, Stopwatch, build_system,
                                             damping_for, damping_warnings, equilibrium,
                                             equilibrium_for, equilibrium_summary, frf_arrays,
                                             geometry_summary, model_warnings, point_displacement,
                                             receptance, safe, system_modes)
from cdpr_dynamics.cli import interruptible, plain
from cdpr_dynamics.analysis.config import METHODS, ConfigError, Settings, load_settings
from cdpr_dynamics.dynamics.system import tension_change, time_history
from cdpr_dynamics.models.catenary import sag_parameter
from cdpr_dynamics.dynamics.modes import modes
from cdpr_dynamics.mechanics.robot import DOF_NAMES
from cdpr_dynamics.mechanics.tensions import below_text
from cdpr_dynamics.selection.auto import accuracy_warnings, choose_model
from cdpr_dynamics.analysis.controller import controller_document, controller_lines
from cdpr_dynamics.analysis.live import harmonic_history
from cdpr_dynamics.dynamics import shapers
from cdpr_dynamics.dynamics.slack import peak_displacement


def analyze_method(settings: Settings, eq: Equilibrium, excitations_hz, duration_s: float,
                   progress=None, slack_aware: bool = False,
                   controller: dict | None = None) -> dict:
    """The JSON document of one method at equilibrium ``eq``.

    ``slack_aware`` adds to each time history the slack-aware one (cables carry no
    compression, :mod:`cdpr_dynamics.dynamics.slack`) under ``slack_aware``; ``controller``
    (``kind``, ``count``, ``sample_rate_hz``) adds what the node publishes for a controller
    (:func:`~cdpr_dynamics.analysis.controller.controller_document`) under ``controller``.
    """
    watch = Stopwatch()
    choice = None
    method, elements = settings.method, settings.elements_per_cable
    with watch('assembly'):
        if settings.method == 'auto':
            choice = safe(choose_model, settings, eq)
            method, elements = choice.method, choice.elements_per_cable
    with watch('statics'):
        eq = safe(equilibrium_for, settings, eq, method)
    with watch('assembly'):
        system = safe(build_system, settings, eq, method, elements)
    assembly = system.assembly
    sag = sag_parameter(eq.cables)
    warnings = list(assembly.warnings) + model_warnings(settings, eq, assembly)
    if choice is None:
        warnings += accuracy_warnings(settings, eq, assembly.method, assembly.elements_per_cable)
    else:
        warnings += choice.warnings
    if not assembly.valid:
        raise AnalysisError(f'method {assembly.method} fails for this scene: '
                            + '; '.join(assembly.warnings))
    with watch('modes'):        # natural frequencies and their classification
        found = safe(system_modes, settings, system)
    with watch('frf'):          # the FRF only (and the receptance)
        arrays = safe(frf_arrays, settings, system, found)
        damping = safe(damping_for, settings, system)
        gain = safe(receptance, system, arrays['frequency_hz'], damping)
    freqs = arrays['natural_frequencies_hz']
    warnings += damping_warnings(damping, freqs)
    histories = []
    if assembly.blocks is not None:
        with watch('time_history'):
            for f_exc in excitations_hz:
                th = safe(time_history, system, settings.frf_force_n, f_exc, duration_s, damping,
                          settings.dt_s, settings.newmark_alpha, settings.newmark_beta,
                          progress=progress and progress(f'time history {f_exc:g} Hz'),
                          moment_nm=settings.frf_moment_nm)
                u_point = point_displacement(th.u, eq.geometry.rotation, settings.frf_point_m)
                tension = eq.tensions.tension_n + tension_change(system, th.u)
                min_tension = float(tension.min())
                slack = min_tension <= 0.0
                if slack:
                    warnings.append(f'{f_exc:g} Hz time history: a cable would go slack '
                                    f'(lowest tension {min_tension:.1f} N): the linear '
                                    'response is not valid')
                elif min_tension < settings.tension_min_n:
                    warnings.append(f'{f_exc:g} Hz time history: tension drops to '
                                    f'{below_text(min_tension, settings.tension_min_n)} N, '
                                    f'below tension.min_n {settings.tension_min_n:g} N')
                histories.append({'excitation_hz': float(f_exc), 't_s': th.t_s.tolist(),
                                  'u_m': u_point.tolist(), 'min_tension_n': min_tension,
                                  'slack': bool(slack),
                                  'force_n': np.outer(np.sin(2 * np.pi * f_exc * th.t_s),
                                                      settings.frf_force_n).tolist(),
                                  'lowest_tension_n': tension.min(axis=1).tolist()})
                if slack_aware:
                    histories[-1]['slack_aware'] = _slack_aware(
                        settings, assembly.method, assembly.elements_per_cable, f_exc,
                        duration_s)
                    histories[-1]['slack_aware']['peak_uz_linear_m'] = peak_displacement(th.u_m)
    else:
        warnings.append(f'method {assembly.method} has no finite matrices: no time history')
    amplitude = np.stack([arrays['amplitude_x_m'], arrays['amplitude_y_m'],
                          arrays['amplitude_z_m']], axis=1)
    phase = np.stack([arrays['phase_x_rad'], arrays['phase_y_rad'], arrays['phase_z_rad']],
                     axis=1)
    chosen = {'method': assembly.method, 'elements_per_cable': assembly.elements_per_cable,
              'reason': choice.reason if choice else
              f'model.method = {settings.method} as configured'}
    if choice:
        chosen['estimated_error'] = choice.estimated_error
    extra = {}
    if controller is not None and found is not None:
        extra['controller'] = controller_document(
            settings.robot, system, found, damping, eq, settings.f_max_hz, controller['kind'],
            controller['count'], controller['sample_rate_hz'], settings.frf_point_m)
    return {
        **extra,
        'method': assembly.method,
        'dofs': system.dofs,
        'tensions_n': eq.tensions.tension_n.tolist(),
        'cable_lengths_m': eq.geometry.cable_length_m.tolist(),
        'sag_parameter': sag.tolist(),
        'equilibrium': equilibrium_summary(settings, eq),
        'geometry': geometry_summary(eq),
        'natural_frequencies_hz': freqs.tolist(),
        'damping': {'mass_factor': damping.mass_factor,
                    'stiffness_factor': damping.stiffness_factor,
                    'modal_ratio': settings.damping_modal_ratio,
                    'modal_damping_ratios': [r if np.isfinite(r) else None  # 0 Hz modes
                                             for r in damping.ratios(freqs).tolist()]},
        'modes': mode_entries(found, freqs, damping),
        'platform_natural_frequencies_hz': (None if found is None
                                            else found.platform_hz.tolist()),
        'frf': {'frequency_hz': arrays['frequency_hz'].tolist(),
                'amplitude_m': amplitude.tolist(), 'phase_rad': phase.tolist(),
                'point_m': np.asarray(settings.frf_point_m, dtype=float).tolist(),
                'force_n': np.asarray(settings.frf_force_n, dtype=float).tolist(),
                'moment_nm': np.asarray(settings.frf_moment_nm, dtype=float).tolist(),
                'receptance': {'real': _finite(gain.real), 'imag': _finite(gain.imag)}},
        'time_history': histories,
        'model_choice': chosen,
        'warnings': warnings,
        'timings_s': watch.seconds,
    }


def _finite(values: np.ndarray):
    """Nested lists with non-finite entries (an undamped resonance) as None (valid JSON)."""
    values = np.asarray(values, dtype=float)
    if np.all(np.isfinite(values)):
        return values.tolist()
    return np.where(np.isfinite(values), values, None).tolist()


def mode_entries(found, freqs, damping) -> list[dict]:
    """The JSON ``modes``: per mode its frequency, kind, cable, platform
    energy fraction, effective mass per platform DOF (kg, kg m^2) and damping ratio;
    ``found`` None (dsm): frequency and damping ratio only, the rest null."""
    ratios = damping.ratios(freqs)
    entries = []
    for i, f in enumerate(np.asarray(freqs, dtype=float)):
        zeta = float(ratios[i]) if np.isfinite(ratios[i]) else None     # 0 Hz modes
        if found is None:
            entries.append({'frequency_hz': float(f), 'kind': None, 'cable': None,
                            'platform_energy_fraction': None, 'effective_mass': None,
                            'damping_ratio': zeta})
            continue
        cable = int(found.cable[i])
        entries.append({'frequency_hz': float(f), 'kind': found.kind[i],
                        'cable': cable if cable >= 0 else None,
                        'platform_energy_fraction': float(found.platform_fraction[i]),
                        'effective_mass': found.effective_mass[i].tolist(),
                        'damping_ratio': zeta})
    return entries


def _slack_aware(settings: Settings, method: str, elements: int, f_exc: float,
                 duration_s: float) -> dict:
    """The slack-aware time history of ``method`` as JSON: the live predictor's
    (:func:`~cdpr_dynamics.analysis.live.harmonic_history`), linear while every cable is taut,
    the compression-free platform-only model while one is slack."""
    history = safe(harmonic_history, settings.replace(method=method,
                                                      elements_per_cable=elements),
                   f_exc, duration_s)
    u_m = history.u[:, :3]
    return {'method': history.method, 'elements_per_cable': history.elements_per_cable,
            'slack_method': history.slack_method, 'u_m': u_m.tolist(),
            'peak_uz_m': peak_displacement(u_m),
            'min_tension_n': float(history.cable_force_n.min()),
            'lowest_tension_n': history.cable_force_n.min(axis=1).tolist(),
            'slack_fraction': history.slack.mean(axis=0).tolist()}


def _plot(documents: list[dict], plot_dir: Path, settings: Settings, eq: Equilibrium,
          direction: str = 'z', scene_name: str = '') -> list[Path]:
    """frf.png and time_history.png of every method's document, geometry.png and modes.png of
    the first method (:mod:`cdpr_dynamics.analysis.figures`) at the chord equilibrium ``eq``."""
    from cdpr_dynamics.analysis import figures   # matplotlib: imported only when plotting
    first = documents[0]
    figures.frf_figure(documents, plot_dir / 'frf.png', direction)
    paths = [plot_dir / 'frf.png']
    axis = (DOF_NAMES.index(direction) if direction in ('x', 'y', 'z')
            else int(np.argmax(np.abs(settings.frf_force_n))))
    if figures.time_history_figure(documents, plot_dir / 'time_history.png', axis,
                                   settings.tension_min_n):
        paths.append(plot_dir / 'time_history.png')
    method, elements = first['method'], first['model_choice']['elements_per_cable']
    title = ', '.join(filter(None, (scene_name, figures.method_name(method, elements))))
    eq = safe(equilibrium_for, settings, eq, method)
    figures.geometry_figure(figures.scene(settings, eq), plot_dir / 'geometry.png', title)
    paths.append(plot_dir / 'geometry.png')
    system = safe(build_system, settings, eq, method, elements or None)
    if system.assembly.blocks is not None:      # dsm: no mode shapes
        found = safe(modes, system, settings.f_max_hz, shapes=True)
        wanted = 3 if system.assembly.interior_dofs else 6
        picked = figures.pick_modes(found.kind, found.platform_fraction, wanted, 3,
                                    found.frequency_hz)
        shapes = figures.mode_shapes(settings, eq, system, found, picked)
        platform = sum(k == 'platform' for k in found.kind)
        note = (f' ({platform} platform mode{"s" if platform != 1 else ""} below '
                f'{settings.f_max_hz:g} Hz: the modes of the largest platform energy shown)'
                if platform < wanted else '')
        figures.modes_figure(shapes, settings.robot.anchors_m, plot_dir / 'modes.png',
                             title + note)
        paths.append(plot_dir / 'modes.png')
    return paths


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='cdpr_analyze',
                                     description=plain(__doc__.split('\n')[0]))
    parser.add_argument('--config', help='ROS 2 parameter YAML (default: the paper robot)')
    parser.add_argument('--method', nargs='+', choices=METHODS,
                        help='cable model(s); the first fills the top level of the JSON')
    parser.add_argument('--elements', type=int, help='elements per cable (fem, fem_sag)')
    parser.add_argument('--json', type=Path, help='write the results to this JSON file')
    parser.add_argument('--plot-dir', type=Path, help='write frf.png, time_history.png, '
                        'geometry.png and modes.png here')
    parser.add_argument('--plot-direction', choices=DOF_NAMES, default='z',
                        help='the FRF plotted: translation (m/N) or rotation (rad/(N m))'),
    parser.add_argument('--f-min', type=float, help='lowest FRF frequency (Hz)')
    parser.add_argument('--f-max', type=float, help='highest FRF frequency (Hz)')
    parser.add_argument('--n-points', type=int, help='FRF frequencies')
    parser.add_argument('--excitation-hz', type=float, nargs='+', default=[5.0],
                        help='harmonic excitation frequencies of the time histories (Hz)')
    parser.add_argument('--duration', type=float, default=1.0, help='time history length (s)')
    parser.add_argument('--slack-aware', action='store_true',
                        help='also a time history where cables carry no compression')
    parser.add_argument('--position', type=float, nargs=3, metavar=('X', 'Y', 'Z'),
                        help='analyse at this platform position (m) instead of '
                        'robot.initial_position')
    parser.add_argument('--shaper', choices=('none',) + shapers.KINDS,
                        help='print (and write to the JSON) the input shaper and notch filters '
                        'the node publishes, the modes table and the length offsets')
    parser.add_argument('--shaper-modes', type=int, default=1,
                        help='lowest platform modes the shaper covers (default 1)')
    parser.add_argument('--notch-sample-rate', type=float, default=1000.0,
                        help='sample rate of the notch biquads (Hz, default 1000)')
    return parser.parse_args(argv)


def settings_for(args: argparse.Namespace) -> Settings:
    """The config of ``args.config`` with the command line's overrides; refuses bad flags."""
    settings = load_settings(args.config)
    overrides = {'f_min_hz': args.f_min, 'f_max_hz': args.f_max, 'n_points': args.n_points,
                 'elements_per_cable': args.elements}
    position = getattr(args, 'position', None)
    if position is not None:
        overrides['initial_position_m'] = np.asarray(position, dtype=float)
    settings = settings.replace(**{k: v for k, v in overrides.items() if v is not None})
    if getattr(args, 'shaper', None) and (args.shaper_modes < 1 or
                                          not args.notch_sample_rate > 0):
        raise ConfigError('--shaper-modes must be at least 1 and --notch-sample-rate '
                          'positive')
    if args.duration <= 0 or any(not f > 0 for f in args.excitation_hz):
        raise ConfigError('--duration and --excitation-hz must be positive')
    direction = getattr(args, 'plot_direction', 'z')
    if direction.startswith('r') and settings.robot.point_mass:
        raise ConfigError(f'--plot-direction {direction} needs a 6-DOF platform: this robot\'s '
                          'platform is a point mass (x, y, z only)')
    return settings


def run(args: argparse.Namespace, progress=None) -> dict:
    """Load, solve and analyse as the arguments say; returns the JSON document."""
    settings = settings_for(args)
    watch = Stopwatch()
    with watch('tensions'):
        eq = equilibrium(settings)
    controller = None
    if getattr(args, 'shaper', None):
        controller = {'kind': args.shaper, 'count': args.shaper_modes,
                      'sample_rate_hz': args.notch_sample_rate}
    documents = [analyze_method(settings.replace(method=m), eq, args.excitation_hz,
                                args.duration, progress, getattr(args, 'slack_aware', False),
                                controller)
                 for m in (args.method or [settings.method])]
    result = dict(documents[0])
    result['timings_s'] = {**watch.seconds, **result['timings_s']}
    if len(documents) > 1:
        result['methods'] = documents
    return result


@interruptible('cdpr_analyze')
def main(argv=None) -> int:
    args = parse_args(argv)
    from tqdm import tqdm

    def progress(label):
        return lambda it: tqdm(it, desc=label, unit='step', leave=False, disable=None)
    try:
        result = run(args, progress)
    except (ConfigError, AnalysisError) as exc:
        print(f'cdpr_analyze: error: {exc}', file=sys.stderr)
        return 1
    try:
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(result, indent=1))
            print(f'wrote {args.json}')
        if args.plot_dir:
            settings = settings_for(args)
            name = Path(args.config).stem if args.config else 'paper_cdpr'
            for path in _plot(result.get('methods', [result]), args.plot_dir, settings,
                              equilibrium(settings), args.plot_direction, name):
                print(f'wrote {path}')
    except (ConfigError, AnalysisError, ValueError) as exc:     # FigureError too
        print(f'cdpr_analyze: error: {exc}', file=sys.stderr)
        return 1
    except OSError as exc:
        print(f'cdpr_analyze: error: cannot write {exc.filename or ""}: {exc.strerror}',
              file=sys.stderr)
        return 1
    freqs = ', '.join(f'{f:.2f}' for f in result['natural_frequencies_hz'][:6])
    print(f"{result['method']}: {result['dofs']} DOFs; tensions "
          f"{np.round(result['tensions_n'], 1).tolist()} N; lowest modes {freqs} Hz")
    if 'controller' in result:
        for line in controller_lines(result['controller']):
            print(line)
    for warning in result['warnings']:
        print(f'warning: {warning}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
