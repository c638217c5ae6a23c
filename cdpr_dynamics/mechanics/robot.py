"""Robot geometry: cable vectors, lengths and the structure matrix (paper Eqs. 1-6).

Frames follow REP-103: anchors ``a_i`` and the platform position ``p`` are in ``robot.frame_id``;
attachments ``b_i`` are in the platform frame and rotate with it, ``r_i = R b_i``. The cable
vector points from the platform attachment to the anchor,

    l_i = a_i - (p + R b_i),    L_i = |l_i|,    u_i = l_i / L_i,

so a cable pulls the platform with force ``T_i u_i`` and moment ``r_i x T_i u_i``. The wrench
the cables must supply is ``W^T T = w`` with the 6 x n structure matrix (transpose of Eq. 5)

    W^T = [[u_1 ... u_n], [r_1 x u_1 ... r_n x u_n]],    w = -(m g + f_e, tau_e).

A point-mass platform (all ``b_i = 0``, centre of mass at the reference point) has 3 DOFs
(translation); a rigid platform has 6 (translation of the reference point, then small rotation
about it).

Pulleys (:func:`pulley_exits`): with a swivelling pulley of radius r_i and swivel axis k_i at
anchor i, ``a_i`` is D_i (where the cable from the winch meets the groove) and the cable's free
span runs from the exit point B_i to the attachment: then ``l_i = B_i - (p + R b_i)``, and the
cable's length from D_i is r_i beta_i + |l_i| with beta_i the wrap angle.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import math

import numpy as np
from scipy.linalg.lapack import dgesdd as _gesdd

from cdpr_dynamics.models.base import AnchorEnd, row_norm  # noqa: F401 (geometry helpers')


_DIAG3 = (0, 1, 2)    # the diagonal of a 3 x 3 block, as an index

#: Names of the wrench components (force, then moment), as messages name a direction.
WRENCH_AXES = ('force x', 'force y', 'force z', 'moment x', 'moment y', 'moment z')
#: Names of the platform DOFs (translation, then small rotation), as figures name a direction.
DOF_NAMES = ('x', 'y', 'z', 'rx', 'ry', 'rz')


class GeometryError(ValueError):
    """A pose the robot cannot take (not finite, an attachment at its anchor)."""


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix of the unit quaternion ``(qx, qy, qz, qw)`` (normalised here)."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(rotation) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` of a rotation matrix (Shepperd's method: from the
    largest of the diagonal and the trace, as scipy's ``Rotation.from_matrix`` picks it, so
    the sign agrees with scipy's). Scalar arithmetic: microseconds, for every prediction."""
    r = [[float(v) for v in row] for row in np.asarray(rotation)]
    trace = r[0][0] + r[1][1] + r[2][2]
    decision = (r[0][0], r[1][1], r[2][2], trace)
    i = max(range(4), key=decision.__getitem__)
    q = [0.0] * 4
    if i == 3:
        q = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1], 1.0 + trace]
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1.0 - trace + 2.0 * r[i][i]
        q[j] = r[j][i] + r[i][j]
        q[k] = r[k][i] + r[i][k]
        q[3] = r[k][j] - r[j][k]
    norm = math.sqrt(sum(v * v for v in q))
    return np.array(q) / norm


def rotation_vector_quaternion(theta_rad) -> np.ndarray:
    """Quaternion of the rotation vector ``theta_rad`` (axis times angle, rad):
    (sin(a/2) theta/a, cos(a/2)), a = |theta|; its series below a = 1e-4."""
    x, y, z = (float(v) for v in theta_rad)
    angle = math.sqrt(x * x + y * y + z * z)
    half = 0.5 - angle * angle / 48.0 if angle < 1e-4 else math.sin(angle / 2.0) / angle
    return np.array([half * x, half * y, half * z, math.cos(angle / 2.0)])


def quaternion_product(p, q) -> np.ndarray:
    """Hamilton product p q of quaternions ``(x, y, z, w)``: the rotation q, then p."""
    px, py, pz, pw = (float(v) for v in p)
    qx, qy, qz, qw = (float(v) for v in q)
    return np.array([pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy + py * qw + pz * qx - px * qz,
                     pw * qz + pz * qw + px * qy - py * qx,
                     pw * qw - px * qx - py * qy - pz * qz])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of stacked 3-vectors (..., 3) x (..., 3): numpy's formula (bit for bit
    the same numbers as ``np.cross``) without its argument handling, ~10x cheaper on small
    stacks."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    first = a1 * b2 - a2 * b1
    out = np.empty(first.shape + (3,))          # filled in place: np.stack costs ~3 products
    out[..., 0] = first
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` of vectors ``v`` of shape (..., 3): (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


@dataclass(frozen=True, eq=False)
class Robot:
    """A CDPR: n anchors (n, 3) m, attachments (n, 3) m in the platform frame, mass kg,
    inertia (3, 3) kg m^2 about the centre of mass in the platform frame, gravity (3,) m/s^2.

    Optional (defaults give the ideal robot): ``pulley_axes`` (n, 3) swivel axes k_i (unit
    vectors along the cable's travel from the winch into the pulley; zero rows: eyelets),
    ``pulley_radii_m`` (n,), ``winch_side_lengths_m`` (n,) the cable between drum and anchor,
    ``center_of_mass_m`` (3,) in the platform frame.
    """

    frame_id: str
    anchors_m: np.ndarray
    attachments_m: np.ndarray
    mass_kg: float
    inertia_kg_m2: np.ndarray
    gravity_m_s2: np.ndarray
    pulley_axes: np.ndarray | None = field(default=None)
    pulley_radii_m: np.ndarray | None = field(default=None)
    winch_side_lengths_m: np.ndarray | None = field(default=None)
    center_of_mass_m: np.ndarray | None = field(default=None)

    def __post_init__(self):
        n = self.anchors_m.shape[0]
        defaults = {'pulley_axes': np.zeros((n, 3)), 'pulley_radii_m': np.zeros(n),
                    'winch_side_lengths_m': np.zeros(n), 'center_of_mass_m': np.zeros(3)}
        for name, default in defaults.items():
            value = getattr(self, name)
            value = default if value is None else np.asarray(value, dtype=float)
            object.__setattr__(self, name, value.reshape(default.shape))
        norm = row_norm(self.pulley_axes)
        unit = np.divide(self.pulley_axes, norm[:, None], out=np.zeros((n, 3)),
                         where=norm[:, None] > 0)
        object.__setattr__(self, 'pulley_axes', unit)

    @property
    def n_cables(self) -> int:
        return self.anchors_m.shape[0]

    @functools.cached_property
    def pulley_index(self) -> np.ndarray | None:
        """Indices of the cables over a pulley (swivel axis and radius > 0), or None."""
        index = np.flatnonzero((self.pulley_radii_m > 0) & row_norm(self.pulley_axes).astype(bool))
        return index if index.size else None

    @functools.cached_property
    def pulley_references(self) -> np.ndarray:
        """(n, 3) unit vectors normal to each swivel axis: swivel angle zero (the world z axis
        projected on the pulley's swivel plane, else the x axis)."""
        k = self.pulley_axes
        out = np.zeros_like(k)
        for axis in (np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])):
            projected = axis - (k @ axis)[:, None] * k
            norm = row_norm(projected)
            todo = (norm > 1e-6) & ~row_norm(out).astype(bool)
            out[todo] = projected[todo] / norm[todo, None]
        return out

    @functools.cached_property
    def pulley_axes_cross(self) -> np.ndarray:
        """(n, 3, 3) the cross-product matrices [k_i]x of the swivel axes."""
        return skew(self.pulley_axes)

    @functools.cached_property
    def has_anchor_ends(self) -> bool:
        """True when a pulley or a winch-side length lies in series with a free span."""
        return self.pulley_index is not None or bool(np.any(self.winch_side_lengths_m))

    @functools.cached_property
    def centred_attachments(self) -> bool:
        """True when every cable ends at the platform frame's origin (all b_i = 0)."""
        return not np.any(self.attachments_m)

    @functools.cached_property
    def point_mass(self) -> bool:
        """True when every cable meets the centroid, the centre of mass: 3 platform DOFs
        instead of 6."""
        return self.centred_attachments and not np.any(self.center_of_mass_m)

    @property
    def platform_dofs(self) -> int:
        return 3 if self.point_mass else 6

    @functools.cached_property
    def frame_bounds_m(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box spanned by the anchors (the frame), lower and upper corner."""
        return self.anchors_m.min(axis=0), self.anchors_m.max(axis=0)

    @functools.cached_property
    def offset_mass(self) -> bool:
        """True when the centre of mass is away from the platform frame's origin."""
        return bool(np.any(self.center_of_mass_m))

    def platform_mass_matrix(self, rotation: np.ndarray) -> np.ndarray:
        """Mass matrix of the platform DOFs about the reference point (Eq. 7 for a centred
        mass): [[m I, -m [c]x], [m [c]x, R I_P R^T - m [c]x [c]x]] with c = R c_P the centre
        of mass in world axes (the kinetic energy of v_com = v - [c]x omega)."""
        n = self.platform_dofs
        mass = np.zeros((n, n))
        mass[_DIAG3, _DIAG3] = self.mass_kg                 # m I
        if n == 6:
            mass[3:, 3:] = rotation @ self.inertia_kg_m2 @ rotation.T
            if self.offset_mass:
                c = skew(rotation @ self.center_of_mass_m)
                mass[:3, 3:] = -self.mass_kg * c
                mass[3:, :3] = self.mass_kg * c
                mass[3:, 3:] -= self.mass_kg * (c @ c)
        return mass


@dataclass(frozen=True, eq=False)
class PulleyState:
    """The pulleys at one pose, stacked over every cable (eyelets: exit at the anchor, zeros).

    ``exit_m`` (n, 3) the exit points B_i; ``wrap_rad`` (n,) the wrap angles beta_i;
    ``center_m`` (n, 3) the pulley centres; ``plane_m`` (n, 3) the unit vectors e_i from each
    swivel axis towards its attachment (zero for eyelets); :attr:`swivel_rad` each pulley
    plane's angle about its swivel axis from ``references`` (:attr:`Robot.pulley_references`).
    """

    exit_m: np.ndarray
    wrap_rad: np.ndarray
    center_m: np.ndarray
    plane_m: np.ndarray
    axes: np.ndarray
    references: np.ndarray

    @functools.cached_property
    def swivel_rad(self) -> np.ndarray:
        """(n,) the swivel angles, atan2(e . (k x ref), e . ref); 0 for eyelets."""
        e = self.plane_m
        return np.arctan2(np.add.reduce(e * cross(self.axes, self.references), axis=-1),
                          np.add.reduce(e * self.references, axis=-1))


@dataclass(frozen=True, eq=False)
class Geometry:
    """Cable geometry at one pose; every array is stacked over cables (first axis n).

    The chord is the free span, from the attachment to the exit point (the anchor without a
    pulley); ``path_length_m`` is the cable's length from its anchor D_i (wrap included),
    ``anchor_end`` what lies in series with the free span at its anchor end (None: nothing).
    """

    position_m: np.ndarray        # (3,) platform reference point
    rotation: np.ndarray          # (3, 3) platform to world
    lever_m: np.ndarray           # (n, 3) r_i = R b_i, world frame
    chord_m: np.ndarray           # (n, 3) l_i, attachment -> anchor (exit point)
    length_m: np.ndarray          # (n,) L_i, the free span
    unit: np.ndarray              # (n, 3) u_i
    structure_matrix: np.ndarray  # (ndof, n) W^T: wrench per unit tension
    pulleys: PulleyState | None = None
    anchor_end: AnchorEnd | None = None
    path_length_m: np.ndarray | None = None      # (n,); None: the free span's length

    @property
    def n_cables(self) -> int:
        return self.length_m.shape[0]

    @property
    def cable_length_m(self) -> np.ndarray:
        """(n,) each cable's length from its anchor D_i to its attachment (wrap included)."""
        return self.length_m if self.path_length_m is None else self.path_length_m

    def attachment_map(self) -> np.ndarray:
        """(n, 3, ndof): attachment displacement per platform DOF, G_i = [I, -[r_i]x]."""
        ndof = self.structure_matrix.shape[0]
        g = np.zeros((self.n_cables, 3, ndof))
        g[:, _DIAG3, _DIAG3] = 1.0                          # I
        if ndof == 6:
            g[:, :, 3:] = -skew(self.lever_m)
        return g


def pulley_exits(anchors_m, axes, radii_m, attachments_m, axes_cross=None):
    """Exit points of swivelling pulleys, stacked over cables.

    The pulley plane holds the swivel axis k and the attachment A; its centre is
    C = D + r e (e the unit normal from the axis towards A); the cable runs along k into the
    groove at D, wraps by beta and leaves at the tangent point B = C + r n towards A, with
    n = (-cos beta, sin beta) in the plane's (e, k) axes. With A - C = (x, y) there, d^2 =
    x^2 + y^2 and the free span s = sqrt(d^2 - r^2), n = (r x - s y, s x + r y) / d^2 (the
    unit normal with n . (A - C) = r and the span leaving along the cable's travel), so
    beta = pi - atan2(n_y, n_x) and the swivel pivot c = r tan(beta/2) = r n_y / (1 - n_x).
    Returns (exit B (n, 3), wrap beta (n,), plane normal m = k x e (n, 3), centre C (n, 3),
    e (n, 3), pivot c (n,)); raises :class:`GeometryError` where an attachment lies on a
    swivel axis or inside its pulley. ``axes_cross`` (n, 3, 3): the axes' [k]x, if at hand.
    """
    d, k, r = anchors_m, axes, radii_m
    v = attachments_m - d
    y = np.add.reduce(v * k, axis=-1)
    off_axis = v - y[:, None] * k
    out = row_norm(off_axis)
    if out.min() < 1e-9:
        raise GeometryError(f'an attachment lies on the swivel axis of its pulley (cable '
                            f'{int(np.argmin(out))}): the pulley plane is undefined')
    e = off_axis / out[:, None]
    x = out - r
    d2 = x * x + y * y
    span2 = d2 - r * r
    if span2.min() <= 0.0:
        raise GeometryError(f'an attachment lies inside its pulley (cable '
                            f'{int(np.argmin(span2))})')
    s = np.sqrt(span2)
    nx, ny = r * x - s * y, s * x + r * y                 # n d^2
    wrap = np.pi - np.arctan2(ny, nx)
    scale = r / d2
    centre = d + r[:, None] * e
    exit_m = centre + (scale * nx)[:, None] * e + (scale * ny)[:, None] * k
    pivot = r * ny / (d2 - nx)
    normal = cross(k, e) if axes_cross is None else (axes_cross @ e[:, :, None])[:, :, 0]
    return exit_m, wrap, normal, centre, e, pivot


def _pulley_span(robot: Robot, attach: np.ndarray):
    """(exit points over every cable, :class:`PulleyState`, :class:`AnchorEnd`, path
    lengths' wrapped part) of ``robot``'s pulleys for attachments ``attach`` (n, 3)."""
    i = robot.pulley_index
    if i is None:                   # a winch side alone
        n = robot.n_cables
        end = AnchorEnd(robot.winch_side_lengths_m, np.zeros((n, 3)), np.zeros(n))
        return robot.anchors_m, None, end, None
    radius = robot.pulley_radii_m
    if i.size == robot.n_cables:    # every cable over a pulley: no scatter
        anchors, wrap, normal, centre, plane, pivot = pulley_exits(
            robot.anchors_m, robot.pulley_axes, radius, attach, robot.pulley_axes_cross)
    else:
        n = robot.n_cables
        anchors, centre = robot.anchors_m.copy(), robot.anchors_m.copy()
        wrap, pivot, normal, plane = np.zeros(n), np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3))
        anchors[i], wrap[i], normal[i], centre[i], plane[i], pivot[i] = pulley_exits(
            anchors[i], robot.pulley_axes[i], radius[i], attach[i])
    wrapped = radius * wrap
    end = AnchorEnd(wrapped + robot.winch_side_lengths_m, normal, pivot)
    state = PulleyState(anchors, wrap, centre, plane, robot.pulley_axes,
                        robot.pulley_references)
    return anchors, state, end, wrapped


def geometry(robot: Robot, position_m, rotation=None) -> Geometry:
    """Cable vectors, lengths, unit vectors and structure matrix at pose (p, R).

    The platform may be anywhere, below or beside its anchors (a suspended robot) included.
    Raises :class:`GeometryError` when the pose is not finite or puts an attachment on its
    anchor (a zero-length cable), on a pulley's swivel axis or inside its pulley. Called on
    every pose update: its tests run on the three coordinates as Python floats and the arrays
    take one numpy call per line (``|l_i|`` as ``np.linalg.norm`` computes it, without its
    argument handling).
    """
    p = np.asarray(position_m, dtype=float).reshape(3)
    xyz = p.tolist()
    rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    if not (all(map(math.isfinite, xyz)) and (rotation is None or np.isfinite(rot).all())):
        raise GeometryError('pose is not finite')
    if robot.centred_attachments:                # every b_i = 0: r_i = R b_i = 0
        lever = np.zeros(robot.anchors_m.shape)
        attach = p
    else:
        lever = robot.attachments_m @ rot.T
        attach = p + lever
    pulleys = anchor_end = path = None
    anchors = robot.anchors_m
    if robot.has_anchor_ends:
        anchors, pulleys, anchor_end, wrapped = _pulley_span(
            robot, attach if attach.ndim == 2 else attach + np.zeros(robot.anchors_m.shape))
    chord = anchors - attach
    length = row_norm(chord)
    if length.min() < 1e-6:
        i = int(np.argmin(length))
        raise GeometryError(f'cable {i} has zero length: attachment on its anchor')
    if pulleys is not None:
        path = length + wrapped
    unit = chord / length[:, None]
    if robot.point_mass:
        wt = unit.T.copy()
    else:
        wt = np.empty((6, robot.n_cables))
        wt[:3] = unit.T
        wt[3:] = cross(lever, unit).T
    return Geometry(p, rot, lever, chord, length, unit, wt, pulleys, anchor_end, path)


def required_wrench(robot: Robot, external_force_n=(0, 0, 0), external_moment_nm=(0, 0, 0),
                    rotation=None):
    """The wrench the cables must supply, w = -(m g + f_e, c x m g + tau_e) (Eq. 9), sized to
    the DOFs: gravity acts at the centre of mass c = R c_P (``rotation`` R, default identity),
    the external wrench at the reference point."""
    weight = robot.mass_kg * robot.gravity_m_s2
    force = -(weight + np.asarray(external_force_n))
    if robot.point_mass:
        return force
    moment = -np.asarray(external_moment_nm, dtype=float)
    if robot.offset_mass:
        arm = robot.center_of_mass_m if rotation is None else rotation @ robot.center_of_mass_m
        moment = moment - np.cross(arm, weight)
    return np.concatenate([force, moment])


def singular_values(matrix: np.ndarray) -> np.ndarray:
    """Singular values of a real 2-D array, descending: LAPACK gesdd as ``np.linalg.svd(a,
    compute_uv=False)`` calls it, without numpy's wrapper (a third of the cost of a (3, 8)
    structure matrix's values, checked on every pose)."""
    _, sing, _, info = _gesdd(matrix, 0)
    return sing if info == 0 else np.linalg.svd(matrix, compute_uv=False)
