"""ModelBuilder: bodies from trimesh meshes and primitives into a ``Model``."""

import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
import warp as wp

from ._runtime import resolve_device
from ._validate import QUATERNION_TOLERANCE, SCALE_RANGE, blend_eps_problem, check_barrier_support, check_coordinates, checked_flag, is_gain, is_positive_finite, is_real, is_whole, real_array, scale_problem, shown, unit_inertia_problem
from .articulation import BASE_DOFS, JOINT_AXES, JOINT_KINDS, ArticulationModel, Joint, connected_labels, default_limit_margins, effective_limit_margins, frame_in_body, limit_margin_problem
from .contact import CENTRED_WEIGHTS, CONTACT_MODES, PRESSED_GAP, ContactModel
from .leaf import float32_search
from .rotation import pose_mul, quat_rotate
from .sphere_tree import validated_mesh
from .types import Model

__all__ = ["MODEL_CONTACT_MODES", "ModelBuilder"]


@dataclass
class _Body:
    name: str
    vertices: np.ndarray  # body frame, origin at the centre of mass
    faces: np.ndarray
    mass: float
    second_moment: np.ndarray
    pose: np.ndarray  # (7,) of the centre-of-mass frame
    static: bool
    kp_linear: np.ndarray
    kd_linear: np.ndarray
    kp_angular: float
    kd_angular: float
    center_of_mass: np.ndarray  # in the mesh frame


def _second_moment_from_inertia(inertia: np.ndarray) -> np.ndarray:
    """S = sum m X X^T from the inertia tensor J = tr(S) I - S."""
    return 0.5 * np.trace(inertia) * np.eye(3) - inertia


_ARTICULATION_CONTACT = ("nonadjacent", "all", "none")
# Below this blend margin the blend is steep enough to slow Newton several times (measured,
# docs/architecture.md, "Small eps"); the builder warns, and step failures say so.
STEEP_BLEND_EPS = 1e-2


# Below this eps the "pairs" centred weights can pull separated bodies together (the
# paper's proof that blends push needs S >= P_c, which weighted centred terms need not meet).
PAIRS_PUSH_EPS = 0.1


def steep_blend(eps: float, contact_mode: str) -> bool:
    """Whether ``eps`` makes the blend of contact mode ``contact_mode`` steep (brute force's
    friction weight blends over the same margin; sdrs and ipc have no blend)."""
    return eps < STEEP_BLEND_EPS and contact_mode in ("bsh", "brute")


# The contact models a ModelBuilder makes: ContactModel's modes and the IPC baseline.
MODEL_CONTACT_MODES = (*CONTACT_MODES, "ipc")


_SETTING_UNITS = {"contact_stiffness": "", "friction_smoothing": "m/s", "eps": ""}


def contact_setting_problem(name: str, value: float) -> str | None:
    """Why ``value`` is not admissible for the ModelBuilder contact setting ``name``
    (contact_stiffness, friction, friction_smoothing or eps), or None. One rule for the
    builder and for ``io.load_scene``, which names the USD attribute."""
    if not is_real(value):
        return f"must be a number, not {type(value).__name__}"
    if name == "friction":
        if not (np.isfinite(value) and value >= 0):
            return "must be >= 0 and finite"
        return None if value == 0 else scale_problem(value, "")
    if not is_positive_finite(value):
        return "must be positive and finite"
    problem = scale_problem(value, _SETTING_UNITS[name])
    return blend_eps_problem(value) if problem is None and name == "eps" else problem


def check_contact_setting(name: str, value, label: str | None = None) -> None:
    """ValueError ``label: <problem>, got <value>`` (label defaults to ``name``) unless
    ``value`` is admissible for the contact setting ``name`` (``contact_setting_problem``)."""
    problem = contact_setting_problem(name, value)
    if problem is not None:
        raise ValueError(f"{label or name}: {problem}, got {value!r}")


def gravity_problem(value) -> str | None:
    """Why ``value`` is not a gravitational acceleration (m/s^2), or None: 3 finite numbers,
    none beyond SCALE_RANGE's bound (1e300 made the step's free fall overflow)."""
    gravity = finite_vector(value, 3)
    if gravity is None:
        return "expected 3 finite numbers (m/s^2)"
    if np.abs(gravity).max() > SCALE_RANGE[1]:
        return f"must be at most {SCALE_RANGE[1]:g} m/s^2 in magnitude on each axis"
    return None


_IDENTITY_POSE = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])


def _per_coordinate(value, count: int, label: str, where: str) -> np.ndarray:
    raw = np.asarray(value)
    if raw.dtype.kind not in "iuf":  # a text "10" converted silently
        raise ValueError(f"{where}: {label} must be numbers, got {value!r}")
    arr = raw.astype(np.float64)
    try:
        arr = np.broadcast_to(arr, (count,)).copy()
    except ValueError:
        wanted = "1 value" if count == 1 else f"1 or {count} values"
        raise ValueError(f"{where}: {label} needs {wanted}, got shape {arr.shape}") from None
    return arr


def coordinate_limits(limits, count: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of ``count`` joint coordinates from ``add_joint``'s ``limits``: None (no
    limits), one (lower, upper) pair for every coordinate, or one pair per coordinate (flat
    or nested). ValueError naming ``where`` otherwise."""
    if limits is None:
        return np.full(count, -np.inf), np.full(count, np.inf)
    pairs = real_array(limits)
    if pairs is None or pairs.size % 2:
        raise ValueError(f"{where}: limits must be {count} (lower, upper) pairs with lower < upper, got {limits!r}")
    pairs = pairs.reshape(-1, 2)
    if pairs.shape[0] == 1 and count > 1:
        pairs = np.repeat(pairs, count, axis=0)
    if pairs.shape[0] != count or np.isnan(pairs).any() or (pairs[:, 0] >= pairs[:, 1]).any():
        raise ValueError(f"{where}: limits must be {count} (lower, upper) pairs with lower < upper, got {limits!r}")
    return pairs[:, 0].copy(), pairs[:, 1].copy()


def _unit_axes(axis, count: int, where: str) -> np.ndarray:
    axes = real_array(axis) if axis is not None else np.zeros((0, 3))
    if axes is None or axes.size % 3:
        raise ValueError(f"{where}: expected {count} axis vector(s) of 3 values, got {axis!r}")
    axes = axes.reshape(-1, 3)
    if axes.shape[0] != count or not np.isfinite(axes).all():
        raise ValueError(f"{where}: expected {count} finite axis vector(s) of 3 values, got {axis!r}")
    with np.errstate(over="ignore"):
        norms = np.linalg.norm(axes, axis=1)
    huge = ~np.isfinite(norms)
    if huge.any():
        # The norm of an axis given as (1e300, 1e300, 0) overflowed, and the axis was
        # normalised to zero (a hinge that never turned), silently.
        axes[huge] /= np.abs(axes[huge]).max(axis=1, keepdims=True)
        norms[huge] = np.linalg.norm(axes[huge], axis=1)
    if (norms < 1e-12).any():
        raise ValueError(f"{where}: joint axis has zero length")
    axes = axes / norms[:, None]
    if count == 2 and abs(axes[0] @ axes[1]) > 1e-9:
        raise ValueError(f"{where}: the two universal-joint axes must be orthogonal (cosine {axes[0] @ axes[1]:.3g})")
    return axes


def _volume_pieces(mesh: trimesh.Trimesh) -> tuple | None:
    """The mesh's closed pieces (``_pieces``) when it is closed and consistently
    outward-oriented around a positive volume, else None. A closed mesh with some faces wound
    inward still has a positive signed volume, but the wrong one (one flipped face of a unit
    cube gave 500 kg at 1,000 kg/m^3 and its centre of mass 0.25 m off); a flat closed mesh
    has none (trimesh divides by it). The pieces are returned for the overlap check, which
    labelled them again (~85 ms at 81,920 faces)."""
    if not _closed_outward(mesh):
        return None
    pieces = _pieces(mesh)
    return None if _inside_out_piece(mesh, pieces) else pieces


def _closed_outward(mesh: trimesh.Trimesh) -> bool:
    """Closed, consistently wound and of positive total volume (each piece aside)."""
    # The volume of a mesh too large or small for float64 over- or underflows: _mass_properties names it.
    with np.errstate(all="ignore"):
        return bool(mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0)


def winding_numbers(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Generalised winding numbers of ``points`` (n, 3) about closed ``triangles`` (m, 3, 3):
    about 1 inside an outward-oriented surface, 0 outside (solid angles, Van Oosterom and
    Strackee)."""
    a, b, c = (triangles[None, :, k] - points[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
    det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", a, c) * lb + np.einsum("pfi,pfi->pf", b, c) * la
    return np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)


# Ray crossings whose barycentric coordinates or height lie within this fraction of the
# triangles' extent of an edge or of the probe are left to ``winding_numbers``.
_RAY_SLACK = 1e-9


def _ray_windings(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Winding numbers of ``points`` about closed ``triangles`` by counting the signed
    crossings of a ray from each point towards +z, and the points whose count rounding could
    decide (a crossing within ``_RAY_SLACK`` of an edge, a vertex or the point itself), which
    ``winding_numbers`` must settle. A grid over the xy-plane lists each triangle under the
    cells its projection's bounding box covers, so a point meets only the triangles listed in
    its cell: all of them (``winding_numbers``, points x triangles) took minutes for a hollow
    ball of 40,960 faces. Points go in batches of at most ``_WINDING_BATCH`` (point, triangle)
    pairs; a grid that large (triangles spanning most of it) leaves every point unsure."""
    n = len(points)
    windings, unsure = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=bool)
    if not n or not len(triangles):
        return windings, unsure
    low, high = triangles.min(axis=1), triangles.max(axis=1)
    origin = low.min(axis=0)
    slack = _RAY_SLACK * float(np.max(high.max(axis=0) - origin))
    cells = max(1, int(np.sqrt(len(triangles))))
    size = (high.max(axis=0) - origin)[:2] / cells
    size = np.where(size > 0, size, 1.0)

    def cell(xy):
        return np.clip(((xy - origin[:2]) / size).astype(np.int64), 0, cells - 1)

    def spread(counts):
        """Each entry's index within its group of ``counts``."""
        return np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)

    first, last = cell(low[:, :2] - slack), cell(high[:, :2] + slack)
    span = last - first + 1
    count = span[:, 0] * span[:, 1]
    if count.sum() > _WINDING_BATCH:
        unsure[:] = True
        return windings, unsure
    owner = np.repeat(np.arange(len(triangles)), count)
    offset = spread(count)
    key = (first[owner, 0] + offset % span[owner, 0]) * cells + first[owner, 1] + offset // span[owner, 0]
    order = np.argsort(key, kind="stable")
    listed, key = owner[order], key[order]
    listed_per_cell = np.bincount(key, minlength=cells * cells)
    starts = np.cumsum(listed_per_cell) - listed_per_cell
    probe_cell = cell(points[:, :2])
    pk = probe_cell[:, 0] * cells + probe_cell[:, 1]
    per = listed_per_cell[pk]
    bounds = np.searchsorted(np.cumsum(per), np.arange(0, per.sum(), _WINDING_BATCH), side="right")
    for lo, hi in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [n]])):
        if hi <= lo:
            continue
        probe = np.repeat(np.arange(lo, hi), per[lo:hi])
        tri = listed[np.repeat(starts[pk[lo:hi]], per[lo:hi]) + spread(per[lo:hi])]
        counted, doubtful = _ray_crossings(points[probe], triangles[tri], slack)
        np.add.at(windings, probe, counted)
        unsure[probe[doubtful]] = True
    return windings, unsure


def _ray_crossings(p: np.ndarray, triangles: np.ndarray, slack: float) -> tuple[np.ndarray, np.ndarray]:
    """Per (point, triangle) pair: the signed crossing (+1 out through an outward face, -1 in,
    0 none) of the ray from the point towards +z, and whether rounding could decide it."""
    a, b, c = (triangles[:, k] for k in range(3))
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    edge = np.linalg.norm(np.stack([b - a, c - b, a - c], axis=1), axis=2).max(axis=1)
    flat = np.abs(area) <= _RAY_SLACK * edge * edge  # seen edge-on from the ray
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # flat ones: not used
        u = ((b[:, 0] - p[:, 0]) * (c[:, 1] - p[:, 1]) - (b[:, 1] - p[:, 1]) * (c[:, 0] - p[:, 0])) / area
        v = ((c[:, 0] - p[:, 0]) * (a[:, 1] - p[:, 1]) - (c[:, 1] - p[:, 1]) * (a[:, 0] - p[:, 0])) / area
        w = 1.0 - u - v
        height = u * a[:, 2] + v * b[:, 2] + w * c[:, 2]
    inside = ~flat & (u > _RAY_SLACK) & (v > _RAY_SLACK) & (w > _RAY_SLACK)
    near_edge = ~flat & ~inside & (u > -_RAY_SLACK) & (v > -_RAY_SLACK) & (w > -_RAY_SLACK)
    above = inside & (height > p[:, 2] + slack)
    level = inside & (np.abs(height - p[:, 2]) <= slack)
    # A triangle seen edge-on counts nothing, unless the ray may run in its plane: then its
    # neighbours' crossings are not to be trusted either.
    along = flat & np.all((triangles[:, :, :2].min(axis=1) - slack <= p[:, :2]) & (p[:, :2] <= triangles[:, :, :2].max(axis=1) + slack), axis=1)
    return np.where(above, np.sign(area), 0.0).astype(np.int64), near_edge | level | along


def _pieces(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(label per face, 0 .. pieces - 1, of the closed pieces, faces connected through edges;
    each piece's signed volume; each piece's sum of |volume| terms, its volume's rounding
    scale). Each piece's volume is taken about its own centre, so that rounding far from the
    mesh's origin cannot flip a small piece's sign."""
    triangles = mesh.triangles
    # trimesh's labelling needs scipy, which this package does not.
    labels = np.unique(connected_labels(len(triangles), mesh.face_adjacency), return_inverse=True)[1].reshape(-1)
    counts = np.bincount(labels)
    centre = np.stack([np.bincount(labels, weights=triangles[:, :, k].mean(axis=1)) for k in range(3)], axis=1) / counts[:, None]
    local = triangles - centre[labels][:, None, :]
    signed = np.einsum("fi,fi->f", local[:, 0], np.cross(local[:, 1], local[:, 2])) / 6.0
    return labels, np.bincount(labels, weights=signed), np.bincount(labels, weights=np.abs(signed))


def _inside_out_piece(mesh: trimesh.Trimesh, pieces: tuple) -> bool:
    """Whether a closed piece of the mesh (``_pieces``) encloses a negative volume without
    lying inside the material of the other pieces, as a cavity's inward wall does (their
    winding number there at least 1): a separate inside-out box beside a body's box had its
    volume subtracted (8,125 kg read as 7,875 kg, the centre of mass on the wrong side); a
    piece of no volume (a double-sided sheet) is no inside-out piece."""
    triangles = mesh.triangles
    labels, volumes, scale = pieces
    for piece in np.flatnonzero(volumes < -1e-9 * scale):
        inside = labels == piece
        probe = triangles[inside][0].mean(axis=0, keepdims=True)
        if winding_numbers(probe, triangles[~inside])[0] < 0.5:
            return True
    return False


# How far inside its piece an overlap probe lies below a face, per unit of the piece's size.
_PROBE_INSET = 1e-6
# Most (probe, triangle) pairs one winding-number batch holds (memory).
_WINDING_BATCH = 2_000_000


def _overlapping_pieces(mesh: trimesh.Trimesh, pieces: tuple) -> bool:
    """Whether the material of an outward closed piece (``_pieces``) lies inside another
    piece's, where the mesh's volume counts it twice: two boxes joined by concatenating their
    meshes (1 + 1 m^3 overlapping by 0.25 read as 2,000 kg at 1,000 kg/m^3 instead of 1,750).
    Probes just inside each of the piece's triangles, off their centres and their corners,
    are wound about by the other pieces (a cavity's inward wall cancels the body around it,
    so an island in a cavity is no overlap); only pieces whose bounding boxes overlap are
    probed."""
    labels, volumes, scale = pieces
    if len(volumes) < 2:
        return False
    triangles = mesh.triangles
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(len(volumes)))
    low = np.minimum.reduceat(triangles.min(axis=1)[order], starts)
    high = np.maximum.reduceat(triangles.max(axis=1)[order], starts)
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    for piece in np.flatnonzero(volumes > 1e-9 * scale):
        others = np.flatnonzero(np.all((low <= high[piece]) & (high >= low[piece]), axis=1) & (np.arange(len(volumes)) != piece))
        if not others.size:
            continue
        own = (labels == piece) & (lengths > 0.0)
        # Three probes per triangle, each towards a corner of it, so that a face lying in
        # another piece's face plane (aligned boxes) still has probes off that plane's edges.
        corners = triangles[own]
        centres = corners.mean(axis=1, keepdims=True)
        probes = (0.5 * (corners + centres)).reshape(-1, 3)
        inward = np.repeat(-normals[own] / lengths[own, None], 3, axis=0)
        probes = probes + _PROBE_INSET * float(np.max(high[piece] - low[piece])) * inward
        probes = probes[np.any(np.all((probes[:, None] >= low[others]) & (probes[:, None] <= high[others]), axis=2), axis=1)]
        near = triangles[np.isin(labels, others)]
        counted, unsure = _ray_windings(probes, near)
        if (counted[~unsure] >= 1).any():
            return True
        probes = probes[unsure]
        batch = max(1, _WINDING_BATCH // len(near))
        for first in range(0, len(probes), batch):
            if (winding_numbers(probes[first:first + batch], near) >= 0.5).any():
                return True
    return False


@dataclass(frozen=True)
class _MeshNames:
    """How errors name a mesh's faces and vertices (``add_body``'s ``mesh_names``)."""

    face: Callable[[int], str]
    vertex: Callable[[int], str]


def _closure_hint(mesh: trimesh.Trimesh, names: _MeshNames) -> str:
    """Why a mesh that does not enclose a volume may not: a closed piece wound inside out
    (``_inside_out_piece``), a face naming a vertex twice, the whole mesh wound inside out,
    or faces that share no vertices (a triangle soup, as many exporters write), which close
    once coincident vertices are merged."""
    if _closed_outward(mesh):
        return " (a separate closed piece of it is wound inside out: invert that piece's faces)"
    repeated = np.flatnonzero((mesh.faces[:, 0] == mesh.faces[:, 1]) | (mesh.faces[:, 1] == mesh.faces[:, 2]) | (mesh.faces[:, 2] == mesh.faces[:, 0]))
    if repeated.size:
        a, b, _ = mesh.faces[repeated[0]]
        return f" ({names.face(repeated[0])} names {names.vertex(a if a in mesh.faces[repeated[0], 1:] else b)} twice, which closes nothing: remove such faces)"
    with np.errstate(invalid="ignore", divide="ignore"):
        if mesh.is_watertight and mesh.is_winding_consistent and mesh.volume < 0:
            return " (it is wound inside out, its faces' normals pointing inwards: invert its faces, e.g. trimesh's invert())"
    merged = mesh.copy()
    merged.merge_vertices()
    if len(merged.vertices) < len(mesh.vertices) and _volume_pieces(merged) is not None:
        return f" (its {len(mesh.vertices)} vertices merge into {len(merged.vertices)} of a closed mesh: merge coincident vertices first, e.g. trimesh's merge_vertices())"
    # A closed, outward solid whose pieces meet along an edge (two cubes sharing one) was
    # refused without a word of why (a probe, stop 58).
    edges, inverse, counts = np.unique(mesh.edges_sorted, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    shared = np.flatnonzero(counts > 2)
    if shared.size:
        a, b = (int(v) for v in edges[shared[0]])
        # A stray flat face along an edge was blamed on the pieces meeting there (a probe).
        on_edge = mesh.edges_face[inverse == shared[0]]
        flat = on_edge[_flat_faces(mesh.vertices, mesh.faces[on_edge])]
        if flat.size:
            return f" ({names.face(flat[0])} has no area, its corners on a line, and lies on the edge between {names.vertex(a)} and {names.vertex(b)}, which {int(counts[shared[0]])} faces then share: remove such faces)"
        return f" (the edge between {names.vertex(a)} and {names.vertex(b)} is shared by {int(counts[shared[0]])} faces, {shared.size} such edge(s) in all: a surface closes a volume where every edge has two faces; split the pieces apart there)"
    # A face wound the other way, a hole, a T-junction: refused without a word of why (a probe).
    open_edges = np.flatnonzero(counts == 1)
    if open_edges.size:
        a, b = (int(v) for v in edges[open_edges[0]])
        face = int(mesh.edges_face[np.flatnonzero(inverse == open_edges[0])[0]])
        return f" (the edge between {names.vertex(a)} and {names.vertex(b)} borders {names.face(face)} alone, {open_edges.size} such open edge(s) in all: a hole or a T-junction, where a closed surface has two faces on every edge)"
    directed, directed_counts = np.unique(mesh.edges, axis=0, return_counts=True)
    twice = np.flatnonzero(directed_counts > 1)
    if twice.size:
        a, b = (int(v) for v in directed[twice[0]])
        faces = mesh.edges_face[np.flatnonzero((mesh.edges[:, 0] == a) & (mesh.edges[:, 1] == b))]
        return f" ({names.face(faces[0])} and {names.face(faces[1])} both run from {names.vertex(a)} to {names.vertex(b)}: one of them is wound the other way round; invert it)"
    return ""


def _about_own_centre(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The mesh to take volume integrals of, and where its frame's origin moved: its bounding
    box's centre where that lies farther from the origin than the mesh is across (integrals
    about a far origin lose the inertia to cancellation in the parallel-axis shift: a 1 cm
    part 1 km out came out 77% off, silently, a probe at stop 58), else the mesh itself
    (its integrals bit for bit as before)."""
    low, high = mesh.bounds
    centre = 0.5 * (low + high)
    if not np.linalg.norm(centre) > np.max(high - low):
        return mesh, np.zeros(3)
    return trimesh.Trimesh(mesh.vertices - centre, mesh.faces, process=False), centre


# A triangle whose area is below this fraction of its longest edge squared is a segment or a
# point as far as float64 geometry goes.
_FLAT_TRIANGLE = 1e-12


def flat_twice_area(edge, coordinate, *, float32: bool = False):
    """Twice the area below which a triangle of longest edge ``edge`` (m), among coordinates
    up to ``coordinate`` (m) in magnitude, is flat: 1e-12 of its edge squared, or what rounding
    its corners' coordinates makes of a straight corner (a 1 mm polygon 100 m from the
    origin: 1e-11 of its edge squared), to float64, or with ``float32`` (coordinates that are
    all float32 values: USD points, STL vertices) to float32, 8 float32 epsilons of the
    largest coordinate times the edge (a 0.2 m box's T-junction in float32 closed with a
    sliver of twice the area 6.8e-10 m^2, which the float64 bound took for a triangle, and
    each leaf pair counted it as one more copy of its edge; a probe). One rule for meshes and
    for the polygons of USD faces."""
    epsilon = float(np.finfo(np.float32).eps) * 8.0 if float32 else float(np.finfo(np.float64).eps) * 64.0
    return np.maximum(_FLAT_TRIANGLE * np.square(edge), epsilon * np.asarray(coordinate) * edge)


def float32_values(points: np.ndarray) -> bool:
    """Whether every coordinate is a float32 value (read from float32 data), so rounding to
    float32 is what bent its straight corners."""
    points = np.asarray(points, dtype=np.float64)
    with np.errstate(over="ignore"):
        return bool(np.array_equal(points.astype(np.float32).astype(np.float64), points))


def _flat_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which of ``faces`` (m, 3) are flat (``flat_twice_area``), as a boolean mask (m,)."""
    corners = vertices[faces]
    edges = corners[:, [1, 2, 0]] - corners
    area2 = np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)
    return area2 <= flat_twice_area(np.sqrt(np.max(np.sum(edges * edges, axis=2), axis=1)), np.abs(vertices).max(), float32=float32_values(vertices))


def _contact_faces(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without its zero-area triangles and the vertices only they used, where any
    triangle has an area (a mesh that is all points and segments is kept as it is).

    A zero-area triangle (a polygon fanned over a straight corner, a face naming a vertex
    twice) encloses nothing, but a leaf pair counts it as one more copy of its edge: one
    lying on a box's bottom edge pushed the box sideways with ~600 N. Mass properties keep
    these triangles, which close some meshes' T-junctions."""
    flat = _flat_faces(vertices, faces)
    if flat.all() or not flat.any():
        return vertices, faces
    return _used_vertices(vertices, faces[~flat])[:2]


def _used_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh without the vertices no face uses, faces renumbered, and each kept vertex's
    index in the given mesh."""
    used, renumbered = np.unique(faces, return_inverse=True)
    return vertices[used], renumbered.reshape(-1, 3), used


def finite_vector(value, size: int) -> np.ndarray | None:
    """``value`` as ``size`` finite float64 numbers (``real_array``), or None."""
    array = real_array(value)
    if array is None or array.shape != (size,) or not np.isfinite(array).all():
        return None
    return array


def _mass_properties(mesh: trimesh.Trimesh, name: str, *, density, mass, inertia, center_of_mass, names: "_MeshNames") -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, centre of mass in the mesh frame, second moment about it) of a dynamic body
    from ``add_body``'s arguments, each checked and named (its mesh's faces and vertices
    by ``names``)."""
    where = f"body {name!r}"
    pieces = _volume_pieces(mesh)
    closed = pieces is not None
    if density is not None and mass is not None:
        raise ValueError(f"{where}: give either a density or a mass, not both")
    if density is None and mass is None:
        raise ValueError(f"{where}: give a density or a mass (or mark it static)")
    label, value = ("density", density) if density is not None else ("mass", mass)
    if not is_positive_finite(value):
        raise ValueError(f"{where}: {label} must be positive and finite, got {value!r}")
    # The model settings' range: a mass of 1e300 (or 1e-300) was taken, and the first step
    # failed "no convergence", blaming Newton (a probe, stop 64).
    problem = scale_problem(value, "kg/m^3" if label == "density" else "kg")
    if problem is not None:
        raise ValueError(f"{where}: {label} {problem}, got {value!r}")
    if density is not None and not closed:
        raise ValueError(f"{where}: mass from density needs a closed, consistently outward-oriented mesh{_closure_hint(mesh, names)}; give mass and inertia instead")
    if closed and (density is not None or inertia is None or center_of_mass is None) and _overlapping_pieces(mesh, pieces):
        raise ValueError(
            f"{where}: closed pieces of its mesh overlap, so their shared volume would count twice in its mass properties; "
            "join them into one surface (a boolean union) or give mass, inertia and center_of_mass"
        )
    if inertia is None and not closed:
        raise ValueError(f"{where}: inertia is needed for a mesh that is not closed and consistently outward-oriented (no volume to take it from){_closure_hint(mesh, names)}")
    centred, origin = _about_own_centre(mesh)
    with np.errstate(all="ignore"):  # the inertia check below names a body too large or small for them
        props = centred.mass_properties if closed else None
    body_mass = float(props["volume"]) * float(density) if density is not None else float(mass)
    if center_of_mass is not None:
        com = real_array(center_of_mass)
        if com is None or com.shape != (3,) or not np.isfinite(com).all():
            raise ValueError(f"{where}: center_of_mass must be 3 finite numbers (m, mesh frame), got {center_of_mass!r}")
        check_coordinates(com, f"{where}: center_of_mass")  # it was blamed on the mesh's vertices
    elif closed:
        com = np.asarray(props["center_mass"], dtype=np.float64) + origin
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            com = np.asarray(centred.centroid, dtype=np.float64) + origin
        if not np.isfinite(com).all():  # no area either: the points themselves
            com = mesh.vertices.mean(axis=0)
    computed = inertia is None
    if computed:
        scale = float(density) if density is not None else body_mass / float(props["mass"])
        inertia = np.asarray(props["inertia"], dtype=np.float64) * scale
    given = inertia
    inertia = real_array(given)
    if inertia is None:
        raise ValueError(f"{where}: inertia must be a finite, symmetric positive definite 3x3 matrix (kg m^2), got {given!r}")
    with np.errstate(over="ignore", invalid="ignore"):
        second_moment = _second_moment_from_inertia(inertia) if inertia.shape == (3, 3) else None
    # Symmetric relative to its own size, and definite as a whole matrix: an absolute 1e-8
    # kg m^2 passed a 1 g box's inertia of 1e-9 with an 8e-9 off-diagonal on one side only,
    # and eigvalsh reads one triangle (the matrix's symmetric part had an eigenvalue -3e-9).
    if (
        second_moment is None
        or not (np.isfinite(inertia).all() and np.isfinite(second_moment).all())
        or np.abs(inertia - inertia.T).max() > 1e-6 * np.abs(inertia).max()
        or np.linalg.eigvalsh(0.5 * (inertia + inertia.T)).min() <= 0
    ):
        if computed:  # it was blamed on an inertia the caller never gave
            extent = float(np.ptp(mesh.vertices, axis=0).max())
            raise ValueError(f"{where}: the inertia of its mesh ({extent:.3g} m across) at mass {body_mass:.3g} kg is not a finite positive definite float64 matrix (it grows as the fifth power of the size); give mass and inertia, or rescale the scene")
        raise ValueError(f"{where}: inertia must be a finite, symmetric positive definite 3x3 matrix (kg m^2)")
    problem = unit_inertia_problem(np.linalg.eigvalsh(0.5 * (inertia + inertia.T)) / body_mass)
    if problem is not None:
        what = f"the inertia of its mesh ({float(np.ptp(mesh.vertices, axis=0).max()):.3g} m across)" if computed else "inertia"
        raise ValueError(f"{where}: {what} over its mass {body_mass:.3g} kg {problem}; {'rescale the scene' if computed else 'check the inertia (kg m^2) and mass (kg)'}")
    smallest = np.linalg.eigvalsh(second_moment).min()
    if smallest < -1e-12 * np.trace(inertia):
        raise ValueError(f"{where}: inertia violates the triangle inequality (not physical)")
    if smallest <= 0.0:  # the solver needs a positive definite second moment; it refused this only at the first step
        raise ValueError(
            f"{where}: inertia meets the triangle inequality with equality (e.g. I_zz = I_xx + I_yy), which puts the whole mass in a plane "
            "or on a line, a body of no thickness; give the inertia of the body's real thickness"
        )
    return body_mass, com, second_moment


def _added_name(name, kind: str, index: int, taken: set[str]) -> str:
    """The name the ``index``-th body or joint (``kind``) gets, after those named ``taken``:
    ``name``, a non-empty string, or by default the first of kind<index>, kind<index + 1>,
    ... not taken (add_body(name="body1") and then an unnamed second body, "body1" by
    default, ended in finalize's "used more than once"; "" was replaced by the default
    silently). ``taken`` is the builder's set, kept as it adds (a list made each call cost
    1.8 s over 10,000 bodies)."""
    if name is None:
        while f"{kind}{index}" in taken:
            index += 1
        return f"{kind}{index}"
    if not isinstance(name, str):
        raise ValueError(f"{kind} {index}: name must be a string, got {name!r}")
    if not name:
        raise ValueError(f"{kind} {index}: name must not be empty, got ''; leave it out (None) for the default, {kind}<index> or the next free such name")
    return name


# The ipc barrier (ipctk's, on squared distances) holds a body of weight m g about this times
# mu dhat^4 / (m g) above a support: 28.0 measured for a box on two triangles over mu 1e3 -
# 1e5, dhat 1e-2 - 2e-2 m and 32 - 320 kg (2026-11-27).
_IPC_GAP_FACTOR = 28.0


class ModelBuilder:
    """Collects bodies, then ``finalize()`` builds a ``Model``.

    Args:
        gravity: (3,) gravitational acceleration (m/s^2).
        contact_stiffness: potential coefficient mu (J m: P is 1/m; the paper uses 1e-6 ..
            5e-9). It sets
            how far above a support a body rests: about sqrt(100 mu / (m g)) for a box on a
            face (measured: a 1 m box of 1,000 kg/m^3 rests 1.1e-4 m up at mu 1e-6; a 1 mm
            box of the same density rests 1.2e-4 m up at mu 1e-15, and at 1e-6 the barrier
            throws it ~17 m high). Choose it for the lightest body that rests on another;
            ``finalize`` warns about dynamic bodies whose estimated gap exceeds a tenth of
            their radius (a 1 cm cube of 500 kg/m^3 at 1e-6: thrown 0.69 m up, resting 0.25 m
            above the table after 16 s), and whose gap falls below 2e-7 of their radius,
            where impacts stall Newton. Between, gaps below ~1e-4 of the radius make impact
            steps stiff enough to land on one of several nearby solutions: gradients through
            such impacts are right locally but jump (docs/architecture.md, "Where it cannot
            be solved"); the shipped scenes rest at 2e-4 to 6e-3 of their radii. Large
            steps can do so at any gap (a spinning box landing at 3 m/s in one step of
            0.1 s): optimise through impacts at dt <= 0.04 s. The
            estimate holds for supports of few triangles: the potential sums over triangle
            pairs, so a finely tessellated support holds a body higher (a 0.1 m, 2.1 kg ball
            at mu 1e-6 rests 3.6 mm above an 8-triangle ground, 4.8 mm above 200 triangles,
            32 mm above 1,250 and 48 mm above 5,000; the estimate is 2.2 mm).
        eps: blend margin of the hierarchical contact potential; below 0.01 the blend is
            steep and Newton slow (warned about).
        friction: friction coefficient (default 0); 0 disables friction (and all its work, its gradient
            included unless ``model.friction.requires_grad`` is set).
        friction_smoothing: slip speed (m/s) below which the friction law is smoothed.
        centred_weight: ``"paper"`` or ``"pairs"``: how a far cluster pair's centred term
            counts in the hierarchical potential (``ContactModel``).
        contact_mode: ``"bsh"``, ``"brute"`` (the paper's model, hierarchical or exact),
            ``"ipc"`` (the IPC baseline through ipctk, with IPC's lagged friction; CPU only)
            or ``"sdrs"`` (the SDRS baseline: locally supported log barrier on separating
            planes). Every mode takes friction's lagged normal forces from its own potential.
        leaf_precision: float type of the leaf plane searches of ``"bsh"`` and ``"brute"``,
            ``"float64"`` or ``"float32"`` (``ContactModel``); the baselines solve in float64.
        ipc_dhat: barrier support distance of the ``"ipc"`` baseline (m).
        sdrs_dhat: barrier support of the ``"sdrs"`` baseline on vertex-to-plane gaps (m);
            triangles interact below 2 sdrs_dhat.
        articulation_contact: contact between bodies of one articulation: ``"nonadjacent"``
            (default: all pairs except a joint's parent and child), ``"all"`` or ``"none"``;
            a static parent counts as a link of its joints. Links of one articulation keep
            each other's contact forces, but the solver's pass-through check does not follow
            them (they move on joint arcs, not the straight motion it tests), so a step that
            swings one link through another within one step is not refused.
    """

    def __init__(self, *, gravity=(0.0, 0.0, -9.81), contact_stiffness: float = 1e-6, friction: float = 0.0, friction_smoothing: float = 1e-4, eps: float = 0.5, centred_weight: str = "paper", contact_mode: str = "bsh", leaf_precision: str = "float64", ipc_dhat: float = 1e-2, sdrs_dhat: float = 1e-2, articulation_contact: str = "nonadjacent"):
        problem = gravity_problem(gravity)
        if problem is not None:
            raise ValueError(f"gravity: {problem}, got {gravity!r}")
        gravity = finite_vector(gravity, 3)
        for name, value in (("contact_stiffness", contact_stiffness), ("friction", friction), ("friction_smoothing", friction_smoothing), ("eps", eps)):
            problem = contact_setting_problem(name, value)
            if problem:
                raise ValueError(f"{name}: {problem}, got {shown(value)}")
        # These were checked only by finalize, the supports under the name "dhat".
        if centred_weight not in CENTRED_WEIGHTS:
            raise ValueError(f"centred_weight: {centred_weight!r} is not one of {CENTRED_WEIGHTS}")
        for name, value in (("ipc_dhat", ipc_dhat), ("sdrs_dhat", sdrs_dhat)):
            check_barrier_support(value, name)
        self.gravity = gravity
        self.contact_stiffness = float(contact_stiffness)
        self.friction = float(friction)
        self.friction_smoothing = float(friction_smoothing)
        self.eps = eps
        self.centred_weight = centred_weight
        if contact_mode not in MODEL_CONTACT_MODES:
            raise ValueError(f"contact_mode: {contact_mode!r} is not one of {MODEL_CONTACT_MODES}")
        self.contact_mode = contact_mode
        if steep_blend(eps, contact_mode):
            warnings.warn(
                f"eps {eps:g} is below {STEEP_BLEND_EPS:g}: the blend over a margin of eps times the spheres' "
                "radii is steep (its slope grows as 1/eps), and implicit steps take more Newton iterations "
                "(a ball dropped on a grid: 5 a frame at eps 0.5, 8 at 0.01, 35 at 0.001); below about 1e-4 a body "
                "can come to rest on a blend shell, centimetres above its support (that ball 4.9 cm up at 3e-5), or "
                "the steps stop converging",
                stacklevel=2,
            )
        if centred_weight == "pairs" and eps < PAIRS_PUSH_EPS and contact_mode == "bsh":
            warnings.warn(
                f"eps {eps:g} is below {PAIRS_PUSH_EPS:g} with centred_weight 'pairs': its weighted centred terms can then "
                "exceed the blend's exact sums, and net forces pull separated bodies together (5 of 3,600 random poses of "
                "two boxes in the blend shells at eps 0.05, 45 at eps 0.01; none at 0.1 and above); use eps >= 0.1 or the paper's weights",
                stacklevel=2,
            )
        float32_search(leaf_precision, mode=contact_mode)
        self.leaf_precision = leaf_precision
        self.ipc_dhat = ipc_dhat
        if articulation_contact not in _ARTICULATION_CONTACT:
            raise ValueError(f"articulation_contact: {articulation_contact!r} is not one of {_ARTICULATION_CONTACT}")
        self.articulation_contact = articulation_contact

        self.sdrs_dhat = sdrs_dhat
        self._bodies: list[_Body] = []
        self._joints: list[Joint] = []
        # Names given so far, per kind ("body", "joint"): the defaults skip them.
        self._names_taken: dict[str, set[str]] = {"body": set(), "joint": set()}
        # Each joint's parent body as given (a static one too), for contact exclusion: a
        # Joint holds a static parent as the world (-1).
        self._joint_parents: list[int] = []

    def add_body(
        self,
        mesh,
        *,
        name: str | None = None,
        pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        density: float | None = None,
        mass: float | None = None,
        inertia=None,
        center_of_mass=None,
        static: bool = False,
        kp_linear=0.0,
        kd_linear=0.0,
        kp_angular: float = 0.0,
        kd_angular: float = 0.0,
        mesh_names=None,
    ) -> int:
        """Add a rigid body; returns its index.

        Args:
            mesh: ``trimesh.Trimesh`` or (vertices (nv, 3), faces (nf, 3)) in the mesh frame (m).
            pose: (7,) pose of the mesh frame (px, py, pz, qx, qy, qz, qw).
            name: unique body name, not empty (default ``body{index}``, or the next
                ``body{n}`` no body added before has).
            density: kg/m^3: the mass of the mesh's volume (a closed, consistently
                outward-wound mesh); or ``mass`` instead.
            mass: kg, instead of ``density``.
            inertia: kg m^2 about the centre of mass in the mesh frame's axes; default the
                mesh volume's, scaled to the mass.
            center_of_mass: (3,) in the mesh frame (m); default the mesh volume's centroid,
                or for a mesh without a volume (given an inertia) its surface's centroid.
            static: fixed in place; no degrees of freedom and no mass properties.
            kp_linear, kd_linear: PD gains per translation axis (scalar or 3 values; N/m,
                N s/m).
            kp_angular, kd_angular: PD gains of the orientation (N m/rad, N m s/rad).
            mesh_names: (face_name, vertex_name), functions of a face's and a vertex's index
                in ``mesh`` returning how an error about the mesh names them (default
                "face i", "vertex v"; ``io`` names the collider prims' authored faces and
                points, which its triangulation numbers otherwise).
        """
        name = self._body_name(name)
        static = checked_flag(static, f"body {name!r}: static")
        if isinstance(mesh, trimesh.Trimesh):
            vertices, faces = mesh.vertices, mesh.faces
        else:
            try:
                vertices, faces = mesh
            except (TypeError, ValueError) as exc:
                raise ValueError(f"body {name!r}: mesh must be a trimesh.Trimesh or (vertices, faces): {exc}") from None
        # Checked before anything reads the mesh: trimesh would cast fractional indices to
        # integers and the mass properties would blame an index out of range on the shape.
        vertices, faces = validated_mesh(vertices, faces, name, face_name=None if mesh_names is None else mesh_names[0])
        # Vertices no face uses are not part of the body: they moved the centre of mass of
        # the mass and inertia path, and the body radius that sizes the solver's tolerance.
        vertices, faces, used = _used_vertices(vertices, faces)
        face_name, vertex_name = mesh_names if mesh_names is not None else (lambda f: f"face {f}", lambda v: f"vertex {v}")
        # The errors name what the caller gave: a vertex by its index before unused ones went.
        names = _MeshNames(face=lambda f: face_name(int(f)), vertex=lambda v: vertex_name(int(used[v])))
        tm = trimesh.Trimesh(vertices, faces, process=False)
        given = pose
        pose = finite_vector(pose, 7)
        if pose is None:
            raise ValueError(f"body {name!r}: pose must be 7 finite numbers (px, py, pz, qx, qy, qz, qw), got {given!r}")
        check_coordinates(pose[:3], f"body {name!r}: pose position")
        qnorm = np.linalg.norm(pose[3:])
        if abs(qnorm - 1.0) > QUATERNION_TOLERANCE:
            raise ValueError(f"body {name!r}: pose quaternion has norm {qnorm:.9g}, expected 1")
        pose[3:] /= qnorm

        if static:
            given = [label for label, value in (("density", density), ("mass", mass), ("inertia", inertia), ("center_of_mass", center_of_mass)) if value is not None]
            if given:
                raise ValueError(f"body {name!r}: a static body takes no mass properties, got {', '.join(given)}")
            com = vertices.mean(axis=0)
            body_mass, second_moment = 1.0, np.zeros((3, 3))
        else:
            body_mass, com, second_moment = _mass_properties(tm, name, density=density, mass=mass, inertia=inertia, center_of_mass=center_of_mass, names=names)

        gains = {}
        for label, value, count in (("kp_linear", kp_linear, 3), ("kd_linear", kd_linear, 3), ("kp_angular", kp_angular, 1), ("kd_angular", kd_angular, 1)):
            gain = real_array(value)
            if gain is not None and gain.size in (1, count) and gain.ndim <= 1:
                gain = np.broadcast_to(gain, (count,)).copy()
            else:
                gain = None
            if gain is None or not is_gain(gain):
                wanted = "1 or 3 numbers, each >= 0 and finite" if count == 3 else "a number >= 0 and finite"
                raise ValueError(f"body {name!r}: {label} must be {wanted}, got {value!r}")
            gains[label] = gain
        kp_lin, kd_lin = gains["kp_linear"], gains["kd_linear"]
        kp_angular, kd_angular = float(gains["kp_angular"][0]), float(gains["kd_angular"][0])
        if static and (kp_lin.any() or kd_lin.any() or kp_angular or kd_angular):
            raise ValueError(f"body {name!r}: a static body cannot be PD-actuated")

        vertices, faces = _contact_faces(vertices, faces)
        # Body frame: origin at the centre of mass, axes of the mesh frame.
        com_pose = pose.copy()
        com_pose[:3] = pose[:3] + quat_rotate(pose[3:], com)
        self._bodies.append(
            _Body(name, vertices - com, faces, body_mass, second_moment, com_pose, bool(static), kp_lin, kd_lin, float(kp_angular), float(kd_angular), com)
        )
        self._names_taken["body"].add(name)
        return len(self._bodies) - 1

    def add_joint(
        self,
        kind: str,
        *,
        child: int,
        parent: int | None = None,
        anchor=None,
        axis=None,
        parent_frame=None,
        child_frame=None,
        dofs=None,
        limits=None,
        kp=0.0,
        kd=0.0,
        limit_margin=None,
        limit_stiffness=None,
        cone_limit: float | None = None,
        target=None,
        name: str | None = None,
    ) -> int:
        """Connect ``child`` to ``parent`` (a body index, or None for the world); returns the joint index.

        Args:
            kind: ``"revolute"`` (1 coordinate, rad), ``"prismatic"`` (1, m), ``"universal"``
                (2 rad: a ball joint with its twist locked), ``"ball"`` (3 rotations, no
                coordinates, no gimbal singularity) or ``"base"`` (to the world: ``dofs``).
            anchor: world point (m) of the joint in the initial poses; the joint frame is then
                aligned with the world and ``axis`` is in world axes.
            axis: revolute/prismatic: (3,); universal: (2, 3), the first fixed in the parent,
                the second in the child.
            parent_frame, child_frame: instead of ``anchor``: (7,) joint-frame poses in the
                parent's (world's) and the child's mesh frames, as UsdPhysics localPos/localRot;
                ``axis`` is then in the joint frame. The initial poses must satisfy the joint.
            dofs: base joints: a subset of ("x", "y", "z", "rx", "ry", "rz") (world axes,
                rotations about the child's centre of mass). A base joint's coordinates are
                offsets from the child's initial pose (0 at the start), and so are its
                ``limits`` and ``target``: a body at z = 1 with target 0.2 on "z" is driven to
                z = 1.2. The three rotations together are one free rotation without
                coordinates (no limits, gains or target; use the body's ``kp_angular``).
            limits: per coordinate (lower, upper) in rad or m, or None.
            kp, kd: PD gains per coordinate (scalar or one per coordinate), N m/rad, N m s/rad
                (N/m, N s/m for translations); targets come from ``Control.joint_target``.
                Ball joints: one kp and one kd (N m/rad, N m s/rad) on the relative rotation,
                kp (1 - cos theta*) + kd/dt (1 - cos theta^t) (theta: angle to the target,
                and to the rotation at the step's start); targets come from
                ``Control.ball_target``.
            limit_margin: support of the limit barrier, at most half the range (default: a
                tenth of the range as it is at each step, so also of limits set after
                ``finalize``, or of a ball joint's cone_limit, at most 0.1; stored as NaN);
                limit_stiffness: its scale (J, default 1).
            cone_limit: ball joints: the largest swing (rad, in (0, pi)) between ``axis`` (in
                the joint frame, default X) fixed in the parent and fixed in the child.
            target: per coordinate, the PD target (rad or m) of ``Model.control()``'s
                ``joint_target`` (a USD drive's targetPosition); default, or NaN for a
                coordinate: the initial coordinates.
            name: unique joint name, not empty (default ``joint{index}``, or the next
                ``joint{n}`` free); coordinates are named
                ``{name}:{k}`` (a base joint's ``{name}:{dof}``).
        """
        name = _added_name(name, "joint", len(self._joints), self._names_taken["joint"])
        where = f"joint {name!r}"
        if kind not in JOINT_KINDS:
            raise ValueError(f"{where}: unknown joint type {kind!r}; supported: {JOINT_KINDS}")
        n = len(self._bodies)
        if not is_whole(child) or not 0 <= child < n:
            raise ValueError(f"{where}: child must be a body index in [0, {n}), got {child!r}")
        if parent is not None and (not is_whole(parent) or not 0 <= parent < n):
            raise ValueError(f"{where}: parent must be a body index in [0, {n}) or None, got {parent!r}")
        if parent == child:
            raise ValueError(f"{where}: parent and child are the same body {self._bodies[child].name!r}")
        child_body = self._bodies[child]
        if child_body.static:
            raise ValueError(f"{where}: child body {child_body.name!r} is static; a joint needs a dynamic child")
        if any(j.child == child for j in self._joints):
            other = next(j.name for j in self._joints if j.child == child)
            raise ValueError(f"{where}: body {child_body.name!r} already has parent joint {other!r}; articulations must be trees, each body the child of one joint (kinematic loops are not supported; in USD a joint's body1 is its child)")
        parent_pose = _IDENTITY_POSE
        parent_index = -1
        if parent is not None:
            parent_body = self._bodies[parent]
            parent_pose = parent_body.pose
            if not parent_body.static:
                parent_index = int(parent)
        if kind == "base":
            # A static parent too: the base moves its body along world axes all the same, and
            # the body's contact with that parent was dropped as a joint's (it fell through).
            if parent is not None:
                raise ValueError(f"{where}: a base joint connects a body to the world (parent None)")
            given = [label for label, value in (("anchor", anchor), ("axis", axis), ("parent_frame", parent_frame), ("child_frame", child_frame)) if value is not None]
            if given:
                # They were ignored: a base with dofs ("ry",) and an anchor turned about its centre.
                raise ValueError(f"{where}: a base joint moves its body along world axes through its centre of mass; {', '.join(given)} do not apply to it")
            if isinstance(dofs, str):
                # Split into letters: "xyz" was taken as three translations, "rz" refused as ('r', 'z').
                raise ValueError(f"{where}: dofs must be a sequence of names from {BASE_DOFS}, such as ('x', 'rz'), got the string {dofs!r}")
            if isinstance(dofs, (set, frozenset)):
                # The per-coordinate gains, targets and limits follow dofs' order, which a set's
                # iteration changes with PYTHONHASHSEED (a probe, stop 65).
                raise ValueError(f"{where}: dofs must be a sequence (a list or tuple, in the order of the per-coordinate values), got the set {sorted(map(str, dofs))!r}")
            dofs = tuple(dofs or ())
            unknown = [d for d in dofs if d not in BASE_DOFS]
            if unknown or len(set(dofs)) != len(dofs) or not dofs:
                raise ValueError(f"{where}: dofs must be a non-empty subset of {BASE_DOFS}, got {dofs!r}")
            # Coordinates run in BASE_DOFS order; the per-coordinate arguments follow ``dofs``
            # as given (they stayed in that order: dofs ("rz", "x") put rz's limits on x).
            # Three free rotations are one rotation vector without coordinates (num_coordinates).
            canonical = tuple(d for d in BASE_DOFS if d in dofs)
            rotations = sum(d not in ("x", "y", "z") for d in dofs)
            owning = [d for d in dofs if d in ("x", "y", "z") or rotations < 3]
            if rotations == 3:
                # A single gain or target was spread over the translations alone (none with only
                # the rotations): the free rotation went undriven, silently.
                spread = [label for label, value in (("kp", kp), ("kd", kd), ("target", target)) if value is not None and np.ndim(value) == 0 and (label == "target" or value != 0)]
                if spread or (target is not None and not owning):
                    raise ValueError(
                        f"{where}: a base joint's three free rotations have no coordinates (one rotation vector), so no drive or target; "
                        f"give {', '.join(spread or ['target'])} one value per translation {tuple(d for d in BASE_DOFS[:3] if d in dofs)}, or drive the rotation with the body's kp_angular (add_body)"
                    )
            order = [owning.index(d) for d in canonical if d in owning]
            dofs = canonical
            axes = np.zeros((0, 3))
            frames = (_IDENTITY_POSE.copy(), _IDENTITY_POSE.copy())
        else:
            if dofs is not None:
                raise ValueError(f"{where}: dofs only applies to base joints")
            dofs = ()
            order = None
            axes = _unit_axes(axis, JOINT_AXES.get(kind, 0 if axis is None else 1), where)
            if anchor is not None:
                if parent_frame is not None or child_frame is not None:
                    raise ValueError(f"{where}: give an anchor or joint frames, not both")
                given = anchor
                anchor = real_array(given)
                if anchor is None or anchor.shape != (3,) or not np.isfinite(anchor).all():
                    raise ValueError(f"{where}: anchor must be 3 finite numbers, got {given!r}")
                check_coordinates(anchor, f"{where}: anchor")  # beyond it, a hinged body's step went silently wrong
                world_frame = np.concatenate([anchor, [0.0, 0.0, 0.0, 1.0]])
                frames = (frame_in_body(parent_pose, world_frame), frame_in_body(child_body.pose, world_frame))
            elif parent_frame is not None and child_frame is not None:
                frames = []
                for label, frame, body in (("parent_frame", parent_frame, self._bodies[parent] if parent is not None else None), ("child_frame", child_frame, child_body)):
                    given = frame
                    frame = real_array(given)
                    if frame is None or frame.shape != (7,) or not np.isfinite(frame).all() or abs(np.linalg.norm(frame[3:]) - 1.0) > QUATERNION_TOLERANCE:
                        raise ValueError(f"{where}: {label} must be 7 finite numbers (p, unit quaternion), got {given!r}")
                    check_coordinates(frame[:3], f"{where}: {label} position")
                    frame = frame.copy()
                    frame[3:] /= np.linalg.norm(frame[3:])
                    if body is not None:  # mesh frame -> centre-of-mass frame (same axes)
                        frame[:3] -= body.center_of_mass
                    frames.append(frame)
                frames = tuple(frames)
            else:
                raise ValueError(f"{where}: give an anchor (world point) or both parent_frame and child_frame")
        if parent is not None and parent_index < 0:  # a static parent is part of the world
            frames = (pose_mul(parent_pose, frames[0]), frames[1])
        probe = Joint(name, kind, parent_index, int(child), frames[0], frames[1], axes, dofs)
        if parent is not None and parent_index < 0:
            probe.static_parent, probe.static_parent_pose = int(parent), np.array(parent_pose, dtype=np.float64)
        count = probe.num_coordinates()
        if kind == "ball" and limits is not None:
            raise ValueError(f"{where}: ball joints have no coordinates, so no coordinate limits (a swing limit is cone_limit)")
        lower, upper = coordinate_limits(limits, count, where)
        if cone_limit is not None:
            if kind != "ball":
                raise ValueError(f"{where}: cone_limit only applies to ball joints")
            if not (is_real(cone_limit) and 0.0 < cone_limit < np.pi):
                raise ValueError(f"{where}: cone_limit must be in (0, pi) rad, got {cone_limit!r}")
            probe.cone_limit = float(cone_limit)
        for label, value in (("limit_margin", limit_margin), ("limit_stiffness", limit_stiffness)):
            if value is None:
                continue
            if kind == "ball" and cone_limit is None:
                raise ValueError(f"{where}: {label} applies to a ball joint's cone_limit, and it has none")
            if kind != "ball" and limits is None:  # accepted and ignored before
                raise ValueError(f"{where}: {label} applies to limits, and it has none")
        limit_stiffness = 1.0 if limit_stiffness is None else limit_stiffness
        if kind == "ball":
            # One barrier, on the swing angle, where a cone limit is given.
            limit_count = 0 if cone_limit is None else 1
            span = np.full(limit_count, probe.cone_limit)
        else:
            limit_count = count
            span = np.where(np.isfinite(upper - lower), upper - lower, np.inf)
        if kind == "ball" and (np.size(kp) != 1 or np.size(kd) != 1):
            raise ValueError(f"{where}: a ball joint takes one kp and one kd (they drive its whole relative rotation), got kp={kp!r}, kd={kd!r}")
        # A ball joint's single gain pair drives its relative rotation (no coordinates).
        gain_count = 1 if kind == "ball" else count
        gains = {}
        given = (("limit_margin", limit_margin, limit_count),) if limit_margin is not None else ()
        for label, value, size in (("kp", kp, gain_count), ("kd", kd, gain_count), ("limit_stiffness", limit_stiffness, limit_count), *given):
            arr = _per_coordinate(value, size, label, where)
            if not np.isfinite(arr).all() or (arr < 0).any() or (label.startswith("limit") and (arr <= 0).any()):
                raise ValueError(f"{where}: {label} must be finite and {'positive' if label.startswith('limit') else '>= 0'}, got {value!r}")
            gains[label] = arr
        if limit_margin is None:
            # A coordinate's default follows its range at each step (limits set after
            # finalize kept an unlimited coordinate's 0.1); a cone's limit is fixed.
            gains["limit_margin"] = default_limit_margins(span) if kind == "ball" else np.full(limit_count, np.nan)
        else:
            # Wider, the barrier acted across the whole range (or at zero swing).
            room = span if kind == "ball" else 0.5 * span
            wide = np.flatnonzero(gains["limit_margin"] > room)
            if wide.size:
                what = "the cone limit" if kind == "ball" else f"half the range of coordinate {int(wide[0])}"
                raise ValueError(f"{where}: limit_margin {float(gains['limit_margin'][wide[0]])!r} exceeds {what}, {float(room[wide[0]])!r}")
        margins = effective_limit_margins(gains["limit_margin"], span)
        for c in np.flatnonzero(np.isfinite(lower) | np.isfinite(upper)) if kind != "ball" else range(limit_count):
            problem = limit_margin_problem(float(margins[c]), given=limit_margin is not None)
            if problem is not None:
                what = f"cone_limit {probe.cone_limit!r}" if kind == "ball" else f"coordinate {int(c)}'s limits [{float(lower[c])!r}, {float(upper[c])!r}]"
                raise ValueError(f"{where}: {what}: {problem}")
        if target is not None:
            if kind == "ball":
                raise ValueError(f"{where}: ball joints have no coordinates to target (their targets are Control.ball_target rotations)")
            gains["target"] = _per_coordinate(target, count, "target", where)
            if np.isinf(gains["target"]).any():
                raise ValueError(f"{where}: target must be finite (NaN: that coordinate's initial value), got {target!r}")
        if kind == "ball" and axis is not None and cone_limit is None:  # accepted and ignored before
            raise ValueError(f"{where}: axis applies to a ball joint's cone_limit (the swing limit's axis), and it has none")
        if order is not None:
            lower, upper = lower[order], upper[order]
            gains = {label: arr[order] for label, arr in gains.items()}
        probe.lower, probe.upper = lower, upper
        probe.limit_margin, probe.limit_stiffness = gains["limit_margin"], gains["limit_stiffness"]
        probe.kp, probe.kd = gains["kp"], gains["kd"]
        if "target" in gains:
            probe.target = gains["target"]
        self._joints.append(probe)
        self._names_taken["joint"].add(probe.name)
        self._joint_parents.append(-1 if parent is None else int(parent))
        return len(self._joints) - 1

    def body_center_of_mass(self, index: int) -> np.ndarray:
        """(3,) centre of mass of added body ``index`` in its mesh frame (m); a static body's
        frame origin (the mean of its vertices)."""
        if not (is_whole(index) and 0 <= index < len(self._bodies)):
            added = f"from 0 to {len(self._bodies) - 1}" if self._bodies else "(no body has been added)"
            raise ValueError(f"index: expected a body index {added}, got {index!r}")
        return self._bodies[index].center_of_mass.copy()

    def _body_name(self, name: str | None) -> str:
        """The name a body being added gets (``_added_name``)."""
        return _added_name(name, "body", len(self._bodies), self._names_taken["body"])

    def add_box(self, extents, **kwargs) -> int:
        """Add a box with the given (x, y, z) extents (m), centred on its frame."""
        sizes = real_array(extents)
        if sizes is None or sizes.shape != (3,) or not (np.isfinite(sizes).all() and (sizes > 0).all()):
            raise ValueError(f"body {self._body_name(kwargs.get('name'))!r}: box extents must be 3 positive finite numbers (m), got {extents!r}")
        return self.add_body(trimesh.creation.box(extents=sizes), **kwargs)

    def add_sphere(self, radius: float, *, subdivisions: int = 2, **kwargs) -> int:
        """Add an icosphere of the given radius (m); ``subdivisions`` (0-6) refine it from 20
        triangles, 4x each."""
        where = f"body {self._body_name(kwargs.get('name'))!r}"
        if not is_positive_finite(radius):
            raise ValueError(f"{where}: sphere radius must be positive and finite (m), got {radius!r}")
        # Beyond it trimesh's icosphere came out NaN, and the error blamed the mesh (a probe, stop 64).
        problem = scale_problem(radius, "m")
        if problem is not None:
            raise ValueError(f"{where}: sphere radius {problem}, got {radius!r}")
        if not is_whole(subdivisions) or not 0 <= subdivisions <= 6:
            raise ValueError(f"{where}: sphere subdivisions must be a whole number from 0 to 6, got {subdivisions!r}")
        return self.add_body(trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=float(radius)), **kwargs)

    def _warn_floating_bodies(self, body_radius: np.ndarray) -> None:
        """Warn about dynamic bodies that the paper's potential would hold above a support by
        more than a tenth of their own radius (about sqrt(100 mu / (m g)), see
        ``contact_stiffness``): a mu chosen for heavier bodies makes light ones float or be
        thrown up, which no error reports. With the ipc baseline, about
        _IPC_GAP_FACTOR mu ipc_dhat^4 / (m g), and only bodies it presses too close are named:
        at the default mu 1e-6 a 32 kg box sank to 6e-17 m, where every step failed to
        converge."""
        weight = float(np.linalg.norm(self.gravity))
        if weight == 0.0 or self.contact_mode not in ("bsh", "brute", "ipc"):
            return
        ipc = self.contact_mode == "ipc"
        # Without a support there is nothing to rest on (a lone body, a hanging chain): a
        # support is a static body or a body jointed to the world (a table on a rail), other
        # than those of the body's own joint tree (a lone pendulum was warned of by its hinge).
        tree = connected_labels(len(self._bodies), [(joint.parent, joint.child) for joint in self._joints if joint.parent >= 0])
        anchored_trees = {tree[joint.child] for joint in self._joints if joint.parent < 0}
        any_static = any(body.static for body in self._bodies)
        floating, pressed = [], []
        for b, (body, radius) in enumerate(zip(self._bodies, body_radius)):
            if body.static or not (any_static or anchored_trees - {tree[b]}):
                continue
            gap = _IPC_GAP_FACTOR * self.contact_stiffness * self.ipc_dhat**4 / (body.mass * weight) if ipc else float(np.sqrt(100.0 * self.contact_stiffness / (body.mass * weight)))
            described = f"{body.name!r} (mass {body.mass:.3g} kg, radius {radius:.3g} m: ~{gap:.2g} m)"
            if gap > 0.1 * radius and not ipc:
                floating.append(described)
            elif gap < PRESSED_GAP * radius:
                pressed.append(described)
        for bodies, what, advice in (
            (floating, "holds these bodies above a support by more than a tenth of their radius", "choose mu for the lightest resting body"),
            # A 1 m, 1,000 kg cube dropped at mu 1e-12 (gap ~1e-7 m, 1.2e-7 of its radius) stalled Newton
            # at its impact with "no convergence"; at 1e-11 it lands.
            (pressed, f"lets these bodies rest closer than {PRESSED_GAP:g} of their radius to a support, where Newton may not converge at impacts", "choose mu for the heaviest resting body"),
        ):
            if bodies:
                estimate = (
                    f"the ipc barrier's resting gap ~{_IPC_GAP_FACTOR:g} mu ipc_dhat^4 / (m g)"
                    if ipc
                    else "resting gap ~sqrt(100 mu / (m g)) on a support of few triangles; finely tessellated ones hold bodies higher"
                )
                warnings.warn(
                    f"contact_stiffness {self.contact_stiffness:g} {what} ({estimate}): "
                    f"{', '.join(bodies[:5])}{' ...' if len(bodies) > 5 else ''}; {advice} (the gap scales as {'mu' if ipc else 'sqrt(mu)'})",
                    stacklevel=3,
                )

    def finalize(self, *, device="cpu") -> Model:
        """The ``Model`` of the bodies and joints added, its arrays on ``device`` ("cpu",
        "cuda:0", or a ``wp.Device``): float64 poses (nbodies, 7), masses (kg), inertias
        (kg m^2) and PD gains, the contact model (sphere trees) and the articulation. Raises
        ValueError for a builder without bodies or a device Warp does not have."""
        if not self._bodies:
            raise ValueError("ModelBuilder: no bodies were added")
        dev = resolve_device(device)
        bodies = self._bodies
        names = [b.name for b in bodies]
        for kind, given in (("body", names), ("joint", [j.name for j in self._joints])):
            repeated = sorted(name for name, count in Counter(given).items() if count > 1)
            if repeated:
                raise ValueError(f"ModelBuilder: {kind} names must be unique; used more than once: {repeated}")
        meshes = [(b.vertices, b.faces) for b in bodies]
        static = [b.static for b in bodies]
        initial_q = np.array([b.pose for b in bodies])
        body_radius = np.array([np.linalg.norm(b.vertices, axis=1).max() for b in bodies])
        self._warn_floating_bodies(body_radius)
        articulation = ArticulationModel(self._joints, body_names=names, body_static=static, body_poses=initial_q, body_radius=body_radius)
        exclude = np.array(self._excluded_pairs(), dtype=np.int64).reshape(-1, 2)
        if self.contact_mode == "ipc":
            from .ipc import IpcContactModel

            contact = IpcContactModel(meshes, dhat=self.ipc_dhat, static=static, names=names, device=dev, exclude_pairs=exclude)
        else:
            contact = ContactModel(meshes, eps=self.eps, centred_weight=self.centred_weight, mode=self.contact_mode, leaf_precision=self.leaf_precision, dhat=self.sdrs_dhat, static=static, names=names, device=dev, exclude_pairs=exclude)
        with wp.ScopedDevice(dev):
            return Model(
                body_names=names,
                body_mass=wp.array([b.mass for b in bodies], dtype=wp.float64, requires_grad=True),
                body_unit_second_moment=wp.array(np.array([b.second_moment / b.mass for b in bodies]), dtype=wp.mat33d),
                body_dynamic=wp.array([0 if b.static else 1 for b in bodies], dtype=wp.int32),
                body_kp_linear=wp.array(np.array([b.kp_linear for b in bodies]), dtype=wp.vec3d),
                body_kd_linear=wp.array(np.array([b.kd_linear for b in bodies]), dtype=wp.vec3d),
                body_kp_angular=wp.array([b.kp_angular for b in bodies], dtype=wp.float64),
                body_kd_angular=wp.array([b.kd_angular for b in bodies], dtype=wp.float64),
                body_radius=body_radius,
                body_center_of_mass=np.array([b.center_of_mass for b in bodies]),
                body_meshes=[(b.vertices, b.faces) for b in bodies],
                gravity=self.gravity.copy(),
                contact_stiffness=wp.array([self.contact_stiffness], dtype=wp.float64, requires_grad=True),
                # Without friction its gradient costs a friction evaluation a taped step: asked
                # for by setting requires_grad (ImplicitSolver._friction_rate_frame).
                friction=wp.array([self.friction], dtype=wp.float64, requires_grad=self.friction > 0),
                friction_smoothing=self.friction_smoothing,
                contact=contact,
                initial_q=initial_q,
                articulation=articulation,
                device=dev,
            )

    def _excluded_pairs(self) -> list[tuple[int, int]]:
        """Body pairs without contact, from ``articulation_contact``. A static parent counts
        as a link of its joint (a robot's fixed base), but does not join the articulations
        fixed to it into one: under ``"none"`` it is excluded from contact with each of them."""
        links = [(parent, j.child) for parent, j in zip(self._joint_parents, self._joints) if parent >= 0]
        if self.articulation_contact == "all" or not links:
            return []
        if self.articulation_contact == "nonadjacent":
            return sorted({(min(a, b), max(a, b)) for a, b in links})
        static = [body.static for body in self._bodies]
        group = connected_labels(len(self._bodies), [(parent, child) for parent, child in links if not static[parent]])
        members = {}
        for b in range(len(self._bodies)):
            if not static[b]:
                members.setdefault(group[b], []).append(b)
        pairs = {(a, b) for group_members in members.values() for i, a in enumerate(group_members) for b in group_members[i + 1 :]}
        pairs |= {(min(parent, b), max(parent, b)) for parent, child in links if static[parent] for b in members[group[child]]}
        return sorted(pairs)
