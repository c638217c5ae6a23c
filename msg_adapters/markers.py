"""visualization_msgs/MarkerArray of the robot for RViz and Foxglove (doc/node_interface.md).

Namespaces and ids are stable from one message to the next, so each message replaces the
last one's markers in place: ``cables`` (one LINE_STRIP per cable, id i), ``anchors`` (one
SPHERE_LIST, id 0), ``platform`` (a CUBE for a rigid platform, a SPHERE for a point mass,
id 0), ``displacement`` (an ARROW, id 0), and for a robot with pulleys ``pulleys`` (a
LINE_LIST of every pulley's groove circle, id 0; each cable's line then runs on through its
wrap to the anchor D_i). Every marker: ``frame_locked = True``, lifetime 0
(kept until replaced), in the robot's frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from msg_adapters.validation import s_to_stamp

CABLE_WIDTH_M = 0.01
ANCHOR_DIAMETER_M = 0.05
POINT_MASS_DIAMETER_M = 0.1
ARROW_SHAFT_M = 0.01
THIN_PLATFORM_M = 0.02        # the box's side along an axis the attachments do not span
PULLEY_SEGMENTS = 24          # straight pieces of a drawn groove circle
NAMESPACES = ('cables', 'anchors', 'platform', 'displacement', 'pulleys')


@dataclass(frozen=True)
class RobotShape:
    """What the markers draw, world frame (m): ``cable_points_m`` (n, s, 3) each cable from
    its platform end to its anchor, ``tension_n`` (n,), ``anchor_m`` (n, 3),
    ``position_m`` (3,) and ``quaternion`` (4,) qx qy qz qw of the platform, ``size_m`` (3,)
    of its box in the platform frame or None for a point mass; ``pulley_circles_m``
    (p, PULLEY_SEGMENTS + 1, 3) the groove circles of the robot's pulleys or None."""

    cable_points_m: np.ndarray
    tension_n: np.ndarray
    anchor_m: np.ndarray
    position_m: np.ndarray
    quaternion: np.ndarray
    size_m: np.ndarray | None
    pulley_circles_m: np.ndarray | None = None


def _pulley_drawing(geo, robot, samples: int):
    """(wrap arcs (n, samples, 3) from each exit point back to its anchor D_i, groove circles
    (p, PULLEY_SEGMENTS + 1, 3) of the pulleys) at ``geo``."""
    pulleys = geo.pulleys
    centre, exit_m = pulleys.center_m, pulleys.exit_m
    radius = robot.pulley_radii_m[:, None, None]
    k = robot.pulley_axes[:, None, :]
    e = pulleys.plane_m[:, None, :]
    angle = pulleys.wrap_rad[:, None] * np.linspace(1.0, 0.0, samples)[None, :]
    arcs = centre[:, None, :] + radius * (np.sin(angle)[..., None] * k
                                          - np.cos(angle)[..., None] * e)
    arcs[:, 0] = exit_m
    turn = np.linspace(0.0, 2.0 * np.pi, PULLEY_SEGMENTS + 1)[None, :, None]
    circles = centre[:, None, :] + radius * (np.sin(turn) * k - np.cos(turn) * e)
    return arcs, circles[robot.pulley_index]


def robot_shape(eq, samples: int = 33, robot=None) -> RobotShape:
    """The :class:`RobotShape` of an equilibrium: cables along
    :func:`cdpr_dynamics.analysis.pipeline.cable_shapes` (the catenary of a sag equilibrium, the
    chord otherwise) shifted by the attachments p + R b_i, and where ``robot`` has pulleys on
    through each wrap to the anchor; the box spans the attachments' extent max_i b_i - min_i
    b_i (platform frame; ``THIN_PLATFORM_M`` where that is 0)."""
    from cdpr_dynamics.analysis.pipeline import cable_shapes
    from cdpr_dynamics.analysis.live import rotated_quaternion
    geo = eq.geometry
    attachment = geo.position_m + geo.lever_m
    points = cable_shapes(eq, samples) + attachment[:, None, :]
    circles, anchors = None, attachment + geo.chord_m
    if geo.pulleys is not None and robot is not None:
        arcs, circles = _pulley_drawing(geo, robot, max(samples // 4, 2))
        points = np.concatenate([points, arcs[:, 1:]], axis=1)
        anchors = robot.anchors_m
    size = None
    if geo.structure_matrix.shape[0] == 6:
        local = geo.lever_m @ geo.rotation          # b_i = R^T r_i, rows
        size = np.maximum(local.max(axis=0) - local.min(axis=0), THIN_PLATFORM_M)
    return RobotShape(points, np.asarray(eq.tensions.tension_n, dtype=float), anchors,
                      np.asarray(geo.position_m, dtype=float),
                      rotated_quaternion(geo.rotation, np.zeros(3)), size, circles)


def tension_colours(tension_n, min_n: float, max_n: float) -> np.ndarray:
    """(n, 4) RGBA: blue at ``min_n``, red at ``max_n``, linear in s = (T - min)/(max - min)
    clipped to [0, 1]: (s, 0, 1 - s, 1)."""
    span = max(max_n - min_n, 1e-12)
    s = np.clip((np.asarray(tension_n, dtype=float) - min_n) / span, 0.0, 1.0)
    return np.stack([s, np.zeros_like(s), 1.0 - s, np.ones_like(s)], axis=-1)


def _marker(ns: str, kind: int, frame_id: str, stamp) -> Marker:
    m = Marker()
    m.header.frame_id = frame_id
    m.header.stamp = stamp
    m.ns, m.id, m.type, m.action = ns, 0, kind, Marker.ADD
    m.frame_locked = True
    m.lifetime = Duration(sec=0, nanosec=0)
    m.pose.orientation.w = 1.0
    m.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
    return m


def _points(xyz) -> list:
    return [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in np.asarray(xyz)]


def markers_message(shape: RobotShape, tension_min_n: float, tension_max_n: float,
                    displacement_m=(0.0, 0.0, 0.0), scale: float = 100.0,
                    frame_id: str = 'world', stamp=None) -> MarkerArray:
    """The MarkerArray of ``shape``: cables coloured by :func:`tension_colours`, anchors,
    platform, and an arrow from the platform centroid p to p + ``scale`` u for the predicted
    displacement u (m; ``scale`` exaggerates it, dimensionless)."""
    stamp = stamp if stamp is not None else s_to_stamp(0.0)
    out = MarkerArray()
    colours = tension_colours(shape.tension_n, tension_min_n, tension_max_n)
    for i, (line, rgba) in enumerate(zip(shape.cable_points_m, colours)):
        m = _marker('cables', Marker.LINE_STRIP, frame_id, stamp)
        m.id = i
        m.scale.x = CABLE_WIDTH_M
        m.points = _points(line)
        m.color = ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=1.0)
        out.markers.append(m)
    m = _marker('anchors', Marker.SPHERE_LIST, frame_id, stamp)
    m.scale.x = m.scale.y = m.scale.z = ANCHOR_DIAMETER_M
    m.points = _points(shape.anchor_m)
    m.color = ColorRGBA(r=0.3, g=0.3, b=0.3, a=1.0)
    out.markers.append(m)
    kind = Marker.SPHERE if shape.size_m is None else Marker.CUBE
    m = _marker('platform', kind, frame_id, stamp)
    m.pose.position = _points(shape.position_m[None])[0]
    qx, qy, qz, qw = (float(v) for v in shape.quaternion)
    m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z = qx, qy, qz
    m.pose.orientation.w = qw
    size = (np.full(3, POINT_MASS_DIAMETER_M) if shape.size_m is None else shape.size_m)
    m.scale.x, m.scale.y, m.scale.z = (float(v) for v in size)
    m.color = ColorRGBA(r=0.8, g=0.8, b=0.8, a=0.6)
    out.markers.append(m)
    m = _marker('displacement', Marker.ARROW, frame_id, stamp)
    tip = shape.position_m + scale * np.asarray(displacement_m, dtype=float)
    m.points = _points([shape.position_m, tip])
    m.scale.x, m.scale.y, m.scale.z = ARROW_SHAFT_M, 2 * ARROW_SHAFT_M, 2 * ARROW_SHAFT_M
    m.color = ColorRGBA(r=0.1, g=0.8, b=0.1, a=1.0)
    out.markers.append(m)
    if shape.pulley_circles_m is not None:
        m = _marker('pulleys', Marker.LINE_LIST, frame_id, stamp)
        m.scale.x = CABLE_WIDTH_M / 2
        ends = np.stack([shape.pulley_circles_m[:, :-1], shape.pulley_circles_m[:, 1:]], axis=2)
        m.points = _points(ends.reshape(-1, 3))
        m.color = ColorRGBA(r=0.2, g=0.2, b=0.2, a=1.0)
        out.markers.append(m)
    return out


def update_arrow(array: MarkerArray, displacement_m, scale: float, stamp) -> MarkerArray:
    """Point the ``displacement`` arrow of ``array`` (in place: the rest is not rebuilt) from
    its tail p to p + ``scale`` u; restamp every marker. Returns ``array``."""
    for m in array.markers:
        m.header.stamp = stamp
        if m.ns == 'displacement':
            tail = m.points[0]
            tip = np.array([tail.x, tail.y, tail.z]) + scale * np.asarray(displacement_m, float)
            m.points = [tail, _points(tip[None])[0]]
    return array


def equilibrium_markers(settings, eq, displacement_m=(0.0, 0.0, 0.0), scale: float = 100.0,
                        stamp=None) -> MarkerArray:
    """:func:`markers_message` of an equilibrium with the settings' tension bounds and frame."""
    return markers_message(robot_shape(eq, robot=settings.robot), settings.tension_min_n,
                           settings.tension_max_n,
                           displacement_m, scale, settings.robot.frame_id, stamp)


def _box_edges(m: Marker) -> np.ndarray:
    """(12, 2, 3) world-frame edges of a CUBE marker (its pose and scale)."""
    from cdpr_dynamics.mechanics.robot import quaternion_to_matrix
    o, p = m.pose.orientation, m.pose.position
    rotation = quaternion_to_matrix((o.x, o.y, o.z, o.w))
    half = np.array([m.scale.x, m.scale.y, m.scale.z]) / 2
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)])
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8)
             if np.sum(corners[a] != corners[b]) == 1]
    world = (corners * half) @ rotation.T + np.array([p.x, p.y, p.z])
    return np.array([[world[a], world[b]] for a, b in pairs])


def plot_markers(array: MarkerArray, path, title: str = '', tension_range_n=None) -> None:
    """Render a MarkerArray offline to a PNG (matplotlib, 3-D axes, equal scale): cables as
    coloured lines, anchors as dots, the platform's box (or centre), the displacement arrow;
    with ``tension_range_n`` (min, max) a colour bar of the cables' tension scale."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection='3d')
    every = []
    for m in array.markers:
        xyz = np.array([[p.x, p.y, p.z] for p in m.points]).reshape(-1, 3)
        colour = (m.color.r, m.color.g, m.color.b)
        if m.type == Marker.LINE_STRIP:
            ax.plot(*xyz.T, color=colour, linewidth=2)
        elif m.type == Marker.LINE_LIST:
            for segment in xyz.reshape(-1, 2, 3):
                ax.plot(*segment.T, color=colour, linewidth=1)
        elif m.type == Marker.SPHERE_LIST:
            ax.scatter(*xyz.T, color='k', s=30, label='anchors')
        elif m.type == Marker.CUBE:
            edges = _box_edges(m)
            for k, edge in enumerate(edges):
                ax.plot(*edge.T, color='0.3', linewidth=1, label=None if k else 'platform')
            xyz = edges.reshape(-1, 3)
        elif m.type == Marker.SPHERE:
            p = m.pose.position
            xyz = np.array([[p.x, p.y, p.z]])
            ax.scatter(*xyz.T, color='0.4', s=120, label='platform')
        elif m.type == Marker.ARROW and len(xyz) == 2:
            ax.quiver(*xyz[0], *(xyz[1] - xyz[0]), color=colour, label='displacement x scale')
        every.append(xyz)
    pts = np.concatenate(every)
    centre, half = (pts.max(0) + pts.min(0)) / 2, (pts.max(0) - pts.min(0)).max() / 2
    for axis, c in zip('xyz', centre):
        getattr(ax, f'set_{axis}lim')(c - half, c + half)
        getattr(ax, f'set_{axis}label')(f'{axis} (m)')
    ax.set_title(title or 'cdpr_markers: cables coloured by tension (blue T_min, red T_max)')
    ax.legend(loc='upper left', fontsize=8)
    if tension_range_n is not None:
        from matplotlib.colors import LinearSegmentedColormap, Normalize
        cmap = LinearSegmentedColormap.from_list('tension', [(0, 0, 1), (1, 0, 0)])
        bar = plt.cm.ScalarMappable(norm=Normalize(*tension_range_n), cmap=cmap)
        fig.colorbar(bar, ax=ax, shrink=0.6, pad=0.1, label='cable tension (N)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
