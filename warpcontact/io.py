"""USD scenes in and out (usd-core, imported lazily so the contact core works without it).

Import reads the UsdPhysics schemas through ``UsdPhysics.LoadUsdPhysicsFromRange`` (or its
newer name) plus warpcontact's own attributes; export writes a scene (round-trippable) or a
simulated trajectory (time-sampled transforms, meshes authored once).

warpcontact namespace (all optional; defaults in ``SimulationSettings`` / ``BodySpec``; for users, with
units and defaults: docs/scene_format.md):

    on the PhysicsScene prim
        warpcontact:timeStep (double, s)          warpcontact:frames (int)
        warpcontact:contactStiffness (double)     warpcontact:eps (double)
        warpcontact:friction (double)             warpcontact:frictionSmoothing (double, m/s)
        warpcontact:contactMode (token: bsh | brute | ipc | sdrs)
        warpcontact:centredWeight (token: paper | pairs)
        warpcontact:leafPrecision (token: float64 | float32)
        warpcontact:task:name (string)            warpcontact:task:control (token)
        warpcontact:task:horizon (int)            warpcontact:task:recedingHorizon (int)
        warpcontact:task:learningRate (double)    warpcontact:task:iterations (int)
        warpcontact:task:recedingStride (int: frames executed per window, default 1)
        warpcontact:task:quick:horizon (int)      warpcontact:task:quick:recedingHorizon (int)
        warpcontact:task:quick:learningRate (double)  warpcontact:task:quick:iterations (int)
        warpcontact:task:quick:recedingStride (int)
            (the ``--quick`` preset: minutes on a 2-core CPU; horizon 0 = no preset, when no other quick value is authored)
        warpcontact:task:sampleLow (double[])     warpcontact:task:sampleHigh (double[])
            (per control DOF, in warpcontact:control:dofs order: the box that
            ``--init-samples`` draws initial-state controls from)
    on a rigid-body prim
        warpcontact:target:position (double3)     warpcontact:target:tolerance (double)
            (the goal of the body's centre of mass, the paper's x_com, not of the prim's origin;
            stage units, in the stage's world frame, whatever transforms the prim's parents carry)
        warpcontact:pd:kpLinear (double3)         warpcontact:pd:kdLinear (double3)
        warpcontact:pd:kpAngular (double)         warpcontact:pd:kdAngular (double)
        warpcontact:control:dofs (string[]: the optimised DOFs, each once: x y z rx ry rz
            yaw (the rotation about the stage's up axis: rz, or ry on a Y-up stage), and vx vy vz
            for initial_state control; a PD target needs PD stiffness)
        warpcontact:group (int, e.g. the label of a Sort cube)

Any other warpcontact: attribute, or one on another kind of prim, is an error naming it (a
typo would otherwise fall back to the default silently).

Primitive colliders are triangulated: Cube exactly (12 triangles), Sphere as an icosphere
with ``SPHERE_SUBDIVISIONS`` = 2 (320 triangles), Capsule and Cylinder with 32 segments; use
Mesh prims to control resolution; Cone with 32 segments; Capsule_1 and Cylinder_1 (two end
radii) as the hull of their end spheres or rings; a mass from density is the triangulated
shape's (a Sphere's 3.4% below the sphere's). A static Plane (infinite) becomes a square of
``PLANE_SIZE_FACTOR`` times the other bodies' extent, centred under them. Polygons are fan-triangulated where convex and ear-clipped where not; self-intersecting ones are refused.
Kinematic or disabled rigid bodies load as static bodies (an animated kinematic body is an
error; their authored velocities are dropped with a warning). Scales anywhere above a collider
apply as USD composes them; a rigid body's frame is its prim's with the scale removed (the
nearest rotation where the scale is not uniform). Where UsdPhysics' description of a
collider (a rigid pose and a scale along the collider's own axes) cannot hold its
transform (a shear from a non-uniform scale above a rotated collider, or any collider of a
non-uniformly scaled body), its points are moved by its full world matrix instead (Mesh,
Cube, Sphere, Capsule and Cylinder colliders). A mirroring transform (negative
determinant) or a leftHanded Mesh reverses the triangles' winding, so closed meshes stay
outward-oriented for mass from density; a joint on a mirrored body is an error. Faces in
holeIndices are not collided. MeshCollisionAPI approximations that stand in for the exact
triangles (convexDecomposition, meshSimplification, sdf) collide the triangles themselves;
convexHull collides the hull of the mesh's points; boundingSphere and boundingCube are errors. The initial state is read at the default time
code; a body or collider transform animated (time samples or a spline) without a default value is an error,
as are bodies or colliders under a PointInstancer and physics:startsAsleep.
Bound physics materials give density (per body) and dynamicFriction (the scene's one
coefficient, unless warpcontact:friction is authored; a collider without a material takes
the PhysicsScene's, and one with none beside others with one is warned about); values that
differ where one is needed are errors, as are per-collider MassAPI properties beyond a single collider's
mass or density; mass properties authored at UsdPhysics' "not specified" values (a mass,
density or inertia of 0, a centre of mass of -inf) are read as not specified. Collision filters (FilteredPairsAPI, CollisionGroup filtering) are errors.
PhysX schema attributes are not read; non-zero PhysX body damping and material restitution
(not a parameter here: the implicit step's damping sets how much bodies bounce) are named in a
warning.
A stage that does not compose (a missing reference, payload or sublayer, which USD only
warns about) is an error listing what is missing. Stage metersPerUnit is applied to lengths
(unauthored, USD's fallback of 0.01 applies: centimetres; zero, negative or NaN is an
error), and UsdPhysics' kilogramsPerUnit (fallback 1) to masses; densities, inertias and
DriveAPI gains (linear: mass/s^2 and mass/s; angular: mass distance^2 per degree, per s^2
and per s) take both, and become SI per radian. warpcontact: attributes other than target
positions and tolerances are SI. The stage up axis only sets the default gravity when no
PhysicsScene gives one.
A stage holds at most one PhysicsScene; a non-finite gravity magnitude is an error (a
negative one means Earth's gravity, as UsdPhysics specifies).
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import os
import re
import shutil
import warnings
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import trimesh

from ._files import replace_file
from ._validate import MAX_COORDINATE, MAX_FRAMES, QUATERNION_TOLERANCE, checked_flag, is_gain, is_positive_finite, is_real, real_array, shown, time_step_problem
from .articulation import frame_in_body
from .builder import MODEL_CONTACT_MODES, ModelBuilder, _per_coordinate, contact_setting_problem, coordinate_limits, flat_twice_area, float32_values
from .contact import CENTRED_WEIGHTS, UNSOLVED_HINT
from .hull import convex_hull_mesh
from .leaf import LEAF_PRECISIONS
from .rotation import normalized_poses, pose_mul, quat_conjugate, quat_from_matrix, quat_mul, quat_rotate, quat_to_matrix, rotation_vector_from_quat
from .sphere_tree import repeated_corner_sets

__all__ = [
    "BodySpec",
    "ColliderPart",
    "JointSpec",
    "MeshOrigin",
    "Scene",
    "SimulationSettings",
    "TaskSpec",
    "load_scene",
    "target_problem",
    "USD_SUFFIXES",
    "USD_READ_SUFFIXES",
    "save_scene",
    "export_trajectory",
    "model_to_scene_poses",
    "SPHERE_SUBDIVISIONS",
    "PLANE_SIZE_FACTOR",
    "ROUND_SEGMENTS",
]

SPHERE_SUBDIVISIONS = 2
ROUND_SEGMENTS = 32
_NS = "warpcontact:"


# The model settings a scene leaves out take ModelBuilder's own defaults.
_BUILDER_DEFAULTS = {name: parameter.default for name, parameter in inspect.signature(ModelBuilder.__init__).parameters.items()}


@dataclass
class SimulationSettings:
    """Simulation settings of a scene (SI units); the model's default to ModelBuilder's."""

    time_step: float = 0.04
    frames: int = 100
    contact_stiffness: float = _BUILDER_DEFAULTS["contact_stiffness"]
    eps: float = _BUILDER_DEFAULTS["eps"]
    centred_weight: str = _BUILDER_DEFAULTS["centred_weight"]
    leaf_precision: str = _BUILDER_DEFAULTS["leaf_precision"]
    friction: float = _BUILDER_DEFAULTS["friction"]
    friction_smoothing: float = _BUILDER_DEFAULTS["friction_smoothing"]
    contact_mode: str = _BUILDER_DEFAULTS["contact_mode"]


@dataclass
class TaskSpec:
    """Optimisation task metadata (used by the task runner)."""

    name: str = ""
    control: str = ""
    horizon: int = 0
    receding_horizon: int = 0
    learning_rate: float = 0.0
    iterations: int = 0
    # Frames executed from each optimised window before the next (the paper's is 1).
    receding_stride: int = 1
    # The ``--quick`` preset (tasks.TaskSettings.from_task); quick_horizon 0: none.
    quick_horizon: int = 0
    quick_receding_horizon: int = 0
    quick_learning_rate: float = 0.0
    quick_iterations: int = 0
    quick_receding_stride: int = 1
    # The box initial-state controls are sampled from (tasks.TaskSettings.initial_samples):
    # one bound per control DOF, in ``control_dofs`` order; empty: no box.
    sample_low: tuple = ()
    sample_high: tuple = ()


def _specs_equal(a, b) -> bool:
    """Field-by-field equality of scene specs whose fields hold numpy arrays (the dataclass
    ``==`` compared them with ``==`` and raised "the truth value of an array is ambiguous"
    for a scene against its pickled copy, a probe): arrays equal in shape and values, lists
    and tuples item by item."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and np.array_equal(a, b)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_specs_equal(x, y) for x, y in zip(a, b, strict=True))
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(_specs_equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a) if f.compare)
    return bool(a == b)


class _ArrayFieldEquality:
    """``==`` for the scene dataclasses that hold numpy arrays (``_specs_equal``); unhashable,
    as the dataclass ``==`` left them."""

    def __eq__(self, other):
        return _specs_equal(self, other) if type(other) is type(self) else NotImplemented

    __hash__ = None


@dataclass(eq=False)
class BodySpec(_ArrayFieldEquality):
    """One rigid body: triangle mesh in the body's prim frame and its physical data."""

    name: str
    path: str
    vertices: np.ndarray
    faces: np.ndarray
    pose: np.ndarray  # (7,) prim frame in world: px py pz qx qy qz qw
    static: bool = False
    mass: float | None = None
    density: float | None = None
    inertia: np.ndarray | None = None  # about the centre of mass, prim axes
    center_of_mass: np.ndarray | None = None  # prim frame
    linear_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad/s
    kp_linear: np.ndarray = field(default_factory=lambda: np.zeros(3))
    kd_linear: np.ndarray = field(default_factory=lambda: np.zeros(3))
    kp_angular: float = 0.0
    kd_angular: float = 0.0
    target_position: np.ndarray | None = None
    target_tolerance: float = 0.0
    control_dofs: tuple = ()
    group: int = -1
    # Where its mesh was read from (``MeshOrigin``; None for a body built in Python), which
    # errors about the mesh name while the mesh is the one read. Not part of equality: a body
    # is what it is, wherever it came from.
    mesh_origin: MeshOrigin | None = field(default=None, compare=False)


@dataclass(frozen=True, eq=False)
class ColliderPart(_ArrayFieldEquality):
    """A run of a loaded body's triangles and vertices and the collider prim it came from:
    ``faces`` holds each triangle's authored face for a Mesh (None for a primitive or a
    convex hull, which the loader triangulates); a Mesh's vertices are its points, in order."""

    prim: str
    first_triangle: int
    first_vertex: int
    faces: np.ndarray | None = None

    def face_name(self, triangle: int) -> str:
        return f"face {int(self.faces[triangle])} of {self.prim}" if self.faces is not None else f"triangle {triangle} of {self.prim}'s triangulation"

    def vertex_name(self, vertex: int) -> str:
        return f"point {vertex} of {self.prim}" if self.faces is not None else f"vertex {vertex} of {self.prim}'s triangulation"


@dataclass(frozen=True, eq=False)
class MeshOrigin(_ArrayFieldEquality):
    """The colliders a loaded body's mesh was joined from (``ColliderPart``s, in mesh order)
    and a digest of the mesh they describe."""

    parts: tuple
    digest: str

    @staticmethod
    def mesh_digest(vertices: np.ndarray, faces: np.ndarray) -> str:
        return hashlib.sha1(np.ascontiguousarray(vertices, dtype=np.float64).tobytes() + np.ascontiguousarray(faces, dtype=np.int64).tobytes()).hexdigest()


def _mesh_names(body: BodySpec):
    """``ModelBuilder.add_body``'s ``mesh_names`` for a loaded body whose mesh is still the one
    read (``BodySpec.mesh_origin``), else None: errors counted the triangulated faces of all
    its colliders together (an authored quad 2 was "faces 5"; a probe, stop 64), and a mesh
    replaced since must not be named by the old one's colliders (a review: an IndexError)."""
    origin = body.mesh_origin
    if origin is None or origin.digest != MeshOrigin.mesh_digest(body.vertices, body.faces):
        return None
    parts = origin.parts
    triangles = np.array([part.first_triangle for part in parts])
    vertices = np.array([part.first_vertex for part in parts])

    def face_name(triangle: int) -> str:
        part = parts[int(np.searchsorted(triangles, triangle, side="right")) - 1]
        return part.face_name(triangle - part.first_triangle)

    def vertex_name(vertex: int) -> str:
        part = parts[int(np.searchsorted(vertices, vertex, side="right")) - 1]
        return part.vertex_name(vertex - part.first_vertex)

    return face_name, vertex_name


@dataclass(eq=False)
class JointSpec(_ArrayFieldEquality):
    """One joint: frames in the parent's and child's prim frames (the world's for parent None),
    axes in the joint frame, per-coordinate limits (rad or m) and PD gains (SI, per radian;
    ball joints: one kp and one kd on the relative rotation)."""

    name: str
    path: str
    kind: str  # revolute | prismatic | universal | ball | base
    parent: str | None
    child: str
    parent_frame: np.ndarray
    child_frame: np.ndarray
    axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    dofs: tuple = ()
    limits: list | None = None
    kp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    kd: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cone_limit: float | None = None  # ball joints: swing limit about the first axis (rad)
    targets: np.ndarray | None = None  # per coordinate, drive target positions (rad or m); None: the initial ones


@dataclass(eq=False)
class Scene(_ArrayFieldEquality):
    """A complete task scene: bodies, joints, gravity, settings and task metadata."""

    bodies: list
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    settings: SimulationSettings = field(default_factory=SimulationSettings)
    task: TaskSpec = field(default_factory=TaskSpec)
    source: str = ""
    joints: list = field(default_factory=list)
    # The stage's up axis, "Z" or "Y": poses and gravity are in its frame, and the files this
    # scene is saved or exported to say so (a Y-up scene's trajectory was labelled Z-up).
    up_axis: str = "Z"

    def body(self, name: str) -> BodySpec:
        """The body named ``name``; KeyError naming the scene otherwise."""
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(f"scene {self.source or '<memory>'}: no body named {name!r}")

    def build_model(self, *, device="cpu"):
        """The simulation ``Model`` of this scene.

        Raises ValueError naming the prim for bad bodies, and naming both prims when bodies
        touch or intersect in their initial poses.
        """
        s = self.settings
        builder = ModelBuilder(
            gravity=self.gravity,
            contact_stiffness=s.contact_stiffness,
            friction=s.friction,
            friction_smoothing=s.friction_smoothing,
            eps=s.eps,
            centred_weight=s.centred_weight,
            contact_mode=s.contact_mode,
            leaf_precision=s.leaf_precision,
        )
        for b in self.bodies:
            kwargs = dict(name=b.name, pose=b.pose, static=b.static)
            if not b.static:
                kwargs.update(kp_linear=b.kp_linear, kd_linear=b.kd_linear, kp_angular=b.kp_angular, kd_angular=b.kd_angular)
                # An authored inertia or centre of mass counts with a mass from density too
                # (both were dropped: the trajectory then started 0.2 m off the stage's pose).
                kwargs.update(inertia=b.inertia, center_of_mass=b.center_of_mass)
                if b.mass is not None:
                    kwargs.update(mass=b.mass)
                else:
                    kwargs.update(density=b.density if b.density is not None else 1000.0)
            try:
                builder.add_body((b.vertices, b.faces), mesh_names=_mesh_names(b), **kwargs)
            except ValueError as exc:
                raise ValueError(f"{self.source or '<scene>'}: prim {b.path}: {exc}") from None
        index = {b.name: i for i, b in enumerate(self.bodies)}
        for j in self.joints:
            for role, name in (("child", j.child), ("parent", j.parent)):
                if name is not None and name not in index:  # a bare KeyError
                    raise ValueError(f"{self.source or '<scene>'}: prim {j.path}: joint {j.name!r} names {role} body {name!r}, which is not a body of the scene (bodies: {', '.join(index)})")
            if j.kind == "base" and set(j.dofs) & {"rx", "ry", "rz"}:
                # A base joint turns the body about its centre of mass along world axes through
                # it, and its translations are the centre's. A D6 anchor elsewhere would turn it
                # about the anchor (held by locked translations), and its free translations,
                # with their drives and limits, would be the anchor's: it silently turned about
                # the centre of mass, and drives held the centre where they hold the anchor.
                off = float(np.linalg.norm(j.child_frame[:3] - builder.body_center_of_mass(index[j.child])))
                if off > 1e-6 * max(1.0, float(np.linalg.norm(j.child_frame[:3]))):
                    held = "free translations (the anchor's)" if {"x", "y", "z"} <= set(j.dofs) else "locked translations"
                    raise ValueError(
                        f"{self.source or '<scene>'}: prim {j.path}: a D6 joint from the world with {held} and free "
                        f"rotations turns its body about the centre of mass here, but its anchor is {off:.3g} m from it; "
                        "put localPos1 at the body's centre of mass"
                    )
            options = {"dofs": j.dofs} if j.kind == "base" else {"parent_frame": j.parent_frame, "child_frame": j.child_frame, "axis": j.axes if len(j.axes) and (j.kind != "ball" or j.cone_limit is not None) else None}
            if j.cone_limit is not None:  # a ball joint's axis is its cone's, passed only with one
                options["cone_limit"] = j.cone_limit
            # Each gain as given (none: the builder's 0): a damper without a stiffness lost its
            # kd here, which a save and load then restored, and a scalar kp raised TypeError.
            options.update({label: gain for label, gain in (("kp", j.kp), ("kd", j.kd)) if np.size(gain)})
            limits, targets = j.limits, j.targets
            if j.kind == "base":
                try:
                    start = _base_start_coordinates(j, self.bodies[index[j.child]].pose)
                    # A base's coordinates start at 0; UsdPhysics' start where its frames put the
                    # body. The builder's rule for the pairs (one pair served every coordinate
                    # for the other joints, and crashed here).
                    if limits is not None:
                        lower, upper = coordinate_limits(limits, len(start), f"joint {j.name!r}")
                        limits = np.column_stack((lower - start, upper - start))
                except ValueError as exc:
                    raise ValueError(f"{self.source or '<scene>'}: prim {j.path}: {exc}") from None
                targets = None if targets is None else targets - start
            if targets is not None:
                options["target"] = targets
            try:
                builder.add_joint(j.kind, child=index[j.child], parent=index[j.parent] if j.parent is not None else None, limits=limits, name=j.name, **options)
            except ValueError as exc:
                raise ValueError(f"{self.source or '<scene>'}: prim {j.path}: {exc}") from None
        try:
            model = builder.finalize(device=device)
        except ValueError as exc:
            # A coordinate's message named the joint ('hinge:0'), not its prim (a probe).
            joint = next((j for j in self.joints if f"'{j.name}:" in str(exc) or f"joint {j.name!r}" in str(exc)), None)
            where = f"prim {joint.path}: " if joint is not None else ""
            raise ValueError(f"{self.source or '<scene>'}: {where}{exc}") from None
        start = model.contact.evaluate(model.initial_q)
        paths = {b.name: b.path for b in self.bodies}
        if start.contact_pairs:
            pairs = ", ".join(f"{paths[a]} and {paths[b]}" for a, b in start.contact_pairs)
            raise ValueError(f"{self.source or '<scene>'}: bodies intersect in the initial pose: {pairs}")
        if start.unsolved_pairs:
            pairs = ", ".join(f"{paths[a]} and {paths[b]}" for a, b in start.unsolved_pairs)
            raise ValueError(f"{self.source or '<scene>'}: in the initial pose, {pairs}: {UNSOLVED_HINT}")
        return model

    def initial_velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """(nbodies, 3) linear velocities of the centres of mass and (nbodies, 3) angular velocities."""
        lin = np.array([b.linear_velocity for b in self.bodies], dtype=np.float64)
        ang = np.array([b.angular_velocity for b in self.bodies], dtype=np.float64)
        return lin, ang


# --- import ---------------------------------------------------------------------------------


def _pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a declared dependency
        raise ImportError("USD support needs usd-core (pip install usd-core)") from exc
    return Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt


def _load_physics(stage, UsdPhysics):
    loader = getattr(UsdPhysics, "LoadUsdPhysicsFromRange", None)
    newer = getattr(UsdPhysics, "UsdPhysicsLoadStageFromPrimRange", None)
    return (newer or loader)(stage, ["/"])


def _quat_xyzw(q) -> np.ndarray:
    """Gf quaternion -> (x, y, z, w)."""
    im = q.GetImaginary()
    return np.array([im[0], im[1], im[2], q.GetReal()], dtype=np.float64)


def _attr(prim, name):
    """The authored value of ``prim``'s attribute ``name``, or None."""
    attr = prim.GetAttribute(name)
    return attr.Get() if attr and attr.HasAuthoredValue() else None


def _flattened_polygons(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Polygons of n corners each ((m, n, 3), in order) in two coordinates of their planes:
    their Newell normals (m, 3), the corners (m, n, 2) counter-clockwise about the normals
    and relative to corner 0, each corner's turn (m, n): the cross product of the edges into
    and out of corner k + 1, positive at a convex corner, and the turn (m,) below which a
    corner is straight (``flat_twice_area``)."""
    straight = flat_twice_area(np.linalg.norm(np.roll(corners, -1, axis=1) - corners, axis=2).max(axis=1), np.abs(corners).max(axis=(1, 2)), float32=float32_values(corners))
    corners = corners - corners[:, :1]
    normal = np.sum(np.cross(corners, np.roll(corners, -1, axis=1)), axis=1)
    drop = np.argmax(np.abs(normal), axis=1)
    # The other two axes in cyclic order keep the polygon counter-clockwise about +normal[drop].
    kept_axes = np.stack([(drop + 1) % 3, (drop + 2) % 3], axis=1)
    flat = np.take_along_axis(corners, kept_axes[:, None, :], axis=2).copy()
    flat[np.take_along_axis(normal, drop[:, None], axis=1)[:, 0] < 0, :, 1] *= -1.0
    edges = np.roll(flat, -1, axis=1) - flat
    following = np.roll(edges, -1, axis=1)
    return normal, flat, edges[..., 0] * following[..., 1] - edges[..., 1] * following[..., 0], straight


def _strictly_convex(normal: np.ndarray, turns: np.ndarray, straight: np.ndarray) -> np.ndarray:
    """Per polygon of ``_flattened_polygons``: convex with no straight corner, where a fan
    from corner 0 is exact and has no zero-area triangle."""
    return (np.linalg.norm(normal, axis=1) > 0) & (turns > straight[:, None]).all(axis=1)


def _cross(o, a, b):
    """Twice the signed area of triangle (o, a, b) (positive counter-clockwise), for points or
    broadcast arrays of points (..., 2), in one operation order: the same rounding for one
    triangle as for many."""
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def _edges_meet(flat: np.ndarray) -> bool:
    """Whether two edges of the closed polygon ``flat`` (n, 2) that share no corner meet
    (touching or collinear overlap counts). All pairs at once, a block of rows at a time so
    that a polygon of thousands of corners stays within ~100 MB."""
    n = len(flat)
    starts, ends = flat, np.roll(flat, -1, axis=0)
    # Extent axis of each edge for the collinear case: its longer coordinate.
    axis = np.argmax(np.abs(ends - starts), axis=1)
    rows = max(1, (1 << 20) // n)
    for a0 in range(0, n - 2, rows):
        a = np.arange(a0, min(a0 + rows, n - 2))[:, None]
        b = np.arange(a0 + 2, n)[None, :]
        # Pairs b >= a + 2, except the last edge with the first: they share corner 0.
        pairs = (b >= a + 2) & ~((a == 0) & (b == n - 1))
        p, q = starts[a], ends[a]
        r, t = starts[b], ends[b]
        d1, d2, d3, d4 = _cross(p, q, r), _cross(p, q, t), _cross(r, t, p), _cross(r, t, q)
        collinear = (d1 == 0.0) & (d2 == 0.0)
        # Collinear edges meet only where their extents overlap along the first edge's axis.
        along_x = axis[a] == 0
        pa, qa = np.where(along_x, p[..., 0], p[..., 1]), np.where(along_x, q[..., 0], q[..., 1])
        ra, ta = np.where(along_x, r[..., 0], r[..., 1]), np.where(along_x, t[..., 0], t[..., 1])
        overlap = (np.maximum(pa, qa) >= np.minimum(ra, ta)) & (np.maximum(ra, ta) >= np.minimum(pa, qa))
        crossing = (d1 * d2 <= 0.0) & (d3 * d4 <= 0.0)
        if (pairs & np.where(collinear, overlap, crossing)).any():
            return True
    return False


def _polygon_triangles(corners: np.ndarray) -> list | None:
    """Triangles (index triples into ``corners``, (n, 3) points in order) covering a polygon:
    a fan where the polygon is strictly convex (the common case; exact there), else ear
    clipping in its plane, which never cuts at a straight corner (a fan over an L-shaped
    face covered its notch with a floor; one over a corner in the middle of an edge, as CAD
    exports write, made a zero-area triangle); None for a self-intersecting polygon."""
    n = len(corners)
    fan = [(0, k, k + 1) for k in range(1, n - 1)]
    if n == 3:
        return fan
    # A corner listed twice in a row (common in exported meshes) is one corner: its zero-length
    # edge read as a crossing and refused a simple concave face.
    distinct = np.flatnonzero(np.any(corners != np.roll(corners, -1, axis=0), axis=1))
    if 3 <= len(distinct) < n:
        inner = _polygon_triangles(corners[distinct])
        return None if inner is None else [tuple(int(distinct[k]) for k in t) for t in inner]
    normal, flat, turns, straight = (a[0] for a in _flattened_polygons(corners[None]))
    if not np.linalg.norm(normal) > 0:
        return fan  # degenerate (collinear): any split is as good
    if _strictly_convex(normal[None], turns[None], straight[None])[0]:
        return fan
    straight = float(straight)

    # Ear clipping needs a simple polygon: no two edges that do not share a corner may meet.
    if _edges_meet(flat):
        return None

    # Per corner, a remaining corner inside the triangle it would cut off. While that corner
    # remains and the corner's neighbours stay, it is still no ear, so it is not tested again
    # (retesting every corner before the ear against every corner took 134 s at 3,200 corners).
    # Index n means none, and ``alive[n]`` is False.
    blocker = np.full(n, n)
    alive = np.ones(n + 1, dtype=bool)
    alive[n] = False

    def ear(remaining, twice_areas, area_left, keep_area):
        """Position in ``remaining`` of a corner to cut off (the first in order), or None.
        With ``keep_area``, the cut must leave an area: cutting one end of a straight run's
        neighbour could leave the run's corners alone, all on one line."""
        candidates = ~(twice_areas <= straight) & ~alive[blocker[remaining]]  # a reflex or straight corner is no ear
        if keep_area:
            candidates &= ~(area_left - twice_areas <= straight)
        points = flat[remaining]
        for k in np.flatnonzero(candidates):
            k_before, k_after = k - 1, (k + 1) % len(remaining)
            a, b, c = points[k_before], points[k], points[k_after]
            inside = (_cross(a, b, points) >= 0.0) & (_cross(b, c, points) >= 0.0) & (_cross(c, a, points) >= 0.0)
            inside[[k_before, k, k_after]] = False  # the triangle's own corners
            if not inside.any():
                return k
            blocker[remaining[k]] = remaining[np.argmax(inside)]
        return None

    remaining = np.arange(n)
    area_left = float(np.sum(flat[:, 0] * np.roll(flat[:, 1], -1) - np.roll(flat[:, 0], -1) * flat[:, 1]))  # twice the area
    triangles = []
    while len(remaining) > 3:
        before, after = np.roll(remaining, 1), np.roll(remaining, -1)
        twice_areas = _cross(flat[before], flat[remaining], flat[after])
        k = ear(remaining, twice_areas, area_left, True)
        if k is None:
            k = ear(remaining, twice_areas, area_left, False)
        if k is None:
            return None
        i, j, m = int(before[k]), int(remaining[k]), int(after[k])
        triangles.append((i, j, m))
        area_left -= twice_areas[k]
        alive[j] = False
        blocker[[i, m]] = n  # their triangles change with their new neighbours
        remaining = np.delete(remaining, k)
    triangles.append(tuple(remaining.tolist()))
    return triangles


def _mesh_triangles(prim, UsdGeom, source, *, refuse_repeats: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Mesh prim's points, triangles and the authored face of each triangle."""
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    where = f"{source}: prim {prim.GetPath()}"
    if len(points) == 0 or len(counts) == 0:
        raise ValueError(f"{where}: mesh has no points or faces")
    if not np.isfinite(points).all():
        bad = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise ValueError(f"{where}: point {bad} is not finite")
    short = np.flatnonzero(counts < 3)
    if len(short):
        # Before the sums: a negative count could balance them and index out of the mesh.
        f = int(short[0])
        raise ValueError(f"{where}: face {f} has {counts[f]} vertices; cannot be triangulated")
    if counts.sum() != len(indices) or (indices < 0).any() or (indices >= len(points)).any():
        raise ValueError(f"{where}: faceVertexIndices do not match faceVertexCounts and points")
    holes = np.asarray(mesh.GetHoleIndicesAttr().Get() or [], dtype=np.int64)
    outside = np.flatnonzero((holes < 0) | (holes >= len(counts)))
    if outside.size:  # a mistyped hole left its face solid, silently
        raise ValueError(f"{where}: holeIndices has {holes[outside[0]]}, not a face index (the mesh has faces 0 to {len(counts) - 1})")
    kept = np.ones(len(counts), dtype=bool)
    kept[holes] = False
    if refuse_repeats:
        _refuse_repeated_polygons(points, counts, indices, kept, where)
    faces, owners = _polygon_mesh_faces(points, counts, indices, kept, where)
    if not len(faces):
        raise ValueError(f"{where}: every face is a hole (holeIndices)")
    faces = np.asarray(faces, dtype=np.int64)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        # Clockwise winding: reversed, so that a closed mesh stays outward-oriented for its mass.
        faces = faces[:, ::-1]
    tri = points[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area2 > 0).any():
        raise ValueError(f"{where}: mesh is degenerate (every triangle has zero area)")
    return points, faces, owners


def _refuse_repeated_polygons(points: np.ndarray, counts: np.ndarray, indices: np.ndarray, kept: np.ndarray, where: str) -> None:
    """Refuse a polygon listed twice (the same corners, by position, from any corner or in
    either winding: a two-sided copy; a corner named twice in a row counts once, as in the
    triangulation). Split along other diagonals its copies share no triangle, which the
    meshes' own check (``sphere_tree``) compares, and the surface pushed twice as hard (a box
    rested 0.156 mm over such a ground against 0.111 mm)."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    groups: dict[int, list] = {}  # corner count -> [(faces, corner indices)]
    for count in np.unique(counts[kept & (counts > 3)]):
        faces = np.flatnonzero(kept & (counts == count))
        corners = indices[starts[faces, None] + np.arange(count)]
        named_twice = (corners == np.roll(corners, -1, axis=1)).any(axis=1)
        groups.setdefault(int(count), []).append((faces[~named_twice], corners[~named_twice]))
        for face, row in zip(faces[named_twice], corners[named_twice]):
            row = row[row != np.roll(row, -1)]
            if len(row) > 3:  # triangles are the meshes' own check's
                groups.setdefault(len(row), []).append((face[None], row[None]))
    for count, parts in groups.items():
        faces = np.concatenate([f for f, _ in parts])
        repeated = repeated_corner_sets(points[np.concatenate([c for _, c in parts])])
        if repeated is not None:
            first, second = sorted((int(faces[repeated[0]]), int(faces[repeated[1]])))
            raise ValueError(
                f"{where}: faces {first} and {second} have the same {count} corners (a polygon listed twice, "
                "or a two-sided copy); each copy would push in the contact potential: remove the repeats"
            )


def _polygon_mesh_faces(points: np.ndarray, counts: np.ndarray, indices: np.ndarray, kept: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (nt, 3) of a mesh's polygons (those ``kept``: holes are not), face by face
    in order, and the authored face of each (nt,). Triangles and strictly convex quads, the
    common polygons, are split at once (one face at a time, 229k triangles took 2.9 s and a
    90,000-quad ground 25 s)."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    left = kept.copy()
    single = np.flatnonzero(left & (counts == 3))
    triangles = [indices[starts[single, None] + np.arange(3)]]
    owners = [single]
    quads = np.flatnonzero(left & (counts == 4))
    quad_corners = indices[starts[quads, None] + np.arange(4)]
    normal, _, turns, straight = _flattened_polygons(points[quad_corners])
    fanned = _strictly_convex(normal, turns, straight)
    triangles.append(quad_corners[fanned][:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3))
    owners.append(np.repeat(quads[fanned], 2))
    left[single] = False
    left[quads[fanned]] = False
    for f in np.flatnonzero(left):
        poly = indices[starts[f] : starts[f] + counts[f]]
        corners = _polygon_triangles(points[poly])
        if corners is None:
            raise ValueError(f"{where}: face {f} ({counts[f]} vertices) is a self-intersecting polygon, which has no triangulation; split it into simple polygons")
        triangles.append(poly[np.asarray(corners)])
        owners.append(np.full(len(corners), f))
    owners = np.concatenate(owners)
    order = np.argsort(owners, kind="stable")
    return np.concatenate(triangles).astype(np.int64).reshape(-1, 3)[order], owners[order].astype(np.int64)


def _shape_triangles(kind, prim, UsdGeom, source, desc=None, *, exact: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A collider's vertices, triangles and, for a Mesh, the authored face of each triangle
    (None for a primitive): with ``desc``, in UsdPhysics' description (its own-axis scale
    folded into the dimensions, meshScale for a Mesh); without, in its prim frame from its
    unscaled attributes (for the exact path, ``_in_frame``). ``exact``: the triangles are
    collided themselves (not replaced by a hull of the points), so a Mesh's repeated
    polygons are refused."""
    where = f"{source}: prim {prim.GetPath()}"
    if kind == "MeshShape":
        points, faces, owners = _mesh_triangles(prim, UsdGeom, source, refuse_repeats=exact)
        return (points if desc is None else points * np.asarray(desc.meshScale, dtype=np.float64)), faces, owners
    for name in _READ_GEOMETRY:
        attr = prim.GetAttribute(name)
        if attr and attr.Get() is None:
            # A schema attribute reads None only when a value block hides its value and fallback
            # (`double size = None`): float(None) was a TypeError traceback.
            raise ValueError(f"{where}: {name} is blocked (authored as None), which leaves the shape without that dimension; author a value")
    _check_dimensions(kind, prim, where)
    size = _primitive_size(kind, prim, UsdGeom, desc)
    if size is None:
        raise ValueError(f"{where}: collider type {kind} is not supported (use a Mesh, Cube, Sphere, Capsule, Cylinder, Cone or Plane)")
    if "axis" in size:  # the parser's axis took any token as X
        size["axis"] = _axis_token(prim, "axis", where)
    if kind == "CubeShape":
        m = trimesh.creation.box(extents=size["extents"])
    elif kind == "SphereShape":
        m = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=size["radius"])
    elif kind == "CapsuleShape":
        m = trimesh.creation.capsule(height=size["height"], radius=size["radius"], count=[ROUND_SEGMENTS, ROUND_SEGMENTS])
    elif kind == "CylinderShape":
        m = trimesh.creation.cylinder(radius=size["radius"], height=size["height"], sections=ROUND_SEGMENTS)
    elif kind == "ConeShape":
        m = _cone(size["radius"], size["height"])
    else:
        m = _tapered(size["bottom"], size["top"], size["height"], rounded=kind == "Capsule1Shape", where=where)
    if "axis" in size:
        m = _align_axis(m, size["axis"])
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64), None


# The dimensions of the primitives that have no tapered form (``_tapered`` checks those),
# and whether each may be 0 (a capsule of height 0 is a sphere).
_DIMENSIONS = {
    "CubeShape": (("size", False),),
    "SphereShape": (("radius", False),),
    "CapsuleShape": (("radius", False), ("height", True)),
    "CylinderShape": (("radius", False), ("height", False)),
    "ConeShape": (("radius", False), ("height", False)),
}


def _check_dimensions(kind, prim, where: str) -> None:
    """Refuse a primitive's own dimension that is not finite, or negative or 0 where that
    makes no solid: a Cube of size -0.5 loaded as a 0.5 m cube unscaled and inside out under
    a scaled body, and a Sphere of radius inf as NaN vertices that named no attribute."""
    for name, zero_allowed in _DIMENSIONS.get(kind, ()):
        value = float(prim.GetAttribute(name).Get())
        if not (np.isfinite(value) and (value > 0 or (zero_allowed and value == 0))):
            wanted = "a finite number >= 0" if zero_allowed else "a positive finite number"
            raise ValueError(f"{where}: {name} must be {wanted}, got {value:g}")


def _primitive_size(kind, prim, UsdGeom, desc=None) -> dict | None:
    """A primitive collider's dimensions (extents, radius, height, bottom / top radii, axis
    token) from UsdPhysics' ``desc`` (scaled), else from the prim's own attributes; None for
    a kind that is not built here."""
    round_kinds = ("CapsuleShape", "CylinderShape", "ConeShape")
    tapered_kinds = ("Capsule1Shape", "Cylinder1Shape")
    if desc is not None:
        if kind == "CubeShape":
            return {"extents": 2.0 * np.asarray(desc.halfExtents, dtype=np.float64)}
        if kind == "SphereShape":
            return {"radius": float(desc.radius)}
        if kind in round_kinds:
            return {"radius": float(desc.radius), "height": 2.0 * float(desc.halfHeight), "axis": str(desc.axis)}
        if kind in tapered_kinds:
            return {"bottom": float(desc.bottomRadius), "top": float(desc.topRadius), "height": 2.0 * float(desc.halfHeight), "axis": str(desc.axis)}
        return None
    if kind == "CubeShape":
        return {"extents": [float(UsdGeom.Cube(prim).GetSizeAttr().Get())] * 3}
    if kind == "SphereShape":
        return {"radius": float(UsdGeom.Sphere(prim).GetRadiusAttr().Get())}
    schema = {"CapsuleShape": UsdGeom.Capsule, "CylinderShape": UsdGeom.Cylinder, "ConeShape": UsdGeom.Cone, "Capsule1Shape": UsdGeom.Capsule_1, "Cylinder1Shape": UsdGeom.Cylinder_1}.get(kind)
    if schema is None:
        return None
    shape = schema(prim)
    size = {"height": float(shape.GetHeightAttr().Get()), "axis": str(shape.GetAxisAttr().Get())}
    if kind in round_kinds:
        return {**size, "radius": float(shape.GetRadiusAttr().Get())}
    # Magnitudes, as UsdPhysics reads them.
    return {**size, "height": abs(size["height"]), "bottom": abs(float(shape.GetRadiusBottomAttr().Get())), "top": abs(float(shape.GetRadiusTopAttr().Get()))}


def _tapered(bottom: float, top: float, height: float, *, rounded: bool, where: str):
    """UsdGeom's Cylinder_1 (a frustum) or Capsule_1 (the hull of its two end spheres) of
    radii ``bottom`` and ``top`` (at -height/2 and +height/2 on the z spine): the convex hull
    of two rings, or two spheres, of ROUND_SEGMENTS segments."""
    if not (min(bottom, top) >= 0.0 and max(bottom, top) > 0.0 and height >= 0.0 and np.isfinite([bottom, top, height]).all()):
        raise ValueError(f"{where}: radii must be >= 0 (one of them > 0) and height >= 0, got radii {bottom:g}, {top:g} and height {height:g}")
    if rounded:
        unit = np.asarray(trimesh.creation.uv_sphere(radius=1.0, count=[ROUND_SEGMENTS, ROUND_SEGMENTS]).vertices)
    else:
        angle = 2.0 * np.pi * np.arange(ROUND_SEGMENTS) / ROUND_SEGMENTS
        unit = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
    lift = np.array([0.0, 0.0, 0.5 * height])
    points = np.vstack([unit * bottom - lift, unit * top + lift])
    return trimesh.Trimesh(*convex_hull_mesh(points), process=False)


def _cone(radius: float, height: float):
    """UsdGeom's cone: centred on its origin, its apex up the +z spine (trimesh's stands on z = 0)."""
    m = trimesh.creation.cone(radius=radius, height=height, sections=ROUND_SEGMENTS)
    m.apply_translation((0.0, 0.0, -0.5 * height))
    return m


def _align_axis(mesh, axis: str):
    """trimesh round shapes run along z; ``axis`` is the shape's checked token (``_axis_token``)."""
    if axis == "X":
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    elif axis == "Y":
        mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return mesh


# How far an orient's norm may be off 1 (it is then read as its rotation): a half-precision
# (quath) quaternion's rounding moves the norm by up to 2^-11 relative (90 degrees about z,
# norm 0.99979), and files write quaternions rounded to 4 or 5 decimals ((0.7071, 0, 0,
# 0.7071), norm 0.99999; a review found them refused at the 1e-6 of localRot0/1).
_ORIENT_NORM_TOLERANCE = 1e-3
# A matrix op's last column may differ from (0, 0, 0, 1) by this much (rounding).
_AFFINE_COLUMN_TOLERANCE = 1e-12
# A transform whose smallest singular value is this fraction of its largest or less flattens
# what it places: a collider under a scale of (1, 1, 0) was refused as a mesh of repeated
# triangles, a Cube as an open mesh, and one under (1e-12, 1, 1) for its inertia.
_FLAT_TRANSFORM = 1e-12


def _world_matrix(prim, UsdGeom, Usd, source: str):
    """A prim's local-to-world matrix; ValueError naming the transform attribute (the prim's
    own or an ancestor's) whose value is not finite (an SVD failed on it, naming nothing; an
    orient of real part NaN composed to the identity), an orient that is not a unit
    quaternion, or a matrix op that is not affine (its projective column was dropped: the
    body sat metres from where USD draws it)."""
    for attr in _transform_attributes(prim, UsdGeom):
        value = attr.Get()
        if value is None:
            continue
        numbers = np.asarray(_quat_xyzw(value) if hasattr(value, "GetReal") else value, dtype=np.float64)
        if not np.isfinite(numbers).all():
            raise ValueError(f"{source}: prim {prim.GetPath()}: {attr.GetPath()} must be finite, got {value}")
        if hasattr(value, "GetReal"):
            # An orient op: USD draws a quaternion off unit norm as given, neither as its
            # normalised rotation nor (except (0, 0, 0, 0), the identity) as any rotation the
            # loader would read back; a body oriented (0, 0, 0, 0) loaded unturned, silently.
            norm = float(np.linalg.norm(numbers))
            if not abs(norm - 1.0) <= _ORIENT_NORM_TOLERANCE:
                raise ValueError(f"{source}: prim {prim.GetPath()}: {attr.GetPath()} must be a unit quaternion, got {value} (norm {norm:.9g})")
        # Within rounding of (0, 0, 0, 1): a matrix made by multiplying by an inverse (keeping
        # a reparented prim's world pose) carries 1 - 2e-16 there, which USD draws 2e-16 away.
        if numbers.shape == (4, 4) and not np.abs(numbers[:, 3] - [0.0, 0.0, 0.0, 1.0]).max() <= _AFFINE_COLUMN_TOLERANCE:
            raise ValueError(f"{source}: prim {prim.GetPath()}: {attr.GetPath()} is not an affine transform (its last column must be 0, 0, 0, 1), got {value}")
    matrix = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    if np.isfinite(np.array(matrix)).all():
        return matrix
    raise ValueError(f"{source}: prim {prim.GetPath()}: its world transform is not finite (its transform values overflow)")


def _flat(linear: np.ndarray) -> bool:
    """Whether a 3x3 linear map squashes some direction to nothing (``_FLAT_TRANSFORM``)."""
    singular = np.linalg.svd(linear, compute_uv=False)
    return bool(singular[-1] <= _FLAT_TRANSFORM * singular[0])


def _flattening_problem(prim, linear: np.ndarray, points: np.ndarray, UsdGeom) -> str | None:
    """Why a collider's ``_flat`` world transform (``linear``, row vectors: x L) cannot place
    its ``points`` (prim frame), or None: it squashes a direction along which they have
    extent. A mesh already flat along it (a ground in z = 0 under a scale of (2, 2, 0)) loads
    as before; an infinite Plane is never asked."""
    rows = np.linalg.svd(linear)[0]
    extent = float(np.ptp(points, axis=0).max())
    if float(np.ptp(points @ rows[:, -1])) <= _FLAT_TRANSFORM * extent:
        return None
    culprit = next((attr for attr in _transform_attributes(prim, UsdGeom) if _flat_op(attr, UsdGeom)), None)
    blame = f"{culprit.GetPath()} is {culprit.Get()}" if culprit is not None else "its transform ops, none flat alone, compose to a singular matrix"
    return f"its world transform flattens it ({blame}); a scale must be non-zero on every axis the shape has extent along"


def _flat_op(attr, UsdGeom) -> bool:
    """Whether an xformOp attribute is a flattening scale or matrix op."""
    kind, value = UsdGeom.XformOp(attr).GetOpType(), attr.Get()
    if value is None or kind not in (UsdGeom.XformOp.TypeScale, UsdGeom.XformOp.TypeTransform):
        return False
    numbers = np.asarray(value, dtype=np.float64)
    return _flat(numbers[:3, :3] if kind == UsdGeom.XformOp.TypeTransform else np.diag(numbers))


def _linear_part(m) -> np.ndarray:
    """The 3x3 linear part of a Gf 4x4 matrix (USD's row-vector convention: x' = x L + t)."""
    return np.array([[m[i][j] for j in range(3)] for i in range(3)], dtype=np.float64)


def _unscaled(linear: np.ndarray) -> bool:
    """Whether x L is a rotation (the only case Gf's rotation extraction is exact for): not
    scaled, and not mirrored."""
    return bool(np.abs(linear @ linear.T - np.eye(3)).max() <= 1e-9 and np.linalg.det(linear) > 0)


def _scaled_along_own_axes(linear: np.ndarray) -> bool:
    """Whether x L scales along the prim's own axes, then rotates (no shear): L L^T diagonal."""
    gram = linear @ linear.T
    return bool(np.abs(gram - np.diag(np.diag(gram))).max() <= 1e-9 * np.abs(gram).max())


def _uniformly_scaled(linear: np.ndarray) -> bool:
    """Whether x L (scaled along the prim's own axes) scales every axis alike."""
    scales = np.sqrt(np.diag(linear @ linear.T))
    return bool(scales.max() - scales.min() <= 1e-9 * scales.max())


def _transform_attributes(prim, UsdGeom):
    """The xformOp attributes that compose a prim's world transform: its own and its ancestors'."""
    ancestor = prim
    while ancestor and not ancestor.IsPseudoRoot():
        if ancestor.IsA(UsdGeom.Xformable):
            yield from (op.GetAttr() for op in UsdGeom.Xformable(ancestor).GetOrderedXformOps())
        ancestor = ancestor.GetParent()


# The attributes a load reads (besides transforms): animating others (visibility, colours)
# is left alone.
_READ_PREFIXES = ("physics:", "warpcontact:")
_READ_PER_AXIS = re.compile(r"(drive|limit):[^:]+:physics:")
_READ_GEOMETRY = ("points", "faceVertexCounts", "faceVertexIndices", "holeIndices", "orientation", "size", "radius", "height", "axis", "radiusTop", "radiusBottom")


def _require_default_values(prim, UsdGeom, Usd, source: str) -> None:
    """Refuse a prim with an attribute, or a transform (its own or an ancestor's), that is
    only time-sampled: the initial state is read at the default time, where such a value is
    missing and silently counted as its fallback (a body authored at z = 1 m in samples
    loaded at the origin; a sampled mass of 7 kg gave the default density's, a sampled Cube
    size of 0.5 the fallback 2)."""
    for attr in (*_transform_attributes(prim, UsdGeom), *_read_attributes(prim)):
        _require_default_value(attr, Usd, f"{source}: prim {prim.GetPath()}")


def _read_attributes(prim) -> list:
    """The attributes of ``prim`` a load reads besides its transform: the physics and
    warpcontact ones, those of the drive and limit schemas, which apply per axis
    (``drive:angular:physics:stiffness``, ``limit:rotY:physics:low``: time-sampled alone, a
    drive's gain loaded as 0 and a locked D6 axis as free), and a collider's geometry. Not
    other multiple-apply attributes a load does not read (a recording's animated
    ``state:angular:physics:position``)."""
    return [attr for attr in prim.GetAttributes() if attr.GetName().startswith(_READ_PREFIXES) or _READ_PER_AXIS.match(attr.GetName()) or attr.GetName() in _READ_GEOMETRY]


def _refuse_animated(animated: list, what: str, where: str, hint: str = "") -> None:
    """Refuse the first of ``animated`` attributes (``where`` names their prim), of ``what``
    a load reads once, at the default time: they would be held there."""
    if animated:
        raise ValueError(f"{where}: {animated[0].GetName()} is animated, but {what} read once, at the default time (they would be held there); remove the animation{hint}")


def _require_default_value(attr, Usd, where: str) -> None:
    """Refuse an attribute that is animated but has no default value, or whose time samples
    are authored in a stronger layer than its default (``where`` names it): USD then shows
    the samples at every time code, and the default the load reads is one no viewer shows (a
    layout layer placing an asset's box by one time sample loaded it at the asset's default,
    silently; a probe, stop 59)."""
    if not _varies(attr):
        return
    if attr.GetResolveInfo(Usd.TimeCode.Default()).GetSource() != Usd.ResolveInfoSourceDefault:
        raise ValueError(
            f"{where}: {attr.GetPath()} is animated (time samples or a spline) but has no default value; the initial "
            "state is read at the default time (author the first frame's value as the default)"
        )
    stack = attr.GetPropertyStack(Usd.TimeCode.Default())
    sampled = next((i for i, spec in enumerate(stack) if spec.layer.GetNumTimeSamplesForPath(spec.path)), None)
    default = next((i for i, spec in enumerate(stack) if spec.HasDefaultValue()), None)
    if sampled is not None and default is not None and sampled < default:
        raise ValueError(
            f"{where}: {attr.GetPath()} has time samples in {stack[sampled].layer.identifier}, which override at every time "
            f"code its default in the weaker {stack[default].layer.identifier}; the initial state is read at the default "
            "time (author the first frame's value as the default in the stronger layer, or remove the samples)"
        )


def _varies(attr) -> bool:
    """Whether an attribute is animated: by time samples or by a spline (USD 0.25+), which
    has no time samples (a spline-turned body loaded at the identity)."""
    return bool(attr.GetNumTimeSamples()) or attr.ValueMightBeTimeVarying()


def _disabled_owner(prim, disabled: set, UsdPhysics) -> str:
    """The path of the disabled rigid body (``disabled``) that a collider prim lies under
    (the prim itself included), or "" when the nearest rigid body above it is enabled or
    there is none."""
    ancestor = prim
    while ancestor and not ancestor.IsPseudoRoot():
        path = str(ancestor.GetPath())
        if path in disabled:
            return path
        if ancestor.HasAPI(UsdPhysics.RigidBodyAPI):
            return ""
        ancestor = ancestor.GetParent()
    return ""


def _enabled_body_above(prim, disabled: set, UsdPhysics) -> bool:
    """Whether an enabled rigid body (not in ``disabled``) lies above ``prim``."""
    ancestor = prim.GetParent()
    while ancestor and not ancestor.IsPseudoRoot():
        if ancestor.HasAPI(UsdPhysics.RigidBodyAPI) and str(ancestor.GetPath()) not in disabled:
            return True
        ancestor = ancestor.GetParent()
    return False


def _animated(prim, UsdGeom) -> bool:
    """Whether a prim's world transform is animated (its own ops or an ancestor's): one time
    sample equal to the default, as exporters write a constant, is not motion."""
    return any(_moves(attr) for attr in _transform_attributes(prim, UsdGeom))


def _moves(attr) -> bool:
    """Whether an attribute takes another value over time than the one loads read (its
    default): samples that all repeat it, as exporters baking every frame write, are no
    motion (three such samples were refused as moving). A spline has no samples to compare:
    it moves."""
    samples = attr.GetTimeSamples()
    if not samples:
        return attr.ValueMightBeTimeVarying()
    default = attr.Get()
    return any(attr.Get(time) != default for time in samples)


def _polar_factor(linear: np.ndarray) -> np.ndarray:
    """The orthogonal matrix nearest to a linear part (row-vector convention); a reflection
    where the part mirrors (negative determinant)."""
    u, _, vt = np.linalg.svd(linear)
    return u @ vt


def _nearest_rotation(linear: np.ndarray) -> np.ndarray:
    """The rotation nearest to a linear part; for a mirroring part, the one that differs from
    its polar factor only along the least-stretched axis."""
    u, _, vt = np.linalg.svd(linear)
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] = -u[:, -1]
    return u @ vt


def _frame(matrix) -> np.ndarray:
    """A world matrix's frame with its scale removed: (px, py, pz, qx, qy, qz, qw), stage units."""
    t = matrix.ExtractTranslation()
    linear = _linear_part(matrix)
    if _unscaled(linear):
        q = _quat_xyzw(matrix.ExtractRotationQuat())
    else:
        # Gf's extraction tilts the rotation of a scaled frame (30 degrees about x came back as
        # 34.2 under a scale of 2, and 30 about z as 32.5 under (1, 2, 3)).
        q = quat_from_matrix(_nearest_rotation(linear).T)
    return np.array([t[0], t[1], t[2], *(q / np.linalg.norm(q))])


def _frame_on_body(prim, body_prim, body_frame: np.ndarray, matrix, transforms) -> np.ndarray:
    """A collider's frame (``_frame``) in the frame of its rigid body, an ancestor: composed
    from the transforms between the two (``transforms``, the load's UsdGeom.XformCache),
    exact where there are none; from the world matrices where the collider resets the
    transform stack."""
    relative, reset = transforms.ComputeRelativeTransform(prim, body_prim)
    if reset:
        return frame_in_body(body_frame, _frame(matrix))
    return _frame(relative)


# physics:approximation tokens (MeshCollisionAPI) that stand in for the exact triangles in
# engines that cannot collide a dynamic triangle mesh; this contact model collides the
# triangles themselves. convexHull asks for the hull of the mesh's points, which is built;
# boundingSphere and boundingCube, whose fits engines choose differently, are refused
# rather than guessed.
_EXACT_APPROXIMATIONS = ("none", "convexDecomposition", "meshSimplification", "sdf")
_SUPPORTED_APPROXIMATIONS = (*_EXACT_APPROXIMATIONS, "convexHull")


def _approximation(kind, desc, prim, source: str) -> str:
    """A collider's physics:approximation ("none" for primitives); refuses unsupported ones."""
    approximation = str(desc.approximation) if kind == "MeshShape" else "none"
    if approximation not in _SUPPORTED_APPROXIMATIONS:
        raise ValueError(
            f"{source}: prim {prim.GetPath()}: physics:approximation {approximation!r} is not supported (its fit is the "
            f"engine's choice); author one of {_SUPPORTED_APPROXIMATIONS}, or model the shape as its own Mesh"
        )
    return approximation


# A Plane collider (infinite in UsdPhysics) becomes a square this many times the diagonal of
# the other bodies' bounding box, centred under them (two triangles).
PLANE_SIZE_FACTOR = 100.0
# A Plane's in-plane axes (u, v, with u x v = its normal) per axis token.
_PLANE_AXES = {"X": (1, 2), "Y": (2, 0), "Z": (0, 1)}


def _plane_body(path: str, frame: np.ndarray, axis: str, meters: float, others: list) -> BodySpec:
    """A static square standing in for the infinite Plane at ``path``: PLANE_SIZE_FACTOR times
    the diagonal of the ``others``' bounding box (their faces' posed vertices: one point no
    face used, 1e6 m out, made a ground 1e8 m across and moved how a box rested on it),
    centred on their centre's projection onto the plane, its triangles facing the plane's axis."""
    pose = frame.copy()
    pose[:3] *= meters
    rotation = quat_to_matrix(pose[3:])
    posed = np.concatenate([b.vertices[np.unique(b.faces)] @ quat_to_matrix(b.pose[3:]).T + b.pose[:3] for b in others if len(b.faces)])
    low, high = posed.min(axis=0), posed.max(axis=0)
    half = 0.5 * PLANE_SIZE_FACTOR * np.linalg.norm(high - low)
    centre = (0.5 * (low + high) - pose[:3]) @ rotation  # in the plane's frame
    u, v = _PLANE_AXES[axis]
    corners = np.zeros((4, 3))
    for k, (su, sv) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
        corners[k, u] = centre[u] + su * half
        corners[k, v] = centre[v] + sv * half
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    return BodySpec(name=path.rsplit("/", 1)[-1], path=path, vertices=corners, faces=faces, pose=pose, static=True)


def _plane_frame(matrix, axis: str) -> np.ndarray:
    """A Plane's frame (``_frame``), turned where a shear tilts the plane away from it so that
    its ``axis`` is the plane's normal as USD draws it, L^-1 axis (a Plane turned 45 degrees
    inside a parent scaled (1, 1, 3) loaded at 45 degrees, USD draws it at 71.6)."""
    frame = _frame(matrix)
    linear = _linear_part(matrix)
    if _scaled_along_own_axes(linear):
        return frame
    normal = np.linalg.solve(linear, _AXES[axis])
    normal /= np.linalg.norm(normal)
    drawn = quat_rotate(frame[3:], _AXES[axis])
    if drawn @ normal < 0.0:  # the plane is two-sided: the nearer of its two normals
        normal = -normal
    half_turn = np.array([*np.cross(drawn, normal), 1.0 + drawn @ normal])
    frame[3:] = quat_mul(half_turn / np.linalg.norm(half_turn), frame[3:])
    return frame


def _in_frame(points: np.ndarray, matrix, frame: np.ndarray) -> np.ndarray:
    """Points of a prim's own frame, moved by its world ``matrix`` (scale and shear
    included), in the frame ``frame`` = (position, xyzw quaternion) of the same stage."""
    world = points @ _linear_part(matrix) + np.asarray(matrix.ExtractTranslation(), dtype=np.float64)
    return world @ quat_to_matrix(frame[3:]) - frame[:3] @ quat_to_matrix(frame[3:])


def _usd_error_text(exc) -> str:
    """The first message of a USD error, without the C++ function and source line."""
    try:
        text = str(exc)
    except UnicodeDecodeError:  # the message quotes the file's bytes, and they are not UTF-8
        return "it holds bytes that are not UTF-8 text; USD files are UTF-8"
    for line in text.splitlines():
        if " : " in line:
            return line.split(" : ", 1)[1].strip().strip("'")
    return text.strip()


def _checked_path(path, label: str = "path") -> Path:
    """``path`` as a Path; ValueError naming ``label`` for anything but text or a path (None
    or a list gave pathlib's TypeError; a probe, stop 64)."""
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{label}: expected a file path (str or pathlib.Path), got {type(path).__name__}")
    return Path(path)


def check_scene_type(scene) -> None:
    """ValueError unless ``scene`` is a ``Scene`` (None failed with an AttributeError in every
    function that takes one; a probe, stop 64)."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected a warpcontact Scene (io.load_scene, scenes.build_scene), got {type(scene).__name__}")


def _checked_scene(scene, path) -> None:
    """ValueError unless ``scene`` is a ``Scene`` whose up axis a file can hold (an up axis
    "X" was written as Z without a word; a probe, stop 64)."""
    check_scene_type(scene)
    if scene.up_axis not in ("Y", "Z"):
        raise ValueError(f"{path}: scene.up_axis must be 'Y' or 'Z' (USD's up axes), got {scene.up_axis!r}")


def load_scene(path) -> Scene:
    """Read a USD stage into a ``Scene``.

    Raises ValueError naming the file or prim and the problem (missing or unreadable file, no
    rigid body, bad meshes, non-positive mass, non-finite or out-of-range values of poses,
    velocities, mass properties, targets and ``warpcontact:`` settings, values of the wrong
    type, unsupported joints or colliders).
    """
    Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt = _pxr()
    path = _checked_path(path)
    source = str(path)
    if not path.exists():
        raise ValueError(f"{source}: file not found")
    if not path.is_file():
        raise ValueError(f"{source}: not a file")
    from pxr import Tf

    # USD keeps one copy of each open file a process: while anything holds a stage of it (a
    # viewer's, or a failed load's, kept alive by a notebook's last traceback), Stage.Open hands
    # that copy back without reading the file, and a file edited or saved since loaded as it
    # was (the fixed file raised its old error again; a probe, stop 63).
    already_open = {layer.identifier for layer in Sdf.Layer.GetLoadedLayers()}
    try:
        stage = Usd.Stage.Open(str(path))
        if stage is not None:
            for layer in stage.GetUsedLayers():
                if layer.anonymous or layer.identifier not in already_open:
                    continue
                if layer.dirty:
                    warnings.warn(f"{source}: {layer.realPath or layer.identifier} has unsaved changes in this process, which are loaded instead of the file on disk", stacklevel=2)
                else:
                    layer.Reload(force=True)
    except Tf.ErrorException as exc:
        raise ValueError(f"{source}: not a readable USD stage ({_usd_error_text(exc)})") from None
    if stage is None:
        raise ValueError(f"{source}: not a readable USD stage")
    # USD composes around a missing reference, payload or sublayer with only a warning, and
    # the scene would silently lack the bodies it holds.
    composition_errors = stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else []
    if composition_errors:
        listed = "; ".join(str(error).strip() for error in composition_errors[:3])
        more = f" (and {len(composition_errors) - 3} more)" if len(composition_errors) > 3 else ""
        raise ValueError(f"{source}: the stage does not compose: {listed}{more}")
    exported = stage.GetRootLayer().customLayerData.get(_TRAJECTORY_MARK)
    if exported is not None:
        # It holds meshes and poses, no physics: "no dynamic rigid bodies (apply
        # PhysicsRigidBodyAPI ...)" sent its reader to edit it.
        origin = f" ({exported})" if exported else ""
        raise ValueError(f"{source}: a trajectory written by warpcontact for viewing (meshes and time-sampled poses, no physics); load the scene it was simulated from{origin}")
    # Unauthored, USD's fallback applies: 0.01 (centimetres). A hand-written scene in metres
    # that leaves it out becomes a scene 100 times smaller, silently but for this warning.
    if not stage.HasAuthoredMetadata("metersPerUnit"):
        warnings.warn(f"{source}: metersPerUnit is not authored, so USD's fallback of 0.01 (centimetres) applies; author metersPerUnit = 1 for a scene in metres", stacklevel=2)
    # Bounded so that densities (kg/m^3) and inertias (kg m^2) convert to finite, non-zero
    # factors: 1e-110 m ended in a ZeroDivisionError, 1e105 m in an OverflowError.
    meters = float(UsdGeom.GetStageMetersPerUnit(stage))
    if not (np.isfinite(meters) and meters > 0):
        raise ValueError(f"{source}: metersPerUnit must be positive and finite, got {meters}")
    if not _UNIT_RANGE[0] <= meters <= _UNIT_RANGE[1]:
        raise ValueError(f"{source}: metersPerUnit must be from {_UNIT_RANGE[0]:g} to {_UNIT_RANGE[1]:g}, got {meters:g}")
    kilograms = float(UsdPhysics.GetStageKilogramsPerUnit(stage))
    if not (np.isfinite(kilograms) and kilograms > 0):
        raise ValueError(f"{source}: kilogramsPerUnit must be positive and finite, got {kilograms}")
    if not _UNIT_RANGE[0] <= kilograms <= _UNIT_RANGE[1]:
        raise ValueError(f"{source}: kilogramsPerUnit must be from {_UNIT_RANGE[0]:g} to {_UNIT_RANGE[1]:g}, got {kilograms:g}")
    units = _Units(meters, kilograms)
    up = UsdGeom.GetStageUpAxis(stage)
    if up not in (UsdGeom.Tokens.y, UsdGeom.Tokens.z):
        # UsdGeom knows only these two; another one gave gravity along -X or -Y depending on
        # whether the stage had a PhysicsScene, and a trajectory labelled Z-up.
        raise ValueError(f"{source}: upAxis must be \"Y\" or \"Z\", got {str(up)!r}")
    _warn_foreign_layer_units(stage, {"metersPerUnit": meters, "kilogramsPerUnit": kilograms, "upAxis": up}, source)
    _refuse_unreadable_schema_attributes(stage, Usd, source)
    _refuse_mistyped_xform_ops(stage, Sdf, Usd, UsdGeom, source)
    parsed = _load_physics(stage, UsdPhysics)
    descs = {str(k): list(zip(v[0], v[1])) for k, v in parsed.items()}
    _refuse_collision_filters(stage, UsdPhysics, Usd, source)
    _refuse_point_instanced_physics(stage, UsdGeom, UsdPhysics, Usd, source)
    _refuse_unread_mass_and_velocity(stage, UsdPhysics, Usd, source)
    for kind in ("DistanceJoint", "CustomJoint"):
        for prim_path, _ in descs.get(kind, []):
            raise ValueError(f"{source}: prim {prim_path}: {kind} is not supported (supported: revolute, prismatic, spherical and D6 joints, and fixed joints to the world)")
    welds = _world_welds(descs, source)
    # Bodies and colliders are checked where they are read (with their ancestors' transforms).
    for kind, items in descs.items():
        if kind in ("Scene", "RigidBody") or kind.endswith("Joint"):
            for prim_path, _ in items:
                prim = stage.GetPrimAtPath(prim_path)
                _require_default_values(prim, UsdGeom, Usd, source)
                # A drive target animated over the frames was held at its default silently, as
                # were a body's animated task target, PD gains and density (a probe).
                hint = " (a joint's targets over time are a Control's joint_target)" if kind.endswith("Joint") else ""
                _refuse_animated([attr for attr in _read_attributes(prim) if _moves(attr)], f"a {kind}'s values are", f"{source}: prim {prim_path}", hint)

    # Gravity: the PhysicsScene's, else standard gravity along -up.
    gravity = np.array([0.0, 0.0, -9.81]) if up == UsdGeom.Tokens.z else np.array([0.0, -9.81, 0.0])
    scene_prim = None
    physics_scenes = descs.get("Scene", [])
    if len(physics_scenes) > 1:
        # Bodies may belong to different scenes (simulationOwner), with their own gravity.
        paths = ", ".join(str(prim_path) for prim_path, _ in physics_scenes)
        raise ValueError(f"{source}: several PhysicsScene prims ({paths}); a stage here holds one scene")
    for prim_path, desc in physics_scenes:
        scene_prim = stage.GetPrimAtPath(prim_path)
        direction = np.asarray(desc.gravityDirection, dtype=np.float64)
        magnitude = float(desc.gravityMagnitude)
        if np.isnan(magnitude) or magnitude == np.inf or not np.isfinite(direction).all():
            raise ValueError(f"{source}: prim {prim_path}: gravity must be finite, got direction {direction.tolist()}, magnitude {magnitude}")
        if np.linalg.norm(direction) > 0:
            # UsdPhysics: a negative magnitude (unauthored: -inf) means Earth's gravity.
            magnitude = 9.81 if magnitude < 0 else magnitude * meters
            gravity = direction / np.linalg.norm(direction) * magnitude

    bodies: dict[str, BodySpec] = {}
    body_frames: dict[str, tuple] = {}  # rigid body path -> (frame in stage units, unscaled)
    mirrored: set[str] = set()  # paths of bodies whose world matrix mirrors (negative determinant)
    for prim_path, desc in descs.get("RigidBody", []):
        prim = stage.GetPrimAtPath(prim_path)
        _require_default_values(prim, UsdGeom, Usd, source)
        if desc.startsAsleep and desc.rigidBodyEnabled and not desc.kinematicBody and str(prim_path) not in welds:
            raise ValueError(
                f"{source}: prim {prim_path}: physics:startsAsleep is not supported (a sleeping body would hang until touched; "
                "every dynamic body here moves from the start); remove it, or make the body kinematic to hold it"
            )
        if desc.kinematicBody and _animated(prim, UsdGeom):
            raise ValueError(
                f"{source}: prim {prim_path}: a kinematic body moved by time-sampled transforms is not supported (it would be "
                "held at its default pose as a static body); remove the animation or make the body dynamic"
            )
        matrix = _world_matrix(prim, UsdGeom, Usd, source)
        linear = _linear_part(matrix)
        body_frames[str(prim_path)] = (_frame(matrix), _unscaled(linear))
        if np.linalg.det(linear) < 0:
            mirrored.add(str(prim_path))
        pose = body_frames[str(prim_path)][0].copy()
        pose[:3] *= meters
        body = BodySpec(
            name=prim.GetName(),
            path=str(prim_path),
            vertices=np.zeros((0, 3)),
            faces=np.zeros((0, 3), dtype=np.int64),
            pose=pose,
            static=bool(desc.kinematicBody) or not bool(desc.rigidBodyEnabled) or str(prim_path) in welds,
            linear_velocity=np.asarray(desc.linearVelocity, dtype=np.float64) * meters,
            angular_velocity=np.radians(np.asarray(desc.angularVelocity, dtype=np.float64)),
        )
        for label, value in (("velocity", body.linear_velocity), ("angularVelocity", body.angular_velocity)):
            if not np.isfinite(value).all():
                raise ValueError(f"{source}: prim {prim_path}: physics:{label} must be finite, got {np.asarray(value).tolist()}")
        # A Scope or a typeless prim has no transform: its nearest transformable ancestor
        # places the body (a Scope under a turned root read velocities in world axes).
        parent = prim.GetParent()
        while parent and not parent.IsPseudoRoot() and not parent.IsA(UsdGeom.Xformable):
            parent = parent.GetParent()
        # A prim that resets the transform stack is placed in the world, not in its parent.
        if parent.IsA(UsdGeom.Xformable) and not UsdGeom.Xformable(prim).GetResetXformStack():
            # Velocities are authored "in the same space as the node's xform": its parent's.
            above = _linear_part(_world_matrix(parent, UsdGeom, Usd, source))
            if not np.array_equal(above, np.eye(3)):
                body.linear_velocity = body.linear_velocity @ above
                # An angular velocity is a pseudovector: a mirroring parent also reverses it.
                reflection = _polar_factor(above)
                body.angular_velocity = np.linalg.det(reflection) * (body.angular_velocity @ reflection)
        _read_mass(prim, body, UsdPhysics, units, source)
        if body.center_of_mass is not None and not body_frames[str(prim_path)][1]:
            # centerOfMass is in the prim's local, scaled space; the body frame is unscaled.
            body.center_of_mass = body.center_of_mass @ linear @ quat_to_matrix(body.pose[3:])
        if body.inertia is not None and str(prim_path) in mirrored:
            # The geometry and centre of mass come through the mirror into the body's proper
            # frame; the inertia, a tensor in the prim's axes, reflects with them (it was only
            # turned: a spin at 3 rad/s ended 66 degrees off in 20 frames).
            reflection = _polar_factor(linear) @ quat_to_matrix(body.pose[3:])
            body.inertia = reflection.T @ body.inertia @ reflection
        _read_warpcontact_body(prim, body, meters, source)
        if body.static and (np.any(body.linear_velocity) or np.any(body.angular_velocity)):
            # Kept, it never moved the body, and a save dropped it (a probe, stop 63).
            warnings.warn(
                f"{source}: prim {prim_path}: a static body here (kinematic, disabled or welded to the world) does not move: its authored "
                f"physics:velocity {body.linear_velocity.tolist()} m/s and physics:angularVelocity {np.degrees(body.angular_velocity).tolist()} deg/s are ignored",
                stacklevel=2,
            )
            body.linear_velocity, body.angular_velocity = np.zeros(3), np.zeros(3)
        dynamic_only = _dynamic_only(body)
        if dynamic_only:
            raise ValueError(f"{source}: prim {prim_path}: a static body here (kinematic, disabled or welded to the world) has {dynamic_only}, which only a dynamic body takes")
        bodies[str(prim_path)] = body

    static_bodies: dict[str, BodySpec] = {}
    disabled = {str(prim_path) for prim_path, desc in descs.get("RigidBody", []) if not desc.rigidBodyEnabled}
    colliders: dict[str, list] = {}  # rigid body path -> its collider prims
    mesh_parts: dict[int, tuple] = {}  # id(body) -> (body, its colliders' (vertices, faces, (prim, authored faces)))
    collider_materials: dict[str, list] = {}  # collider path -> its bound physics materials
    scene_materials = _scene_physics_materials(scene_prim)
    planes = []  # (path, world frame in stage units, axis token) of Plane colliders
    shape_kinds = [k for k in descs if k.endswith("Shape")]
    transforms = UsdGeom.XformCache(Usd.TimeCode.Default())
    for kind in shape_kinds:
        for prim_path, desc in descs[kind]:
            prim = stage.GetPrimAtPath(prim_path)
            if not desc.collisionEnabled:
                continue
            _require_default_values(prim, UsdGeom, Usd, source)
            owner = str(desc.rigidBody) if desc.rigidBody and str(desc.rigidBody) in bodies else ""
            # UsdPhysics gives a disabled body's colliders no body (rigidBodyEnabled = false
            # loads as static, and was refused for having no collider): they are its all the
            # same, placed by their world matrix, since their localPos is then the world's.
            adopted = "" if owner else _disabled_owner(prim, disabled, UsdPhysics)
            owner = owner or adopted
            if not owner and _animated(prim, UsdGeom):
                raise ValueError(
                    f"{source}: prim {prim_path}: a static collider moved by time-sampled transforms is not supported (it would be "
                    "held at its default pose); remove the animation, or make it a rigid body"
                )
            # Its shape, and where it sits on its body, are read once, at the default time:
            # animated, they were held at their default values without a word.
            body_attributes = set(_transform_attributes(stage.GetPrimAtPath(owner), UsdGeom)) if owner else set()
            animated = [attr for attr in prim.GetAttributes() if attr.GetName() in _READ_GEOMETRY and _moves(attr)]
            animated += [attr for attr in _transform_attributes(prim, UsdGeom) if owner and attr not in body_attributes and _moves(attr)]
            _refuse_animated(animated, "a collider's shape and its place on its body are", f"{source}: prim {prim_path}")
            collider_materials[str(prim_path)] = _bound_physics_materials(stage, prim, desc, scene_materials)
            if kind == "PlaneShape":
                if owner:
                    raise ValueError(f"{source}: prim {prim_path}: a Plane collider is infinite; it cannot belong to rigid body {owner}")
                # Its size depends on every other body: built after them.
                axis = _axis_token(prim, "axis", f"{source}: prim {prim_path}")
                planes.append((str(prim_path), _plane_frame(_world_matrix(prim, UsdGeom, Usd, source), axis), axis))
                continue
            approximation = _approximation(kind, desc, prim, source)
            matrix = _world_matrix(prim, UsdGeom, Usd, source)
            linear = _linear_part(matrix)
            # A zero scale was blamed on the shape: "repeated triangles", an open Cube.
            problem = _flattening_problem(prim, linear, _shape_triangles(kind, prim, UsdGeom, source, exact=False)[0], UsdGeom) if _flat(linear) else None
            if problem is not None:
                raise ValueError(f"{source}: prim {prim_path}: {problem}")
            exact = approximation != "convexHull"  # a hull is taken of the points alone
            owner_frame, owner_unscaled = body_frames[owner] if owner else (None, True)
            if adopted or not (_scaled_along_own_axes(linear) and np.linalg.det(linear) > 0 and owner_unscaled and (kind in ("CubeShape", "MeshShape") or _uniformly_scaled(linear))):
                # UsdPhysics describes a collider by a rigid pose and a scale along its own axes,
                # which cannot hold a shear (a box under a body scaled (1, 1, 3) and turned 45
                # degrees inside it came out 0.5 m off at its corners); and a scaled body's frame
                # is the polar one (``_frame``). Its round shapes keep one radius, the largest
                # scale's (a Sphere scaled (1, 1, 4) came out a sphere of radius 4, 16x the mass
                # of the ellipsoid USD draws). Its points are then moved by the full world
                # matrix into the frame of its body (or its own); a mirroring matrix also
                # reverses the triangles' winding, which keeps a closed mesh outward-oriented.
                vertices, faces, owners = _shape_triangles(kind, prim, UsdGeom, source, exact=exact)
                frame = owner_frame if owner else _frame(matrix)
                vertices = _in_frame(vertices, matrix, frame) * meters
                if np.linalg.det(linear) < 0:
                    faces = faces[:, ::-1]
                    if not owner:
                        mirrored.add(str(prim_path))
                local_pose = frame.copy()
                local_pose[:3] *= meters
            else:
                vertices, faces, owners = _shape_triangles(kind, prim, UsdGeom, source, desc, exact=exact)
                # localPos / localRot place the collider in its rigid body's frame, or in the
                # world for a collider without a rigid body (a static body of its own). Scale is
                # already in the shape's dimensions (meshScale, radius, halfExtents).
                # Both are read from the transforms, in double: localPos / localRot are float32 (a
                # ground at x = 1000.123456789 moved 1.7e-5 m, and a collider placed there on its
                # body at the origin overlapped a ground 1e-5 m from it).
                local_pose = _frame(matrix) if not owner else _frame_on_body(prim, stage.GetPrimAtPath(owner), owner_frame, matrix, transforms)
                local_pose[3:] /= np.linalg.norm(local_pose[3:])
                local_pose[:3] *= meters
                vertices = vertices * meters
                if owner:
                    vertices = quat_rotate(local_pose[3:], vertices) + local_pose[:3]
            if approximation == "convexHull":
                owners = None
                try:
                    vertices, faces = convex_hull_mesh(vertices)
                except ValueError as exc:
                    raise ValueError(f"{source}: prim {prim_path}: physics:approximation 'convexHull': {exc}; author 'none' to collide the mesh's own triangles") from None
            if owner:
                target = bodies[owner]
            else:
                target = static_bodies.setdefault(
                    str(prim_path),
                    BodySpec(name=prim.GetName(), path=str(prim_path), vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), pose=local_pose, static=True),
                )
            # Joined once all are read: joining at each collider was quadratic (a body of
            # 4,000 colliders loaded in 7.5 s, now 2.6 s).
            mesh_parts.setdefault(id(target), (target, []))[1].append((vertices, faces, (str(prim_path), owners)))
            if owner:
                colliders.setdefault(owner, []).append(prim)
    for target, parts in mesh_parts.values():
        first_triangles = np.cumsum([0] + [len(faces) for _, faces, _ in parts[:-1]])
        first_vertices = np.cumsum([0] + [len(vertices) for vertices, _, _ in parts[:-1]])
        target.vertices = np.concatenate([vertices for vertices, _, _ in parts])
        target.faces = np.concatenate([faces + offset for (_, faces, _), offset in zip(parts, first_vertices)])
        colliders_read = tuple(ColliderPart(prim, int(t), int(v), owners) for (_, _, (prim, owners)), t, v in zip(parts, first_triangles, first_vertices))
        target.mesh_origin = MeshOrigin(colliders_read, MeshOrigin.mesh_digest(target.vertices, target.faces))
    for body_path, body_welds in welds.items():
        for joint_path, desc in body_welds:
            _check_weld(stage, bodies[body_path], joint_path, desc, static_bodies, meters, UsdGeom, Usd, source)
    # UsdPhysics gives a disabled body's colliders to the nearest enabled body above it (its
    # MassAPI): one left with none is not simulated and has nothing to load (it was refused
    # as having no collider). UsdPhysics takes a joint to it to that body too.
    for path in disabled:
        if len(bodies[path].faces) == 0 and _enabled_body_above(stage.GetPrimAtPath(path), disabled, UsdPhysics):
            del bodies[path]
    others = [*bodies.values(), *static_bodies.values()]  # without the planes: each sized by the rest alone
    for path, frame, axis in planes:
        static_bodies[path] = _plane_body(path, frame, axis, meters, others)
    for owner, prims in colliders.items():
        _read_collider_mass(stage.GetPrimAtPath(owner), prims, bodies[owner], UsdPhysics, units, source)
        _read_material_density(prims, collider_materials, bodies[owner], UsdPhysics, units, source)

    # Keep the stage's prim order, so bodies come back in the order they were authored.
    order = {str(prim.GetPath()): i for i, prim in enumerate(_all_prims(stage, Usd))}
    all_bodies = sorted(list(bodies.values()) + list(static_bodies.values()), key=lambda b: order.get(b.path, len(order)))
    for b in all_bodies:
        if len(b.faces) == 0:
            raise ValueError(f"{source}: prim {b.path}: rigid body has no collider (apply PhysicsCollisionAPI to a Mesh or primitive under it)")
    if not any(not b.static for b in all_bodies):
        raise ValueError(f"{source}: no dynamic rigid bodies (apply PhysicsRigidBodyAPI to at least one prim)")
    _make_names_unique(all_bodies, "body", source)

    _check_namespace(stage, scene_prim, bodies, Usd, UsdPhysics, source)
    settings = SimulationSettings()
    task = TaskSpec()
    if scene_prim is not None:
        _read_settings(scene_prim, settings, task, source)
    _read_material_friction(collider_materials, scene_prim, settings, UsdPhysics, source)
    _warn_unmodelled(stage, collider_materials, UsdPhysics, Usd, source)
    joints = _read_joints(stage, descs, {**bodies, **static_bodies}, mirrored, units, source, UsdPhysics)
    # In the stage's order too: grouped by joint type, a prismatic joint authored before a
    # revolute one came back after it, permuting the joint coordinates (and their targets).
    joints.sort(key=lambda joint: order.get(joint.path, len(order)))
    return Scene(bodies=all_bodies, gravity=gravity, settings=settings, task=task, source=source, joints=joints, up_axis="Y" if up == UsdGeom.Tokens.y else "Z")


# The stage units a load takes (metersPerUnit, kilogramsPerUnit): nanometres and light
# years are well inside.
_UNIT_RANGE = (1e-30, 1e30)
_AXES = {"X": np.array([1.0, 0.0, 0.0]), "Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}
_DEGREE = np.pi / 180.0


@dataclass(frozen=True)
class _Units:
    """A stage's units in SI: metersPerUnit and UsdPhysics' kilogramsPerUnit."""

    meters: float
    kilograms: float

    @property
    def density(self) -> float:
        return self.kilograms / self.meters**3

    @property
    def inertia(self) -> float:
        return self.kilograms * self.meters**2

    def drive_gain(self, angular: bool) -> float:
        """The SI factor of a DriveAPI stiffness or damping: mass/s^2 and mass/s for a linear
        drive; mass distance^2/degree/s^2 and /s for an angular one (to per radian)."""
        return self.kilograms * self.meters**2 / _DEGREE if angular else self.kilograms
_BALL_DRIVE_AXES = ("RotX", "RotY", "RotZ")  # DriveAPI instances rotX, rotY, rotZ
# D6 axes (LimitAPI / DriveAPI instance names, capitalised) and the base-joint DOF of each.
_D6_AXIS_DOF = {"TransX": "x", "TransY": "y", "TransZ": "z", "RotX": "rx", "RotY": "ry", "RotZ": "rz"}


def _api_token(axis: str) -> str:
    """The multiple-apply API instance name of a D6 axis: TransX -> transX."""
    return axis[0].lower() + axis[1:]


# The PhysicsDriveAPI / PhysicsLimitAPI instances a load reads on each kind of joint
# (revolute and prismatic limits are physics:lowerLimit / upperLimit, a spherical joint's
# its cone angles).
_AXIS_SCHEMA_INSTANCES = {
    "revolute": {"PhysicsDriveAPI": ("angular",), "PhysicsLimitAPI": ()},
    "prismatic": {"PhysicsDriveAPI": ("linear",), "PhysicsLimitAPI": ()},
    "ball": {"PhysicsDriveAPI": tuple(_api_token(axis) for axis in _BALL_DRIVE_AXES), "PhysicsLimitAPI": ()},
    "d6": {"PhysicsDriveAPI": tuple(_api_token(axis) for axis in _D6_AXIS_DOF), "PhysicsLimitAPI": tuple(_api_token(axis) for axis in _D6_AXIS_DOF)},
}


def _refuse_unread_axis_schemas(prim, usd_kind: str, kind: str, where: str) -> None:
    """Refuse a drive or limit instance this kind of joint does not read, and drive or limit
    attributes authored without their instance applied: both were dropped without a word
    (a misspelt PhysicsDriveAPI:angualr loaded the joint unactuated, a limit:rotx a locked
    axis as free)."""
    read = _AXIS_SCHEMA_INSTANCES[kind]
    applied = [str(schema) for schema in prim.GetAppliedSchemas()]
    for schema in applied:
        api, _, instance = schema.partition(":")
        if api in read and instance not in read[api]:
            reads = ", ".join(f"{api}:{token}" for token in read[api]) or "none"
            raise ValueError(f"{where}: {schema} is not read on a {usd_kind} (it reads {reads}); rename or remove it")
    for attr in prim.GetAttributes():
        name = attr.GetName()
        if _READ_PER_AXIS.match(name):
            api = "PhysicsDriveAPI" if name.startswith("drive:") else "PhysicsLimitAPI"
            instance = name.split(":")[1]
            if f"{api}:{instance}" not in applied:
                raise ValueError(f"{where}: {name} is authored without {api}:{instance} applied, so it would be ignored; apply the API or remove the attribute")


def _coordinate_axes(free: list) -> list:
    """The free D6 axes that are joint coordinates: all, except that three free rotations
    make a ball, whose rotation is not a coordinate (articulation.Joint.num_coordinates)."""
    if sum(a.startswith("Rot") for a in free) == 3:
        return [a for a in free if a.startswith("Trans")]
    return free


_AXIS_TOKENS = ("X", "Y", "Z")  # the allowedTokens of UsdPhysics' and UsdGeom's axis attributes


def _axis_token(prim, name: str, where: str) -> str:
    """The axis token, X, Y or Z, of a prim's attribute ``name`` (a joint's physics:axis; a
    Capsule's, Cylinder's, Cone's or Plane's axis), its fallback where unauthored. Any other
    value is refused naming the prim and attribute: the UsdPhysics parser read "W", or a
    lowercase "y", as X, silently (USD does not enforce a schema's allowedTokens)."""
    attr = prim.GetAttribute(name)
    value = attr.Get() if attr else None
    if value not in _AXIS_TOKENS:
        raise ValueError(f"{where}: {name} must be one of the tokens {', '.join(_AXIS_TOKENS)} (upper case), got {value!r}")
    return str(value)


def _world_welds(descs: dict, source: str) -> dict:
    """{rigid body path: [(joint path, desc), ...]} of the enabled FixedJoints that weld a rigid body
    to the world (or to a collider without a rigid body): such a body never moves, so it
    loads as a static body (an articulated robot's fixed base). A fixed joint between two
    rigid bodies is refused: merge them into one body."""
    rigid = {str(path) for path, _ in descs.get("RigidBody", [])}
    welds = {}
    for prim_path, desc in descs.get("FixedJoint", []):
        if not desc.jointEnabled:
            continue
        moving = [str(end) for end in (desc.body0, desc.body1) if str(end) in rigid]
        if len(moving) != 1:
            what = "joins two rigid bodies (merge them into one body)" if moving else "joins no rigid body"
            raise ValueError(f"{source}: prim {prim_path}: this fixed joint {what}; fixed joints are supported only to the world")
        # Every weld of a body is checked: keeping the last one let a contradicting weld
        # authored before it through.
        welds.setdefault(moving[0], []).append((str(prim_path), desc))
    return welds


def _joint_frames(desc, meters: float) -> tuple[np.ndarray, np.ndarray]:
    """A UsdPhysics joint's frames on body0 and body1, (7,) poses in metres."""
    frames = []
    for position, orientation in ((desc.localPose0Position, desc.localPose0Orientation), (desc.localPose1Position, desc.localPose1Orientation)):
        frame = np.array([*(np.asarray(position, dtype=np.float64) * meters), *_quat_xyzw(orientation)])
        frame[3:] /= np.linalg.norm(frame[3:])
        frames.append(frame)
    return frames[0], frames[1]


def _check_weld(stage, body: BodySpec, joint_path: str, desc, static_bodies: dict, meters: float, UsdGeom, Usd, source: str) -> None:
    """Refuse a world weld whose two joint frames disagree at the initial pose (the body
    would be held where it is, not where the joint puts it)."""
    poses = []
    for end, frame in zip((desc.body0, desc.body1), _joint_frames(desc, meters)):
        end = str(end)
        if end == body.path:
            owner = body.pose
        elif end in static_bodies:
            owner = static_bodies[end].pose
        elif end:
            owner = _frame(_world_matrix(stage.GetPrimAtPath(end), UsdGeom, Usd, source))
            owner[:3] *= meters
        else:
            owner = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        poses.append(pose_mul(owner, frame))
    apart = float(np.linalg.norm(poses[0][:3] - poses[1][:3]))
    turned = 2.0 * float(np.arccos(min(1.0, abs(np.dot(poses[0][3:], poses[1][3:])))))
    if apart > 1e-5 * max(1.0, float(np.linalg.norm(poses[0][:3]))) or turned > 1e-5:
        raise ValueError(
            f"{source}: prim {joint_path}: the fixed joint's frames on {body.path} and on the world disagree by {apart:.3g} m and "
            f"{np.degrees(turned):.3g} degrees in the initial pose; move the body to where the joint holds it"
        )


def _read_joints(stage, descs, bodies: dict, mirrored: set, units: _Units, source: str, UsdPhysics) -> list[JointSpec]:
    """UsdPhysics joints -> JointSpec. Angles in degrees and angular gains per degree (UsdPhysics)
    become radians and gains per radian; lengths and gains take the stage's units. A joint on a
    ``mirrored`` body is refused: its frame on that body would be a reflection."""
    joints = []
    kinds = [("RevoluteJoint", "revolute"), ("PrismaticJoint", "prismatic"), ("SphericalJoint", "ball"), ("D6Joint", "d6")]
    for usd_kind, kind in kinds:
        for prim_path, desc in descs.get(usd_kind, []):
            where = f"{source}: prim {prim_path}"
            if not desc.jointEnabled:
                continue
            prim = stage.GetPrimAtPath(prim_path)
            _refuse_unread_axis_schemas(prim, usd_kind, kind, where)
            for label in ("body0", "body1"):
                rel = prim.GetRelationship(f"physics:{label}")
                targets = rel.GetTargets() if rel else []
                if len(targets) > 1:
                    raise ValueError(f"{where}: physics:{label} targets {len(targets)} prims; a joint joins one body on each side")
                if targets and not stage.GetPrimAtPath(targets[0]):
                    # The UsdPhysics parser reads such a body as none: body0 became the world.
                    raise ValueError(f"{where}: physics:{label} targets {targets[0]}, which does not exist")
            for label in ("localRot0", "localRot1"):
                # The parser reads a zero quaternion as the identity and normalises others.
                rotation = _attr(prim, f"physics:{label}")
                if rotation is not None:
                    norm = float(np.linalg.norm(_quat_xyzw(rotation)))
                    if not abs(norm - 1.0) <= QUATERNION_TOLERANCE:
                        raise ValueError(f"{where}: physics:{label} must be a unit quaternion, got {rotation} (norm {norm:.9g})")
            parent_path, child_path = str(desc.body0), str(desc.body1)
            if not child_path:
                targets = prim.GetRelationship("physics:body1").GetTargets() if prim.GetRelationship("physics:body1") else []
                if targets:  # the parser reads a prim that is no body as none
                    raise ValueError(f"{where}: body1 {targets[0]} is not a rigid body with a collider (every link needs a mesh)")
                raise ValueError(f"{where}: physics:body1 is not set; a joint here moves the rigid body in body1 (and body0 empty joins it to the world)")
            if child_path not in bodies:
                raise ValueError(f"{where}: body1 {child_path} is not a rigid body with a collider (every link needs a mesh)")
            if parent_path and parent_path not in bodies:
                raise ValueError(f"{where}: body0 {parent_path} is not a rigid body or collider")
            if desc.collisionEnabled and parent_path:
                raise ValueError(
                    f"{where}: physics:collisionEnabled is not supported: a joint's two bodies never collide here "
                    "(ModelBuilder's articulation_contact sets that for every joint); remove it"
                )
            if np.isfinite(desc.breakForce) or np.isfinite(desc.breakTorque):
                raise ValueError(
                    f"{where}: breakable joints are not supported (physics:breakForce {desc.breakForce:g}, physics:breakTorque "
                    f"{desc.breakTorque:g}); the joint would never break"
                )
            for label, path in (("body0", parent_path), ("body1", child_path)):
                if path in mirrored:
                    raise ValueError(
                        f"{where}: {label} {path} is mirrored (a negative scale in its transform), which a joint frame "
                        "cannot follow; mirror its points in the mesh instead"
                    )
            frames = _joint_frames(desc, units.meters)
            spec = JointSpec(
                name=str(prim_path).rsplit("/", 1)[-1],
                path=str(prim_path),
                kind=kind,
                parent=bodies[parent_path].name if parent_path else None,
                child=bodies[child_path].name,
                parent_frame=frames[0],
                child_frame=frames[1],
            )
            if kind in ("revolute", "prismatic"):
                spec.axes = _AXES[_axis_token(prim, "physics:axis", where)][None]
                scale = _DEGREE if kind == "revolute" else units.meters
                # The parser disables a limit with an open side: its values are read instead.
                bounds = _limit_bounds(desc.limit, scale, where, "limit")
                spec.limits = [bounds] if bounds else None
                drive = desc.drive
                gain = units.drive_gain(angular=kind == "revolute")
                gains = (drive.stiffness * gain, drive.damping * gain) if drive.enabled else (0.0, 0.0)
                spec.kp, spec.kd = np.array([gains[0]]), np.array([gains[1]])
                if drive.enabled:
                    token = "angular" if kind == "revolute" else "linear"
                    _check_drive(_drive_fields(drive), where, token)
                    target = _drive_target(prim, token, drive, scale, where)
                    if target is not None:
                        spec.targets = np.array([target])
            elif kind == "ball":
                spec.axes = _AXES[_axis_token(prim, "physics:axis", where)][None]
                cones = [prim.GetAttribute(f"physics:coneAngle{i}Limit") for i in (0, 1)]
                angles = [float(a.Get()) for a in cones if a and a.HasAuthoredValue()]
                if any(np.isnan(angles)) or (len(angles) == 2 and (np.isfinite(angles[0]) != np.isfinite(angles[1]))):
                    # The parser drops such a limit: it loaded as no limit at all.
                    raise ValueError(f"{where}: cone limits must be numbers, both finite for a cone or both infinite for none, got {angles}")
                if len(angles) == 2 and sum(a < 0.0 for a in angles) == 1 and max(angles) < 180.0:
                    # UsdPhysics: a negative angle leaves that direction free; the parser then
                    # reports no limit, and the other direction's limit was dropped.
                    raise ValueError(f"{where}: a cone limited in one direction only (coneAngle0Limit {angles[0]:g}, coneAngle1Limit {angles[1]:g} degrees) is not supported; give both cone angles the same value")
                if desc.limit.enabled and min(abs(desc.limit.lower), abs(desc.limit.upper)) < 180.0:
                    # coneAngle0Limit / coneAngle1Limit: only a circular cone is modelled
                    if abs(desc.limit.lower - desc.limit.upper) > 1e-6:
                        raise ValueError(f"{where}: elliptical cone limits ({desc.limit.lower} and {desc.limit.upper} degrees) are not supported; give both cone angles the same value")
                    if not desc.limit.lower > 0.0:
                        # It was "cone_limit must be in (0, pi) rad, got 0.0", the builder's name (a probe, stop 64).
                        raise ValueError(f"{where}: physics:coneAngle0Limit / coneAngle1Limit of {desc.limit.lower:g} degrees leave no swing; a cone limit must be in (0, 180) degrees (negative: no limit)")
                    spec.cone_limit = float(desc.limit.lower) * _DEGREE
                # UsdPhysics parses no drives for spherical joints: read DriveAPI:rot* off the prim.
                drives = {}
                for axis in _BALL_DRIVE_AXES:
                    token = _api_token(axis)
                    if prim.HasAPI(UsdPhysics.DriveAPI, token):
                        drive = UsdPhysics.DriveAPI(prim, token)
                        fields = {name: getattr(drive, f"Get{attr}Attr")().Get() for name, attr in _DRIVE_API_ATTRIBUTES.items()}
                        _check_drive(fields, where, token, ball=True)
                        drives[axis] = (float(fields["stiffness"] or 0.0), float(fields["damping"] or 0.0))
                spec.kp, spec.kd = _ball_gains(drives, units, where)
            else:
                _read_d6(desc, spec, where, units, prim)
            joints.append(spec)
    _make_names_unique(joints, "joint", source)
    return joints


def _make_names_unique(specs: list, kind: str, source: str) -> None:
    """Name each spec by its prim's name, or, where several share it, by its path
    (/World/A/box -> World_A_box); ValueError naming the prims when a name still repeats
    (a path-derived name that another prim has as its own)."""
    uses = Counter(spec.name for spec in specs)
    for spec in specs:
        if uses[spec.name] > 1:
            spec.name = spec.path.strip("/").replace("/", "_")
    uses = Counter(spec.name for spec in specs)
    clashes = [spec.path for spec in specs if uses[spec.name] > 1]
    if clashes:
        raise ValueError(f"{source}: prims {', '.join(clashes)} would all be the {kind} named {next(s.name for s in specs if uses[s.name] > 1)!r}; rename one")


# DriveAPI attributes by the names of UsdPhysics' parsed JointDrive fields.
_DRIVE_API_ATTRIBUTES = {"stiffness": "Stiffness", "damping": "Damping", "targetPosition": "TargetPosition", "targetVelocity": "TargetVelocity", "type": "Type", "forceLimit": "MaxForce"}


def _drive_fields(drive) -> dict:
    """A parsed UsdPhysics JointDrive as the fields ``_check_drive`` reads."""
    return {
        "stiffness": drive.stiffness,
        "damping": drive.damping,
        "targetPosition": drive.targetPosition,
        "targetVelocity": drive.targetVelocity,
        "type": "acceleration" if drive.acceleration else "force",
        "forceLimit": drive.forceLimit,
    }


def _check_drive(fields: dict, where: str, token: str, *, ball: bool = False) -> None:
    """Refuse what a PD drive here cannot do, rather than drop it: a target velocity (the
    damping acts on the joint velocity itself), an acceleration drive (its gains are scaled
    by inertia), a force limit, and, on a ball joint, a target position (its targets are
    Control.ball_target rotations)."""
    name = f"drive:{token}"
    if fields["targetVelocity"]:
        raise ValueError(f"{where}: {name}:physics:targetVelocity {fields['targetVelocity']:g} is not supported (drives damp towards rest); remove it")
    if fields["type"] == "acceleration":
        raise ValueError(f"{where}: {name}:physics:type 'acceleration' is not supported (drives are force drives: gains in N m/rad or N/m)")
    if fields["forceLimit"] is not None and np.isfinite(fields["forceLimit"]):
        raise ValueError(f"{where}: {name}:physics:maxForce {fields['forceLimit']:g} is not supported (drive forces are not limited); remove it")
    if ball and fields["targetPosition"]:
        raise ValueError(f"{where}: {name}:physics:targetPosition {fields['targetPosition']:g} is not supported on a ball joint (its PD targets are Control.ball_target rotations)")


def _ball_gains(drives: dict, units: _Units, where: str) -> tuple[np.ndarray, np.ndarray]:
    """A ball joint's (kp, kd) per radian from its angular drives {"RotX": (stiffness, damping)
    per degree, ...}: none, or all three axes with equal gains, since one gain pair drives
    the whole relative rotation (no per-axis gains)."""
    if not drives:
        return np.zeros(0), np.zeros(0)
    gains = [drives.get(axis) for axis in _BALL_DRIVE_AXES]
    if any(g is None for g in gains) or not all(np.allclose(g, gains[0], rtol=1e-6, atol=0.0) for g in gains):
        found = ", ".join(f"{axis} " + ("missing" if g is None else f"stiffness {g[0]:g} damping {g[1]:g}") for axis, g in zip(_BALL_DRIVE_AXES, gains, strict=True))
        raise ValueError(f"{where}: a ball joint's drives need equal stiffness and damping on rotX, rotY and rotZ (one gain pair drives its whole rotation); got {found}")
    gain = units.drive_gain(angular=True)
    return np.array([gains[0][0] * gain]), np.array([gains[0][1] * gain])


def _limit_bounds(limit, scale: float, where: str, name: str) -> tuple | None:
    """An enabled UsdPhysics limit as (lower, upper) in SI units, one side infinite where
    UsdPhysics leaves it open, or None with both open; a NaN side is refused. (A one-sided
    limit used to be dropped whole, and a NaN one read as none.)"""
    lower, upper = float(limit.lower), float(limit.upper)
    if np.isnan(lower) or np.isnan(upper):
        raise ValueError(f"{where}: {name} must be numbers (-inf or inf for an open side), got ({lower}, {upper})")
    if not (np.isfinite(lower) or np.isfinite(upper)):
        return None
    if lower == upper:
        # Refused further on as "limits must be ... lower < upper", which named no way out (a
        # probe, stop 64): authors lock axes this way.
        raise ValueError(
            f"{where}: {name} has lower == upper ({lower:g}), which locks the coordinate: a joint's limits must leave it room; "
            "lock a D6 axis with low > high, or join the bodies with a fixed joint (or merge them)"
        )
    return (lower * scale if np.isfinite(lower) else -np.inf, upper * scale if np.isfinite(upper) else np.inf)


def _drive_target(prim, token: str, drive, scale: float, where: str) -> float | None:
    """A drive's authored targetPosition in SI units, or None when it is not authored (the
    coordinate then holds its initial value). An authored 0 used to be read as none."""
    attr = prim.GetAttribute(f"drive:{token}:physics:targetPosition")
    if not (attr and attr.HasAuthoredValue()):
        return None
    if not np.isfinite(drive.targetPosition):
        raise ValueError(f"{where}: drive:{token}:physics:targetPosition must be finite, got {drive.targetPosition}")
    return drive.targetPosition * scale


def _base_start_coordinates(j: JointSpec, child_pose: np.ndarray) -> np.ndarray:
    """A base joint's UsdPhysics D6 coordinates at the start (m, rad; one per coordinate):
    its child frame's offset from its world-aligned parent frame along each free
    translation, and its turn about a free rotation axis. Limits and drive targets are
    authored in those coordinates, while a base's own start at 0. ValueError naming the axis
    for a locked axis the start violates (the body would be held where it is, not where the
    joint puts it), and for two free rotations that start turned (their angles would follow
    UsdPhysics' decomposition, which a base does not)."""
    child = pose_mul(child_pose, j.child_frame)
    offset = child[:3] - j.parent_frame[:3]
    turn = rotation_vector_from_quat(quat_mul(quat_conjugate(j.parent_frame[3:]), child[3:]))
    length_tol = 1e-5 * max(1.0, float(np.linalg.norm(j.parent_frame[:3])))
    rotations = [d for d in j.dofs if d.startswith("r")]
    for k, axis in enumerate("xyz"):
        if axis not in j.dofs and abs(offset[k]) > length_tol:
            raise ValueError(
                f"its locked trans{axis.upper()} axis starts {offset[k]:.6g} m apart (the frames of body0 and body1 disagree in the initial pose); "
                "move the body to where the joint holds it, or free that axis"
            )
        if len(rotations) < 3 and f"r{axis}" not in rotations and abs(turn[k]) > 1e-5:
            raise ValueError(f"its locked rot{axis.upper()} axis starts turned by {np.degrees(turn[k]):.6g} degrees; turn the body to where the joint holds it, or free that axis")
    if len(rotations) == 2 and np.linalg.norm(turn) > 1e-5:
        raise ValueError(f"its two free rotations start turned by {np.degrees(np.linalg.norm(turn)):.6g} degrees; author its frames so that they agree in the initial pose")
    coordinates = [d for d in j.dofs if not (len(rotations) == 3 and d.startswith("r"))]
    return np.array([offset["xyz".index(d)] if not d.startswith("r") else turn["xyz".index(d[1])] for d in coordinates])


def _read_d6(desc, spec: JointSpec, where: str, units: _Units, prim):
    """A D6 joint: locked axes have low > high. Free rotations make a revolute (1), universal
    (2, in X, Y, Z order) or ball (3) joint; free translations are allowed only on a joint to
    the world with world-aligned axes, which makes a base joint."""
    limits = {str(pair.first).split(".")[-1]: pair.second for pair in desc.jointLimits}
    drives = {str(pair.first).split(".")[-1]: pair.second for pair in desc.jointDrives}
    free = [axis for axis in _D6_AXIS_DOF if not (axis in limits and limits[axis].enabled and limits[axis].lower > limits[axis].upper)]
    translations = [a for a in free if a.startswith("Trans")]
    rotations = [a for a in free if a.startswith("Rot")]
    if translations:
        if spec.parent is not None or abs(abs(spec.parent_frame[6]) - 1.0) > 1e-9:
            raise ValueError(f"{where}: free translations are supported only on a D6 joint from the world (no body0) with world-aligned axes (a base joint)")
        # Three free rotations of a base joint are one rotation group, with no coordinates
        # to drive or limit (one or two are coordinates, with both).
        shaped = [a for a in rotations if (a in drives and drives[a].enabled) or (a in limits and limits[a].enabled)] if len(rotations) == 3 else []
        if shaped:
            raise ValueError(f"{where}: a D6 joint with free translations and three free rotations takes no drives or limits on its rotations ({', '.join(shaped)}); they were ignored")
        spec.kind = "base"
        spec.dofs = tuple(_D6_AXIS_DOF[a] for a in free)
        coordinates = _coordinate_axes(free)
    elif len(rotations) == 3:
        spec.kind = "ball"
        coordinates = []
    elif rotations:
        spec.kind = "revolute" if len(rotations) == 1 else "universal"
        spec.axes = np.array([_AXES[a[-1]] for a in rotations])
        coordinates = rotations
    else:
        raise ValueError(f"{where}: a D6 joint with every axis locked is a fixed joint, which is not supported (merge the two bodies)")
    locked = [axis for axis, drive in drives.items() if drive.enabled and axis not in free]
    if locked:
        # Its gain was dropped and nothing moved (a probe at stop 61).
        raise ValueError(f"{where}: drive:{_api_token(locked[0])} drives an axis its limit locks (low > high), which it cannot move; remove the drive or free the axis")
    for axis, drive in drives.items():
        if drive.enabled:
            _check_drive(_drive_fields(drive), where, _api_token(axis), ball=spec.kind == "ball")
    bounds, kp, kd, targets = [], [], [], []
    for axis in coordinates:
        scale = units.meters if axis.startswith("Trans") else _DEGREE
        limit = limits.get(axis)
        bounded = _limit_bounds(limit, scale, where, f"the {axis} limit") if limit is not None and limit.enabled else None
        bounds.append(bounded or (-np.inf, np.inf))
        drive = drives.get(axis)
        driven = drive is not None and drive.enabled
        gain = units.drive_gain(angular=axis.startswith("Rot"))
        kp.append(drive.stiffness * gain if driven else 0.0)
        kd.append(drive.damping * gain if driven else 0.0)
        target = _drive_target(prim, _api_token(axis), drive, scale, where) if driven else None
        targets.append(np.nan if target is None else target)
    if spec.kind == "ball" and any(axis in limits and limits[axis].enabled for axis in rotations):
        raise ValueError(f"{where}: a D6 joint with three free rotations is a ball joint, which takes no rotation limits here")
    spec.limits = bounds if np.isfinite(bounds).any() else None
    spec.kp, spec.kd = np.array(kp), np.array(kd)
    if not np.isnan(targets).all():
        spec.targets = np.array(targets)  # NaN: that coordinate's initial value
    if spec.kind == "ball":
        spec.kp, spec.kd = _ball_gains({axis: (drive.stiffness, drive.damping) for axis, drive in drives.items() if axis in _BALL_DRIVE_AXES and drive.enabled}, units, where)


# MassAPI attributes and the value that, authored or not, means "not specified" (UsdPhysics:
# "if non-zero, ..."; a centre of mass of -inf): exported assets often author these.
_MASS_UNSPECIFIED = {
    "mass": 0.0,
    "density": 0.0,
    "centerOfMass": (-np.inf, -np.inf, -np.inf),
    "diagonalInertia": (0.0, 0.0, 0.0),
    "principalAxes": (0.0, 0.0, 0.0, 0.0),
}


def _mass_properties(api) -> dict:
    """A MassAPI's specified properties: {name: value} of those authored with a value other
    than the one meaning "not specified" (``_MASS_UNSPECIFIED``); quaternions as (x, y, z, w)."""
    found = {}
    for name, unspecified in _MASS_UNSPECIFIED.items():
        attr = getattr(api, f"Get{name[0].upper()}{name[1:]}Attr")()
        if not (attr and attr.HasAuthoredValue()):
            continue
        value = attr.Get()
        value = _quat_xyzw(value) if name == "principalAxes" else np.asarray(value, dtype=np.float64)
        if name == "principalAxes" and not value.any():
            continue
        if name != "principalAxes" and np.array_equal(value, unspecified):
            continue
        found[name] = value
    return found


def _read_mass(prim, body: BodySpec, UsdPhysics, units: _Units, source: str):
    if not prim.HasAPI(UsdPhysics.MassAPI):
        return
    specified = _mass_properties(UsdPhysics.MassAPI(prim))
    where = f"{source}: prim {prim.GetPath()}"
    if "mass" in specified:
        mass = float(specified["mass"])
        if not np.isfinite(mass) or mass <= 0:
            raise ValueError(f"{where}: mass must be positive (or 0: not specified), got {mass}")
        body.mass = mass * units.kilograms
    if "density" in specified:
        density = float(specified["density"])
        if not np.isfinite(density) or density <= 0:
            raise ValueError(f"{where}: density must be positive (or 0: not specified), got {density}")
        body.density = density * units.density
    if "centerOfMass" in specified:
        body.center_of_mass = specified["centerOfMass"] * units.meters
        if not np.isfinite(body.center_of_mass).all():
            raise ValueError(f"{where}: centerOfMass must be finite (or -inf on every axis: not specified), got {body.center_of_mass.tolist()}")
    if "diagonalInertia" in specified:
        diag = specified["diagonalInertia"] * units.inertia
        axes = specified.get("principalAxes", np.array([0.0, 0.0, 0.0, 1.0]))
        norm = float(np.linalg.norm(axes))
        # Not normalised, the rotation also scaled the inertia: (0.1, 0.1, 0.1) became 0.05s.
        if not abs(norm - 1.0) <= QUATERNION_TOLERANCE:
            raise ValueError(f"{where}: physics:principalAxes must be a unit quaternion (or all 0: not specified), got {UsdPhysics.MassAPI(prim).GetPrincipalAxesAttr().Get()} (norm {norm:.9g})")
        R = quat_to_matrix(axes / norm)
        if not (np.isfinite(diag).all() and (diag > 0).all()):
            raise ValueError(f"{where}: diagonalInertia must be positive (or 0 on every axis: not specified), got {diag}")
        body.inertia = R @ np.diag(diag) @ R.T


def _read_collider_mass(body_prim, collider_prims, body: BodySpec, UsdPhysics, units: _Units, source: str):
    """MassAPI authored on a body's collider prims rather than on the body prim (UsdPhysics
    allows both): it used to be ignored, so a collider's density of 5,000 kg/m^3 gave the
    default 1,000. The mass or density of a body's only collider is the body's when the body
    prim authors neither; any other per-collider mass property is refused, naming the prim."""
    authored = []
    for prim in collider_prims:
        if prim == body_prim or not prim.HasAPI(UsdPhysics.MassAPI):
            continue
        names = list(_mass_properties(UsdPhysics.MassAPI(prim)))
        if names:
            authored.append((prim, names))
    if not authored:
        return
    prim, names = authored[0]
    transferable = len(collider_prims) == 1 and set(names) <= {"mass", "density"} and body.mass is None and body.density is None
    if not transferable:
        raise ValueError(
            f"{source}: prim {prim.GetPath()}: physics:{', physics:'.join(names)} on a collider of rigid body {body_prim.GetPath()} "
            "is not supported (per-collider mass properties); author them on the rigid body prim"
        )
    _read_mass(prim, body, UsdPhysics, units, source)


# PhysX schema attributes (Isaac assets author them) that change a body's motion and that
# this simulator does not model; the rest of that schema tunes PhysX's own solver.
_PHYSX_MOTION = (
    "physxRigidBody:linearDamping",
    "physxRigidBody:angularDamping",
    "physxRigidBody:disableGravity",
    "physxRigidBody:lockedPosAxis",
    "physxRigidBody:lockedRotAxis",
)


def _all_prims(stage, Usd):
    """Every active, defined prim of the stage, those inside instances included (the UsdPhysics
    parser reads bodies there, and a plain traversal skipped their filters, typos and damping)."""
    return stage.Traverse(Usd.TraverseInstanceProxies())


def _refuse_unreadable_schema_attributes(stage, Usd, source: str) -> None:
    """ValueError naming the prim and attribute when a value is written with another type than
    its schema declares (a Cube's ``float size``, ``double physics:gravityMagnitude``): USD's
    readers, UsdPhysics' parser among them, then ignore it silently and use the schema's
    default (a 0.5 m cube loaded as a 2 m one, a joint's limits and drive gains dropped). Role
    names do not count (``float3`` for ``point3f`` reads as the same value). Also when a
    UsdPhysics attribute's value is blocked (``= None``): the parser then reads whatever its
    memory held (gravity along a different random direction each run, a joint's open side
    limited at 90 degrees), not the schema's fallback."""
    for prim in _all_prims(stage, Usd):
        definition = prim.GetPrimDefinition()
        for attr in prim.GetAuthoredAttributes():
            declared = definition.GetAttributeDefinition(attr.GetName())
            if not declared:
                continue  # not a schema attribute: read, and checked, by this module if at all
            if "physics:" in attr.GetName() and attr.GetResolveInfo().ValueIsBlocked():
                raise ValueError(
                    f"{source}: prim {prim.GetPath()}: {attr.GetName()} is blocked (authored as None), which UsdPhysics' parser does not reliably read as "
                    f"its fallback; author the value instead (the fallback is {declared.GetFallbackValue()})"
                )
            expected = declared.GetTypeName()
            for spec in attr.GetPropertyStack(Usd.TimeCode.Default()):
                if spec.typeName.type != expected.type:
                    raise ValueError(
                        f"{source}: prim {prim.GetPath()}: {attr.GetName()} is written as {spec.typeName} but its schema declares {expected}; "
                        f"USD would ignore the value and use the default (write it as {expected})"
                    )


# The value types an xformOp of each kind takes (any precision; role names count as their type).
_XFORM_OP_VALUE_TYPES = {
    **dict.fromkeys(("translate", "scale", "rotateXYZ", "rotateXZY", "rotateYXZ", "rotateYZX", "rotateZXY", "rotateZYX"), ("double3", "float3", "half3")),
    **dict.fromkeys(("translateX", "translateY", "translateZ", "scaleX", "scaleY", "scaleZ", "rotateX", "rotateY", "rotateZ"), ("double", "float", "half")),
    "orient": ("quatd", "quatf", "quath"),
    "transform": ("matrix4d",),
}


def _refuse_mistyped_xform_ops(stage, Sdf, Usd, UsdGeom, source: str) -> None:
    """ValueError naming the prim and op when an ``xformOpOrder`` names an op USD does not
    know, or an op whose value has another type than its kind takes (``float xformOp:scale =
    2``, ``double xformOp:rotateXYZ = 30``): UsdPhysics' parser raised a raw pxr error naming
    neither the file nor the prim, and an orient written as ``float4`` composed as the
    identity, silently (a probe)."""
    value_types = {kind: [Sdf.ValueTypeNames.Find(t).type for t in names] for kind, names in _XFORM_OP_VALUE_TYPES.items()}
    for prim in _all_prims(stage, Usd):
        if not prim.IsA(UsdGeom.Xformable):
            continue
        for token in UsdGeom.Xformable(prim).GetXformOpOrderAttr().Get() or []:
            if token == "!resetXformStack!":
                continue
            name = token[len("!invert!") :] if token.startswith("!invert!") else token
            parts = name.split(":")
            allowed = _XFORM_OP_VALUE_TYPES.get(parts[1]) if len(parts) >= 2 and parts[0] == "xformOp" else None
            if allowed is None:
                raise ValueError(f"{source}: prim {prim.GetPath()}: xformOpOrder names {token!r}, which is not a transform op USD knows ({', '.join(_XFORM_OP_VALUE_TYPES)})")
            attr = prim.GetAttribute(name)
            if not attr:
                continue  # USD warns and skips it, as its readers do
            for spec in attr.GetPropertyStack(Usd.TimeCode.Default()):
                if spec.typeName.type not in value_types[parts[1]]:
                    raise ValueError(
                        f"{source}: prim {prim.GetPath()}: {name} is written as {spec.typeName}, but a transform op of type {parts[1]} takes "
                        f"{' or '.join(allowed)} (USD would not apply it; a raw pxr error or no transform at all)"
                    )


def _warn_unmodelled(stage, collider_materials: dict, UsdPhysics, Usd, source: str) -> None:
    """Warn, naming the prims, about authored physics this simulator does not model: non-zero
    PhysX body damping, gravity switched off and locked axes, and restitution of the colliders' physics materials (not a parameter
    here: the implicit step dissipates part of the normal impact velocity, more at larger
    time steps; docs/architecture.md, "Impacts bounce a little")."""
    found = []
    for prim in _all_prims(stage, Usd):
        for name in _PHYSX_MOTION:
            attr = prim.GetAttribute(name)
            if attr and attr.HasAuthoredValue() and attr.Get():
                found.append(f"{prim.GetPath()} {name} {attr.Get():g}")
    materials = {str(m.GetPath()): m for bound in collider_materials.values() for m in bound if m and m.HasAPI(UsdPhysics.MaterialAPI)}
    for path, material in materials.items():
        attr = UsdPhysics.MaterialAPI(material).GetRestitutionAttr()
        if attr and attr.HasAuthoredValue() and attr.Get():
            found.append(f"{path} physics:restitution {attr.Get():g}")
    if found:
        warnings.warn(f"{source}: not modelled, so ignored: {', '.join(found[:5])}{' ...' if len(found) > 5 else ''}", stacklevel=3)


def _usd_physics_attribute_names(UsdPhysics) -> frozenset:
    """The physics: attribute names of UsdPhysics' schemas (the pxr installed)."""
    names = set()
    for schema in vars(UsdPhysics).values():
        listed = getattr(schema, "GetSchemaAttributeNames", None)
        if listed is not None:
            names.update(name for name in listed(True) if name.startswith("physics:"))
    return frozenset(names)


def _warn_foreign_layer_units(stage, stage_units: dict, source: str) -> None:
    """Warn where a layer the stage uses (a reference, payload or sublayer) authors other
    units or another up axis than the stage: USD never converts them, so a 50 cm asset in
    a metre stage is read as 50 m (unless the referencing prim scales it)."""
    root = stage.GetRootLayer()
    for layer in stage.GetUsedLayers():
        if layer == root or layer.anonymous:
            continue
        for key, value in stage_units.items():
            if layer.pseudoRoot.HasInfo(key) and layer.pseudoRoot.GetInfo(key) != value:
                warnings.warn(
                    f"{source}: layer {layer.identifier} authors {key} = {layer.pseudoRoot.GetInfo(key)}, the stage {value}; "
                    "USD does not convert between them, so its prims are read in the stage's (scale or turn the prim that references it)",
                    stacklevel=3,
                )


# MassAPI's and RigidBodyAPI's attributes, which UsdPhysics reads only with the API applied.
_MASS_API_ATTRIBUTES = ("physics:mass", "physics:density", "physics:centerOfMass", "physics:diagonalInertia", "physics:principalAxes")
_RIGID_BODY_VELOCITIES = ("physics:velocity", "physics:angularVelocity")


def _refuse_unread_mass_and_velocity(stage, UsdPhysics, Usd, source: str) -> None:
    """MassAPI's attributes authored on a prim without the API, MassAPI on a prim that is
    neither a rigid body nor a collider, and a velocity on a prim that is no rigid body are
    refused, naming the prim: UsdPhysics reads none of them, and a body took its mass from the
    default density (125 kg for an authored 7 kg, its centre of mass at the box's centre; a
    probe at stop 58)."""
    for prim in _all_prims(stage, Usd):
        authored = [name for name in _MASS_API_ATTRIBUTES + _RIGID_BODY_VELOCITIES if prim.HasAttribute(name) and prim.GetAttribute(name).HasAuthoredValue()]
        # Declared by none of the prim's schemas (a physics material's own physics:density is
        # read as the material's).
        declared = set(prim.GetPrimDefinition().GetPropertyNames()) if authored else set()
        body = prim.HasAPI(UsdPhysics.RigidBodyAPI)
        mass = [name for name in authored if name in _MASS_API_ATTRIBUTES and name not in declared]
        if mass:
            raise ValueError(f"{source}: prim {prim.GetPath()}: {', '.join(mass)} authored without PhysicsMassAPI applied, which UsdPhysics does not read; apply it (prepend apiSchemas = [\"PhysicsMassAPI\"]) or remove them")
        if prim.HasAPI(UsdPhysics.MassAPI) and not (body or prim.HasAPI(UsdPhysics.CollisionAPI)):
            raise ValueError(f"{source}: prim {prim.GetPath()}: PhysicsMassAPI on a prim that is neither a rigid body nor a collider is not read; move it to the body or to its collider")
        velocity = [name for name in authored if name in _RIGID_BODY_VELOCITIES and name not in declared]
        if velocity:
            raise ValueError(f"{source}: prim {prim.GetPath()}: {', '.join(velocity)} authored on a prim without PhysicsRigidBodyAPI, which UsdPhysics does not read; apply it to make the prim a body, or remove them")


def _refuse_collision_filters(stage, UsdPhysics, Usd, source: str) -> None:
    """Collision filters (FilteredPairsAPI, CollisionGroup filtering) are refused, naming the
    prim: every body pair interacts here, so ignoring a filter would add contact forces (and
    far-field ones) the scene's author switched off."""
    for prim in _all_prims(stage, Usd):
        if prim.HasAPI(UsdPhysics.FilteredPairsAPI) and UsdPhysics.FilteredPairsAPI(prim).GetFilteredPairsRel().GetTargets():
            raise ValueError(f"{source}: prim {prim.GetPath()}: physics:filteredPairs is not supported (every body pair interacts); remove the filter")
        if prim.IsA(UsdPhysics.CollisionGroup):
            group = UsdPhysics.CollisionGroup(prim)
            inverted = group.GetInvertFilteredGroupsAttr().Get() if group.GetInvertFilteredGroupsAttr() else False
            if group.GetFilteredGroupsRel().GetTargets() or inverted:
                raise ValueError(f"{source}: prim {prim.GetPath()}: collision-group filtering is not supported (every body pair interacts); remove physics:filteredGroups")


def _bound_physics_materials(stage, prim, desc, scene_materials: list) -> list:
    """A collider's physics materials: those the UsdPhysics parser lists (per GeomSubset too),
    and the one UsdShade binds to it for the physics purpose, which it may inherit from an
    ancestor (the parser lists a material only for prims with MaterialBindingAPI: a body's
    binding was ignored by its colliders); without any, ``scene_materials``, the scene's
    default (``_scene_physics_materials``)."""
    from pxr import UsdShade

    materials = [stage.GetPrimAtPath(m) for m in desc.materials]
    bound, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial("physics")
    if bound and bound.GetPrim() not in materials:
        materials.append(bound.GetPrim())
    return materials or list(scene_materials)


def _scene_physics_materials(scene_prim) -> list:
    """The material bound to the PhysicsScene for the physics purpose, as a list (empty
    without one): the default of colliders that bind none (PhysX's convention; it was
    ignored, a probe)."""
    from pxr import UsdShade

    if scene_prim is None:
        return []
    default, _ = UsdShade.MaterialBindingAPI(scene_prim).ComputeBoundMaterial("physics")
    return [default.GetPrim()] if default else []


def _refuse_point_instanced_physics(stage, UsdGeom, UsdPhysics, Usd, source: str) -> None:
    """Bodies and colliders among a PointInstancer's prototypes are refused, naming the
    instancer: the UsdPhysics parser does not expand instancers, and they were dropped
    (a scene of instanced boxes loaded without them)."""
    for prim in _all_prims(stage, Usd):
        if not prim.IsA(UsdGeom.PointInstancer):
            continue
        for target in UsdGeom.PointInstancer(prim).GetPrototypesRel().GetTargets():
            # Every prim under the prototype: also those under an ``over`` or ``class`` container
            # and inside instanceable references, which the default traversal skips (their
            # instances were dropped silently; a probe, stop 59).
            for proto in Usd.PrimRange(stage.GetPrimAtPath(target), Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
                if proto.HasAPI(UsdPhysics.RigidBodyAPI) or proto.HasAPI(UsdPhysics.CollisionAPI):
                    raise ValueError(
                        f"{source}: prim {prim.GetPath()}: a PointInstancer of rigid bodies or colliders ({proto.GetPath()}) is not "
                        "supported (its instances would be dropped); author the bodies as prims, or as instanceable references"
                    )


def _material_value(materials, name: str, UsdPhysics, where: str):
    """The ``density`` or ``dynamicFriction`` (``name``) that a collider's bound physics
    materials author, else None; ValueError naming ``where`` when they author different
    values (a collider with per-face materials took the first one's)."""
    from pxr import Usd

    values = {}
    for material in materials:
        if not material or not material.HasAPI(UsdPhysics.MaterialAPI):
            continue
        attr = getattr(UsdPhysics.MaterialAPI(material), f"Get{name[0].upper()}{name[1:]}Attr")()
        if attr:
            # Sampled only, it read as its fallback 0: "not specified".
            _require_default_value(attr, Usd, where)
        if attr and attr.HasAuthoredValue():
            values[str(material.GetPath())] = float(attr.Get())
    if len(set(values.values())) > 1:
        listed = ", ".join(f"{path}: {value:.6g}" for path, value in values.items())
        raise ValueError(f"{where}: its physics materials author different {name} ({listed}); one value holds for a whole collider here")
    return next(iter(values.values()), None)


def _read_material_density(collider_prims, collider_materials, body: BodySpec, UsdPhysics, units: _Units, source: str):
    """The density of the physics materials bound to a body's colliders (they were ignored:
    5,000 kg/m^3 gave the default 1,000), where the body has no mass or density of its own.
    Colliders of one body with different densities are refused: they are not combined."""
    densities = {str(prim.GetPath()): _material_value(collider_materials[str(prim.GetPath())], "density", UsdPhysics, f"{source}: prim {prim.GetPath()}") for prim in collider_prims}
    # A material density of 0 means "not specified" (UsdPhysics: "if non-zero").
    densities = {path: (None if d == 0.0 else d) for path, d in densities.items()}
    values = {d for d in densities.values() if d is not None}
    if not values or body.mass is not None or body.density is not None:
        return
    if len(values) > 1 or None in densities.values():
        listed = ", ".join(f"{path}: {'none' if d is None else d}" for path, d in densities.items())
        raise ValueError(f"{source}: prim {body.path}: its colliders' physics materials give different densities ({listed}); author a mass or density on the rigid body prim")
    density = values.pop()
    if not np.isfinite(density) or density <= 0:
        raise ValueError(f"{source}: prim {body.path}: its physics material's density must be positive, got {density}")
    body.density = density * units.density


def _read_material_friction(collider_materials, scene_prim, settings: SimulationSettings, UsdPhysics, source: str):
    """The dynamic friction of the colliders' physics materials as the scene's one friction
    coefficient, unless ``warpcontact:friction`` is authored (it was ignored: 0.9 on every
    collider simulated without friction). Different values are refused: one coefficient
    holds for all contacts."""
    every = {path: _material_value(materials, "dynamicFriction", UsdPhysics, f"{source}: prim {path}") for path, materials in collider_materials.items()}
    values = {path: value for path, value in every.items() if value is not None}
    if not values:
        return
    authored = scene_prim is not None and scene_prim.GetAttribute("warpcontact:friction").HasAuthoredValue()
    if authored:
        return
    if len(set(values.values())) > 1:
        listed = ", ".join(f"{path}: {value:.6g}" for path, value in values.items())
        raise ValueError(f"{source}: colliders bind physics materials with different dynamicFriction ({listed}); one friction coefficient holds for all contacts: author warpcontact:friction on the PhysicsScene")
    friction = next(iter(values.values()))
    problem = contact_setting_problem("friction", friction)
    if problem:
        raise ValueError(f"{source}: physics material dynamicFriction: {problem}, got {friction}")
    unbound = [path for path, value in every.items() if value is None]
    if unbound:
        # Their contacts among themselves took the bound coefficient without a word.
        others = f" and {len(unbound) - 1} more colliders bind" if len(unbound) > 1 else " binds"
        warnings.warn(
            f"{source}: prim {unbound[0]}{others} no physics material giving dynamicFriction, but others do: the scene's one coefficient, "
            f"{friction:.6g}, holds for their contacts too; bind a default material to the PhysicsScene or author warpcontact:friction to say so",
            stacklevel=3,
        )
    settings.friction = friction


def target_problem(body: BodySpec) -> str | None:
    """What is wrong with a target body's goal (``target_position``: 3 finite numbers,
    ``target_tolerance``: in [0, MAX_COORDINATE]), or None: one rule for scenes read from
    USD and scenes built in Python (``tasks.validate_task``)."""
    position = np.asarray(body.target_position, dtype=np.float64)
    if position.shape != (3,) or not np.isfinite(position).all() or np.abs(position).max() > MAX_COORDINATE:
        # Beyond MAX_COORDINATE the squared distance of the loss overflowed to inf.
        return f"warpcontact:target:position must be 3 finite numbers of at most {MAX_COORDINATE:g} m in magnitude, got {position.tolist()}"
    tolerance = body.target_tolerance
    # Beyond MAX_COORDINATE its square overflowed in the receding loss, and a run of hours
    # ended in a traceback with nothing written (1e155; a probe, stop 63).
    if not is_real(tolerance) or not np.isfinite(tolerance) or not 0 <= tolerance <= MAX_COORDINATE:
        return f"warpcontact:target:tolerance must be finite, >= 0 and at most {MAX_COORDINATE:g} m, got {tolerance}"
    return None


def _dynamic_only(body: BodySpec) -> str:
    """What a static body holds that only a dynamic body takes ("" where nothing): one rule
    for loading and saving (a kinematic body with a target loaded, and could not be saved)."""
    if not body.static:
        return ""
    return ", ".join(
        label
        for label, present in (
            ("a target", body.target_position is not None),
            ("PD gains", bool(np.any(body.kp_linear) or np.any(body.kd_linear) or body.kp_angular or body.kd_angular)),
            ("control dofs", bool(body.control_dofs)),
            # It never moves, and a save wrote it as a bare collider (a probe, stop 63).
            ("a velocity", bool(np.any(body.linear_velocity) or np.any(body.angular_velocity))),
        )
        if present
    )


def _read_warpcontact_body(prim, body: BodySpec, meters: float, source: str):
    target = _cast_attr(prim, "target:position", _numbers, source)
    tolerance = _cast_attr(prim, "target:tolerance", _number, source)
    if target is None and tolerance is not None:
        # A misspelt position met this error before the unknown-attribute one that names it.
        others = [a.GetName() for a in prim.GetAttributes() if a.GetName().startswith(_NS + "target:") and a.GetName() not in (_NS + "target:position", _NS + "target:tolerance")]
        hint = f" (found {', '.join(others)}: misspelt?)" if others else ""
        raise ValueError(f"{source}: prim {prim.GetPath()}: warpcontact:target:tolerance is authored without a warpcontact:target:position, which makes a body a target{hint}")
    if target is not None:
        body.target_position = target * meters
        body.target_tolerance = (0.0 if tolerance is None else tolerance) * meters
        problem = target_problem(body)
        if problem:
            # The check reads metres; the file's own values name what to change.
            authored = f" (authored: position {target.tolist()}, tolerance {tolerance}, at metersPerUnit {meters:g})" if meters != 1.0 else ""
            raise ValueError(f"{source}: prim {prim.GetPath()}: {problem}{authored}")
    _read_casts(prim, body, _BODY_ATTRIBUTES, source)
    # Here, by attribute: the builder's check named its own argument and a numpy repr
    # ("kp_linear must be ..., got array([ 400., 400., -400.])"; a probe, stop 64).
    for attr_name, (field_name, _cast) in _BODY_ATTRIBUTES.items():
        if not attr_name.startswith("pd:"):
            continue
        gain = np.asarray(getattr(body, field_name), dtype=np.float64)
        if not is_gain(gain):
            raise ValueError(f"{source}: prim {prim.GetPath()}: warpcontact:{attr_name} must be finite and >= 0 (a PD gain), got {gain.tolist()}")


def _read_casts(prim, target, casts: dict, source: str):
    """Set ``target``'s fields from the authored ``warpcontact:`` attributes named in ``casts``."""
    for attr_name, (field_name, cast) in casts.items():
        value = _cast_attr(prim, attr_name, cast, source)
        if value is not None:
            setattr(target, field_name, value)


def _cast_attr(prim, attr_name: str, cast, source: str):
    """The authored ``warpcontact:`` attribute through ``cast``, or None when not authored;
    ValueError naming the prim and attribute when the value does not fit."""
    value = _attr(prim, _NS + attr_name)
    if value is None:
        return None
    try:
        return cast(value)
    except (TypeError, ValueError, OverflowError):
        kind = {_whole: "a whole number", _number: "a number", _text: "text", _vector3: "1 or 3 numbers", _numbers: "a list of numbers", _strings: "a list of strings"}[cast]
        raise ValueError(f"{source}: prim {prim.GetPath()}: warpcontact:{attr_name} must be {kind}, got {value!r}") from None


def _whole(value) -> int:
    """An integer, authored as one (or as a float without a fraction); a fraction used to be
    truncated (a horizon of 5.7 ran 5 frames)."""
    if isinstance(value, (bool, str, np.bool_)) or float(value) != int(value):
        raise ValueError(value)
    return int(value)


def _number(value) -> float:
    """A number, authored as one: float() read a bool as 0 or 1 and the text "0.1" as 0.1
    (a `bool warpcontact:timeStep = 1` ran frames of 1 s)."""
    if not is_real(value):
        raise ValueError(value)
    return float(value)


def _text(value) -> str:
    if not isinstance(value, str):
        raise ValueError(value)
    return value


def _numbers(value) -> np.ndarray:
    """Numbers, flat (``real_array``: text and bools are not numbers)."""
    array = real_array(value)
    if array is None:
        raise ValueError(value)
    return array.reshape(-1)


def _vector3(value) -> np.ndarray:
    """Three numbers, or one for all three axes."""
    vector = _numbers(value)
    if vector.size not in (1, 3):
        raise ValueError(value)
    return np.broadcast_to(vector, (3,)).copy()


def _strings(value) -> tuple:
    if isinstance(value, str) or not all(isinstance(v, str) for v in value):
        raise ValueError(value)
    return tuple(value)


# The warpcontact: namespace (module docstring): attribute -> (field, cast) on the PhysicsScene
# prim (settings, task) and on rigid-body prims; target:position and task:sample* are read
# apart (units, tuples).
_SETTING_ATTRIBUTES = {
    "timeStep": ("time_step", _number),
    "frames": ("frames", _whole),
    "contactStiffness": ("contact_stiffness", _number),
    "eps": ("eps", _number),
    "centredWeight": ("centred_weight", _text),
    "leafPrecision": ("leaf_precision", _text),
    "friction": ("friction", _number),
    "frictionSmoothing": ("friction_smoothing", _number),
    "contactMode": ("contact_mode", _text),
}
TASK_ATTRIBUTES = {
    "task:name": ("name", _text),
    "task:control": ("control", _text),
    "task:horizon": ("horizon", _whole),
    "task:recedingHorizon": ("receding_horizon", _whole),
    "task:learningRate": ("learning_rate", _number),
    "task:iterations": ("iterations", _whole),
    "task:recedingStride": ("receding_stride", _whole),
    "task:quick:horizon": ("quick_horizon", _whole),
    "task:quick:recedingHorizon": ("quick_receding_horizon", _whole),
    "task:quick:learningRate": ("quick_learning_rate", _number),
    "task:quick:iterations": ("quick_iterations", _whole),
    "task:quick:recedingStride": ("quick_receding_stride", _whole),
}
_BODY_ATTRIBUTES = {
    "pd:kpLinear": ("kp_linear", _vector3),
    "pd:kdLinear": ("kd_linear", _vector3),
    "pd:kpAngular": ("kp_angular", _number),
    "pd:kdAngular": ("kd_angular", _number),
    "control:dofs": ("control_dofs", _strings),
    "group": ("group", _whole),
}
_SCENE_PRIM_NAMES = (*_SETTING_ATTRIBUTES, *TASK_ATTRIBUTES, "task:sampleLow", "task:sampleHigh")
_BODY_PRIM_NAMES = (*_BODY_ATTRIBUTES, "target:position", "target:tolerance")


def _check_namespace(stage, scene_prim, body_paths, Usd, UsdPhysics, source: str):
    """Every authored warpcontact: attribute must be one this module reads, on the kind of
    prim it is read from; a typo or a misplaced attribute would otherwise be ignored. Authored
    physics: attributes that no UsdPhysics schema has (a typo, physics:densty, or another
    tool's name, physics:linearDamping: ignored without a word until stop 62), and API schemas
    that look like UsdPhysics' but that USD does not know (``_unknown_physics_schemas``), are
    named in a warning, not refused: a newer UsdPhysics may add names."""
    import difflib

    physics = _usd_physics_attribute_names(UsdPhysics)
    physics_schemas = _usd_physics_api_schemas(Usd, UsdPhysics)
    unknown_physics = []
    scene_path = str(scene_prim.GetPath()) if scene_prim is not None else None
    for prim in _all_prims(stage, Usd):
        path = str(prim.GetPath())
        unknown_physics.extend(f"{path} apiSchemas {name}{f' (did you mean {close}?)' if close else ''}" for name, close in _unknown_physics_schemas(prim, physics_schemas, difflib))
        known = _SCENE_PRIM_NAMES if path == scene_path else _BODY_PRIM_NAMES if path in body_paths else ()
        for attr in prim.GetAuthoredAttributes():
            name = attr.GetName()
            if name.startswith("physics:") and name not in physics:
                close = difflib.get_close_matches(name, sorted(physics), n=1)
                unknown_physics.append(f"{path} {name}{f' (did you mean {close[0]}?)' if close else ''}")
            if not name.startswith(_NS) or name[len(_NS) :] in known:
                continue
            short = name[len(_NS) :]
            if short in _SCENE_PRIM_NAMES:
                hint = "it belongs on the PhysicsScene prim"
            elif short in _BODY_PRIM_NAMES:
                hint = "it belongs on a rigid-body prim"
            else:
                close = difflib.get_close_matches(short, _SCENE_PRIM_NAMES + _BODY_PRIM_NAMES, n=1)
                hint = f"did you mean {_NS}{close[0]}?" if close else "the attributes read are listed in docs/scene_format.md"
            raise ValueError(f"{source}: prim {path}: unknown attribute {name} here ({hint})")
    if unknown_physics:
        warnings.warn(f"{source}: no UsdPhysics schema has these attributes or schemas, so they are ignored: {', '.join(unknown_physics[:5])}{' ...' if len(unknown_physics) > 5 else ''}", stacklevel=3)


def _unknown_physics_schemas(prim, physics: dict[str, str], difflib) -> list[tuple[str, str | None]]:
    """(name, the UsdPhysics API schema it is closest to, or None) of each API schema in the
    prim's apiSchemas that USD does not know and that looks like one of UsdPhysics' (``physics``:
    their names by their lower-case names): the prefix "Physics", or one of their names but for
    case. USD drops them without a word, and a box listing PhysicsRigidbodyAPI loaded as a
    static obstacle (a probe, stop 64). Other tools' schemas (PhysxRigidBodyAPI, a studio's
    own) are not named."""
    listed = prim.GetMetadata("apiSchemas")
    if listed is None:
        return []
    applied = set(prim.GetAppliedSchemas())
    unknown = []
    for name in dict.fromkeys(listed.GetAddedOrExplicitItems()):
        api = name.split(":")[0]  # a multiple-apply schema's instance name follows its colon
        if name in applied or not (api.startswith("Physics") or api.lower() in physics):
            continue
        close = physics.get(api.lower()) or next(iter(difflib.get_close_matches(api, list(physics.values()), n=1)), None)
        # A multiple-apply schema listed without its instance name is not applied either.
        unknown.append((name, f"{close}:<instance>" if close == name else close))
    return unknown


def _usd_physics_api_schemas(Usd, UsdPhysics) -> dict[str, str]:
    """The names of UsdPhysics' API schemas (the pxr installed), by their lower-case names."""
    from pxr import Tf

    names = sorted(Usd.SchemaRegistry.GetAPISchemaTypeName(Tf.Type.Find(schema)) for schema in vars(UsdPhysics).values() if isinstance(schema, type) and issubclass(schema, Usd.APISchemaBase))
    return {name.lower(): name for name in names}


def _read_settings(prim, settings: SimulationSettings, task: TaskSpec, source: str):
    _read_casts(prim, settings, _SETTING_ATTRIBUTES, source)
    _check_settings(settings, f"{source}: prim {prim.GetPath()}")
    _read_casts(prim, task, TASK_ATTRIBUTES, source)
    for attr_name, field_name in (("task:sampleLow", "sample_low"), ("task:sampleHigh", "sample_high")):
        value = _cast_attr(prim, attr_name, _numbers, source)
        if value is not None:
            setattr(task, field_name, tuple(float(v) for v in value))


def _check_settings(settings: SimulationSettings, where: str):
    """ValueError naming the warpcontact: attribute of the first setting a scene file may not
    hold: the one rule for loading and for saving (``save_scene`` wrote files that
    ``load_scene`` then refused)."""
    problem = time_step_problem(settings.time_step)
    if problem is not None:
        raise ValueError(f"{where}: warpcontact:timeStep {problem}, got {settings.time_step}")
    for attr_name in ("contactStiffness", "eps", "friction", "frictionSmoothing"):
        field_name = _SETTING_ATTRIBUTES[attr_name][0]
        value = getattr(settings, field_name)
        problem = contact_setting_problem(field_name, value)
        if problem:
            raise ValueError(f"{where}: warpcontact:{attr_name} {problem}, got {shown(value)}")
    if not 1 <= settings.frames <= MAX_FRAMES:  # simulate held every frame: 1e11 grew until killed
        raise ValueError(f"{where}: warpcontact:frames must be a whole number from 1 to {MAX_FRAMES:,}, got {settings.frames}")
    if settings.contact_mode not in MODEL_CONTACT_MODES:
        raise ValueError(f"{where}: warpcontact:contactMode must be one of {MODEL_CONTACT_MODES}, got {settings.contact_mode!r}")
    if settings.centred_weight not in CENTRED_WEIGHTS:
        raise ValueError(f"{where}: warpcontact:centredWeight must be one of {CENTRED_WEIGHTS}, got {settings.centred_weight!r}")
    if settings.leaf_precision not in LEAF_PRECISIONS:
        raise ValueError(f"{where}: warpcontact:leafPrecision must be one of {LEAF_PRECISIONS}, got {settings.leaf_precision!r}")


# --- export ---------------------------------------------------------------------------------


def _new_stage(Usd, UsdGeom, path: Path, up_axis: str):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    return stage


def _author_mesh(stage, UsdGeom, Vt, path: str, vertices, faces):
    mesh = UsdGeom.Mesh.Define(stage, path)
    # Whole arrays at once (a Gf.Vec3f per vertex took 0.54 s at 229k triangles); float32
    # rounds to nearest either way, so the file is the same.
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vertices, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(np.asarray(faces).reshape(-1), dtype=np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return mesh


def _pose_ops(xformable, UsdGeom) -> tuple:
    """The prim's translate and orient ops, added (double precision) where it has none."""
    ops = xformable.GetOrderedXformOps()
    if not ops:
        precision = UsdGeom.XformOp.PrecisionDouble
        ops = [xformable.AddTranslateOp(precision=precision), xformable.AddOrientOp(precision=precision)]
    return ops[0], ops[1]


def _set_pose_ops(xformable, Gf, UsdGeom, pose, time=None, *, ops=None):
    """Sets a pose (px, py, pz, qx, qy, qz, qw) on the prim's ops (``_pose_ops``; pass them
    as ``ops`` when setting many frames, which then skip the lookup)."""
    translate, orient = ops or _pose_ops(xformable, UsdGeom)
    t = Gf.Vec3d(*map(float, pose[:3]))
    q = Gf.Quatd(float(pose[6]), Gf.Vec3d(*map(float, pose[3:6])))
    if time is None:
        translate.Set(t)
        orient.Set(q)
    else:
        translate.Set(t, time)
        orient.Set(q, time)


# The file names Usd.Stage reads and writes (text, either, binary), and the packages it
# also reads (a .usdz loaded, but the CLI refused its name).
USD_SUFFIXES = (".usda", ".usd", ".usdc")
USD_READ_SUFFIXES = (*USD_SUFFIXES, ".usdz")


def _atomic_save(stage_writer, path, overwrite: bool):
    """Write via a temporary file in the same folder, then rename: no partial files, no lost data."""
    path = Path(path)
    if path.suffix not in USD_SUFFIXES:
        raise ValueError(f"{path}: a USD file name must end in {', '.join(USD_SUFFIXES)}")
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, not a file name")
    if path.exists() and not checked_flag(overwrite, "overwrite"):
        raise FileExistsError(f"{path}: exists; pass overwrite=True to replace it")
    if not path.parent.is_dir():
        raise ValueError(f"{path.parent}: output folder does not exist")
    if not os.access(path.parent, os.W_OK):
        raise ValueError(f"{path.parent}: output folder is not writable")

    def write(temporary: Path):
        try:
            stage_writer(temporary)
        except RuntimeError as exc:  # pxr's Tf.ErrorException
            # A full disk or a file size limit was a traceback of an empty pxr error, and the
            # CLI's handlers for a failed write (a run's --resume hint) never saw it.
            reason = _usd_error_text(exc) or "no reason given"
            raise OSError(f"{path}: USD could not write the file ({reason}; {shutil.disk_usage(path.parent).free:,} bytes free on its disk)") from None

    replace_file(path, write)


def _usd_scalar(value, kind, Sdf, name: str):
    """``value`` as the Python type USD's ``kind`` takes: numpy scalars (np.float32 time steps,
    np.int64 horizons) raised a raw pxr type-mismatch error. A bool is refused where a
    number belongs (True was written as 1, a horizon load_scene then accepted)."""
    if isinstance(value, (bool, np.bool_)) and kind != Sdf.ValueTypeNames.Bool:
        raise ValueError(f"warpcontact:{name}: expected a number, got {value!r}")
    if kind == Sdf.ValueTypeNames.Double:
        return float(value)
    if kind == Sdf.ValueTypeNames.Int:
        if not float(value).is_integer():  # int() truncated 2.5 frames to 2
            raise ValueError(f"warpcontact:{name}: expected a whole number, got {value!r}")
        if not -(2**31) <= int(value) < 2**31:  # a raw pxr type-mismatch error ('long')
            raise ValueError(f"warpcontact:{name}: expected a whole number a 32-bit int holds, got {value!r}")
        return int(value)
    return str(value)


def save_scene(scene: Scene, path, *, overwrite: bool = False):
    """Write a scene as a .usda with UsdPhysics schemas and warpcontact attributes (round-trippable).

    Poses and ``warpcontact:`` attributes are doubles; what the schemas type as float (mesh
    points, mass properties, velocities) is rounded to float32 (docs/architecture.md, "USD")."""
    path = _checked_path(path)
    _checked_scene(scene, path)
    Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt = _pxr()
    _check_prim_names(scene.bodies, "body", reserved=("physicsScene", "joints"), Sdf=Sdf)
    _check_prim_names(scene.joints, "joint", reserved=(), Sdf=Sdf)
    # What load_scene would refuse, or what the file cannot hold, is refused here, before a
    # file is written (such scenes were written, and failed at load or lost data silently).
    _check_settings(scene.settings, f"{path}: scene settings")
    for body in scene.bodies:
        # "no" read as true, and the body was refused as a static one with a target (a probe, stop 64).
        checked_flag(body.static, f"{path}: body {body.name!r}: static")
    if not any(not body.static for body in scene.bodies):
        raise ValueError(f"{path}: the scene has no dynamic bodies, which load_scene requires")
    for body in scene.bodies:
        for label, values in (("mesh vertices", body.vertices), ("pose", body.pose)):
            if not np.all(np.isfinite(np.asarray(values, dtype=np.float64))):
                raise ValueError(f"{path}: body {body.name!r}: its {label} are not all finite")
        norm = float(np.linalg.norm(np.asarray(body.pose, dtype=np.float64)[3:]))
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            # USD's orient op does not normalise: (0, 0, 1, 1), 90 degrees about z that the
            # builder refuses, was written and loaded as the identity, silently.
            raise ValueError(f"{path}: body {body.name!r}: its pose quaternion has norm {norm:.9g}, expected 1 (the builder's rule; a file's orient is read as given)")
        dynamic_only = _dynamic_only(body)
        if dynamic_only:
            raise ValueError(f"{path}: static body {body.name!r} has {dynamic_only}, which only a dynamic body takes (a static collider's file holds none of them)")
        if not body.static:  # a static body's file holds no mass properties
            _check_float32_mass_properties(body, path)

    def write(tmp: Path):
        stage = _new_stage(Usd, UsdGeom, tmp, scene.up_axis)
        physics = UsdPhysics.Scene.Define(stage, "/World/physicsScene")
        g = np.asarray(scene.gravity, dtype=np.float64)
        magnitude = float(np.linalg.norm(g))
        physics.CreateGravityDirectionAttr(Gf.Vec3f(*map(float, g / magnitude)) if magnitude > 0 else Gf.Vec3f(0, 0, -1))
        physics.CreateGravityMagnitudeAttr(magnitude)
        prim = physics.GetPrim()
        s, t = scene.settings, scene.task
        for name, value, kind in (
            ("timeStep", s.time_step, Sdf.ValueTypeNames.Double),
            ("frames", s.frames, Sdf.ValueTypeNames.Int),
            ("contactStiffness", s.contact_stiffness, Sdf.ValueTypeNames.Double),
            ("eps", s.eps, Sdf.ValueTypeNames.Double),
            ("centredWeight", s.centred_weight, Sdf.ValueTypeNames.Token),
            ("leafPrecision", s.leaf_precision, Sdf.ValueTypeNames.Token),
            ("friction", s.friction, Sdf.ValueTypeNames.Double),
            ("frictionSmoothing", s.friction_smoothing, Sdf.ValueTypeNames.Double),
            ("contactMode", s.contact_mode, Sdf.ValueTypeNames.Token),
        ):
            prim.CreateAttribute(_NS + name, kind).Set(_usd_scalar(value, kind, Sdf, name))
        if t != TaskSpec():  # partial metadata too: what was authored is saved
            for name, value, kind in (
                ("task:name", t.name, Sdf.ValueTypeNames.String),
                ("task:control", t.control, Sdf.ValueTypeNames.Token),
                ("task:horizon", t.horizon, Sdf.ValueTypeNames.Int),
                ("task:recedingHorizon", t.receding_horizon, Sdf.ValueTypeNames.Int),
                ("task:learningRate", t.learning_rate, Sdf.ValueTypeNames.Double),
                ("task:iterations", t.iterations, Sdf.ValueTypeNames.Int),
                ("task:recedingStride", t.receding_stride, Sdf.ValueTypeNames.Int),
                ("task:quick:horizon", t.quick_horizon, Sdf.ValueTypeNames.Int),
                ("task:quick:recedingHorizon", t.quick_receding_horizon, Sdf.ValueTypeNames.Int),
                ("task:quick:learningRate", t.quick_learning_rate, Sdf.ValueTypeNames.Double),
                ("task:quick:iterations", t.quick_iterations, Sdf.ValueTypeNames.Int),
                ("task:quick:recedingStride", t.quick_receding_stride, Sdf.ValueTypeNames.Int),
            ):
                prim.CreateAttribute(_NS + name, kind).Set(_usd_scalar(value, kind, Sdf, name))
            for name, bounds in (("task:sampleLow", t.sample_low), ("task:sampleHigh", t.sample_high)):
                if bounds:
                    prim.CreateAttribute(_NS + name, Sdf.ValueTypeNames.DoubleArray).Set(Vt.DoubleArray([float(v) for v in bounds]))
        for b in scene.bodies:
            path_ = f"/World/{b.name}"
            if b.static and b.group < 0:
                # A static collider is one Mesh prim: the name and pose load back unchanged.
                mesh = _author_mesh(stage, UsdGeom, Vt, path_, b.vertices, b.faces)
                _set_pose_ops(mesh, Gf, UsdGeom, b.pose)
                UsdPhysics.CollisionAPI.Apply(mesh.GetPrim())
                continue
            xform = UsdGeom.Xform.Define(stage, path_)
            _set_pose_ops(xform, Gf, UsdGeom, b.pose)
            mesh = _author_mesh(stage, UsdGeom, Vt, path_ + "/collider", b.vertices, b.faces)
            UsdPhysics.CollisionAPI.Apply(mesh.GetPrim())
            body_prim = xform.GetPrim()
            rb = UsdPhysics.RigidBodyAPI.Apply(body_prim)
            if b.static:
                # A static body in a contact group is a kinematic body, which carries its
                # warpcontact: attributes (a bare collider dropped its group).
                rb.CreateKinematicEnabledAttr(True)
                _write_warpcontact_body(body_prim, b, Sdf, Vt)
                continue
            rb.CreateVelocityAttr(Gf.Vec3f(*map(float, b.linear_velocity)))
            rb.CreateAngularVelocityAttr(Gf.Vec3f(*map(float, np.degrees(b.angular_velocity))))
            mass = UsdPhysics.MassAPI.Apply(body_prim)
            if b.mass is not None:
                mass.CreateMassAttr(float(b.mass))
            if b.density is not None:
                mass.CreateDensityAttr(float(b.density))
            if b.center_of_mass is not None:
                mass.CreateCenterOfMassAttr(Gf.Vec3f(*map(float, b.center_of_mass)))
            if b.inertia is not None:
                values, vectors = np.linalg.eigh(b.inertia)
                if np.linalg.det(vectors) < 0:
                    vectors[:, 0] = -vectors[:, 0]
                q = trimesh.transformations.quaternion_from_matrix(np.block([[vectors, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
                mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*map(float, values)))
                mass.CreatePrincipalAxesAttr(Gf.Quatf(float(q[0]), Gf.Vec3f(*map(float, q[1:]))))
            _write_warpcontact_body(body_prim, b, Sdf, Vt)
        for j in scene.joints:
            _author_joint(stage, j, Gf, UsdPhysics)
        stage.GetRootLayer().Save()
        # The file is held to the loader's rules themselves before it replaces anything: a
        # mass of 1e40 (inf once a float32), a negative target tolerance or a NaN inertia was
        # written, over a good file with overwrite, and refused at load.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                load_scene(tmp)
            except ValueError as exc:
                reason = str(exc).replace(f"{tmp}: ", "", 1).replace(str(tmp), str(path))
                raise ValueError(f"{path}: not written, as load_scene would refuse it (values the schemas type as float are written as float32): {reason}") from None

    _atomic_save(write, path, overwrite)


# The range of normal float32 numbers, in which MassAPI's float attributes hold a value.
_FLOAT32_NORMAL = (float(np.finfo(np.float32).tiny), float(np.finfo(np.float32).max))


def _check_float32_mass_properties(body: BodySpec, path) -> None:
    """ValueError naming the body and attribute when a mass, density or principal moment of
    inertia lies outside the normal float32 range the UsdPhysics schema stores it in: a mass
    of 1e-46 was written as 0, which UsdPhysics reads as "not given", and came back as the
    default density's 64 kg (a probe, stop 65); above the range it became inf."""
    low, high = _FLOAT32_NORMAL
    moments = () if body.inertia is None else np.linalg.eigvalsh(np.asarray(body.inertia, dtype=np.float64))
    for label, values in (("physics:mass", () if body.mass is None else (body.mass,)), ("physics:density", () if body.density is None else (body.density,)), ("physics:diagonalInertia", moments)):
        for value in values:
            if not low <= abs(float(value)) <= high:
                with np.errstate(over="ignore"):
                    stored = float(np.float32(value))
                raise ValueError(
                    f"{path}: body {body.name!r}: {label} {float(value):g} is outside the float32 range [{low:.6g}, {high:.6g}] "
                    f"in which UsdPhysics stores it (written, it would read back as {stored:g}); this scene's mass units cannot be saved"
                )


def _check_prim_names(specs: list, kind: str, *, reserved: tuple, Sdf) -> None:
    """ValueError naming the first body or joint whose name cannot be its prim's name in a
    written stage: not a USD identifier (a raw pxr error before), repeated (a prim written
    twice: a joint was dropped), or one of the writer's own prims (a body named physicsScene
    overwrote the scene's settings)."""
    seen = set()
    for spec in specs:
        if not isinstance(spec.name, str) or not Sdf.Path.IsValidIdentifier(spec.name):
            raise ValueError(f"{kind} {spec.name!r}: not a valid USD prim name (letters, digits and _, not starting with a digit)")
        if spec.name in reserved:
            raise ValueError(f"{kind} {spec.name!r}: the name of a prim the writer uses itself ({', '.join(reserved)}); rename the {kind}")
        if spec.name in seen:
            raise ValueError(f"{kind} {spec.name!r}: more than one {kind} has this name")
        seen.add(spec.name)


def _frames_along_x(j: JointSpec):
    """Joint frames rotated so that the first axis is the frame's X (and the second its Y),
    as UsdPhysics joints name their axes by token."""
    axes = np.asarray(j.axes, dtype=np.float64).reshape(-1, 3)
    if len(axes) == 0:
        return j.parent_frame, j.child_frame
    # Unit axes, as the model reads them: a universal joint's (0, 0, 2), (0, 3, 0) was saved
    # turned 37 degrees.
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    first = axes[0]
    if len(axes) > 1:
        second = axes[1] - (axes[1] @ first) * first
        second /= np.linalg.norm(second)
        align = quat_from_matrix(np.column_stack([first, second, np.cross(first, second)]))
    else:
        # The smallest turn taking X to the axis: none for an axis along X. Any other turn
        # changed the frames at every save (an axis along X turned -90 degrees about X), and
        # with them what a ball joint's target rotations mean.
        turn = np.cross([1.0, 0.0, 0.0], first)
        sine, cosine = np.linalg.norm(turn), first[0]
        if sine < 1e-12:
            align = np.array([0.0, 0.0, 0.0, 1.0]) if cosine > 0 else np.array([0.0, 0.0, 1.0, 0.0])
        else:
            half = 0.5 * np.arctan2(sine, cosine)
            align = np.array([*(np.sin(half) * turn / sine), np.cos(half)])
    turn = np.array([0.0, 0.0, 0.0, *align])
    return pose_mul(j.parent_frame, turn), pose_mul(j.child_frame, turn)


def _author_joint(stage, j: JointSpec, Gf, UsdPhysics):
    path = f"/World/joints/{j.name}"
    if j.kind == "revolute":
        joint = UsdPhysics.RevoluteJoint.Define(stage, path)
        joint.CreateAxisAttr("X")
    elif j.kind == "prismatic":
        joint = UsdPhysics.PrismaticJoint.Define(stage, path)
        joint.CreateAxisAttr("X")
    elif j.kind == "ball":
        joint = UsdPhysics.SphericalJoint.Define(stage, path)
        joint.CreateAxisAttr("X")
        if j.cone_limit is not None:
            joint.CreateConeAngle0LimitAttr(float(j.cone_limit / _DEGREE))
            joint.CreateConeAngle1LimitAttr(float(j.cone_limit / _DEGREE))
    else:  # universal and base: a D6 joint with locked axes
        joint = UsdPhysics.Joint.Define(stage, path)
    prim = joint.GetPrim()
    if j.parent is not None:
        joint.CreateBody0Rel().SetTargets([f"/World/{j.parent}"])
    joint.CreateBody1Rel().SetTargets([f"/World/{j.child}"])
    parent_frame, child_frame = _frames_along_x(j) if j.kind != "base" else (j.parent_frame, j.child_frame)
    for frame, pos_attr, rot_attr in ((parent_frame, joint.CreateLocalPos0Attr, joint.CreateLocalRot0Attr), (child_frame, joint.CreateLocalPos1Attr, joint.CreateLocalRot1Attr)):
        pos_attr(Gf.Vec3f(*map(float, frame[:3])))
        rot_attr(Gf.Quatf(float(frame[6]), Gf.Vec3f(*map(float, frame[3:6]))))
    if j.kind in ("revolute", "prismatic"):
        j = _broadcast_to_coordinates(j, 1)  # a flat limit pair, as the builder takes it
        scale = _DEGREE if j.kind == "revolute" else 1.0
        if j.limits is not None and np.isfinite(j.limits[0]).any():
            joint.CreateLowerLimitAttr(float(j.limits[0][0] / scale))
            joint.CreateUpperLimitAttr(float(j.limits[0][1] / scale))
        if len(j.kp) and (j.kp[0] or j.kd[0]):
            _author_drive(prim, "angular" if j.kind == "revolute" else "linear", j.kp[0] * scale, j.kd[0] * scale, UsdPhysics, _target(j, 0, scale))
        return
    if j.kind == "ball":
        if len(j.kp) and (j.kp[0] or j.kd[0]):
            for axis in _BALL_DRIVE_AXES:
                _author_drive(prim, _api_token(axis), j.kp[0] * _DEGREE, j.kd[0] * _DEGREE, UsdPhysics)
        return
    if j.kind == "universal":
        free = ["RotX", "RotY"]
    else:
        axis_of = {dof: axis for axis, dof in _D6_AXIS_DOF.items()}
        free = [axis_of[d] for d in j.dofs]
    coordinates = _coordinate_axes(free)
    # One value for every coordinate, as the builder broadcasts it (an IndexError here).
    j = _broadcast_to_coordinates(j, len(coordinates))
    for axis in _D6_AXIS_DOF:
        token = _api_token(axis)
        if axis not in free:
            limit = UsdPhysics.LimitAPI.Apply(prim, token)
            limit.CreateLowAttr(1.0)
            limit.CreateHighAttr(-1.0)
            continue
        if axis not in coordinates:
            continue
        c = coordinates.index(axis)
        scale = _DEGREE if axis.startswith("Rot") else 1.0
        if j.limits is not None and np.isfinite(j.limits[c]).any():
            limit = UsdPhysics.LimitAPI.Apply(prim, token)
            limit.CreateLowAttr(float(j.limits[c][0] / scale))
            limit.CreateHighAttr(float(j.limits[c][1] / scale))
        if len(j.kp) and (j.kp[c] or j.kd[c]):
            _author_drive(prim, token, j.kp[c] * scale, j.kd[c] * scale, UsdPhysics, _target(j, c, scale))


def _broadcast_to_coordinates(j: JointSpec, count: int) -> JointSpec:
    """``j`` with its limits, gains and targets one per coordinate, by the builder's own rules
    (``coordinate_limits``, ``_per_coordinate``): a single pair or value serves every
    coordinate, and a flat pair is a pair."""
    where = f"joint {j.name!r}"
    limits = None if j.limits is None else np.column_stack(coordinate_limits(j.limits, count, where))
    targets = None if j.targets is None else _per_coordinate(j.targets, count, "targets", where)
    # No gains given (empty) are zero gains, as the builder's default.
    kp, kd = (_per_coordinate(gain if np.size(gain) else 0.0, count, label, where) for gain, label in ((j.kp, "kp"), (j.kd, "kd")))
    return replace(j, limits=limits, kp=kp, kd=kd, targets=targets)


def _target(j: JointSpec, coordinate: int, scale: float) -> float | None:
    """A joint coordinate's drive target in UsdPhysics units (degrees or stage units), or None."""
    if j.targets is None or np.isnan(j.targets[coordinate]):
        return None
    return float(j.targets[coordinate] / scale)


def _author_drive(prim, token: str, stiffness: float, damping: float, UsdPhysics, target: float | None = None):
    """A DriveAPI instance with gains (and a target position) already in UsdPhysics units
    (per degree and degrees for rotations)."""
    drive = UsdPhysics.DriveAPI.Apply(prim, token)
    drive.CreateStiffnessAttr(float(stiffness))
    drive.CreateDampingAttr(float(damping))
    if target is not None:
        drive.CreateTargetPositionAttr(target)


def _write_warpcontact_body(prim, b: BodySpec, Sdf, Vt):
    if b.target_position is not None:
        prim.CreateAttribute(_NS + "target:position", Sdf.ValueTypeNames.Double3).Set(tuple(map(float, b.target_position)))
        prim.CreateAttribute(_NS + "target:tolerance", Sdf.ValueTypeNames.Double).Set(float(b.target_tolerance))
    if np.any(b.kp_linear) or np.any(b.kd_linear) or b.kp_angular or b.kd_angular:
        # A scalar gain serves all three axes, as add_body reads it (it raised TypeError here).
        for name, gain, label in (("pd:kpLinear", b.kp_linear, "kp_linear"), ("pd:kdLinear", b.kd_linear, "kd_linear")):
            prim.CreateAttribute(_NS + name, Sdf.ValueTypeNames.Double3).Set(tuple(map(float, _per_coordinate(gain, 3, label, f"body {b.name!r}"))))
        prim.CreateAttribute(_NS + "pd:kpAngular", Sdf.ValueTypeNames.Double).Set(float(b.kp_angular))
        prim.CreateAttribute(_NS + "pd:kdAngular", Sdf.ValueTypeNames.Double).Set(float(b.kd_angular))
    if b.control_dofs:
        prim.CreateAttribute(_NS + "control:dofs", Sdf.ValueTypeNames.StringArray).Set(Vt.StringArray(list(b.control_dofs)))
    if b.group >= 0:
        prim.CreateAttribute(_NS + "group", Sdf.ValueTypeNames.Int).Set(int(b.group))


# customLayerData key of a trajectory export; its value is the simulated scene's file ("" if none).
_TRAJECTORY_MARK = "warpcontact:trajectoryOf"


def export_trajectory(scene: Scene, poses, path, *, fps: float | None = None, overwrite: bool = False):
    """Write a simulated trajectory as a .usda for usdview.

    Args:
        scene: the scene that was simulated (meshes, names, targets).
        poses: (frames, nbodies, 7) prim-frame poses per frame (``model_to_scene_poses``).
        path: the .usda (or .usd, .usdc) file to write.
        fps: frames per second; default 1 / time step.
        overwrite: replace an existing file.

    Meshes are authored once per body; each body has one time-sampled translate and orient
    per frame (a static body is time-sampled only if its poses differ between frames); timeCodesPerSecond and framesPerSecond are both set; target positions are drawn
    as small green spheres under /World/targets (targets_1, ... where a body has that name).
    The layer's customLayerData names the scene's file (``warpcontact:trajectoryOf``), and
    ``load_scene`` refuses the export pointing to it.
    """
    path = _checked_path(path)
    _checked_scene(scene, path)
    Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt = _pxr()
    _check_prim_names(scene.bodies, "body", reserved=(), Sdf=Sdf)
    # The target markers' group takes a name no body has: reserving "targets" refused a body
    # so named only once a whole task run had finished (its resume failed the same way).
    names, markers, suffix = {b.name for b in scene.bodies}, "targets", 0
    while markers in names:
        suffix += 1
        markers = f"targets_{suffix}"
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (len(scene.bodies), 7) or len(poses) == 0 or not np.isfinite(poses).all():
        raise ValueError(f"poses: expected finite (frames, {len(scene.bodies)}, 7) with at least one frame, got {poses.shape}")
    norms = np.linalg.norm(poses[..., 3:], axis=-1)
    unrotated = np.argwhere(norms == 0.0)
    if unrotated.size:
        frame, body = unrotated[0]
        raise ValueError(f"poses: body {scene.bodies[body].name!r} has a zero rotation quaternion at frame {frame}")
    # Normalised as the step reads them (a static body's pose may be written at any norm):
    # USD's orient op draws a quaternion as given, and one of norm 1.4 turned 90 degrees drew
    # as another. Those within QUATERNION_TOLERANCE are written as they are.
    far = np.abs(norms - 1.0) > QUATERNION_TOLERANCE
    if far.any():
        poses = poses.copy()
        poses[..., 3:][far] /= norms[far][:, None]
    if fps is None:
        fps = 1.0 / scene.settings.time_step
    if not is_positive_finite(fps):
        raise ValueError(f"fps: must be a positive finite number of frames per second, got {fps!r}")
    fps = float(fps)

    def write(tmp: Path):
        stage = _new_stage(Usd, UsdGeom, tmp, scene.up_axis)
        # Absolute: a path as given is relative to the folder the scene was loaded from.
        stage.GetRootLayer().customLayerData = {_TRAJECTORY_MARK: str(Path(scene.source).resolve()) if scene.source else ""}
        stage.SetTimeCodesPerSecond(fps)
        stage.SetFramesPerSecond(fps)
        stage.SetStartTimeCode(0)
        stage.SetEndTimeCode(len(poses) - 1)
        for i, b in enumerate(scene.bodies):
            xform = UsdGeom.Xform.Define(stage, f"/World/{b.name}")
            _author_mesh(stage, UsdGeom, Vt, f"/World/{b.name}/mesh", b.vertices, b.faces)
            # The first frame is also the default, which readers without a time take.
            ops = _pose_ops(xform, UsdGeom)
            _set_pose_ops(xform, Gf, UsdGeom, poses[0, i], ops=ops)
            # A static body moved by the caller between steps moves here too (its motion was
            # dropped: a paddle drawn still beside the box it pushed).
            if not b.static or (poses[:, i] != poses[0, i]).any():
                for frame in range(len(poses)):
                    _set_pose_ops(xform, Gf, UsdGeom, poses[frame, i], time=frame, ops=ops)
            if b.target_position is not None:
                marker = UsdGeom.Sphere.Define(stage, f"/World/{markers}/{b.name}")
                marker.CreateRadiusAttr(max(float(b.target_tolerance), 0.05))
                marker.CreateDisplayColorAttr([Gf.Vec3f(0.1, 0.8, 0.2)])
                marker.CreateDisplayOpacityAttr([0.4])
                UsdGeom.Xformable(marker).AddTranslateOp().Set(Gf.Vec3d(*map(float, b.target_position)))
        stage.GetRootLayer().Save()

    _atomic_save(write, path, overwrite)


def model_to_scene_poses(scene: Scene, model, body_q) -> np.ndarray:
    """Convert centre-of-mass poses of a ``Model`` built from ``scene`` back to the scene's
    prim-frame poses: the prim frame sits at -R c from the body frame (c: the model's
    ``body_center_of_mass``, in the prim frame)."""
    body_q = np.asarray(body_q, dtype=np.float64)
    if body_q.ndim < 2 or body_q.shape[-2:] != (len(scene.bodies), 7) or model.num_bodies != len(scene.bodies):
        raise ValueError(f"body_q: expected (..., {len(scene.bodies)}, 7) poses of a model of the scene's {len(scene.bodies)} bodies, got shape {body_q.shape} for a model of {model.num_bodies}")
    out = body_q.copy()
    # The step keeps a static body's quaternion at the norm it was given: rotating by it
    # unnormalised put a plate 2 m off its frame at 4 m.
    with np.errstate(invalid="ignore", divide="ignore"):
        rotations = normalized_poses(body_q)[..., 3:]
    if not np.isfinite(rotations).all():
        raise ValueError("body_q: every quaternion must be finite and non-zero (the rotation of a pose)")
    for i in range(len(scene.bodies)):
        out[..., i, :3] = body_q[..., i, :3] - quat_rotate(rotations[..., i, :], model.body_center_of_mass[i])
    return out
