"""Host-side (numpy, float64) rotation helpers shared by the builder, solver, USD I/O,
articulations and the IPC baseline.

Quaternions are (x, y, z, w), Warp's order; every function broadcasts over leading axes.
Rotation vectors w rotate by |w| radians about w / |w| (right-handed).
"""

import numpy as np

__all__ = [
    "cross",
    "quat_mul",
    "quat_conjugate",
    "quat_rotate",
    "quat_from_rotation_vector",
    "quat_to_matrix",
    "quat_from_matrix",
    "rotation_vector_from_quat",
    "skew",
    "axial",
    "pose_mul",
    "pose_inverse",
    "quat_norm",
    "normalized_poses",
    "rigid_step_between",
    "rigid_step_travel",
]


def cross(a, b) -> np.ndarray:
    """a x b of 3-vectors (..., 3), broadcasting, in float64: np.cross's products and
    differences in its order (the same rounding for float64 input) without its axis
    handling, which was most of the time of the host's small rotations (1.5 s of a 4.1 s
    profiled 40-frame Ant-Push rollout)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape[-1:] != (3,) or b.shape[-1:] != (3,):  # indexing would take a pose's first three silently
        raise ValueError(f"cross: expected 3-vectors (..., 3), got shapes {a.shape} and {b.shape}")
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def quat_mul(q, r) -> np.ndarray:
    """Hamilton product q r (apply r first, then q)."""
    q = np.asarray(q, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if q.shape[-1:] != (4,) or r.shape[-1:] != (4,):  # indexing would take a pose's first four silently
        raise ValueError(f"quat_mul: expected quaternions (..., 4), got shapes {q.shape} and {r.shape}")
    x1, y1, z1, w1 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    x2, y2, z2, w2 = r[..., 0], r[..., 1], r[..., 2], r[..., 3]
    return np.stack(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ],
        axis=-1,
    )


def quat_conjugate(q) -> np.ndarray:
    """(..., 4) conjugates (-x, -y, -z, w): the inverse rotations of unit quaternions."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def quat_rotate(q, v) -> np.ndarray:
    """R(q) v for unit quaternions q."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u, w = q[..., :3], q[..., 3:]
    return v + 2.0 * cross(u, cross(u, v) + w * v)


def quat_from_rotation_vector(w) -> np.ndarray:
    """exp of a rotation vector as a unit quaternion (series near zero)."""
    w = np.asarray(w, dtype=np.float64)
    angle = np.linalg.norm(w, axis=-1, keepdims=True)
    small = angle <= 1e-8
    # sin(a/2)/a, with its series where a/2 would lose digits
    scale = np.where(small, 0.5 - angle**2 / 48.0, np.sin(0.5 * angle) / np.where(small, 1.0, angle))
    return np.concatenate([scale * w, np.cos(0.5 * angle)], axis=-1)


def rotation_vector_from_quat(q) -> np.ndarray:
    """log of a quaternion (of any norm: the rotation it stands for): the rotation vector
    with angle in [0, pi]."""
    q = np.asarray(q, dtype=np.float64)
    q = np.where(q[..., 3:] < 0.0, -q, q)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:])
    # Relative to w: the series also holds for quaternions of any norm (a 90 degree turn
    # scaled to norm 1e-12 read 2.0 rad, a 3 rad one 28.2).
    small = s <= 1e-12 * np.abs(q[..., 3:])
    scale = np.where(small, 2.0 / np.maximum(q[..., 3:], 1e-300), angle / np.where(small, 1.0, s))
    return scale * q[..., :3]


def quat_to_matrix(q) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) unit quaternions (column-vector convention: R v)."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_from_matrix(m) -> np.ndarray:
    """Unit quaternion of a single rotation matrix (Shepperd's branch choice)."""
    m = np.asarray(m, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


def skew(v) -> np.ndarray:
    """[v]x, the cross-product matrix."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def axial(m) -> np.ndarray:
    """vee(M - M^T), the axial vector of twice the skew part: tr([w]x M) = -w . axial(M)."""
    m = np.asarray(m, dtype=np.float64)
    return np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1)


def pose_mul(a, b) -> np.ndarray:
    """Composition of (7,) poses (p, q): a after b."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.concatenate([a[..., :3] + quat_rotate(a[..., 3:], b[..., :3]), quat_mul(a[..., 3:], b[..., 3:])], axis=-1)


def quat_norm(q) -> np.ndarray:
    """Euclidean norm over the last axis, without the overflow or underflow of its squares
    (np.linalg.norm gave inf at 1e160 and 0 at 1e-170)."""
    return np.hypot.reduce(np.asarray(q, dtype=np.float64), axis=-1)


# A quaternion divided by its norm has a computed norm within 2 eps of 1 (1e6 random draws
# at scales 1e-150 to 1e150); dividing it again moved 30% of them by an ulp. So a pose
# normalised twice often differed from the pose normalised once, and the solver's start pose
# seldom equalled its previous step's last evaluated pose bit for bit once bodies turned (a
# rolling 16-ball strike reused 1 of 7 start evaluations; 2026-11-28).
_UNIT_NORM_ROUNDING = 4.0 * np.finfo(np.float64).eps


def normalized_poses(poses, *, norms: np.ndarray | None = None) -> np.ndarray:
    """A copy of (..., 7) poses (p, q) with unit quaternions: each divided by its norm,
    unless that is 1 within rounding, so that normalising twice gives the bits of once.
    ``norms``: the quaternions' ``quat_norm`` (...,), where the caller has them already."""
    out = np.array(poses, dtype=np.float64)
    norms = (quat_norm(out[..., 3:]) if norms is None else norms)[..., None]
    out[..., 3:] = np.where(np.abs(norms - 1.0) <= _UNIT_NORM_ROUNDING, out[..., 3:], out[..., 3:] / norms)
    return out


def pose_inverse(a) -> np.ndarray:
    """(..., 7) inverses of poses (p, q): (-R^T p, q*), so that pose_mul(pose_inverse(a), a) is the identity."""
    a = np.asarray(a, dtype=np.float64)
    q = quat_conjugate(a[..., 3:])
    return np.concatenate([-quat_rotate(q, a[..., :3]), q], axis=-1)


def rigid_step_between(poses_from, poses_to) -> np.ndarray:
    """The (..., 6) rigid coordinates (dp, dtheta) that take poses (..., 7) ``poses_from`` to
    ``poses_to``: p + dp, exp([dtheta]x) R (world axes, the shorter rotation)."""
    poses_from = np.asarray(poses_from, dtype=np.float64)
    poses_to = np.asarray(poses_to, dtype=np.float64)
    turn = rotation_vector_from_quat(quat_mul(poses_to[..., 3:], quat_conjugate(poses_from[..., 3:])))
    return np.concatenate([poses_to[..., :3] - poses_from[..., :3], turn], axis=-1)


def rigid_step_travel(step, reach) -> np.ndarray:
    """Upper bound (m) on how far any point within ``reach`` (m) of a body's centre of mass
    moves under its rigid step (..., 6) = (dp, dtheta): |dp| + |dtheta| reach (a chord is
    no longer than its arc). The advancement kernel's pair skip (kernels/reduction.py,
    ``_pair_keeps_clear``) is the same bound on the device."""
    step = np.asarray(step, dtype=np.float64)
    return np.linalg.norm(step[..., :3], axis=-1) + np.linalg.norm(step[..., 3:], axis=-1) * reach
