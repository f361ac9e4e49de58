"""Articulated bodies in reduced (joint) coordinates for the implicit step.

Every dynamic body is the child of exactly one joint: a joint to a parent body, a ``base``
joint to the world (any subset of 3 translations and 3 rotations), or, when the user gave
none, an implicit free joint (3 translations and a 3-axis rotation). The bodies and joints
form a forest; cycles are refused.

Coordinates. A joint contributes degrees of freedom (DOFs) of three kinds:

- PRISMATIC: translation of the child's subtree along a world axis a (m);
- REVOLUTE: rotation of the subtree by an angle about an axis a through a point c (rad);
- ROTATION: one axis of a 3-axis rotation group (ball joints, free and base joints with all
  three rotations), moved together as exp([w]x) about the group's point, so a ball joint
  has no gimbal singularity.

The Newton step works in increments delta of all DOFs at the current configuration (a
chart re-centred every iteration), and moves body i by the product of exponentials
(Brockett) over its ancestor DOFs k_1 < k_2 < ... (root first):

    T_i(delta) = exp(xi_k1 delta_k1) exp(xi_k2 delta_k2) ... T_i,

with the world twists xi_k of the current configuration. Revolute and prismatic
increments are exact joint-coordinate increments (q_k += delta_k), so PD targets and limits
act on plain coordinates. Joints can never separate: every body moves by a rigid motion
that fixes its joint's anchor relative to its parent.

Derivatives. A body's rigid coordinates (dp, dtheta) (see kernels/rigid.py) depend on delta
through J (first derivatives) and through second derivatives (the curvature of forward
kinematics). For k before l on a body's path, with v_k(x) the velocity of point x under DOF
k (a_k for prismatic, a_k x (x - c_k) for rotations) and omega_k = a_k for rotations (0 for
prismatic):

    d2p / dk dl = a_k x v_l(p)      (0 if k is prismatic; a_k x v_k(p) on the diagonal)
    d2theta / dk dl = 1/2 omega_k x omega_l   (0 on the diagonal)

and inside one ROTATION group (an exponential map, symmetric in k and l)
d2p/dk dl = 1/2 (a_k x v_l(p) + a_l x v_k(p)), d2theta = 0. The reduced Hessian of a scalar
with rigid-coordinate gradient g and Hessian H is J^T H J + sum_i g_i . d2(p_i, theta_i).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validate import SCALE_RANGE
from .rotation import axial, cross, pose_inverse, pose_mul, quat_conjugate, quat_from_rotation_vector, quat_mul, quat_rotate, quat_to_matrix, rotation_vector_from_quat

__all__ = [
    "BASE_DOFS",
    "JOINT_AXES",
    "JOINT_KINDS",
    "PRISMATIC",
    "REVOLUTE",
    "ROTATION",
    "ArticulationModel",
    "Joint",
    "frame_in_body",
    "default_limit_margins",
    "effective_limit_margins",
    "limit_margin_problem",
    "joint_limit_energy",
]

PRISMATIC, REVOLUTE, ROTATION = 0, 1, 2
JOINT_KINDS = ("revolute", "prismatic", "universal", "ball", "base")
BASE_DOFS = ("x", "y", "z", "rx", "ry", "rz")
# The world axis of each base DOF: translations along it, turns about it.
_BASE_AXES = dict(zip(BASE_DOFS, np.vstack([np.eye(3), np.eye(3)]), strict=True))
# Axes (= coordinates) of the joint kinds with a fixed count; a ball joint has none, or one
# for a swing limit's axis, and no coordinates; a base joint has its listed dofs.
JOINT_AXES = {"revolute": 1, "prismatic": 1, "universal": 2}

_ANCHOR_TOLERANCE = 1e-6  # m, relative to the larger radius of a joint's two bodies
_ANGLE_TOLERANCE = 1e-6  # rad


@dataclass
class Joint:
    """A joint between ``parent`` (a body index, or -1 for the world) and ``child``.

    Frames are (7,) poses (p, q) of the joint frame in the parent's and the child's body
    frames (origin at the centre of mass; the world frame for parent -1). ``axes`` are unit
    vectors in the joint frame: one for revolute and prismatic joints, two orthogonal ones
    for universal joints (the first fixed in the parent, the second in the child). ``base``
    joints use ``base_dofs`` (a subset of ``BASE_DOFS``, world axes, rotations about the
    child's centre of mass) and ignore frames and axes. Ball joints may carry one axis (the
    joint frame's, default X) and a ``cone_limit`` on the angle between that axis in the
    parent and in the child (a swing limit; twist is free). Per coordinate: ``lower``/``upper``
    limits (rad or m, +-inf for none), ``limit_margin`` (the barrier's support, rad or m; NaN: a tenth of the range),
    ``limit_stiffness`` (J) and PD gains ``kp`` (N m/rad or N/m) and ``kd`` (N m s/rad or
    N s/m). Ball joints have no coordinates but one ``kp`` and one ``kd`` (N m/rad,
    N m s/rad) that drive their relative rotation (see ``ArticulationModel.ball_drive_terms``).
    """

    name: str
    kind: str
    parent: int
    child: int
    parent_frame: np.ndarray
    child_frame: np.ndarray
    axes: np.ndarray
    base_dofs: tuple = ()
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    limit_margin: np.ndarray | None = None
    limit_stiffness: np.ndarray | None = None
    kp: np.ndarray | None = None
    kd: np.ndarray | None = None
    # Per coordinate, the PD target of ``ArticulationModel.default_targets`` (rad or m);
    # None or NaN: the initial coordinates.
    target: np.ndarray | None = None
    cone_limit: float = np.inf  # ball joints: largest angle (rad) between the axis in parent and child
    # A static parent is part of the world: its pose as built is folded into ``parent_frame``
    # (parent -1), so the body may not move; -1 and None where the parent is not static.
    static_parent: int = -1
    static_parent_pose: np.ndarray | None = None

    def num_coordinates(self) -> int:
        """How many joint coordinates (rad or m) this joint owns in ``State.joint_q``."""
        if self.kind in ("revolute", "prismatic"):
            return 1
        if self.kind == "universal":
            return 2
        if self.kind == "base":
            translations = sum(d in ("x", "y", "z") for d in self.base_dofs)
            rotations = len(self.base_dofs) - translations
            return translations + (rotations if rotations < 3 else 0)
        return 0


def default_limit_margins(span: np.ndarray) -> np.ndarray:
    """A limit barrier's default margin: a tenth of the range (or cone limit), at most 0.1."""
    return np.minimum(0.1 * span, 0.1)


# Smallest limit barrier margin, and distance of a coordinate to its limit (rad or m): the
# barrier squares s - m and divides by s^2 (s, the distance to the limit, below the margin
# m), which underflow below SCALE_RANGE's 1e-150. Limits of +-1e-200 rad (default margin
# 2e-201) gave a NaN step; a coordinate 1e-200 from a limit stayed there (the step refuses it).
MIN_LIMIT_MARGIN = SCALE_RANGE[0]


def effective_limit_margins(limit_margin: np.ndarray, span: np.ndarray) -> np.ndarray:
    """The limit barriers' margins as the step uses them: ``limit_margin``, where NaN (the
    default) ``default_limit_margins`` of the range or cone limit ``span``."""
    return np.where(np.isnan(limit_margin), default_limit_margins(span), limit_margin)


def limit_margin_problem(margin: float, *, given: bool) -> str | None:
    """Why a limit barrier's margin (``given``, else the default ``default_limit_margins``)
    is too small for float64, or None."""
    if margin >= MIN_LIMIT_MARGIN:
        return None
    why = f"below {MIN_LIMIT_MARGIN:g}, where the barrier's square of the distance to the limit underflows"
    if given:
        return f"limit_margin {margin:g} is {why}"
    return f"its limit barrier's default margin, a tenth of the range or cone limit, is {margin:g}, {why} (it needs a range of at least {10 * MIN_LIMIT_MARGIN:g})"


def joint_limit_energy(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, margin: np.ndarray, stiffness: np.ndarray):
    """Joint-limit barrier per coordinate: value, gradient and (diagonal) Hessian.

    b(s) = -k (s - m)^2 log(s / m) for 0 < s < m, 0 beyond (C2 at s = m), +inf at s <= 0,
    with s the distance to the nearer limit, m the margin and k the stiffness: like the
    contact model, a limit is never crossed, and it costs nothing away from the limit.
    """
    value = np.zeros_like(q)
    grad = np.zeros_like(q)
    hess = np.zeros_like(q)
    for s, sign in ((q - lower, 1.0), (upper - q, -1.0)):
        active = s < margin
        if not active.any():
            continue
        if (s[active] <= 0).any():
            value[:] = np.inf
            return value, grad, hess
        sa, m, k = s[active], margin[active], stiffness[active]
        log = np.log(sa / m)
        value[active] += -k * (sa - m) ** 2 * log
        grad[active] += sign * k * (-2.0 * (sa - m) * log - (sa - m) ** 2 / sa)
        hess[active] += k * (-2.0 * log - 4.0 * (sa - m) / sa + (sa - m) ** 2 / sa**2)
    return value, grad, hess


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    return quat_from_rotation_vector(axis * angle)


def _signed_angle(q_rel: np.ndarray, axis: np.ndarray) -> float:
    """Angle in (-pi, pi] of a rotation about ``axis`` (q and -q are the same rotation)."""
    sign = -1.0 if q_rel[3] < 0 else 1.0
    return 2.0 * float(np.arctan2(sign * (q_rel[:3] @ axis), sign * q_rel[3]))


def _joint_rotation(joint: "Joint", values: np.ndarray) -> np.ndarray:
    """The relative rotation of a revolute joint at angle values[0], or of a universal one,
    Rot(e1, values[0]) Rot(e2, values[1])."""
    if joint.kind == "revolute":
        return _rotation_about(joint.axes[0], values[0])
    return quat_mul(_rotation_about(joint.axes[0], values[0]), _rotation_about(joint.axes[1], values[1]))


def _rotation_gap(q_a: np.ndarray, q_b: np.ndarray) -> float:
    """Angle (rad) of the rotation between two unit quaternions."""
    return float(np.linalg.norm(rotation_vector_from_quat(quat_mul(q_a, quat_conjugate(q_b)))))


def _relative_rotation(parent: np.ndarray, child: np.ndarray) -> np.ndarray:
    """Rotations (n, 4) of child frames in parent frames, both (n, 4) world quaternions: the
    convention of ``Control.ball_target``."""
    return quat_mul(quat_conjugate(parent), child)


def connected_labels(count: int, links) -> np.ndarray:
    """(count,) label of each of the nodes 0 .. count - 1: the smallest node of its
    connected component under ``links`` ((a, b) pairs). One rule for the groups bodies form
    through joints (the solver's articulation trees, the builder's contact exclusions),
    through excluded pairs (the IPC model's vertex patches) and for the pieces faces form
    through shared edges (the builder's mass check). Union-find in numpy: every link hooks
    the larger of its two roots onto the smaller, then paths are halved until each node
    points at its root, the smallest node of its component."""
    pairs = np.asarray(links, dtype=np.int64).reshape(-1, 2)
    root = np.arange(count, dtype=np.int64)
    while True:
        root_a, root_b = root[pairs[:, 0]], root[pairs[:, 1]]
        apart = root_a != root_b
        if not apart.any():
            return root
        np.minimum.at(root, np.maximum(root_a, root_b)[apart], np.minimum(root_a, root_b)[apart])
        while True:
            grand = root[root]
            if np.array_equal(grand, root):
                break
            root = grand


def _same_group_pairs(groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the ordered pairs of distinct positions of ``groups`` (a body
    chain's DOF groups, -1 for none) that share a group, an index into the chain's DOFs."""
    grouped = np.flatnonzero(groups >= 0)
    order = grouped[np.argsort(groups[grouped], kind="stable")]
    keys = groups[order]
    rows, columns = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    # Sorted by group, members of a group are neighbours: pairs at distance 1, 2, ... until
    # no two positions that far apart share one.
    for distance in range(1, len(order)):
        match = np.flatnonzero(keys[distance:] == keys[:-distance])
        if not match.size:
            break
        first, second = order[match], order[match + distance]
        rows += [first, second]
        columns += [second, first]
    return np.concatenate(rows), np.concatenate(columns)


class ArticulationModel:
    """The kinematic forest of a model's dynamic bodies (host, numpy, float64).

    Args:
        joints: the ``Joint`` list (validated by ``ModelBuilder.add_joint``).
        body_names: names of all bodies.
        body_static: (nbodies,) booleans.
        body_poses: (nbodies, 7) initial centre-of-mass poses; joints must hold in them.
        body_radius: (nbodies,) body radii (m); a joint's anchor tolerance is 1e-6 of its two bodies' larger one.

    Attributes:
        num_dofs: m, the number of reduced coordinates.
        num_coordinates: the number of joint coordinates (revolute and prismatic DOFs), each
            with PD gains and limits; ``coordinate_names``, ``coordinate_dof``,
            ``initial_coordinates``, ``default_targets`` (each joint's ``target``, else the
            initial coordinates), ``kp``, ``kd``, ``lower``, ``upper``, ``limit_margin``,
            ``limit_stiffness`` are (num_coordinates,) arrays.
        identity: True when every body is a free body (J = I, no curvature).
        num_ball_joints: the number of ball joints, each with a relative rotation that PD
            gains may drive; ``ball_joint_names``, ``ball_kp`` (N m/rad), ``ball_kd``
            (N m s/rad) are (num_ball_joints,), ``initial_ball_rotations`` (num_ball_joints,
            4) quaternions (``ball_rotations`` of the initial poses); ``has_ball_drives``
            when any ball gain is non-zero. The gains and limits may be changed after
            ``finalize`` (in place or replaced, same shapes); each step checks them
            (``parameter_problem``).
    """

    def __init__(self, joints: list[Joint], *, body_names, body_static, body_poses, body_radius):
        n = len(body_names)
        self.num_bodies = n
        self.body_names = list(body_names)
        static = np.asarray(body_static, dtype=bool)
        # Rows of J for the non-static bodies, whose blocks the contact Hessians hold.
        self._hessian_rows = np.flatnonzero(np.repeat(~static, 6))
        poses = np.asarray(body_poses, dtype=np.float64)
        self._initial_poses = poses.copy()
        parent_joint = {}
        for j, joint in enumerate(joints):
            assert joint.child not in parent_joint, "ModelBuilder.add_joint admits one parent joint per body"
            parent_joint[joint.child] = j
        # Implicit free joints for dynamic bodies without one.
        all_joints = list(joints)
        for b in range(n):
            if not static[b] and b not in parent_joint:
                parent_joint[b] = len(all_joints)
                all_joints.append(Joint(f"{self.body_names[b]}:free", "free", -1, b, np.array([0, 0, 0, 0, 0, 0, 1.0]), np.array([0, 0, 0, 0, 0, 0, 1.0]), np.zeros((0, 3)), BASE_DOFS))
        order = self._topological_order(all_joints, parent_joint)
        self.joints = [all_joints[j] for j in order]
        self.body_joint = np.full(n, -1, dtype=np.int64)
        for j, joint in enumerate(self.joints):
            self.body_joint[joint.child] = j
        self.identity = all(joint.kind == "free" for joint in self.joints)

        kind, axis_body, axis_local, point_local, owner, group, coord = [], [], [], [], [], [], []
        names, q0, targets, kp, kd, lower, upper, margin, stiffness = [], [], [], [], [], [], [], [], []
        self.joint_dofs = []
        # A joint is held to its own bodies' size: with the scene's largest (a 2 km ground) a
        # hinge whose anchors stood 1 mm apart was accepted.
        radius = np.asarray(body_radius, dtype=np.float64)
        self._anchor_tolerance = [_ANCHOR_TOLERANCE * max(radius[joint.child], radius[joint.parent] if joint.parent >= 0 else 0.0, 1e-300) for joint in self.joints]
        for j, joint in enumerate(self.joints):
            first = len(kind)
            values = self._initial_coordinates(joint, poses, self._anchor_tolerance[j])
            if joint.kind in ("revolute", "universal"):
                values = _angles_within(values, joint.lower, joint.upper)
            dofs = self._joint_dofs(joint, poses)
            coordinate = 0
            for dof_kind, body, axis, point, group_id in dofs:
                kind.append(dof_kind)
                axis_body.append(body)
                axis_local.append(axis)
                point_local.append(point)
                owner.append(joint.child)
                group.append(group_id)
                if joint.kind != "free" and dof_kind != ROTATION:
                    coord.append(len(names))
                    label = joint.base_dofs[coordinate] if joint.kind == "base" else str(coordinate)
                    names.append(f"{joint.name}:{label}")
                    q0.append(values[coordinate])
                    targeted = joint.target is not None and not np.isnan(joint.target[coordinate])
                    targets.append(float(joint.target[coordinate]) if targeted else values[coordinate])
                    for store, source in ((kp, joint.kp), (kd, joint.kd), (lower, joint.lower), (upper, joint.upper), (margin, joint.limit_margin), (stiffness, joint.limit_stiffness)):
                        store.append(float(source[coordinate]))
                    coordinate += 1
                else:
                    coord.append(-1)
            self.joint_dofs.append(np.arange(first, len(kind)))
        self.num_dofs = len(kind)
        self.dof_kind = np.array(kind, dtype=np.int64)
        self.dof_axis_body = np.array(axis_body, dtype=np.int64)
        self.dof_axis_local = np.array(axis_local, dtype=np.float64).reshape(-1, 3)
        self.dof_point_local = np.array(point_local, dtype=np.float64).reshape(-1, 3)
        self.dof_owner = np.array(owner, dtype=np.int64)
        self.dof_group = np.array(group, dtype=np.int64)
        self.dof_coordinate = np.array(coord, dtype=np.int64)
        self.coordinate_names = names
        self.num_coordinates = len(names)
        self.coordinate_dof = np.flatnonzero(self.dof_coordinate >= 0)
        self.initial_coordinates = np.array(q0, dtype=np.float64)
        self.default_targets = np.array(targets, dtype=np.float64)
        self.kp, self.kd = np.array(kp), np.array(kd)
        self.lower, self.upper = np.array(lower), np.array(upper)
        self.limit_margin, self.limit_stiffness = np.array(margin), np.array(stiffness)
        outside = np.flatnonzero((self.initial_coordinates <= self.lower) | (self.initial_coordinates >= self.upper))
        if outside.size:
            c = outside[0]
            raise ValueError(f"joint coordinate {names[c]!r}: initial value {self.initial_coordinates[c]:.6g} is not strictly inside its limits [{self.lower[c]:.6g}, {self.upper[c]:.6g}]")
        # Each body's ancestor DOFs, root first (DOFs are numbered in topological order).
        self.body_dofs = []
        for b in range(n):
            path = []
            j = self.body_joint[b]
            while j >= 0:
                path.append(self.joint_dofs[j])
                parent = self.joints[j].parent
                j = self.body_joint[parent] if parent >= 0 else -1
            self.body_dofs.append(np.concatenate(path[::-1]) if path else np.zeros(0, dtype=np.int64))
        # Dynamic bodies are those with DOFs; rows of J for static bodies stay zero.
        self.dynamic_bodies = np.flatnonzero([len(d) > 0 for d in self.body_dofs])
        # Each body's ancestor DOFs that swing its centre of mass: every rotation but its own
        # free joint's, which turns it about that centre.
        own_turn = [self.joint_dofs[self.body_joint[b]] if self.body_joint[b] >= 0 and self.joints[self.body_joint[b]].kind == "free" else np.zeros(0, dtype=np.int64) for b in range(n)]
        self._body_swinging_dofs = [dofs[(self.dof_kind[dofs] != PRISMATIC) & ~np.isin(dofs, own)] for dofs, own in zip(self.body_dofs, own_turn)]
        # Pairs of distinct DOFs of one body's chain that belong to the same ball joint: a
        # boolean mask per body took time and memory cubic in a chain's length (45 MB at
        # 512 links).
        self._same_group = [_same_group_pairs(self.dof_group[dofs]) for dofs in self.body_dofs]
        # Bodies that only their own free joint moves and that move no other body: the free
        # bodies of a scene with joints elsewhere. Their rows of J are the identity over their
        # six DOFs, so retract, the Jacobian and the reduction take them together, not body by
        # body and through dense products (one hinge elsewhere made a step over 16 free boxes
        # 1.7x slower, the reduction cubic in them: 61 ms at 128; a probe, 2026-11-27).
        parents = {joint.parent for joint in self.joints}
        loose = [b for b in self.dynamic_bodies if self.joints[self.body_joint[b]].kind == "free" and b not in parents]
        self._loose_bodies = np.array(loose, dtype=np.int64)
        self._loose_dofs = np.array([self.joint_dofs[self.body_joint[b]] for b in loose], dtype=np.int64).reshape(-1, 6)
        self._joined_bodies = np.setdiff1d(self.dynamic_bodies, self._loose_bodies)
        # Their rows, and the others', of the Hessian over the non-static bodies.
        loose_rows = np.isin(self._hessian_rows // 6, self._loose_bodies)
        self._loose_rows, self._joined_rows = np.flatnonzero(loose_rows), np.flatnonzero(~loose_rows)
        self._joined_joints = [j for j in range(len(self.joints)) if self.joints[j].child not in self._loose_bodies]
        self._joined_dofs = np.setdiff1d(np.arange(self.num_dofs), self._loose_dofs.reshape(-1))
        self.cones = [self._cone(j, joint, poses) for j, joint in enumerate(self.joints) if joint.kind == "ball" and np.isfinite(joint.cone_limit)]
        balls = [(j, joint) for j, joint in enumerate(self.joints) if joint.kind == "ball"]
        self.num_ball_joints = len(balls)
        self.ball_joint_names = [joint.name for _, joint in balls]
        self._ball_dofs = np.array([self.joint_dofs[j] for j, _ in balls], dtype=np.int64).reshape(-1, 3)
        self._ball_parent = np.array([joint.parent for _, joint in balls], dtype=np.int64)
        self._ball_child = np.array([joint.child for _, joint in balls], dtype=np.int64)
        self._ball_parent_frame = np.array([joint.parent_frame[3:] for _, joint in balls]).reshape(-1, 4)
        self._ball_child_frame = np.array([joint.child_frame[3:] for _, joint in balls]).reshape(-1, 4)
        self.ball_kp = np.array([float(joint.kp[0]) if joint.kp is not None and len(joint.kp) else 0.0 for _, joint in balls])
        self.ball_kd = np.array([float(joint.kd[0]) if joint.kd is not None and len(joint.kd) else 0.0 for _, joint in balls])
        self.initial_ball_rotations = self.ball_rotations(poses)

    # The gains and limits are public arrays that a user may change after ``finalize``: these
    # are read from them at every step (frozen at construction, gains or limits set later on a
    # joint built without them were ignored: a ball drive never turned, a limit was crossed).
    @property
    def has_limits(self) -> bool:
        """Whether any joint coordinate has a finite limit."""
        return bool(np.isfinite(self.lower).any() or np.isfinite(self.upper).any())

    @property
    def has_ball_drives(self) -> bool:
        """Whether any ball joint has a non-zero gain."""
        return bool(np.any(self.ball_kp > 0) or np.any(self.ball_kd > 0))

    def parameter_problem(self) -> str | None:
        """What is wrong with the gains and limits as they are now (a user may change them
        after ``finalize``), or None: shapes, gains finite and >= 0, lower < upper, limit
        margins and stiffnesses positive and finite. A negative kp set later put energy in (a
        driven hinge spun away) and no step said so."""
        count, balls = self.num_coordinates, self.num_ball_joints
        arrays = (("kp", self.kp, count), ("kd", self.kd, count), ("ball_kp", self.ball_kp, balls), ("ball_kd", self.ball_kd, balls),
                  ("lower", self.lower, count), ("upper", self.upper, count), ("limit_margin", self.limit_margin, count), ("limit_stiffness", self.limit_stiffness, count))
        for label, values, size in arrays:
            if not isinstance(values, np.ndarray) or values.shape != (size,) or values.dtype.kind != "f":
                return f"{label}: expected a float numpy array of shape ({size},), got {type(values).__name__} {np.shape(values)}"
        for label, values, names in (("kp", self.kp, self.coordinate_names), ("kd", self.kd, self.coordinate_names), ("ball_kp", self.ball_kp, self.ball_joint_names), ("ball_kd", self.ball_kd, self.ball_joint_names)):
            bad = np.flatnonzero(~(np.isfinite(values) & (values >= 0.0)))
            if bad.size:
                return f"{label}: {names[bad[0]]!r} has {float(values[bad[0]])!r}; gains must be finite and >= 0"
        bad = np.flatnonzero(np.isnan(self.lower) | np.isnan(self.upper) | (self.lower >= self.upper))
        if bad.size:
            c = bad[0]
            return f"lower, upper: {self.coordinate_names[c]!r} has limits [{float(self.lower[c])!r}, {float(self.upper[c])!r}]; expected lower < upper (+-inf: no limit)"
        limited = np.isfinite(self.lower) | np.isfinite(self.upper)
        for label, values in (("limit_margin", self.limit_margin), ("limit_stiffness", self.limit_stiffness)):
            given = ~np.isnan(values) if label == "limit_margin" else True  # NaN: the default margin
            bad = np.flatnonzero(limited & given & ~(np.isfinite(values) & (values > 0.0)))
            if bad.size:
                default = " (or NaN: the default)" if label == "limit_margin" else ""
                return f"{label}: {self.coordinate_names[bad[0]]!r} has {float(values[bad[0]])!r}; a limited coordinate's must be positive and finite{default}"
        # Checked every step: one comparison over the coordinates, the message for the first only.
        margins = self.limit_margins()
        narrow = np.flatnonzero(limited & (margins < MIN_LIMIT_MARGIN))
        if narrow.size:
            c = narrow[0]
            problem = limit_margin_problem(float(margins[c]), given=not np.isnan(self.limit_margin[c]))
            return f"lower, upper, limit_margin: {self.coordinate_names[c]!r} has limits [{float(self.lower[c])!r}, {float(self.upper[c])!r}]: {problem}"
        with np.errstate(invalid="ignore"):
            wide = np.flatnonzero(self.limit_margin > 0.5 * (self.upper - self.lower))
        if wide.size:
            c = wide[0]
            return f"limit_margin: {self.coordinate_names[c]!r} has {float(self.limit_margin[c])!r}, more than half its range [{float(self.lower[c])!r}, {float(self.upper[c])!r}]: the barrier would act across all of it"
        return None

    def limit_margins(self) -> np.ndarray:
        """(num_coordinates,) the limit barriers' margins as the step uses them: ``limit_margin``,
        where NaN (the default) a tenth of the current range, at most 0.1 rad or m."""
        return effective_limit_margins(self.limit_margin, self.upper - self.lower)

    # --- construction ---------------------------------------------------------------------

    def _topological_order(self, joints: list[Joint], parent_joint: dict) -> list[int]:
        """Joint indices with every joint after its parent body's joint. Walks up each
        joint's ancestors iteratively: recursion overflowed Python's stack on chains of
        ~1,000 joints added leaf first."""
        order, done = [], set()
        for first in range(len(joints)):
            trail, on_trail = [], set()
            j = first
            while j not in done:
                if j in on_trail:
                    names = " -> ".join(joints[i].name for i in [*trail, j])
                    raise ValueError(f"joints form a cycle: {names}")
                trail.append(j)
                on_trail.add(j)
                parent = joints[j].parent
                if parent < 0:
                    break
                if parent not in parent_joint:
                    raise ValueError(f"joint {joints[j].name!r}: parent body {self.body_names[parent]!r} is static or unknown; attach to the world (parent None) instead")
                j = parent_joint[parent]
            for j in reversed(trail):
                done.add(j)
                order.append(j)
        return order

    def _frames(self, joint: Joint, poses: np.ndarray):
        parent_pose = poses[joint.parent] if joint.parent >= 0 else np.array([0, 0, 0, 0, 0, 0, 1.0])
        return pose_mul(parent_pose, joint.parent_frame), pose_mul(poses[joint.child], joint.child_frame)

    def _initial_coordinates(self, joint: Joint, poses: np.ndarray, tol: float, poses_label: str = "the initial poses") -> np.ndarray:
        """Joint coordinates of ``poses`` (revolute angles in (-pi, pi]); errors, naming the
        poses by ``poses_label``, if they violate the joint."""
        if joint.kind in ("free", "base"):
            return np.zeros(joint.num_coordinates())
        world_parent, world_child = self._frames(joint, poses)
        where = f"joint {joint.name!r} ({self._link_names(joint)})"
        # Anchors far from the origin carry their coordinates' rounding (USD authors them as
        # float32: 1.9e-7 m at 13.7 m refused a consistent joint).
        tol = max(tol, _ANCHOR_TOLERANCE * float(np.linalg.norm(world_parent[:3])))
        q_rel = _relative_rotation(world_parent[3:], world_child[3:])
        offset = quat_rotate(quat_conjugate(world_parent[3:]), world_child[:3] - world_parent[:3])
        if joint.kind == "prismatic":
            axis = joint.axes[0]
            value = float(offset @ axis)
            off_axis = float(np.linalg.norm(offset - value * axis))
            turn = _rotation_gap(q_rel, np.array([0, 0, 0, 1.0]))
            if off_axis > tol or turn > _ANGLE_TOLERANCE:
                # Both named with their sizes: "off-axis offset 0 m or relative rotation" hid a 0.4 rad turn.
                raise ValueError(f"{where}: {poses_label} violate the prismatic joint (off-axis offset {off_axis:.3g} m, relative rotation {turn:.3g} rad; it allows neither)")
            return np.array([value])
        gap = float(np.linalg.norm(offset))
        if gap > tol:
            raise ValueError(f"{where}: joint anchors are {gap:.3g} m apart in {poses_label}")
        if joint.kind == "ball":
            return np.zeros(0)
        if joint.kind == "revolute":
            values = np.array([_signed_angle(q_rel, joint.axes[0])])
        else:  # universal: R_rel = Rot(e1, q1) Rot(e2, q2)
            e1, e2 = joint.axes
            u = quat_rotate(q_rel, e2)
            q1 = float(np.arctan2(u @ cross(e1, e2), u @ e2))
            values = np.array([q1, _signed_angle(quat_mul(_rotation_about(e1, -q1), q_rel), e2)])
        error = _rotation_gap(_joint_rotation(joint, values), q_rel)
        if error > _ANGLE_TOLERANCE:
            raise ValueError(f"{where}: the relative rotation in {poses_label} is not a {joint.kind} joint motion (off by {error:.3g} rad)")
        return values

    def state_problem(self, poses: np.ndarray, coordinates: np.ndarray) -> str | None:
        """Why body ``poses`` (nbodies, 7) and joint ``coordinates`` (num_coordinates,) are not
        one configuration, or None: a joint the poses violate, or a revolute, prismatic or
        universal coordinate that disagrees with them (angles modulo 2 pi), or a base joint to
        the world whose poses and coordinates disagree (``_base_problem``)."""
        for j, joint in enumerate(self.joints):
            if joint.static_parent >= 0:
                # Moved between steps, the body left the joint behind, hinged where it was
                # built, and the joint came apart silently (a probe, stop 63).
                built, now = joint.static_parent_pose, poses[joint.static_parent]
                moved, turned = float(np.linalg.norm(now[:3] - built[:3])), _rotation_gap(now[3:], built[3:])
                if moved > self._anchor_tolerance[j] or turned > _ANGLE_TOLERANCE:
                    return (
                        f"joint {joint.name!r}: its parent, static body {self.body_names[joint.static_parent]!r}, is {moved:.3g} m and {turned:.3g} rad "
                        "from where the joint was built; a joint's static parent is part of the world and cannot move (make it dynamic and drive it, or build the model again)"
                    )
            if joint.kind == "base" and joint.parent < 0:
                problem = self._base_problem(j, joint, poses, coordinates)
                if problem is not None:
                    return problem
            if joint.kind in ("free", "base"):
                continue
            try:
                values = self._initial_coordinates(joint, poses, self._anchor_tolerance[j], "state_in.body_q")
            except ValueError as exc:
                return str(exc)
            if joint.kind == "ball":
                continue
            owned = self.dof_coordinate[self.joint_dofs[j]]
            given = coordinates[owned[owned >= 0]]
            if joint.kind == "prismatic":
                agree = abs(float(given[0] - values[0])) <= self._anchor_tolerance[j]
            else:
                agree = _rotation_gap(_joint_rotation(joint, given), _joint_rotation(joint, values)) <= _ANGLE_TOLERANCE
            if not agree:
                return f"joint {joint.name!r} ({self._link_names(joint)}): state_in.joint_q gives it {np.array2string(given, precision=6)} but state_in.body_q puts it at {np.array2string(values, precision=6)}"
        return None

    def _base_problem(self, j: int, joint: Joint, poses: np.ndarray, coordinates: np.ndarray) -> str | None:
        """Why a base joint to the world and ``poses`` disagree, or None. Its coordinates are
        the child's centre-of-mass offsets along world axes from its initial pose, and its
        turns about world axes through that centre (the second about an axis turning with the
        first); an axis it does not list stays as it was. A box on an ("x", "z") base set
        0.5 m up with its coordinates at 0 stayed there, outside its z limits, silently. Three
        turns are a rotation vector with no coordinates: only the translations are compared."""
        b = joint.child
        owned = self.dof_coordinate[self.joint_dofs[j]]
        given = dict(zip(joint.base_dofs, coordinates[owned[owned >= 0]], strict=False))
        offset = poses[b, :3] - self._initial_poses[b, :3]
        where = f"joint {joint.name!r} ({self._link_names(joint)})"
        for k, axis in enumerate(("x", "y", "z")):
            expected = given.get(axis, 0.0)
            if abs(offset[k] - expected) > self._anchor_tolerance[j]:
                said = f"state_in.joint_q gives {axis} {expected:.6g}" if axis in given else f"it has no {axis}"
                return f"{where}: {said} but state_in.body_q moves its centre of mass {offset[k]:.6g} m along {axis} from the initial pose"
        turns = [d for d in joint.base_dofs if d in ("rx", "ry", "rz")]
        if len(turns) == 3:
            return None
        expected = self._initial_poses[b, 3:]
        for d in reversed(turns):  # R = Rot1 Rot2 R0
            expected = quat_mul(_rotation_about(_BASE_AXES[d], given[d]), expected)
        if _rotation_gap(poses[b, 3:], expected) > _ANGLE_TOLERANCE:
            listed = f"turns {', '.join(f'{d} {given[d]:.6g}' for d in turns)}" if turns else "no turns"
            return f"{where}: state_in.joint_q gives {listed} but state_in.body_q turns it {_rotation_gap(poses[b, 3:], self._initial_poses[b, 3:]):.6g} rad from its initial rotation otherwise"
        return None

    def _cone(self, j: int, joint: Joint, poses: np.ndarray) -> dict:
        """A ball joint's swing limit: the axis fixed in the parent and in the child, the limit,
        the barrier's margin (rad; default a tenth of the limit, at most 0.1) and stiffness (J)."""
        axis = joint.axes[0] if len(joint.axes) else np.array([1.0, 0.0, 0.0])
        cone = {
            "dofs": self.joint_dofs[j],
            "parent": joint.parent,
            "parent_axis": quat_rotate(joint.parent_frame[3:], axis),
            "child": joint.child,
            "child_axis": quat_rotate(joint.child_frame[3:], axis),
            "limit": float(joint.cone_limit),
            "margin": float(joint.limit_margin[0]),
            "stiffness": float(joint.limit_stiffness[0]),
            "label": f"joint {joint.name!r} ({self._link_names(joint)})",
        }
        problem = self._swing_problem(cone, poses)
        if problem is not None:
            raise ValueError(f"{cone['label']}: initial {problem}")
        return cone

    def _swing_problem(self, cone: dict, poses: np.ndarray) -> str | None:
        angle = self._cone_angle(cone, poses)[0]
        if angle >= cone["limit"]:
            return f"swing {angle:.6g} rad is not strictly inside its cone limit {cone['limit']:.6g} rad"
        return None

    def cone_problem(self, poses: np.ndarray) -> str | None:
        """Why ``poses`` put a ball joint's swing on or past its cone limit, naming the joint,
        or None (the limit's barrier is infinite there)."""
        for cone in self.cones:
            problem = self._swing_problem(cone, poses)
            if problem is not None:
                return f"{cone['label']}: {problem}"
        return None

    @staticmethod
    def _cone_angle(cone: dict, poses: np.ndarray):
        """(swing angle, parent axis, child axis) in the world at ``poses``."""
        parent_axis = cone["parent_axis"] if cone["parent"] < 0 else quat_rotate(poses[cone["parent"], 3:], cone["parent_axis"])
        child_axis = quat_rotate(poses[cone["child"], 3:], cone["child_axis"])
        return float(np.arccos(np.clip(parent_axis @ child_axis, -1.0, 1.0))), parent_axis, child_axis

    def cone_terms(self, poses: np.ndarray):
        """Swing-limit barriers of ball joints: value, gradient (m,) and Hessian (m, m).

        With c = a_p . a_c (a_c turned by the joint's rotation group w: d a_c = w x a_c),
        dc/dw = a_c x a_p and d2c/dw2 = 1/2 (a_c a_p^T + a_p a_c^T) - c I; the swing is
        beta = arccos c, and the barrier is ``joint_limit_energy`` of beta below the limit.
        Ancestor motions turn both axes alike and leave c unchanged.
        """
        value, grad, hess = 0.0, np.zeros(self.num_dofs), np.zeros((self.num_dofs, self.num_dofs))
        for cone in self.cones:
            beta, a_p, a_c = self._cone_angle(cone, poses)
            e_value, e_grad, e_hess = joint_limit_energy(np.array([beta]), np.array([-np.inf]), np.array([cone["limit"]]), np.array([cone["margin"]]), np.array([cone["stiffness"]]))
            if not np.isfinite(e_value[0]):
                return np.inf, grad, hess
            if e_value[0] == 0.0 and e_grad[0] == 0.0:
                continue
            c = a_p @ a_c
            sine = np.sqrt(max(1.0 - c * c, 1e-300))
            dc = cross(a_c, a_p)
            d2c = 0.5 * (np.outer(a_c, a_p) + np.outer(a_p, a_c)) - c * np.eye(3)
            dbeta = -dc / sine
            d2beta = -d2c / sine - c / sine**3 * np.outer(dc, dc)
            d = cone["dofs"]
            value += float(e_value[0])
            grad[d] += e_grad[0] * dbeta
            hess[np.ix_(d, d)] += e_hess[0] * np.outer(dbeta, dbeta) + e_grad[0] * d2beta
        return value, grad, hess

    def pressed_limit(self, poses: np.ndarray, coords: np.ndarray, direction: np.ndarray, *, fraction: float, rounding: float) -> bool:
        """Whether the step ``direction`` (reduced DOFs) moves a coordinate inside its limit
        barrier's margin by more than ``fraction`` of its distance to the nearer limit, or turns
        a swing inside its cone's margin by more than ``fraction`` of its room to the cone (to
        first order), beyond ``rounding`` (relative) of the values: beside a barrier Newton's step is about
        the gap, however unbalanced the force, so such a step is no convergence (a slider
        1e-11 m from its limit, driven away from it at 100 N/m, "converged" there at every step
        and never moved; a probe, stop 65). ``ImplicitSolver._pressed`` is the rule for contacts."""
        if self.has_limits:
            room = np.minimum(coords - self.lower, self.upper - coords)
            near = room < self.limit_margins()
            if near.any():
                scale = np.maximum.reduce([np.abs(coords), np.where(np.isfinite(self.lower), np.abs(self.lower), 0.0), np.where(np.isfinite(self.upper), np.abs(self.upper), 0.0)])
                delta = np.abs(direction[self.coordinate_dof])
                if np.any(near & (delta > np.maximum(fraction * room, rounding * scale))):
                    return True
        for cone in self.cones:
            swing, a_p, a_c = self._cone_angle(cone, poses)
            room = cone["limit"] - swing
            if room >= cone["margin"]:
                continue
            # d swing / d w = -(a_c x a_p) / sin(swing): the swing is near the limit, far from 0.
            turn = abs(float(cross(a_c, a_p) @ direction[cone["dofs"]])) / max(np.sin(swing), 1e-300)
            if turn > max(fraction * room, rounding * cone["limit"]):
                return True
        return False

    def cone_step_limit(self, poses: np.ndarray, direction: np.ndarray, fraction: float) -> float:
        """Largest step fraction whose rotation opens no swing by more than ``fraction`` of its
        room to its cone limit, anywhere along the turn.

        Turning by alpha w carries the child's axis a_c round a circle about w, on which
        a_p . a_c = A + B cos(theta) + C sin(theta), theta = alpha |w|; the bound is the first
        theta at which that cosine falls to the allowed swing's (exact, so twist about a_c
        and motion along the cone's rim cost nothing: bounding a_c's whole motion |w x a_c|
        held a rod whirling on the rim to ~1e-3 of its Newton steps, and Newton stalled)."""
        alpha = 1.0
        for cone in self.cones:
            swing, a_p, a_c = self._cone_angle(cone, poses)
            w = direction[cone["dofs"]]
            speed = float(np.linalg.norm(w))
            if speed == 0.0:
                continue
            axis = w / speed
            centre = (axis @ a_c) * axis
            radial = a_c - centre
            A, B, C = float(a_p @ centre), float(a_p @ radial), float(a_p @ cross(axis, a_c))
            allowed = np.cos(swing + fraction * (cone["limit"] - swing))
            amplitude = float(np.hypot(B, C))
            if amplitude == 0.0 or allowed - A <= -amplitude:
                continue  # the swing never reaches the allowed one on this circle
            # A + amplitude cos(theta - phi) = allowed at theta = phi +- gamma (mod 2 pi); the
            # first positive one (the start, theta = 0, lies inside the allowed arc).
            phi = float(np.arctan2(C, B))
            gamma = float(np.arccos(min(1.0, (allowed - A) / amplitude)))
            theta = min((phi + sign * gamma) % (2.0 * np.pi) for sign in (1.0, -1.0))
            alpha = min(alpha, theta / speed)
        return alpha

    # --- ball-joint drives ------------------------------------------------------------------

    def _ball_frames(self, poses: np.ndarray):
        """World rotations (nball, 4) of every ball joint's frame fixed in the parent and in the child."""
        rotations = poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
        parent = np.where((self._ball_parent >= 0)[:, None], rotations[self._ball_parent], [0.0, 0.0, 0.0, 1.0])
        return quat_mul(parent, self._ball_parent_frame), quat_mul(rotations[self._ball_child], self._ball_child_frame)

    def ball_rotations(self, poses: np.ndarray) -> np.ndarray:
        """Relative rotations (nball, 4) of the ball joints at ``poses`` (nbodies, 7): unit
        quaternions (x, y, z, w) of the child's joint frame in the parent's joint frame (the
        world's for a joint to the world), the convention of ``Control.ball_target``."""
        if not self.num_ball_joints:
            return np.zeros((0, 4))  # read every step: the frames of no joints cost 0.24 ms
        return _relative_rotation(*self._ball_frames(poses))

    def _ball_drive_matrices(self, poses: np.ndarray, target: np.ndarray, start: np.ndarray, dt: float, gains: tuple | None = None):
        """World frame rotations (parent, child) as quaternions, P as matrices, and the spring
        and damper matrices kp P R* C^T and kd/dt P R^t C^T, (nball, 3, 3) each; ``gains``
        (kp, kd) instead of the joints' own."""
        kp, kd = gains if gains is not None else (self.ball_kp, self.ball_kd)
        parent, child = self._ball_frames(poses)
        P = quat_to_matrix(parent)
        C_transposed = np.swapaxes(quat_to_matrix(child), 1, 2)
        spring = kp[:, None, None] * (P @ quat_to_matrix(target) @ C_transposed)
        damper = (kd / dt)[:, None, None] * (P @ quat_to_matrix(start) @ C_transposed)
        return parent, child, P, spring, damper

    def ball_drive_terms(self, poses: np.ndarray, target: np.ndarray, start: np.ndarray, dt: float):
        """Implicit PD of the ball joints: value (J), gradient (m,) and Hessian (m, m).

        Per ball joint, with R its relative rotation (``ball_rotations``), R* its target and
        R^t its relative rotation at the start of the step (``target`` and ``start``,
        (nball, 4) unit quaternions):

            E = kp/2 (3 - tr(R*^T R)) + kd/(2 dt) (3 - tr(R^t^T R))
              = kp (1 - cos theta*) + kd/dt (1 - cos theta^t),

        theta the angle between the two rotations: the body orientation PD's form, smooth on
        the whole rotation group (a hinge's kp/2 theta^2 to fourth order). The joint's rotation
        group w turns the child's frame C to exp([w]x) C in the world and ancestor motions
        turn both frames alike, so with M = P (kp R* + kd/dt R^t) C^T the gradient is
        -1/2 axial(M) and the Hessian 1/2 (tr(M) I - sym(M)). Each value term is evaluated
        as 2 |vec(q_ref^-1 q)|^2 (= 1 - cos theta), which keeps its digits near the
        reference where the trace form cancels.
        """
        parent, child, _, spring, damper = self._ball_drive_matrices(poses, target, start, dt)
        relative = _relative_rotation(parent, child)

        def one_minus_cosine(reference):
            return 2.0 * np.sum(quat_mul(quat_conjugate(reference), relative)[:, :3] ** 2, axis=1)

        value = float(np.sum(self.ball_kp * one_minus_cosine(target) + self.ball_kd / dt * one_minus_cosine(start)))
        grad, hess = np.zeros(self.num_dofs), np.zeros((self.num_dofs, self.num_dofs))
        for dofs, m in zip(self._ball_dofs, spring + damper, strict=True):
            grad[dofs] -= 0.5 * axial(m)
            hess[np.ix_(dofs, dofs)] += 0.5 * (np.trace(m) * np.eye(3) - 0.5 * (m + m.T))
        return value, grad, hess

    def ball_drive_adjoint(self, poses: np.ndarray, poses_start: np.ndarray, lam: np.ndarray, target: np.ndarray, dt: float, *, target_is_start: bool = False, gains: tuple | None = None):
        """lambda^T d(gradient of ``ball_drive_terms``)/d(inputs) at ``poses`` for a reduced
        adjoint ``lam`` (m,), with R^t taken from the step's start poses ``poses_start``.

        Returns the targets' cotangents (nball, 3), as left turns exp([g]x) R* in the parent's
        joint frame, and the start poses' rigid cotangent (nbodies, 6) (dp, dtheta).
        Turning a term's world frame P R_ref by exp([zeta]x) turns M by it and changes the
        gradient by -1/2 (tr(M) I - M) zeta. A start turn beta of the child turns P R^t =
        P P_t^T C_t by P P_t^T beta; the parent's turns it by the opposite.

        ``target_is_start``: the targets are the start's relative rotations (a step without
        ball targets holds each joint where it starts), so their cotangents are also turns of
        the start poses: a left turn g of R^t is a turn P_t g of the child's start.
        ``gains``: (kp, kd) the step used, when the joints' own have changed since.
        """
        parent_start, child_start = self._ball_frames(poses_start)
        start = _relative_rotation(parent_start, child_start)
        _, _, P, spring, damper = self._ball_drive_matrices(poses, target, start, dt, gains)
        P_start = quat_to_matrix(parent_start)

        def turn_adjoint(m, l):
            return -0.5 * (np.trace(m) * l - m.T @ l)

        target_adjoint = np.zeros((self.num_ball_joints, 3))
        start_adjoint = np.zeros((self.num_bodies, 6))
        for i, dofs in enumerate(self._ball_dofs):
            target_adjoint[i] = P[i].T @ turn_adjoint(spring[i], lam[dofs])
            turn = P_start[i] @ (P[i].T @ turn_adjoint(damper[i], lam[dofs]) + (target_adjoint[i] if target_is_start else 0.0))
            start_adjoint[self._ball_child[i], 3:] += turn
            if self._ball_parent[i] >= 0:
                start_adjoint[self._ball_parent[i], 3:] -= turn
        return target_adjoint, start_adjoint

    def _link_names(self, joint: Joint) -> str:
        parent = self.body_names[joint.parent] if joint.parent >= 0 else "world"
        return f"{parent} -> {self.body_names[joint.child]}"

    def _joint_dofs(self, joint: Joint, poses: np.ndarray):
        """(kind, axis body, axis in that body's frame (world for -1), point in the child frame, group)."""
        child_rot = joint.child_frame[3:]
        anchor = joint.child_frame[:3]
        parent_body = joint.parent
        if joint.kind == "revolute":
            return [(REVOLUTE, joint.child, quat_rotate(child_rot, joint.axes[0]), anchor, -1)]
        if joint.kind == "prismatic":
            return [(PRISMATIC, parent_body, quat_rotate(joint.parent_frame[3:], joint.axes[0]), anchor, -1)]
        if joint.kind == "universal":
            return [
                (REVOLUTE, parent_body, quat_rotate(joint.parent_frame[3:], joint.axes[0]), anchor, -1),
                (REVOLUTE, joint.child, quat_rotate(child_rot, joint.axes[1]), anchor, -1),
            ]
        if joint.kind == "ball":
            return [(ROTATION, -1, e, anchor, joint.child) for e in np.eye(3)]
        # base / free: world translations, then rotations about the child's centre of mass
        out = [(PRISMATIC, -1, _BASE_AXES[d], np.zeros(3), -1) for d in joint.base_dofs if d in ("x", "y", "z")]
        rotations = [_BASE_AXES[d] for d in joint.base_dofs if d in ("rx", "ry", "rz")]
        if len(rotations) == 3:
            out += [(ROTATION, -1, e, np.zeros(3), joint.child) for e in rotations]
        elif rotations:
            out.append((REVOLUTE, -1, rotations[0], np.zeros(3), -1))
            if len(rotations) == 2:
                # the second axis turns with the first: fixed in the child (R = Rot1 Rot2 R0)
                out.append((REVOLUTE, joint.child, quat_rotate(quat_conjugate(poses[joint.child, 3:]), rotations[1]), np.zeros(3), -1))
        return out

    # --- kinematics at a configuration ----------------------------------------------------

    def twists(self, poses: np.ndarray):
        """World axes a (m, 3) and points c (m, 3) of every DOF at ``poses`` (nbodies, 7)."""
        body = self.dof_axis_body
        axes = self.dof_axis_local.copy()
        moving = body >= 0
        axes[moving] = quat_rotate(poses[body[moving], 3:], axes[moving])
        owner = self.dof_owner
        points = quat_rotate(poses[owner, 3:], self.dof_point_local) + poses[owner, :3]
        return axes, points

    def _columns(self, dofs: np.ndarray, p: np.ndarray, axes: np.ndarray, points: np.ndarray):
        """The angular and linear velocity (omega, v) per unit increment of each of a body's
        ``dofs`` (its chain's, (n,); or a stack of bodies', (k, n), with ``p`` (k, 1, 3)) for
        the body's centre at ``p``."""
        a = axes[dofs]
        rotating = (self.dof_kind[dofs] != PRISMATIC)[..., None]
        omega = np.where(rotating, a, 0.0)
        velocity = np.where(rotating, cross(a, p - points[dofs]), a)
        return omega, velocity

    @staticmethod
    def _curvature_block(g_p, g_w, omega, velocity, same) -> np.ndarray:
        """A body's block of C over its chain's DOFs (or a stack of them) for its rigid
        gradient (g_p, g_w): g_p . (a_k x v_l) = (g_p x a_k) . v_l, zero rows for prismatic k
        via omega, 1/2 g_w . (omega_k x omega_l), symmetrised inside an exponential group
        (``same``: its (rows, columns))."""
        M = cross(g_p, omega) @ np.swapaxes(velocity, -1, -2)
        N = 0.5 * cross(g_w, omega) @ np.swapaxes(omega, -1, -2)
        upper = np.triu(M + N, 1)
        diagonal = np.zeros_like(M)
        index = range(M.shape[-1])
        diagonal[..., index, index] = M[..., index, index]
        block = upper + np.swapaxes(upper, -1, -2) + diagonal
        rows, columns = same
        block[..., rows, columns] = (0.5 * (M + np.swapaxes(M, -1, -2)))[..., rows, columns]
        return block

    def curvature(self, poses: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """sum_i g_i . d2(p_i, theta_i)/d delta2 (m, m) for a rigid gradient ``grad`` (nbodies, 6)."""
        return self._jacobian_and_curvature(poses, grad)[1]

    def reduce(self, poses: np.ndarray, grad: np.ndarray, hess: np.ndarray):
        """(J, J^T g, J^T H J + C) for a rigid-coordinate gradient (6 nbodies,) and a symmetric
        Hessian over the non-static bodies (6 ndynamic, 6 ndynamic), as the contact models give
        them (with loose bodies, one off-diagonal block is the other's transpose);
        J (6 nbodies, m) holds the rigid coordinates (dp, dtheta) of each body per DOF
        increment (zero rows for static bodies)."""
        J, C = self._jacobian_and_curvature(poses, grad.reshape(-1, 6))
        if not len(self._loose_bodies):
            moving = J[self._hessian_rows]
            return J, J.T @ grad, moving.T @ hess @ moving + C
        # The loose bodies' block of J is the identity (their rows in DOF order), and no other
        # block couples them: J^T H J from H's blocks, without products by the identity. The
        # same sums over fewer rows: BLAS may round them differently (1 ulp in 8 of 1,369
        # entries on a random H), while the shipped Ant-Push rollouts hash unchanged.
        joined, loose = self._joined_rows, self._loose_rows
        joined_dofs, loose_dofs = self._joined_dofs, self._loose_dofs.reshape(-1)
        moved = J[np.ix_(self._hessian_rows[joined], joined_dofs)]
        reduced = np.empty((self.num_dofs, self.num_dofs))
        reduced[np.ix_(joined_dofs, joined_dofs)] = moved.T @ hess[np.ix_(joined, joined)] @ moved
        across = moved.T @ hess[np.ix_(joined, loose)]
        reduced[np.ix_(joined_dofs, loose_dofs)] = across
        reduced[np.ix_(loose_dofs, joined_dofs)] = across.T
        reduced[np.ix_(loose_dofs, loose_dofs)] = hess[np.ix_(loose, loose)]
        return J, J.T @ grad, reduced + C

    def _jacobian_and_curvature(self, poses, grad):
        axes, points = self.twists(poses)
        J = np.zeros((6 * self.num_bodies, self.num_dofs))
        C = np.zeros((self.num_dofs, self.num_dofs))
        loose = self._loose_bodies
        if len(loose):
            # All loose bodies at once, with the products the joined bodies take one by one
            # (each loose chain is its free joint's six DOFs, one exponential group).
            dofs = self._loose_dofs
            omega, velocity = self._columns(dofs, poses[loose, None, :3], axes, points)
            rows = 6 * loose[:, None] + np.arange(3)
            J[rows[:, :, None], dofs[:, None, :]] = np.swapaxes(velocity, 1, 2)
            J[(rows + 3)[:, :, None], dofs[:, None, :]] = np.swapaxes(omega, 1, 2)
            C[dofs[:, :, None], dofs[:, None, :]] += self._curvature_block(grad[loose, None, :3], grad[loose, None, 3:], omega, velocity, self._same_group[loose[0]])
        for b in self._joined_bodies:
            dofs = self.body_dofs[b]
            omega, velocity = self._columns(dofs, poses[b, :3], axes, points)
            J[6 * b : 6 * b + 3, dofs] = velocity.T
            J[6 * b + 3 : 6 * b + 6, dofs] = omega.T
            C[np.ix_(dofs, dofs)] += self._curvature_block(grad[b, :3], grad[b, 3:], omega, velocity, self._same_group[b])
        return J, C

    def swing_bounds(self, step: np.ndarray) -> np.ndarray:
        """(nbodies,) upper bounds on the angle (rad) through which each body's centre of mass
        swings about other points along the product of exponentials of the DOF increments
        ``step`` (m,): the sum of its ancestors' rotational increments' magnitudes (a rotation
        vector's components bound its norm), its own free joint's turn left out."""
        magnitude = np.abs(step)
        return np.array([magnitude[dofs].sum() for dofs in self._body_swinging_dofs])

    def retract(self, poses: np.ndarray, step: np.ndarray) -> np.ndarray:
        """Poses moved by the DOF increments ``step`` (m,) (the product of exponentials)."""
        axes, points = self.twists(poses)
        motion_q = np.zeros((self.num_bodies, 4))
        motion_q[:, 3] = 1.0
        motion_t = np.zeros((self.num_bodies, 3))
        out = poses.copy()
        loose = self._loose_bodies
        if len(loose):
            # The loop's free joint for all loose bodies at once, in its order: the three
            # translations, then the turn about the centre (no parent: G starts at identity).
            # G stays the identity until the turn, and rotating by it or composing with it
            # changes no number: the translations add up, then the turn's shift of the centre.
            dofs = self._loose_dofs
            gt = np.zeros((len(loose), 3))
            for k in range(3):
                gt = gt + axes[dofs[:, k]] * step[dofs[:, k], None]
            group = dofs[:, 3:]
            gq = quat_from_rotation_vector(np.einsum("kji,kj->ki", axes[group], step[group]))
            centre = points[dofs[:, 3]]
            gt = gt + (centre - quat_rotate(gq, centre))
            out[loose, :3] = quat_rotate(gq, poses[loose, :3]) + gt
            q = quat_mul(gq, poses[loose, 3:])
            out[loose, 3:] = q / np.array([np.linalg.norm(row) for row in q])[:, None]
        for j in self._joined_joints:
            joint = self.joints[j]
            b = joint.child
            if joint.parent >= 0:
                gq, gt = motion_q[joint.parent].copy(), motion_t[joint.parent].copy()
            else:
                gq, gt = np.array([0, 0, 0, 1.0]), np.zeros(3)
            dofs = self.joint_dofs[j]
            k = 0
            while k < len(dofs):
                d = dofs[k]
                if self.dof_kind[d] == PRISMATIC:
                    eq, et = np.array([0, 0, 0, 1.0]), axes[d] * step[d]
                    k += 1
                elif self.dof_kind[d] == REVOLUTE:
                    eq = _rotation_about(axes[d], step[d])
                    et = points[d] - quat_rotate(eq, points[d])
                    k += 1
                else:  # one exponential for the whole 3-axis group
                    group = dofs[k : k + 3]
                    eq = quat_from_rotation_vector(axes[group].T @ step[group])
                    et = points[d] - quat_rotate(eq, points[d])
                    k += 3
                # G <- G o E
                gt = gt + quat_rotate(gq, et)
                gq = quat_mul(gq, eq)
            motion_q[b], motion_t[b] = gq, gt
            out[b, :3] = quat_rotate(gq, poses[b, :3]) + gt
            q = quat_mul(gq, poses[b, 3:])
            out[b, 3:] = q / np.linalg.norm(q)
        return out

    def step_between(self, poses_from: np.ndarray, poses_to: np.ndarray, coords_from: np.ndarray, coords_to: np.ndarray) -> np.ndarray:
        """The DOF increments (m,) that ``retract`` takes from ``poses_from`` to ``poses_to``:
        the coordinates' differences, and for free and ball joints the rotation vector and
        translation of each joint's own motion (its child's motion after its parent's), so
        that ``retract(poses_from, f * step)`` follows the joints from one to the other."""
        step = np.zeros(self.num_dofs)
        coordinate = self.dof_coordinate >= 0
        step[coordinate] = coords_to[self.dof_coordinate[coordinate]] - coords_from[self.dof_coordinate[coordinate]]
        axes, points = self.twists(poses_from)
        turn = quat_mul(poses_to[:, 3:], quat_conjugate(poses_from[:, 3:]))
        shift = poses_to[:, :3] - quat_rotate(turn, poses_from[:, :3])
        for j, joint in enumerate(self.joints):
            dofs = self.joint_dofs[j]
            group = dofs[self.dof_kind[dofs] == ROTATION]
            if not len(group):
                continue
            b, p = joint.child, joint.parent
            own_turn, own_shift = turn[b], shift[b]
            if p >= 0:  # E = G_p^-1 G_b
                back = quat_conjugate(turn[p])
                own_turn, own_shift = quat_mul(back, turn[b]), quat_rotate(back, shift[b] - shift[p])
            step[group] = axes[group] @ rotation_vector_from_quat(own_turn)
            sliding = dofs[(self.dof_kind[dofs] == PRISMATIC) & ~coordinate[dofs]]
            if len(sliding):  # a free joint: translation, then the turn about the centre
                centre = points[group[0]]
                step[sliding] = axes[sliding] @ (own_shift - (centre - quat_rotate(own_turn, centre)))
        return step

    def anchor_gaps(self, poses: np.ndarray) -> np.ndarray:
        """Distance (m) between each body joint's anchors in the parent and child (0 for roots)."""
        out = np.zeros(len(self.joints))
        for j, joint in enumerate(self.joints):
            if joint.kind in ("free", "base") or joint.kind == "prismatic":
                continue
            world_parent, world_child = self._frames(joint, poses)
            out[j] = float(np.linalg.norm(world_parent[:3] - world_child[:3]))
        return out

    def coordinates(self, poses: np.ndarray) -> np.ndarray:
        """Revolute and prismatic joint coordinates of joints between bodies, from ``poses``
        (base coordinates are not recoverable from poses alone and come back as NaN)."""
        out = np.full(self.num_coordinates, np.nan)
        for j, joint in enumerate(self.joints):
            if joint.kind in ("free", "base", "ball"):
                continue
            coords = self.dof_coordinate[self.joint_dofs[j]]
            out[coords] = self._initial_coordinates(joint, poses, np.inf)
        return out


def _angles_within(angles: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """``angles`` (in (-pi, pi], as poses give them) moved by whole turns strictly inside
    (lower, upper) where a turn of them lies there (the first above the lower limit, or with
    none the first below the upper): poses tell an angle only modulo 2 pi, and a hinge posed
    at 3.5 rad within limits (3, 4) read as -2.78 was refused. An angle already inside is
    kept, so limits wider than a turn keep the (-pi, pi] reading."""
    out = np.array(angles, dtype=np.float64)
    turn = 2.0 * np.pi
    for i, (angle, low, high) in enumerate(zip(out, lower, upper, strict=True)):
        if low < angle < high:
            continue
        if np.isfinite(low):
            candidate = angle + turn * np.ceil((low - angle) / turn)
            candidate += turn if candidate <= low else 0.0
        else:
            candidate = angle - turn * np.ceil((angle - high) / turn)
            candidate -= turn if candidate >= high else 0.0
        if low < candidate < high:
            out[i] = candidate
    return out


def frame_in_body(body_pose: np.ndarray, world_frame: np.ndarray) -> np.ndarray:
    """A world frame (7,) expressed in a body's frame."""
    return pose_mul(pose_inverse(body_pose), world_frame)
