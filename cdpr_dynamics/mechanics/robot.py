"""Robot geometry: cable vectors, lengths and the structure matrix (paper Eqs. 1-6).

Frames follow REP-103: anchors ``a_i`` and the platform position ``p`` are in ``robot.frame_id``;
attachments ``b_i`` are in the platform frame and rotate with it, ``r_i = R b_i``. The cable
vector points from the platform attachment to the anchor,

    l_i = a_i - (p + R b_i),    L_i = |l_i|,    u_i = l_i / L_i,

so a cable pulls the platform with force ``T_i u_i`` and moment ``r_i x T_i u_i``. The wrench
the cables must supply is ``W^T T = w`` with the 6 x n structure matrix (transpose of Eq. 5)

    W^T = [[u_1 ... u_n], [r_1 x u_1 ... r_n x u_n]],    w = -(m g + f_e, tau_e).

A point-mass platform (all ``b_i = 0``) has 3 DOFs (translation); a rigid platform has 6
(translation, then small rotation about the centroid).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import math

import numpy as np
from scipy.linalg.lapack import dgesdd as _gesdd

from cdpr_dynamics.models.base import row_norm  # noqa: F401 (the geometry helpers' too)


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
    inertia (3, 3) kg m^2 about the centroid in the platform frame, gravity (3,) m/s^2."""

    frame_id: str
    anchors_m: np.ndarray
    attachments_m: np.ndarray
    mass_kg: float
    inertia_kg_m2: np.ndarray
    gravity_m_s2: np.ndarray

    @property
    def n_cables(self) -> int:
        return self.anchors_m.shape[0]

    @functools.cached_property
    def point_mass(self) -> bool:
        """True when every cable meets the centroid: 3 platform DOFs instead of 6."""
        return not np.any(self.attachments_m)

    @property
    def platform_dofs(self) -> int:
        return 3 if self.point_mass else 6

    @functools.cached_property
    def frame_bounds_m(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box spanned by the anchors (the frame), lower and upper corner."""
        return self.anchors_m.min(axis=0), self.anchors_m.max(axis=0)

    def platform_mass_matrix(self, rotation: np.ndarray) -> np.ndarray:
        """diag(m I, R I_P R^T) of the platform DOFs (Eq. 7, inertia in the world frame)."""
        n = self.platform_dofs
        mass = np.zeros((n, n))
        mass[_DIAG3, _DIAG3] = self.mass_kg                 # m I
        if n == 6:
            mass[3:, 3:] = rotation @ self.inertia_kg_m2 @ rotation.T
        return mass


@dataclass(frozen=True, eq=False)
class Geometry:
    """Cable geometry at one pose; every array is stacked over cables (first axis n)."""

    position_m: np.ndarray        # (3,) platform centroid
    rotation: np.ndarray          # (3, 3) platform to world
    lever_m: np.ndarray           # (n, 3) r_i = R b_i, world frame
    chord_m: np.ndarray           # (n, 3) l_i, attachment -> anchor
    length_m: np.ndarray          # (n,) L_i
    unit: np.ndarray              # (n, 3) u_i
    structure_matrix: np.ndarray  # (ndof, n) W^T: wrench per unit tension

    @property
    def n_cables(self) -> int:
        return self.length_m.shape[0]

    def attachment_map(self) -> np.ndarray:
        """(n, 3, ndof): attachment displacement per platform DOF, G_i = [I, -[r_i]x]."""
        ndof = self.structure_matrix.shape[0]
        g = np.zeros((self.n_cables, 3, ndof))
        g[:, _DIAG3, _DIAG3] = 1.0                          # I
        if ndof == 6:
            g[:, :, 3:] = -skew(self.lever_m)
        return g


def geometry(robot: Robot, position_m, rotation=None) -> Geometry:
    """Cable vectors, lengths, unit vectors and structure matrix at pose (p, R).

    The platform may be anywhere, below or beside its anchors (a suspended robot) included.
    Raises :class:`GeometryError` when the pose is not finite or puts an attachment on its
    anchor (a zero-length cable). Called on every pose update:
    its tests run on the three coordinates as Python floats and the arrays take one numpy call
    per line (``|l_i|`` as ``np.linalg.norm`` computes it, without its argument handling).
    """
    p = np.asarray(position_m, dtype=float).reshape(3)
    xyz = p.tolist()
    rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    if not (all(map(math.isfinite, xyz)) and (rotation is None or np.isfinite(rot).all())):
        raise GeometryError('pose is not finite')
    if robot.point_mass:          # every b_i = 0: r_i = R b_i = 0
        lever = np.zeros(robot.anchors_m.shape)
        chord = robot.anchors_m - p
    else:
        lever = robot.attachments_m @ rot.T
        chord = robot.anchors_m - (p + lever)
    length = row_norm(chord)
    if length.min() < 1e-6:
        i = int(np.argmin(length))
        raise GeometryError(f'cable {i} has zero length: attachment on its anchor')
    unit = chord / length[:, None]
    if robot.point_mass:
        wt = unit.T.copy()
    else:
        wt = np.empty((6, robot.n_cables))
        wt[:3] = unit.T
        wt[3:] = cross(lever, unit).T
    return Geometry(p, rot, lever, chord, length, unit, wt)


def required_wrench(robot: Robot, external_force_n=(0, 0, 0), external_moment_nm=(0, 0, 0)):
    """The wrench the cables must supply, w = -(m g + f_e, tau_e) (Eq. 9), sized to the DOFs."""
    force = -(robot.mass_kg * robot.gravity_m_s2 + np.asarray(external_force_n))
    if robot.point_mass:
        return force
    return np.concatenate([force, -np.asarray(external_moment_nm, dtype=float)])


def singular_values(matrix: np.ndarray) -> np.ndarray:
    """Singular values of a real 2-D array, descending: LAPACK gesdd as ``np.linalg.svd(a,
    compute_uv=False)`` calls it, without numpy's wrapper (a third of the cost of a (3, 8)
    structure matrix's values, checked on every pose)."""
    _, sing, _, info = _gesdd(matrix, 0)
    return sing if info == 0 else np.linalg.svd(matrix, compute_uv=False)
