"""Record cdpr_markers of a config to MCAP and render the recorded MarkerArray with matplotlib.

usage: python scripts/render_markers.py [CONFIG.yaml] [OUT.png] [--method M] [--mcap OUT.mcap]

The node's markers without the node: the equilibrium at the config's initial pose, a step
force ``--force-n`` (default 0 0 -200 N) integrated for ``--time-s`` s (Newmark, as the node
does), the MarkerArray with that displacement exaggerated by ``--scale``, written with the
project's RecordingWriter, read back and plotted. The docs' doc/markers_heavy_sag.png:
``python scripts/render_markers.py config/heavy_sag_6dof.yaml doc/markers_heavy_sag.png``.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from cdpr_dynamics.analysis.pipeline import AnalysisError
from cdpr_dynamics.analysis.config import ConfigError, load_settings
from cdpr_dynamics.analysis.live import LivePredictor
from cdpr_dynamics.recording.base import RecordingError
from cdpr_dynamics.recording.reader import read_messages
from cdpr_dynamics.recording.writer import RecordingWriter
from msg_adapters.markers import equilibrium_markers, plot_markers

TOPIC = '/cdpr_markers'


def record_markers(settings, path, force_n, time_s: float, scale: float) -> None:
    """Write a one-topic MCAP: the markers at rest (t = 0) and after ``time_s`` s of force."""
    predictor = LivePredictor(settings)
    predictor.update_pose(settings.initial_position_m, rotation=settings.initial_rotation)
    with RecordingWriter(path, force=True) as writer:
        writer.add_topic(TOPIC, 'visualization_msgs/msg/MarkerArray')
        writer.write(TOPIC, equilibrium_markers(settings, predictor.eq), 0)
        predictor.advance(0, force_n)
        u = predictor.advance(int(round(time_s * 1e9)), force_n)
        writer.write(TOPIC, equilibrium_markers(settings, predictor.eq, u, scale),
                     int(round(time_s * 1e9)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='render_markers', description=__doc__.split('\n')[0])
    parser.add_argument('config', nargs='?', default='config/heavy_sag_6dof.yaml')
    parser.add_argument('out', nargs='?', default='doc/markers_heavy_sag.png')
    parser.add_argument('--method', default=None, help='model.method (default: the config\'s)')
    parser.add_argument('--force-n', type=float, nargs=3, default=[0.0, 0.0, -200.0])
    parser.add_argument('--time-s', type=float, default=0.5)
    parser.add_argument('--scale', type=float, default=100.0)
    parser.add_argument('--mcap', default=None, help='keep the recording here')
    args = parser.parse_args(argv)
    try:
        settings = load_settings(args.config)
        if args.method:
            settings = settings.replace(method=args.method)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(args.mcap or Path(tmp) / 'markers.mcap')
            record_markers(settings, path, args.force_n, args.time_s, args.scale)
            *_, last = read_messages(path, [TOPIC])
            plot_markers(last.message, args.out,
                         f'{Path(args.config).name}, {settings.method}: cdpr_markers '
                         f'(arrow x{args.scale:g})',
                         (settings.tension_min_n, settings.tension_max_n))
    except (AnalysisError, ConfigError, RecordingError, OSError, ValueError) as err:
        print(f'render_markers: {err}', file=sys.stderr)
        return 1
    print(f'render_markers: wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
