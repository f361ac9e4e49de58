"""Body-level contact potential: sphere trees, pair lists, leaf solves and blend reduction.

``ContactModel`` evaluates the scene potential sum over body pairs of P(a, b) with its
exact gradient and Hessian in rigid-body coordinates, in one of these modes:

- ``"bsh"``: the paper's hierarchical potential P_BSH (eq. BSH-potential), evaluated from
  far / blend / leaf term lists that a load-balanced traversal kernel emits in rounds.
- ``"brute"``: the O(T^2) reference sum of exact leaf potentials (eq. potential-slow).
- ``"sdrs"``: the SDRS baseline (Ye et al. 2024): the same separating-plane leaf problem
  with a locally supported log barrier of support ``dhat`` on unit-normal plane gaps
  (``kernels/leaf.py``), summed over the triangle pairs the traversal finds within 2 dhat
  (sphere-tree broad phase, no far or blend terms); exactly zero beyond.

Each mode is a pair-list builder feeding the same term kernels. The IPC baseline is not a
mode: ``IpcContactModel`` (``ipc.py``) evaluates through ipctk on the host, with the same
interface.

Friction (``friction_frame``, ``friction_terms``, ``friction_adjoint``; the law is in
``kernels/friction.py``) takes its lagged normal forces and normals from each mode's own leaf
potential, so the modes differ only in the normal contact potential.
"""

import collections
import functools
import os
from dataclasses import dataclass, field, replace

import numpy as np
import warp as wp

from .kernels import friction as friction_kernels
from .kernels import reduction as reduction_kernels
from .kernels import rigid as rigid_kernels
from .kernels import traversal as traversal_kernels
from ._runtime import HostReadback, LaunchCache, host_buffer, resolve_device, run_concurrently
from ._validate import QUATERNION_TOLERANCE, as_float64_array, blend_eps_problem, check_barrier_support, check_count, checked_flag, is_positive_finite, is_real, is_whole, scale_problem, validated_poses, validated_step
from .leaf import DEFAULT_MAX_ITERATIONS, LeafStatus, float32_search
from .rotation import rigid_step_travel
from .sphere_tree import SphereTree, tree_of_validated_mesh, validated_mesh

__all__ = ["CENTRED_WEIGHTS", "ContactEvaluation", "ContactModel", "CONTACT_MODES", "LaggedFriction", "QUATERNION_TOLERANCE", "TermLists", "symmetric_from_upper"]

CONTACT_MODES = ("bsh", "brute", "sdrs")
# How a cluster pair's centred term counts (ContactModel, centred_weight).
CENTRED_WEIGHTS = ("paper", "pairs")

# Why a leaf plane search fails in practice, for errors about unsolved pairs: a gap so far
# below the triangles' size that the plane Hessian's stiff and soft directions are ~1e16
# apart even in the pair's own frame (coplanar parallel edges 1e-9 of their size apart,
# turned; a box's face 1e-14 of its size over a table; docs/architecture.md, "The leaf
# potential").
# Resting gaps below this fraction of a body's radius make its impacts too stiff for Newton
# (the builder warns of them).
PRESSED_GAP = 2e-7
# Where bodies rest: a weight far beyond the contact stiffness presses them closer than any start.
PRESSED_GAP_HINT = f"a body of mass m rests ~sqrt(100 mu / (m g)) m above its support; the builder warns when that is below {PRESSED_GAP:g} of its radius"
UNSOLVED_HINT = (
    "their leaf plane searches did not converge, most likely because they are closer than float64 resolves against "
    "their triangles' size (a gap below about 1e-9 of it); start them farther apart, raise the contact stiffness if their "
    f"weight presses them this close ({PRESSED_GAP_HINT}), or split triangles far larger than "
    "the bodies on them. Bodies far below a micrometre "
    "meet this at any gap (the search is sized for 1e-6 m and up; docs/architecture.md, 'Its length scale'), and so do "
    "triangles more than 1e27 m apart"
)

_MAX_TRAVERSAL_ATTEMPTS = 8
# Body pairs whose walks the starting task lists can hand on in full (``_upload_model``).
_START_BUSY_PAIRS = 64
# Evaluations with fewer leaf terms than this per chunk are not split (``term_chunks``).
_MIN_CHUNK_LEAF_TERMS = 1024
# Body pairs dealt one by one to the cheapest chunk (``_deal_seed_chunks``); the lighter ones
# after them are dealt in a vectorised snake order: dealing all 79,800 pairs of 400 bodies
# one by one took 14 ms, and made the split evaluation slower than the unsplit one.
_EXACT_DEAL_PAIRS = 1024
# Relative cost of a leaf, far and blend term on a CPU (measured at 6,208 triangles), by
# which body pairs are dealt out to chunks.
_TERM_COSTS = (18.0, 1.0, 2.0)
# Counter slot of traversal round 0's handed-on tasks; round r uses the slot r after it.
_ROUND_SLOT = int(traversal_kernels.COUNTER_ROUND_TASKS)


# Bodies clustered this far out (m, per axis) are evaluated about a nearby whole-metre origin
# instead of the caller's (``ContactModel._local_poses``).
_FAR_ORIGIN = 1024.0


@dataclass(frozen=True)
class ContactEvaluation:
    """Scene contact potential at one configuration.

    Attributes:
        value: total potential (1/m, as its leaf barriers 1/g; the ipc model's is ipctk's barrier on squared
            distances, in m^4; scaled by the contact stiffness in the step);
            +inf when any two bodies touch or intersect, or a leaf solve did not converge
            (``unsolved_pairs``).
        grad: (nbodies, 6) dP/d(dp, dtheta) per body; zero rows for static bodies.
        hessian: (6 m, 6 m) second derivatives in the same coordinates of the m non-static
            bodies (``ContactModel.hessian_bodies``, in index order): static bodies have no
            rows, so a scene of many static bodies costs no (6 nbodies)^2 matrix.
            Where ``value`` is +inf the potential has no derivative: ``grad`` and ``hessian``
            then hold the sums over the other, finite terms only (each touching or unsolved
            triangle pair adds zero), no force of the scene; check ``ok`` or ``value`` first.
        num_far, num_blend, num_leaf: term counts (centred-only, blend records, leaf solves);
            in ``"sdrs"`` mode num_far counts the pruned cluster pairs (no potential).
        contact_pairs: (name_a, name_b) of body pairs with a touching or intersecting
            triangle pair.
        unsolved_pairs: (name_a, name_b) of body pairs where a leaf solve did not converge.
        mean_leaf_iterations: mean Newton iterations per leaf solve.
        pair_separation: (npairs,) lower bound on the surface distance of each body pair in
            ``ContactModel.body_pairs`` (m); 0 on contact. Bounds how far bodies may move
            before they could touch (conservative advancement).
    """

    value: float
    grad: np.ndarray
    hessian: np.ndarray
    num_far: int
    num_blend: int
    num_leaf: int
    contact_pairs: list
    unsolved_pairs: list
    mean_leaf_iterations: float
    pair_separation: np.ndarray

    @property
    def ok(self) -> bool:
        """True when the potential is finite and every leaf solve converged."""
        return not self.contact_pairs and not self.unsolved_pairs


def _read_only(attribute: str, doc: str) -> property:
    """A read-only property returning ``attribute``."""
    return property(lambda self: getattr(self, attribute), doc=doc)


def _static_flags(static, num_bodies: int) -> np.ndarray:
    """(num_bodies,) bool flags from ``static`` (None: all dynamic); entries must be bools or 0/1."""
    if static is None:
        return np.zeros(num_bodies, dtype=bool)
    flags = np.asarray(static, dtype=object)
    if flags.shape != (num_bodies,):
        raise ValueError(f"static: expected {num_bodies} flags, got shape {flags.shape}")
    return np.array([checked_flag(flag, f"static: entry {i}") for i, flag in enumerate(flags)], dtype=bool)


def checked_bodies(meshes, names, static) -> tuple[list, list, np.ndarray]:
    """(meshes as validated (float64 vertices, int64 faces) pairs, one name per body, static
    flags) of a contact model's arguments; ValueError naming the argument and body. One rule
    for every contact model (the IPC baseline took a face index past its vertices into ipctk,
    which crashed the process)."""
    try:
        meshes = list(meshes)
    except TypeError:  # None was "'NoneType' object is not iterable" (a probe, stop 64)
        raise ValueError(f"meshes: expected a list of (vertices, faces) pairs, one per body, got {type(meshes).__name__}") from None
    if len(meshes) < 1:
        raise ValueError("meshes: need at least one body")
    if isinstance(names, str):  # it was read as one name per character
        raise ValueError(f"names: expected one name per body, got the string {names!r}")
    names = [f"body{i}" for i in range(len(meshes))] if names is None else [str(n) for n in names]
    if len(names) != len(meshes):
        raise ValueError(f"names: {len(names)} names for {len(meshes)} bodies")
    repeated = sorted(n for n, count in collections.Counter(names).items() if count > 1)
    if repeated:
        raise ValueError(f"names: {repeated[0]!r} names more than one body; contact_pairs could not tell them apart")
    checked = []
    for i, mesh in enumerate(meshes):
        try:
            vertices, faces = mesh
        except (TypeError, ValueError):
            raise ValueError(f"meshes[{i}] ({names[i]}): expected a (vertices, faces) pair") from None
        checked.append(validated_mesh(vertices, faces, names[i]))
    return checked, names, _static_flags(static, len(meshes))


def hessian_slots(static: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the non-static bodies in index order, whose 6 x 6 blocks the contact and friction
    Hessians hold; each body's block index, -1 for a static body, which has none). One rule
    for every contact model."""
    bodies = np.flatnonzero(~np.asarray(static, dtype=bool))
    slot = np.full(len(static), -1, dtype=np.int32)
    slot[bodies] = np.arange(len(bodies), dtype=np.int32)
    return bodies, slot


def _leading_rows(array: wp.array, count: int) -> wp.array:
    """A device copy of the first ``count`` rows of ``array``. Warp cannot slice an array of
    no rows (brute force over static bodies alone allocates its lists empty)."""
    return wp.clone(array[:count]) if count else wp.empty(0, dtype=array.dtype, device=array.device)


def _copy_evaluation(result: ContactEvaluation) -> ContactEvaluation:
    """A copy whose arrays and lists the caller may change without touching ``result``."""
    return replace(
        result,
        grad=result.grad.copy(),
        hessian=result.hessian.copy(),
        contact_pairs=list(result.contact_pairs),
        unsolved_pairs=list(result.unsolved_pairs),
        pair_separation=result.pair_separation.copy(),
    )


@dataclass(frozen=True)
class LaggedFriction:
    """Friction data of one time step, lagged at its start configuration q^t.

    Attributes:
        pairs: contact pairs with lagged data (leaf pairs, or ipc's active collisions).
        mu: contact stiffness the normal forces were computed with.
        friction: (1,) friction coefficient lambda (the model's array).
        slip_smoothing: e = v_eps dt (m), the slip below which the Coulomb law is smoothed.
        data: the contact model's own lagged data (a ``FrictionFrame``, or ipctk's
            tangential collisions).
    """

    pairs: int
    mu: float
    friction: wp.array
    slip_smoothing: float
    data: object
    # id() of the contact model that made it: another model's data indexed this model's pairs
    # and bodies (a probe, stop 64: friction 3,492 where this model's was 0).
    model_id: int = field(default=0, compare=False, repr=False)


@dataclass(frozen=True)
class AdvancementFrame:
    """Body transforms, term lists and body-pair separations of one configuration, for
    conservative advancement."""

    rotation: wp.array
    position: wp.array
    far: wp.array
    num_far: int
    leaf: wp.array
    leaf_plane: wp.array
    num_leaf: int
    seed_separation: wp.array
    pair_separation: np.ndarray  # host copy of seed_separation
    # id() of the contact model that made it (another model's bounded a step by -0.915; a probe, stop 64).
    model_id: int = field(default=0, compare=False, repr=False)


@dataclass(frozen=True)
class TermLists:
    """Term lists of one configuration (numpy copies, for inspection and tests).

    far: (F, 4) rows (node_a, node_b, parent blend record, body pair); blend: (Bl, 4) same
    layout with blend_level (Bl,); leaf: (L, 4) rows (triangle_a, triangle_b, parent, body
    pair). Node and triangle indices are global (``ContactModel.node_offset`` /
    ``triangle_offset`` per body); body pairs index ``ContactModel.body_pairs``.
    """

    far: np.ndarray
    blend: np.ndarray
    blend_level: np.ndarray
    leaf: np.ndarray


def symmetric_from_upper(upper: np.ndarray) -> np.ndarray:
    """The symmetric matrix whose upper triangle the term kernels accumulated (they add one
    of each pair of mirrored entries: ``kernels/rigid.py``, ``upper_entry``)."""
    full = upper + upper.T
    np.fill_diagonal(full, upper.diagonal())
    return full


def contact_body_pairs(static: np.ndarray, exclude_pairs=()) -> np.ndarray:
    """(npairs, 2) body pairs a < b with contact: not both static, not excluded."""
    n = len(static)
    excluded = _excluded_pair_keys(exclude_pairs, n)
    # By rows, in time and memory proportional to the pairs kept: a Python walk over all
    # n^2 / 2 pairs took 154 ms at 2,049 bodies, and a mask over them 1.45 GB at 10,000.
    static = np.asarray(static, dtype=bool)
    dynamic = np.flatnonzero(~static)
    rows = []
    for a in range(n):
        partners = dynamic[np.searchsorted(dynamic, a, side="right") :] if static[a] else np.arange(a + 1, n)
        rows.append(np.column_stack([np.full(len(partners), a), partners]))
    pairs = np.concatenate(rows) if rows else np.zeros((0, 2), dtype=np.int64)
    if len(excluded):
        pairs = pairs[~np.isin(pairs[:, 0] * n + pairs[:, 1], excluded)]
    return pairs.astype(np.int32).reshape(-1, 2)


def _excluded_pair_keys(exclude_pairs, n: int) -> np.ndarray:
    """min(a, b) n + max(a, b) of each pair in ``exclude_pairs``, or ValueError naming the
    first pair that is not two distinct body indices in [0, n). An integer numpy array of
    pairs (the builder's) is taken as it is; anything else is first read pair by pair, so
    that a list holding True or 0.7 is refused, not made an integer array. The range and
    distinctness checks then run on the whole array: pair by pair, an articulation of 1,050
    links with contact off inside it (550,000 excluded pairs) took 3.3 s."""
    array = exclude_pairs
    if not (isinstance(array, np.ndarray) and array.dtype.kind in "iu" and array.ndim == 2 and array.shape[1] == 2):
        try:
            pairs = [tuple(pair) for pair in exclude_pairs]
        except TypeError:
            raise ValueError(f"exclude_pairs: expected a sequence of (a, b) body index pairs, got {exclude_pairs!r}") from None
        for pair in pairs:
            if len(pair) != 2 or not all(is_whole(i) for i in pair):
                raise ValueError(f"exclude_pairs: {pair!r} is not a pair of distinct body indices in [0, {n})")
        array = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    bad = np.flatnonzero((array < 0).any(axis=1) | (array >= n).any(axis=1) | (array[:, 0] == array[:, 1]))
    if bad.size:
        pair = tuple(array[bad[0]].tolist())
        raise ValueError(f"exclude_pairs: {pair!r} is not a pair of distinct body indices in [0, {n})")
    return np.minimum(array[:, 0], array[:, 1]).astype(np.int64) * n + np.maximum(array[:, 0], array[:, 1])


def check_own(value, kind: type, label: str, model) -> None:
    """ValueError naming ``label`` unless ``value`` is a ``kind`` (a ``LaggedFriction`` or an
    ``AdvancementFrame``) that ``model`` made: another object failed deep inside (an
    AttributeError, a KeyError), and another model's data gave wrong numbers."""
    if not isinstance(value, kind):
        article = "an" if kind.__name__[0] in "AEIOU" else "a"
        raise ValueError(f"{label}: expected {article} {kind.__name__} of this contact model, got {type(value).__name__}")
    if value.model_id != id(model):
        raise ValueError(f"{label}: this {kind.__name__} is another contact model's; use this model's own")


def checked_adjoint_arguments(q_next, q_now, multiplier, names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``friction_adjoint``'s poses (len(names), 7) and multiplier (len(names), 6) as float64
    arrays, or ValueError naming the argument (strings failed inside Warp's array
    constructor, a short multiplier inside a kernel launch; a probe, stop 64)."""
    q_next = validated_poses(q_next, names, normalize=False, label="q_next")
    q_now = validated_poses(q_now, names, normalize=False, label="q_now")
    multiplier = as_float64_array(multiplier, "multiplier", trailing_shape=(6,))
    if multiplier.shape[0] != len(names):
        raise ValueError(f"multiplier: expected {len(names)} rows (one per body), got {multiplier.shape[0]}")
    return q_next, q_now, multiplier


def check_friction_arguments(mu, friction, slip_smoothing, coefficient=None) -> float:
    """The friction coefficient, after a ValueError naming the argument unless ``mu`` (the
    contact stiffness) and ``slip_smoothing`` (the step's slip length, friction smoothing x
    dt, m) are positive and finite and ``friction`` is the model's one-value float64 array
    holding a coefficient >= 0 (``coefficient``, its value where the caller has it;
    ``friction_frame``: NaN gave NaN friction, mu = -1 a negative energy, a float a Warp error
    from inside a kernel launch). Their ranges are the model settings' (``ImplicitSolver``)."""
    for label, value in (("mu", mu), ("slip_smoothing", slip_smoothing)):
        if not is_positive_finite(value):
            raise ValueError(f"{label}: must be a positive finite number, got {value!r}")
    if not (isinstance(friction, wp.array) and friction.dtype == wp.float64 and friction.shape == (1,)):
        raise ValueError(f"friction: expected a wp.array of one float64 (the model's friction), got {friction!r}")
    # Its value too (a NaN gave NaN friction, -0.5 a negative one; a probe, stop 64): read
    # here unless the caller has it (the solver reads it back with the step's poses).
    value = float(friction.numpy()[0]) if coefficient is None else coefficient
    if not (is_real(value) and np.isfinite(value) and value >= 0.0):
        raise ValueError(f"friction: the friction coefficient must be >= 0 and finite, got {value!r}")
    return float(value)


class ContactModel:
    """Contact potential between rigid bodies given as triangle meshes in their body frames.

    Args:
        meshes: list of (V, F) per body: V (nv, 3) vertices in the body frame (m), F (nf, 3)
            triangle vertex indices. Every triangle counts, a zero-area one as the segment or
            point it is (``ModelBuilder.add_body`` drops those from a mesh with an area).
        eps: blend margin epsilon > 0 of P_BSH (d2 = (1 + eps) d1); larger is closer to the
            brute-force sum and costlier.
        mode: ``"bsh"``, ``"brute"`` or ``"sdrs"``.
        centred_weight: ``"paper"`` (default): a cluster pair's centred term is the paper's
            P_c; ``"pairs"``: it is weighed by the triangle pairs it stands for, |I| |J| P_c,
            so the blend joins two estimates of the same sum (docs/architecture.md,
            "Centred weights").
        dhat: barrier support (m) of ``"sdrs"``: vertex-to-plane gaps below it are
            penalised, so triangles interact below 2 dhat; unused by the other modes.
        static: optional (nbodies,) booleans; static bodies have no degrees of freedom (no
            rows in the Hessian: ``hessian_bodies``) and pairs of two static bodies are
            skipped.
        names: optional body names used in messages (default ``body<i>``).
        exclude_pairs: optional (a, b) body index pairs without contact (e.g. the two links of
            a joint); they are never visited.
        device: Warp device.
        max_leaf_iterations: Newton iteration cap of each leaf solve.
        leaf_precision: float type of the leaf plane searches, ``"float64"`` (default) or
            ``"float32"`` (modes ``"bsh"`` and ``"brute"``): the search runs in float32 and
            float64 finishes it to the float64 tolerances; every value and derivative is
            evaluated in float64 (docs/architecture.md, "The leaf potential").
        top_replicas: accumulator records per body pair for its top-level terms (None: 1 on
            a CPU; on a GPU up to 32, capped at ~32 MB, which spreads the atomic adds that
            all of a body pair's top-level terms would make to the same addresses). Any
            value gives the same result up to summation order.
        sync_free: launch the traversal rounds and term kernels over their lists' whole
            capacity, the kernels reading the list lengths on the device, so that one
            evaluation waits for the host only once, at its end (None: on a GPU; on a CPU
            each launch is sized by the counted items, which the host reads for free). The
            results are the same up to summation order: on a CPU bit for bit at the same
            traversal visit budget; at the sync-free default (4 visits a round against the
            host-sized 32) they differ in the last digits (measured on push, sort and
            billiards: values 6e-16, Hessians 6e-16 relative).
        term_chunks: on a CPU with host-sized launches, an evaluation with at least
            ``term_chunks`` x 1,024 leaf terms deals its body pairs out to this many chunks
            of about equal cost, and each chunk's far, leaf and blend terms are launched
            from their own thread, one thread per core (Warp runs a CPU launch on its
            launching thread). A body pair's terms add only into its own records, so the
            chunks never write to the same memory, and each record receives its terms in
            the same order as without chunks: results are bit for bit the same for any
            value and any number of cores (None: the number of cores, at most 8; 1 turns
            chunks off).
    """

    # Where this model's conservative advancement holds Newton steps back, it holds a
    # friction-exact direction back about as much as the plain one, so the implicit step skips
    # building it (``solver._FRICTION_MODEL_MIN_ALPHA``).
    crawl_skips_friction_model = True

    def __init__(
        self,
        meshes,
        *,
        eps: float = 0.5,
        mode: str = "bsh",
        centred_weight: str = "paper",
        dhat: float = 1e-2,
        static=None,
        names=None,
        exclude_pairs=(),
        device="cpu",
        max_leaf_iterations: int = DEFAULT_MAX_ITERATIONS,
        leaf_precision: str = "float64",
        top_replicas: int | None = None,
        sync_free: bool | None = None,
        term_chunks: int | None = None,
    ):
        if mode not in CONTACT_MODES:
            raise ValueError(f"mode: {mode!r} is not one of {CONTACT_MODES}")
        if centred_weight not in CENTRED_WEIGHTS:
            raise ValueError(f"centred_weight: {centred_weight!r} is not one of {CENTRED_WEIGHTS}")
        if not is_positive_finite(eps):
            raise ValueError(f"eps: must be a positive finite number, got {eps!r}")
        problem = scale_problem(eps, "") or blend_eps_problem(eps)
        if problem is not None:  # the builder's range, for a ContactModel made directly
            raise ValueError(f"eps: {problem}, got {eps!r}")
        check_barrier_support(dhat)
        for label, count in (("max_leaf_iterations", max_leaf_iterations), ("top_replicas", top_replicas), ("term_chunks", term_chunks)):
            if count is not None or label == "max_leaf_iterations":
                check_count(count, label)
        meshes, self.names, static_flags = checked_bodies(meshes, names, static)
        num_bodies = len(meshes)

        self._mode = mode
        self._centred_weight = centred_weight
        self._eps = float(eps)
        # The leaf kernels read dhat = 0 as the paper's barrier.
        self._dhat = float(dhat) if mode == "sdrs" else 0.0
        self._max_leaf_iterations = int(max_leaf_iterations)
        self._leaf_precision = leaf_precision
        self._float32_search = float32_search(leaf_precision, mode=mode)
        self.num_bodies = num_bodies
        self.static = static_flags
        # The bodies the Hessians hold, in index order: 6 rows and columns each.
        self.hessian_bodies, self._hessian_slot_host = hessian_slots(static_flags)
        self._hessian_shape = (6 * len(self.hessian_bodies), 6 * len(self.hessian_bodies))
        self.device = resolve_device(device)
        self.sync_free = (not self.device.is_cpu) if sync_free is None else checked_flag(sync_free, "sync_free")
        # Launches sized on the device cannot be split on the host.
        self._term_chunks = 1 if (self.sync_free or not self.device.is_cpu) else (min(os.cpu_count() or 1, 8) if term_chunks is None else int(term_chunks))
        self._min_chunk_leaf_terms = _MIN_CHUNK_LEAF_TERMS  # tests lower it to split small scenes
        self._exact_deal_pairs = _EXACT_DEAL_PAIRS  # and this one to deal small scenes in snake order

        trees, triangles = [], []
        for vertices, faces in meshes:
            trees.append(tree_of_validated_mesh(vertices, faces))
            triangles.append(vertices[faces])
        self.trees: list[SphereTree] = trees
        self.node_offset = np.cumsum([0] + [t.num_nodes for t in trees])[:-1].astype(np.int32)
        self.triangle_offset = np.cumsum([0] + [t.num_triangles for t in trees])[:-1].astype(np.int32)
        self.body_pairs = contact_body_pairs(static_flags, exclude_pairs)
        if top_replicas is None:
            # A CPU thread never contends.
            top_replicas = 1 if self.device.is_cpu else max(1, min(32, (1 << 22) // (reduction_kernels.RECORD_ENTRIES * max(1, len(self.body_pairs)))))
        self._top_replicas = int(top_replicas)
        self._top_entries_per_thread = reduction_kernels.RECORD_ENTRIES if self.device.is_cpu else 1
        self._upload_model(trees, triangles)

    # The settings are read-only: a CUDA graph and the recorded launches hold them, and a
    # changed eps gave the old potential back from evaluate(reuse=True).
    mode = _read_only("_mode", 'The contact model: "bsh", "brute" or "sdrs" (``CONTACT_MODES``).')
    centred_weight = _read_only("_centred_weight", "The far terms' weights (``CENTRED_WEIGHTS``).")
    eps = _read_only("_eps", "The blend margin: node pairs farther than (1 + eps) (R_I + R_J) are far terms.")
    dhat = _read_only("_dhat", "SDRS's barrier support (m); 0 for the paper's barrier.")
    max_leaf_iterations = _read_only("_max_leaf_iterations", "Newton iteration cap of each leaf plane search.")
    leaf_precision = _read_only("_leaf_precision", "The leaf plane search's float type (``LEAF_PRECISIONS``).")

    # --- set-up ---------------------------------------------------------------------------

    def _upload_model(self, trees, triangles):
        def shifted(index, offset):
            return np.where(index >= 0, index + offset, -1).astype(np.int32)

        left = np.concatenate([shifted(t.left, o) for t, o in zip(trees, self.node_offset)])
        right = np.concatenate([shifted(t.right, o) for t, o in zip(trees, self.node_offset)])
        tri = np.concatenate([shifted(t.triangle, o) for t, o in zip(trees, self.triangle_offset)])
        max_depth = max(t.max_depth for t in trees)
        self._max_rounds = max_depth + 1  # the traversal's bound (kernels/traversal.py)
        with wp.ScopedDevice(self.device):
            self._node_center = wp.array(np.concatenate([t.centers for t in trees]), dtype=wp.vec3d)
            self._node_radius = wp.array(np.concatenate([t.radii for t in trees]), dtype=wp.float64)
            # How far from its centre of mass any node sphere of a body reaches (m): child spheres
            # may stick out of their parents', so the maximum over all nodes.
            self._body_reach_host = np.array([float((np.linalg.norm(t.centers, axis=1) + t.radii).max()) for t in trees])
            self._body_reach = wp.array(self._body_reach_host, dtype=wp.float64)
            weights = [t.triangle_count if self._centred_weight == "pairs" else np.ones(t.num_nodes) for t in trees]
            self._node_weight = wp.array(np.concatenate(weights).astype(np.float64), dtype=wp.float64)
            self._node_left = wp.array(left, dtype=wp.int32)
            self._node_right = wp.array(right, dtype=wp.int32)
            self._node_triangle = wp.array(tri, dtype=wp.int32)
            # Round 0 of the traversal: one task per body pair, its two roots at top level.
            roots = self.node_offset[self.body_pairs].reshape(-1, 2)
            root_task = np.column_stack([roots, np.full((len(roots), 1), -1), np.zeros((len(roots), 1))]).astype(np.int32)
            self._root_task = wp.array(root_task.reshape(-1, 4), dtype=wp.vec4i)
            self._root_task_seed = wp.array(np.arange(len(roots), dtype=np.int32), dtype=wp.int32)
            self._triangle_vertices = wp.array(np.concatenate(triangles), dtype=wp.mat33d)
            self._body_dynamic = wp.array((~self.static).astype(np.int32), dtype=wp.int32)
            self._hessian_slot = wp.array(self._hessian_slot_host, dtype=wp.int32)
            self._seed_body_pair = wp.array(self.body_pairs, dtype=wp.vec2i)
            self._pose = wp.empty(self.num_bodies, dtype=wp.transformd)
            self._step = wp.empty(self.num_bodies, dtype=rigid_kernels.vec6d)
            self._rotation = wp.empty(self.num_bodies, dtype=wp.mat33d)
            self._position = wp.empty(self.num_bodies, dtype=wp.vec3d)
            self._friction_pose = wp.empty(self.num_bodies, dtype=wp.transformd)
            self._friction_rotation = wp.empty(self.num_bodies, dtype=wp.mat33d)
            self._friction_position = wp.empty(self.num_bodies, dtype=wp.vec3d)
            # The traversal ends within max_depth + 1 rounds (kernels/traversal.py): one task
            # counter per round.
            self._counters = wp.zeros(_ROUND_SLOT + max_depth + 1, dtype=wp.int32)
            self._seed_status = wp.zeros(len(self.body_pairs), dtype=wp.int32)
            self._seed_separation = wp.zeros(len(self.body_pairs), dtype=wp.float64)
            # Host copy of _seed_separation, written by evaluate; None while the buffers hold no
            # evaluation's planes (before the first, or after term_lists).
            self._pair_separation: np.ndarray | None = None
            # (validated poses, result) of the last evaluate while the buffers still hold its
            # term lists, planes and transforms; None once anything else overwrote them.
            self._last_evaluation: tuple[np.ndarray, ContactEvaluation] | None = None
            self._total_value = wp.zeros(1, dtype=wp.float64)
            self._total_grad = wp.zeros((self.num_bodies, 6), dtype=wp.float64)
            self._total_hess = wp.zeros(self._hessian_shape, dtype=wp.float64)
        # Uploads go through host buffers and results come back through one readback, so
        # an evaluation waits for the device once (and a CUDA graph holds the copies).
        self._pose_host = host_buffer(self.num_bodies, wp.transformd, self.device)
        self._friction_pose_host = host_buffer(self.num_bodies, wp.transformd, self.device)
        # Where the kernels' world frame sits in the caller's (m, per axis): set by the first
        # poses given (``_local_poses``).
        self._origin: np.ndarray | None = None
        self._step_host = host_buffer(self.num_bodies, rigid_kernels.vec6d, self.device)
        self._readback = HostReadback(self.device)
        self._launches = LaunchCache(self.device)
        # Node pairs one traversal thread visits per round (tests lower it to force rounds).
        self._visit_budget = traversal_kernels.SYNC_FREE_VISIT_BUDGET if self.sync_free else traversal_kernels.HOST_SIZED_VISIT_BUDGET
        self._traversal_rounds = 0
        self._graph = None
        self._far = self._blend = self._leaf = self._blend_level = None
        self._tasks = self._task_seeds = None
        self._leaf_iterations = self._leaf_plane = None
        self._alpha = wp.zeros(self._term_chunks, dtype=wp.float64, device=self.device)
        # Chunk of each body pair (term_chunks) and how many chunks the last evaluation used.
        self._seed_chunk = wp.zeros(len(self.body_pairs), dtype=wp.int32, device=self.device)
        self._seed_chunk_count = 1
        self._records = None
        self._friction_records = None  # (records, totals), allocated by the first friction_terms
        self._friction_graphs = (None, {})  # (the LaggedFriction they belong to, {at_poses: graph})
        self._queued_friction = None  # the LaggedFriction whose terms the last evaluation queued
        if self._mode == "brute":
            self._set_brute_leaf_list()
        else:
            # Starting sizes; an evaluation that needs more grows them (``_fill_lists``). Far
            # terms are not reserved per body pair and triangle: 120 bodies of 1,280 triangles
            # would take 1.1 GB for the 7,140 far terms they need apart.
            per_pair = 8 * max(t.num_triangles for t in trees)
            self._reserve_lists(far=per_pair + 16 * len(self.body_pairs), blend=per_pair, leaf=per_pair)
            # Nor are tasks: round 0 reads the root tasks, and only a body pair whose walk outlasts
            # one visit budget hands any on (3 x budget + 1 at most). Reserved per body pair,
            # 1,000 boxes 3 m apart took 48M tasks (1.9 GB, 5 s to zero) for the 17k a round needed.
            self._reserve_tasks((3 * self._visit_budget + 1) * min(max(1, len(self.body_pairs)), _START_BUSY_PAIRS))

    def _set_brute_leaf_list(self):
        rows = []
        for seed, (a, b) in enumerate(self.body_pairs):
            ta = np.arange(self.trees[a].num_triangles) + self.triangle_offset[a]
            tb = np.arange(self.trees[b].num_triangles) + self.triangle_offset[b]
            grid_a, grid_b = np.meshgrid(ta, tb, indexing="ij")
            block = np.empty((grid_a.size, 4), dtype=np.int32)
            block[:, 0] = grid_a.ravel()
            block[:, 1] = grid_b.ravel()
            block[:, 2] = -1
            block[:, 3] = seed
            rows.append(block)
        leaf = np.concatenate(rows) if rows else np.zeros((0, 4), dtype=np.int32)
        with wp.ScopedDevice(self.device):
            self._leaf = wp.array(leaf, dtype=wp.vec4i)
            self._far = wp.zeros(0, dtype=wp.vec4i)
            self._blend = wp.zeros(0, dtype=wp.vec4i)
            self._blend_level = wp.zeros(0, dtype=wp.int32)
            self._leaf_iterations = wp.zeros(len(leaf), dtype=wp.int32)
            self._leaf_plane = wp.zeros(len(leaf), dtype=wp.vec4d)
        # The list never changes: its counter is set once and never cleared.
        counters = np.zeros(self._counters.shape[0], dtype=np.int32)
        counters[int(traversal_kernels.COUNTER_LEAF)] = len(leaf)
        self._counters.assign(counters)
        self._counts = (0, 0, len(leaf), -1)
        self._reserve_records(0)

    def _reserve_lists(self, *, far: int, blend: int, leaf: int):
        """Grows the term lists to hold ``far``, ``blend`` and ``leaf`` terms. A list and its
        companions (levels and records, iterations and planes) are allocated first and then
        replaced together: replaced one by one, an allocation that failed (MemoryError) left a
        longer list beside shorter companions, which the next evaluation's kernels wrote past
        (a segfault)."""
        self._graph = None
        with wp.ScopedDevice(self.device):
            far_list = wp.zeros(far, dtype=wp.vec4i) if self._far is None or self._far.shape[0] < far else self._far
            if self._blend is None or self._blend.shape[0] < blend:
                blend_lists = (wp.zeros(blend, dtype=wp.vec4i), wp.zeros(blend, dtype=wp.int32), self._new_records(blend))
            else:
                blend_lists = (self._blend, self._blend_level, self._records)
            if self._leaf is None or self._leaf.shape[0] < leaf:
                leaf_lists = (wp.zeros(leaf, dtype=wp.vec4i), wp.zeros(leaf, dtype=wp.int32), wp.zeros(leaf, dtype=wp.vec4d))
            else:
                leaf_lists = (self._leaf, self._leaf_iterations, self._leaf_plane)
        self._far, (self._blend, self._blend_level, self._records), (self._leaf, self._leaf_iterations, self._leaf_plane) = far_list, blend_lists, leaf_lists

    def _reserve_tasks(self, count: int):
        """Two task lists of at least ``count``: traversal rounds read one and fill the other."""
        self._graph = None
        if self._tasks is None or self._tasks[0].shape[0] < count:
            with wp.ScopedDevice(self.device):
                self._tasks = [wp.zeros(count, dtype=wp.vec4i) for _ in range(2)]
                self._task_seeds = [wp.zeros(count, dtype=wp.int32) for _ in range(2)]

    def _reserve_records(self, count: int):
        """Accumulator records (``kernels/reduction.py``, ``Targets``): ``count`` blend
        records, then the body pairs' top-level replicas."""
        self._graph = None
        self._records = self._new_records(count)

    def _new_records(self, blend_records: int) -> reduction_kernels.Targets:
        """``blend_records`` blend records (value, gradient, weight), then ``top_replicas``
        top-level records per body pair (value, gradient, Hessian), zeroed."""
        top = len(self.body_pairs) * self._top_replicas
        t = reduction_kernels.Targets()
        with wp.ScopedDevice(self.device):
            t.record_value = wp.zeros(blend_records + top, dtype=wp.float64)
            t.record_grad = wp.zeros((blend_records + top, 12), dtype=wp.float64)
            t.record_hess = wp.zeros((top, 12, 12), dtype=wp.float64)
            t.record_weight = wp.zeros(blend_records, dtype=wp.float64)
        t.top_record = blend_records
        t.top_replicas = self._top_replicas
        t.body_dynamic = self._body_dynamic
        t.hessian_slot = self._hessian_slot
        return t

    def _launch_top_level_sum(self, site: str, records: reduction_kernels.Targets, totals_out):
        """Sums the body pairs' top-level records into ``totals_out`` (value, gradient,
        upper-triangle Hessian), which the caller has zeroed."""
        if len(self.body_pairs):
            self._launches.launch(
                site,
                reduction_kernels.top_level_kernel,
                dim=(len(self.body_pairs), reduction_kernels.RECORD_ENTRIES // self._top_entries_per_thread),
                inputs=[self._seed_body_pair, self._top_entries_per_thread, records],
                outputs=list(totals_out),
            )

    # --- evaluation -------------------------------------------------------------------------

    def _validated_poses(self, poses, *, normalize: bool = True) -> np.ndarray:
        return validated_poses(poses, self.names, normalize=normalize)

    def _local_poses(self, poses: np.ndarray) -> np.ndarray:
        """``poses`` with their positions in the kernels' world frame: the caller's, moved on
        each axis where every body of the first poses given lies ``_FAR_ORIGIN`` m or more
        out, all within a quarter of their distance from the caller's origin, to the whole
        metre nearest their mean (fixed from then on); else the caller's, as given. The
        kernels build world vertices as R v + p: 2e4 m out, their rounding (ulp 3.6e-12 m)
        made the step's Newton directions jitter at ~2e-8 m between two colliding cubes, and
        the step failed to converge (a probe, stop 65); p minus a nearby whole number is
        exact, and the potential depends on relative positions only. Bodies nearer the
        caller's origin than the cluster keep it: one body parked 75 km out moved two cubes'
        collision at the origin 25 km off, where it failed (a review, stop 65)."""
        if self._origin is None:
            positions = poses[:, :3]
            centre = np.round(positions.mean(axis=0))
            clustered = np.all(np.abs(positions - centre) <= 0.25 * np.abs(positions), axis=0)
            self._origin = np.where(clustered & (np.abs(centre) >= _FAR_ORIGIN), centre, 0.0)
        if not self._origin.any():
            return poses
        local = poses.copy()
        local[:, :3] -= self._origin
        return local

    def _set_poses(self, poses: np.ndarray):
        """Stages ``poses`` for the next ``_launch_evaluation`` (which uploads them)."""
        self._pose_host.numpy()[:] = self._local_poses(poses)

    def _launch_transforms(self, site: str, pose_host: wp.array, pose: wp.array, rotation_out: wp.array, position_out: wp.array):
        """Uploads staged poses and computes the bodies' rotations and positions from them."""
        wp.copy(pose, pose_host)
        self._launches.launch(site, rigid_kernels.body_transforms_kernel, dim=self.num_bodies, inputs=[pose], outputs=[rotation_out, position_out])

    def _launch_rounds(self):
        """Traversal rounds (``kernels/traversal.py``) at the current poses into the term lists.

        Host-sized: the host reads each round's task count to size the next round and stops
        when none is left or the next task list overflowed. Sync-free: all max_depth + 1
        rounds the walk can need, each over its task list's capacity, counts read on the
        device; nothing waits for the host."""
        self._counters.zero_()
        tasks, task_seeds, num_tasks, task_slot = self._root_task, self._root_task_seed, len(self.body_pairs), -1
        for rounds in range(self._max_rounds):
            if num_tasks == 0:
                break
            slot = _ROUND_SLOT + rounds
            next_tasks, next_task_seeds = self._tasks[rounds % 2], self._task_seeds[rounds % 2]
            # Rounds after the first alternate between the two task lists: one site each.
            self._launches.launch(
                ("round", 0 if rounds == 0 else 1 + rounds % 2),
                traversal_kernels.traverse_round_kernel(self._visit_budget),
                dim=num_tasks,
                inputs=[
                    self._node_center,
                    self._node_radius,
                    self._node_left,
                    self._node_right,
                    self._node_triangle,
                    self._eps,
                    2.0 * self._dhat,
                    self._rotation,
                    self._position,
                    self._seed_body_pair,
                    tasks,
                    task_seeds,
                    task_slot,
                    slot,
                ],
                outputs=[self._counters, self._far, self._blend, self._blend_level, self._leaf, next_tasks, next_task_seeds],
            )
            tasks, task_seeds, task_slot = next_tasks, next_task_seeds, slot
            if self.sync_free:
                num_tasks = next_tasks.shape[0]
            else:
                num_tasks = int(self._counters.numpy()[slot])
                if num_tasks > next_tasks.shape[0]:
                    break  # tasks were dropped: the lists get grown and the traversal rerun

    def _launch_sizes(self, counters: np.ndarray | None) -> tuple[int, int, int, int]:
        """Threads for the far, blend and leaf kernels and the deepest blend level to reduce:
        from the host's read of the ``counters`` (host-sized), or, without one (sync-free),
        the list capacities and the deepest possible level (the kernels read the counts)."""
        if counters is None:
            return self._far.shape[0], self._blend.shape[0], self._leaf.shape[0], self._max_rounds - 1
        far, blend, leaf, max_level = (int(c) for c in counters[:4])
        return min(far, self._far.shape[0]), min(blend, self._blend.shape[0]), min(leaf, self._leaf.shape[0]), max_level if blend else -1

    def _lists_fit(self, counters: np.ndarray) -> bool:
        far, blend, leaf = (int(c) for c in counters[:3])
        round_tasks = counters[_ROUND_SLOT:]
        task_capacity = self._tasks[0].shape[0] if self._tasks is not None else 0
        return far <= self._far.shape[0] and blend <= self._blend.shape[0] and leaf <= self._leaf.shape[0] and int(round_tasks.max(initial=0)) <= task_capacity

    def _launch_evaluation(self, *, reduce: bool):
        """Uploads the staged poses, fills the term lists and, with ``reduce``, sums the
        potential; enqueues the counters (and the sums) for readback."""
        self._launch_transforms("transforms", self._pose_host, self._pose, self._rotation, self._position)
        if self._mode != "brute" and len(self.body_pairs):
            self._launch_rounds()
        if reduce:
            if self.sync_free:
                self._reduce(self._launch_sizes(None))
            else:
                counters = self._counters.numpy()
                if self._lists_fit(counters):  # host-sized: an overflowed traversal is not reduced
                    self._reduce(self._launch_sizes(counters))
            self._readback.enqueue(
                status=self._seed_status,
                value=self._total_value,
                grad=self._total_grad,
                hess=self._total_hess,
                separation=self._seed_separation,
                leaf_iterations=self._leaf_iterations,
            )
        self._readback.enqueue(counters=self._counters)

    def _read_counters(self) -> np.ndarray:
        self._readback.wait()
        return self._readback.read("counters")

    def _fill_lists(self, *, reduce: bool, friction: LaggedFriction | None = None):
        """Term lists at the current poses (and, with ``reduce``, the potential from them),
        growing the buffers and starting over until they fit; then records the counts.
        ``friction``: a lagged frame whose terms at these poses are queued behind each attempt,
        so that its wait covers them too.

        Sync-free on a GPU, the launches of an evaluation that fitted its buffers are
        captured into a CUDA graph, which later evaluations replay while the buffers stay
        the same (any growth drops it): one graph launch instead of ~30 kernel launches."""
        counters = None
        if reduce and self.sync_free and self._graph is not None:
            wp.capture_launch(self._graph)
            if friction is not None:
                self._queue_friction_terms(friction, at_poses=False)
            counters = self._read_counters()
            if self._take_counts(counters):
                return
        # An overflowing walk counts only up to the first round whose task list overflowed
        # (host-sized), or undercounts the rounds after it (sync-free): each attempt learns at
        # least one more round, so the rounds bound the attempts (a fixed 8 refused a fine
        # plate on a fine ground that needed more).
        attempts = self._max_rounds + _MAX_TRAVERSAL_ATTEMPTS
        for _ in range(attempts):
            if counters is not None:
                self._grow_lists(counters)
            self._launch_evaluation(reduce=reduce)
            if friction is not None:
                self._queue_friction_terms(friction, at_poses=False)
            counters = self._read_counters()
            if self._take_counts(counters):
                if reduce and self.sync_free and self.device.is_cuda and self._graph is None:
                    with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                        self._launch_evaluation(reduce=True)
                    self._graph = capture.graph
                return
        raise RuntimeError(f"sphere-tree traversal did not fit its buffers after {attempts} attempts")

    def _grow_lists(self, counters: np.ndarray):
        """Room for 1.25x the counted terms, and for twice the task lists when a round's
        tasks overflowed (the rounds after it were not counted, and they grow)."""
        far, blend, leaf = (int(c) for c in counters[:3])
        tasks = int(counters[_ROUND_SLOT:].max(initial=0))
        capacity = self._tasks[0].shape[0] if self._tasks is not None else 0
        self._reserve_tasks(max(int(tasks * 1.25) + 16, 2 * capacity if tasks > capacity else 0))
        self._reserve_lists(far=int(far * 1.25) + 16, blend=int(blend * 1.25) + 16, leaf=int(leaf * 1.25) + 16)

    def _take_counts(self, counters: np.ndarray) -> bool:
        """Records the term counts and rounds of a traversal whose lists fit; False otherwise."""
        if not self._lists_fit(counters):
            return False
        if counters[_ROUND_SLOT + self._max_rounds - 1]:
            raise RuntimeError("sphere-tree traversal: tasks left after max_depth + 1 rounds (a broken tree)")
        far, blend, leaf, max_level = (int(c) for c in counters[:4])
        self._counts = (far, blend, leaf, max_level if blend else -1)
        self._traversal_rounds = 1 + int(np.count_nonzero(counters[_ROUND_SLOT:]))
        return True

    def _chunk_count(self, num_leaf: int) -> int:
        """Chunks for an evaluation with ``num_leaf`` leaf terms: ``term_chunks``, or one
        below ``term_chunks`` x 1,024 leaf terms."""
        return self._term_chunks if num_leaf >= self._term_chunks * self._min_chunk_leaf_terms else 1

    def _split_ranges(self, num_far: int, num_leaf: int) -> list[tuple[tuple[int, int], tuple[int, int]]]:
        """Per chunk, the (start, stop) ranges it takes of the far and leaf lists, for a
        kernel whose result does not depend on how its items are split (a minimum)."""
        chunks = self._chunk_count(num_leaf)
        return [((num_far * k // chunks, num_far * (k + 1) // chunks), (num_leaf * k // chunks, num_leaf * (k + 1) // chunks)) for k in range(chunks)]

    def _deal_seed_chunks(self, num_far: int, num_blend: int, num_leaf: int) -> int:
        """Deals the body pairs out to chunks of about equal cost (largest first, each to the
        cheapest chunk so far) into ``_seed_chunk``; returns the number of chunks. Host-sized
        CPU launches only: the lists are read in place."""
        if self._chunk_count(num_leaf) == 1:
            if self._seed_chunk_count != 1:  # all zeros already unless the last evaluation split
                self._seed_chunk.zero_()
                self._seed_chunk_count = 1
            return 1
        pairs = len(self.body_pairs)
        cost = np.zeros(pairs)
        for items, count, unit in zip((self._leaf, self._far, self._blend), (num_leaf, num_far, num_blend), _TERM_COSTS):
            seeds = items.numpy()[:count].view(np.int32).reshape(-1, 4)[:, 3]
            cost += unit * np.bincount(seeds, minlength=pairs)
        order = np.argsort(-cost, kind="stable")
        order = order[cost[order] > 0.0]  # pairs without terms have nothing to deal
        chunk = np.zeros(pairs, dtype=np.int64)
        head, tail = order[: self._exact_deal_pairs], order[self._exact_deal_pairs :]
        # Python floats: numpy's argmin on a few loads cost ~1.6 us a pair (53 ms an
        # evaluation at 32,896 body pairs).
        load = [0.0] * self._term_chunks
        for seed, c in zip(head.tolist(), cost[head].tolist()):
            k = load.index(min(load))
            chunk[seed] = k
            load[k] += c
        if tail.size:
            # Each no costlier than any pair before it: dealt lightest chunk first, there and
            # back (0, 1, ..., 1, 0, ...), the loads stay within one of them of the greedy's.
            chunks = self._term_chunks
            lap = np.arange(tail.size) % (2 * chunks)
            chunk[tail] = np.argsort(load, kind="stable")[np.where(lap < chunks, lap, 2 * chunks - 1 - lap)]
        # Unknown while the labels change: an interruption between the two left a count of 1
        # over split labels, and later unsplit evaluations skipped the pairs of chunk 1.
        self._seed_chunk_count = None
        self._seed_chunk.numpy()[:] = chunk
        self._seed_chunk_count = self._term_chunks
        return self._term_chunks

    def _reduce(self, sizes: tuple[int, int, int, int]):
        num_far, num_blend, num_leaf, _ = sizes
        targets = self._records
        for arr in (targets.record_value, targets.record_grad, targets.record_hess, self._total_value, self._total_grad, self._total_hess, self._seed_status):
            arr.zero_()
        self._seed_separation.fill_(np.inf)
        chunks = 1 if self.sync_free else self._deal_seed_chunks(num_far, num_blend, num_leaf)
        run_concurrently((functools.partial(self._launch_chunk_terms, sizes, chunk) for chunk in range(chunks)), modules=[reduction_kernels], device=self.device)
        self._launch_top_level_sum("top", targets, (self._total_value, self._total_grad, self._total_hess))

    def _launch_chunk_terms(self, sizes: tuple[int, int, int, int], chunk: int):
        """Blend weights, far and leaf terms and the bottom-up blend of the body pairs dealt
        to ``chunk``: everything they add to is their own."""
        num_far, num_blend, num_leaf, max_level = sizes
        targets = self._records
        common = [self._rotation, self._position, self._seed_body_pair]
        select = [self._seed_chunk, chunk]
        if num_blend:
            self._launches.launch(
                ("weight", chunk),
                reduction_kernels.blend_weight_kernel,
                dim=num_blend,
                inputs=[self._node_center, self._node_radius, self._eps, *common, self._blend, self._counters, *select],
                outputs=[targets],
            )
        if num_far:
            self._launches.launch(
                ("far", chunk),
                reduction_kernels.far_term_kernel,
                dim=num_far,
                inputs=[self._node_center, self._node_radius, self._node_weight, self._mode != "sdrs", *common, self._far, self._counters, *select],
                outputs=[targets, self._seed_separation],
            )
        if num_leaf:
            self._launches.launch(
                ("leaf", chunk),
                reduction_kernels.leaf_term_kernel,
                dim=num_leaf,
                inputs=[self._triangle_vertices, self._dhat, self._max_leaf_iterations, self._float32_search, *common, self._leaf, self._counters, *select],
                outputs=[targets, self._seed_status, self._seed_separation, self._leaf_iterations, self._leaf_plane],
            )
        for level in range(max_level if num_blend else -1, -1, -1):
            self._launches.launch(
                ("blend", chunk),
                reduction_kernels.blend_level_kernel,
                dim=num_blend,
                inputs=[self._node_center, self._node_radius, self._node_weight, self._eps, level, *common, self._blend, self._blend_level, self._counters, *select],
                outputs=[targets],
            )

    def evaluate(self, poses, *, reuse: bool = False, friction: LaggedFriction | None = None) -> ContactEvaluation:
        """Potential, gradient and Hessian at ``poses`` (nbodies, 7) = (px, py, pz, qx, qy, qz, qw).

        Quaternions within ``QUATERNION_TOLERANCE`` of unit norm are normalised; others raise
        ValueError naming the body.

        Args:
            reuse: when the validated ``poses`` equal those of the last evaluation bit for
                bit and nothing has overwritten its term lists since (``term_lists``), return
                a copy of its result and launch nothing. An implicit step starts where the
                previous step's last evaluation ended, so this saves one evaluation a step.
            friction: a ``LaggedFriction`` (of ``friction_frame``) whose terms at ``poses`` are
                computed with the evaluation, behind the same wait; ``friction_terms(friction)``
                then returns them without a launch or a wait of its own (on a GPU, one
                synchronisation fewer an evaluation). Not with a reused evaluation.
        """
        poses = self._validated_poses(poses)
        if friction is not None:
            check_own(friction, LaggedFriction, "friction", self)
        last = self._last_evaluation
        if checked_flag(reuse, "reuse") and last is not None and np.array_equal(poses, last[0]):
            return _copy_evaluation(last[1])
        # Until this evaluation succeeds the buffers hold no evaluation's lists and planes.
        self._last_evaluation = None
        self._pair_separation = None
        self._queued_friction = None
        self._set_poses(poses)
        self._fill_lists(reduce=True, friction=friction)
        self._queued_friction = friction
        num_far, num_blend, num_leaf, _ = self._counts
        read = self._readback.read
        status = read("status")
        contact = [tuple(self.names[i] for i in self.body_pairs[s]) for s in np.flatnonzero(status == reduction_kernels.PAIR_CONTACT)]
        unsolved = [tuple(self.names[i] for i in self.body_pairs[s]) for s in np.flatnonzero((status > LeafStatus.CONTACT) & (status != reduction_kernels.PAIR_CONTACT))]
        value = float(read("value")[0])
        if contact or unsolved:
            value = float("inf")
        iterations = read("leaf_iterations")[:num_leaf]
        self._pair_separation = read("separation").copy()
        result = ContactEvaluation(
            value=value,
            grad=read("grad").copy(),
            hessian=symmetric_from_upper(read("hess")),
            num_far=num_far,
            num_blend=num_blend,
            num_leaf=num_leaf,
            contact_pairs=contact,
            unsolved_pairs=unsolved,
            mean_leaf_iterations=float(iterations.mean()) if num_leaf else 0.0,
            pair_separation=self._pair_separation.copy(),  # the model bounds steps with its own
        )
        self._last_evaluation = (poses, _copy_evaluation(result))
        return result

    def _require_evaluation(self, what: str):
        if self._pair_separation is None:
            raise RuntimeError(
                f"{what}: uses the term lists and separating planes of the last evaluate(poses), and the model holds none "
                "(call evaluate at the configuration the step starts from; term_lists does not compute planes)"
            )

    def advancement_frame(self) -> "AdvancementFrame":
        """A copy of the term lists and separating planes of the last ``evaluate``, so that
        steps from that configuration can still be bounded after later evaluations."""
        self._require_evaluation("advancement_frame")
        num_far, _, num_leaf, _ = self._counts
        with wp.ScopedDevice(self.device):
            return AdvancementFrame(
                model_id=id(self),
                rotation=wp.clone(self._rotation),
                position=wp.clone(self._position),
                far=wp.clone(self._far[: max(num_far, 1)]) if self._far.shape[0] else wp.zeros(1, dtype=wp.vec4i),
                num_far=num_far,
                leaf=wp.clone(self._leaf[: max(num_leaf, 1)]) if self._leaf.shape[0] else wp.zeros(1, dtype=wp.vec4i),
                leaf_plane=wp.clone(self._leaf_plane[: max(num_leaf, 1)]) if self._leaf_plane.shape[0] else wp.zeros(1, dtype=wp.vec4d),
                num_leaf=num_leaf,
                seed_separation=wp.clone(self._seed_separation),
                pair_separation=self._pair_separation.copy(),
            )

    def advancement_limit(self, step, *, fraction: float = 0.9, frame: "AdvancementFrame | None" = None) -> float:
        """Largest alpha in (0, 1] such that moving the bodies by alpha * step, along the whole
        path p + alpha dp, exp(alpha [dtheta]x) R, keeps every pair apart.

        Uses the term lists and separating planes of the last ``evaluate`` (call it at the
        configuration the step starts from). No triangle pair may close more than ``fraction``
        of its gap along a fixed axis (restarted where that holds the step back, never below
        1 - ``fraction`` of its distance; docs/architecture.md, "No penetration, no
        tunnelling"), no far cluster pair more than ``fraction`` of its sphere separation, so
        no contact can be skipped between line-search samples.

        Args:
            step: (nbodies, 6) rigid-coordinate step (dp, dtheta); zero rows for static bodies.
            frame: bound from the configuration of an ``advancement_frame()`` instead.
        """
        step = validated_step(step, self.names, self.static)
        if not (is_real(fraction) and 0 < fraction < 1):
            raise ValueError(f"fraction: must be a number in (0, 1), got {fraction!r}")
        if frame is None:
            self._require_evaluation("advancement_limit")
            num_far, _, num_leaf, _ = self._counts
            frame = AdvancementFrame(self._rotation, self._position, self._far, num_far, self._leaf, self._leaf_plane, num_leaf, self._seed_separation, self._pair_separation, model_id=id(self))
        else:
            check_own(frame, AdvancementFrame, "frame", self)
        if self._pairs_keep_clear(step, frame.pair_separation, fraction):
            return 1.0  # no term can cut the step: nothing to launch or wait for
        self._alpha.fill_(1.0)
        if frame.num_far + frame.num_leaf:
            self._step_host.numpy()[:] = step
            wp.copy(self._step, self._step_host)
            chunks = self._split_ranges(frame.num_far, frame.num_leaf)
            run_concurrently((functools.partial(self._launch_advancement, frame, far, leaf, float(fraction), chunk) for chunk, (far, leaf) in enumerate(chunks)), modules=[reduction_kernels], device=self.device)
        self._readback.enqueue(alpha=self._alpha)
        self._readback.wait()
        return float(self._readback.read("alpha").min())

    def _pairs_keep_clear(self, step: np.ndarray, pair_separation: np.ndarray, fraction: float) -> bool:
        """True when every body pair passes the advancement kernel's own skip test
        (``_pair_keeps_clear`` in kernels/reduction.py): the two bodies' travel along
        ``step`` adds up to at most half of ``fraction`` times their closest term's separation.
        The kernel would then skip every term and leave alpha at 1; converged Newton
        iterations, whose steps are tiny, end here without a launch."""
        if not len(self.body_pairs):
            return True
        travel = rigid_step_travel(step, self._body_reach_host)
        pair_travel = travel[self.body_pairs[:, 0]] + travel[self.body_pairs[:, 1]]
        return bool(np.all(2.0 * pair_travel <= fraction * pair_separation))

    def _launch_advancement(self, frame: "AdvancementFrame", far: tuple[int, int], leaf: tuple[int, int], fraction: float, chunk: int):
        """The advancement bound of the ``frame``'s list ranges ``far`` and ``leaf`` into alpha slot ``chunk``."""
        if far[1] - far[0] + leaf[1] - leaf[0] == 0:
            return

        def rows(array, span):
            # The kernel reads no row past its range's length, so a range from row 0 (or an
            # empty one, which Warp cannot slice) needs no view.
            return array[span[0] : span[1]] if 0 < span[0] < span[1] else array

        self._launches.launch(
            ("advancement", chunk),
            reduction_kernels.advancement_kernel,
            dim=far[1] - far[0] + leaf[1] - leaf[0],
            inputs=[
                self._node_center,
                self._node_radius,
                self._triangle_vertices,
                self._body_reach,
                fraction,
                frame.rotation,
                frame.position,
                self._seed_body_pair,
                frame.seed_separation,
                rows(frame.far, far),
                far[1] - far[0],
                rows(frame.leaf, leaf),
                rows(frame.leaf_plane, leaf),
                self._step,
            ],
            outputs=[self._alpha[chunk : chunk + 1] if chunk else self._alpha],
        )

    # --- friction -----------------------------------------------------------------------

    def friction_frame(self, mu: float, friction: wp.array, slip_smoothing: float, *, coefficient: float | None = None) -> LaggedFriction:
        """Lagged friction data at the last evaluated configuration (a step's q^t): per leaf
        pair, its plane normal and, at each vertex of its carrying triangle, the vertex's
        normal force mu W |n| (-b'(g_k)) of this mode's leaf potential and the two bodies'
        material points there (``kernels/friction.py``).

        Args:
            mu: the contact stiffness (the potential's scale in the step; positive, finite).
            friction: the model's (1,) float64 array holding the friction coefficient.
            slip_smoothing: the slip length below which Coulomb friction is smoothed (m; the
                model's friction smoothing speed x dt).
            coefficient: ``friction``'s value where the caller has read it (checked; else it
                is read, on a GPU a synchronisation).
        """
        check_friction_arguments(mu, friction, slip_smoothing, coefficient)
        self._require_evaluation("friction_frame")
        with wp.ScopedDevice(self.device):
            frame = friction_kernels.FrictionFrame()
            frame.leaf_items = self.leaf_items()
            count = frame.leaf_items.shape[0]
            frame.normal = wp.zeros(count, dtype=wp.vec3d)
            frame.plane = _leading_rows(self._leaf_plane, count)
            frame.vertex_force = wp.zeros(3 * count, dtype=wp.float64)
            frame.point_a = wp.zeros(3 * count, dtype=wp.vec3d)
            frame.point_b = wp.zeros(3 * count, dtype=wp.vec3d)
            frame.offset = wp.zeros(3 * count, dtype=wp.vec3d)
            if count:
                wp.launch(
                    friction_kernels.friction_setup_kernel,
                    dim=count,
                    inputs=[self._triangle_vertices, self._eps, self._dhat, float(mu), self._body_dynamic, self._rotation, self._position, self._seed_body_pair],
                    outputs=[frame],
                )
        return LaggedFriction(pairs=count, mu=float(mu), friction=friction, slip_smoothing=float(slip_smoothing), data=frame, model_id=id(self))

    def friction_terms(self, lagged: LaggedFriction, *, poses: np.ndarray | None = None):
        """Friction value, (6 nbodies,) gradient and dense Hessian over ``hessian_bodies`` (as
        ``evaluate``'s) in rigid coordinates at the
        last evaluated poses, or at ``poses`` (nbodies, 7), which leaves the term lists and
        transforms of the last evaluation untouched.

        Each lagged pair adds to one of its body pair's ``top_replicas`` records, which
        ``top_level_kernel`` sums, as for the contact potential's top-level terms: on a GPU
        all of a body pair's lagged pairs would otherwise contend for the same addresses.
        Sync-free on a GPU, the launches are captured into a CUDA graph per lagged frame and
        kind of call, which its later calls replay: a step with friction calls this once per
        trial and per iteration of the solver's friction-exact model."""
        check_own(lagged, LaggedFriction, "lagged", self)
        at_poses = poses is not None
        if not at_poses:
            # term_lists moves the transforms without evaluating: "the last evaluated poses"
            # were silently term_lists' (friction 0 read 0.44).
            self._require_evaluation("friction_terms")
        # Queued with the last evaluation, whose wait covered them: taken once, as the read-backs
        # hold the last queued terms only.
        queued = not at_poses and self._queued_friction is lagged
        self._queued_friction = None
        if not queued:
            if at_poses:
                # The solver's retracted poses as given, to the last bit (their norms are 1 within rounding).
                self._friction_pose_host.numpy()[:] = self._local_poses(self._validated_poses(poses, normalize=False))
            self._queue_friction_terms(lagged, at_poses)
            self._readback.wait()
        read = self._readback.read
        return float(read("friction_value")[0]), read("friction_grad").reshape(-1).copy(), symmetric_from_upper(read("friction_hess"))

    def _queue_friction_terms(self, lagged: LaggedFriction, at_poses: bool):
        """Launches the friction terms (at the last evaluation's transforms, or at the staged
        ``_friction_pose_host`` with ``at_poses``) and enqueues their read-back, no wait."""
        if self._friction_records is None:
            n = self.num_bodies
            with wp.ScopedDevice(self.device):
                totals = (wp.zeros(1, dtype=wp.float64), wp.zeros((n, 6), dtype=wp.float64), wp.zeros(self._hessian_shape, dtype=wp.float64))
            self._friction_records = (self._new_records(0), totals)
        # A graph holds the lagged frame's arrays and numbers: one set per LaggedFriction.
        if self._friction_graphs[0] is not lagged:
            self._friction_graphs = (lagged, {})
        graphs = self._friction_graphs[1]
        if at_poses in graphs:
            wp.capture_launch(graphs[at_poses])
        else:
            self._launch_friction_terms(lagged, at_poses)
            if self.sync_free and self.device.is_cuda:
                with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                    self._launch_friction_terms(lagged, at_poses)
                graphs[at_poses] = capture.graph

    def _launch_friction_terms(self, lagged: LaggedFriction, at_poses: bool):
        targets, (value, grad, hess) = self._friction_records
        for arr in (value, grad, hess):
            arr.zero_()
        rotation, position = self._rotation, self._position
        if at_poses:
            rotation, position = self._friction_rotation, self._friction_position
            self._launch_transforms("friction transforms", self._friction_pose_host, self._friction_pose, rotation, position)
        if lagged.pairs:
            for arr in (targets.record_value, targets.record_grad, targets.record_hess):
                arr.zero_()
            # The body pairs keep the chunks of the last evaluation (``_deal_seed_chunks``).
            chunks = self._seed_chunk_count
            run_concurrently(
                (
                    functools.partial(
                        self._launches.launch,
                        ("friction", chunk),
                        friction_kernels.friction_energy_kernel,
                        dim=lagged.pairs,
                        inputs=[lagged.friction, lagged.slip_smoothing, rotation, position, self._seed_body_pair, lagged.data, self._seed_chunk, chunk],
                        outputs=[targets],
                    )
                    for chunk in range(chunks)
                ),
                modules=[friction_kernels],
                device=self.device,
            )
            self._launch_top_level_sum("friction top", targets, (value, grad, hess))
        self._readback.enqueue(friction_value=value, friction_grad=grad, friction_hess=hess)

    def friction_adjoint(self, lagged: LaggedFriction, q_next: np.ndarray, q_now: np.ndarray, multiplier: np.ndarray):
        """lambda^T d(grad_q D)/dy of the step's friction D at its solution q_next, for y = q^t
        (through the slip, the lagged normal forces and normals), the friction coefficient and mu.

        Returns ((nbodies, 6) rigid-coordinate adjoint of q_now, adjoint of lambda, of mu).
        """
        check_own(lagged, LaggedFriction, "lagged", self)
        q_next, q_now, multiplier = checked_adjoint_arguments(q_next, q_now, multiplier, self.names)
        n = self.num_bodies
        # On a CPU, ranges of the lagged pairs on one thread per core, each into outputs of its
        # own, summed in order: one thread took 44 ms of a 6,208-triangle frame's 48 ms
        # backward (stop 63).
        ranges = [leaf for _, leaf in self._split_ranges(0, lagged.pairs)]
        chunks = len(ranges)
        with wp.ScopedDevice(self.device):
            rot_next = wp.zeros(n, dtype=wp.mat33d)
            pos_next = wp.zeros(n, dtype=wp.vec3d)
            rot_now = wp.zeros(n, dtype=wp.mat33d)
            pos_now = wp.zeros(n, dtype=wp.vec3d)
            wp.launch(rigid_kernels.body_transforms_kernel, dim=n, inputs=[wp.array(self._local_poses(q_next), dtype=wp.transformd)], outputs=[rot_next, pos_next])
            wp.launch(rigid_kernels.body_transforms_kernel, dim=n, inputs=[wp.array(self._local_poses(q_now), dtype=wp.transformd)], outputs=[rot_now, pos_now])
            adj_q = wp.zeros((chunks, n, 6), dtype=wp.float64)
            adj_friction = wp.zeros((chunks, 1), dtype=wp.float64)
            adj_mu = wp.zeros((chunks, 1), dtype=wp.float64)
            lam = wp.array(multiplier, dtype=rigid_kernels.vec6d)
        run_concurrently(
            (
                functools.partial(
                    wp.launch,
                    friction_kernels.friction_adjoint_kernel,
                    dim=stop - start,
                    inputs=[
                        self._triangle_vertices,
                        self._eps,
                        self._dhat,
                        lagged.mu,
                        lagged.friction,
                        lagged.slip_smoothing,
                        self._max_leaf_iterations,
                        rot_next,
                        pos_next,
                        rot_now,
                        pos_now,
                        self._body_dynamic,
                        self._seed_body_pair,
                        lagged.data,
                        lam,
                        start,
                    ],
                    outputs=[adj_q[k], adj_friction[k], adj_mu[k]],
                    device=self.device,
                )
                for k, (start, stop) in enumerate(ranges)
                if stop > start
            ),
            modules=[friction_kernels],
            device=self.device,
        )
        # One wait for the three (three reads were three synchronisations of a GPU a step).
        self._readback.enqueue(adjoint_q=adj_q, adjoint_friction=adj_friction, adjoint_mu=adj_mu)
        self._readback.wait()
        read = self._readback.read
        return read("adjoint_q").sum(axis=0), float(read("adjoint_friction").sum()), float(read("adjoint_mu").sum())

    @property
    def body_rotation(self) -> wp.array:
        """(nbodies,) mat33d rotations of the last evaluated poses (device array, do not modify)."""
        return self._rotation

    @property
    def body_position(self) -> wp.array:
        """(nbodies,) vec3d positions of the last evaluated poses (device array, do not modify),
        less ``origin``."""
        return self._position

    @property
    def origin(self) -> np.ndarray:
        """(3,) where the kernels' world frame sits in the poses' frame (m): zeros unless the
        first poses given put every body far out on an axis, close together (``_local_poses``).
        Fixed from then on: a model moved far from its first placement keeps it."""
        return np.zeros(3) if self._origin is None else self._origin.copy()

    def leaf_items(self) -> wp.array:
        """A device copy of the leaf term list of the last evaluation, (L,) vec4i rows
        (triangle_a, triangle_b, parent blend record, body pair)."""
        return _leading_rows(self._leaf, self._counts[2])

    def term_lists(self, poses) -> TermLists:
        """The far / blend / leaf term lists at ``poses`` (for inspection and tests). They
        replace the last evaluation's: call ``evaluate`` again before bounding a step."""
        self._last_evaluation = None
        self._pair_separation = None
        self._queued_friction = None
        self._set_poses(self._validated_poses(poses))
        self._fill_lists(reduce=False)
        num_far, num_blend, num_leaf, _ = self._counts
        return TermLists(
            far=self._far.numpy()[:num_far].view(np.int32).reshape(-1, 4).copy(),
            blend=self._blend.numpy()[:num_blend].view(np.int32).reshape(-1, 4).copy(),
            blend_level=self._blend_level.numpy()[:num_blend].copy(),
            leaf=self._leaf.numpy()[:num_leaf].view(np.int32).reshape(-1, 4).copy(),
        )
