"""Differentiable implicit time step (paper eq. opt): q^{t+1} = argmin L(q; q^t, q^{t-1}).

    L = inertia + gravity + PD control + mu * P_contact + friction
        (kernels/dynamics.py, contact.py, kernels/friction.py)

solved by Newton's method over the dynamic bodies' rigid coordinates, with a line search
that never leaves the intersection-free set: each trial step is first bounded by
conservative advancement (no point of a body may travel farther than the current
separation lower bound to any other body allows, so no contact can be skipped between
samples), then backtracked until L decreases (Armijo, each cut chosen by a cubic fit); a
trial whose contact evaluation reports contact or an unsolved leaf is rejected. Newton
starts from the inertial prediction (where the bodies would coast to) where that path is
certified. With friction on free bodies, each Newton direction minimises a model of L that
keeps the friction term exact and the rest quadratic (``_friction_exact_direction``): the
smoothed Coulomb law's curvature changes by orders of magnitude within a slip of a few
v_eps dt, which a quadratic model cannot follow, and friction costs a fraction of a contact
evaluation to evaluate.

Differentiation: inside ``with wp.Tape()``, each step records its backward with
``tape.record_func``. By the implicit function theorem, with H = d2L/dq2 at the solution
and lambda solving H lambda = -(adjoint of q^{t+1}), the adjoint of any input y is
lambda^T d(grad_q L)/dy; it is pushed into q^t, q^{t-1}, the PD targets, the masses, mu and
the friction coefficient, and into ball-joint targets and (through their damping) q^t. A
recorded step refuses a model array that asks for a gradient it does not compute (PD gains,
second moments), which would otherwise stay zero.
"""

import dataclasses
import sys
import warnings
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import trimesh
import warp as wp

from ._validate import MAX_COORDINATE, SCALE_RANGE, beyond_coordinates, check_finite_poses, check_time_step, checked_flag, is_real, is_whole, unit_inertia_outside, unit_inertia_problem
from .kernels import dynamics as dynamics_kernels
from .kernels.rigid import vec6d
from ._runtime import HostReadback, LaunchCache, host_buffer, paused_tape
from .articulation import MIN_LIMIT_MARGIN, connected_labels, joint_limit_energy
from .builder import STEEP_BLEND_EPS, contact_setting_problem, gravity_problem, steep_blend, winding_numbers
from .contact import PRESSED_GAP_HINT, UNSOLVED_HINT, ContactModel, LaggedFriction
from .rotation import cross, normalized_poses, quat_from_matrix, quat_norm, quat_from_rotation_vector, quat_mul, quat_to_matrix, rigid_step_between, rigid_step_travel
from .sphere_tree import welded_face_indices
from .types import Control, Model, State, shares_memory

__all__ = ["ImplicitSolver", "SolverError", "StepInfo"]

_GAIN_ARRAYS = ("body_kp_linear", "body_kd_linear", "body_kp_angular", "body_kd_angular")
# Model arrays a recorded step's backward pushes adjoints into, and those it does not (a
# gradient requested of one of those is refused rather than left at zero).
_DIFFERENTIATED_MODEL_ARRAYS = ("body_mass", "contact_stiffness", "friction")
_UNDIFFERENTIATED_MODEL_ARRAYS = ("body_unit_second_moment", *_GAIN_ARRAYS)
# The model arrays a user may change between steps, read once a step (``_checked_model_parameters``).
_CHECKED_MODEL_ARRAYS = ("contact_stiffness", "friction", "body_dynamic", "body_mass", "body_unit_second_moment", *_GAIN_ARRAYS)
# The wp.Tape attribute in which recorded steps note their state and control arrays:
# (the tape.launches list they were recorded into, {id(array): a control array's values at
# that step, on the device or the host, or None for a state array}). tape.reset() replaces the launches list, which
# retires the notes; the tape keeps every noted array alive, so its id is not reused.
_TAPED_STEP_ARRAYS = "_warpcontact_step_arrays"


def _taped_step_arrays(tape: wp.Tape) -> dict:
    """The arrays the steps recorded on ``tape`` since its last reset noted (see above)."""
    launches, noted = tape.__dict__.get(_TAPED_STEP_ARRAYS, (None, None))
    if launches is not tape.launches:
        launches, noted = tape.launches, {}
        tape.__dict__[_TAPED_STEP_ARRAYS] = (launches, noted)
    return noted


def _accumulate(array: wp.array, adjoint) -> None:
    """Add a backward's adjoint to a model array's gradient, where one is kept (a model
    built without friction keeps none for its coefficient unless asked)."""
    if array.requires_grad:
        array.grad.assign(array.grad.numpy() + adjoint)


def _host(values) -> np.ndarray:
    """A noted control snapshot (a device copy, or values already read back) on the host."""
    return values.numpy() if isinstance(values, wp.array) else values


def _taped_control_arrays(control: Control | None) -> list[tuple[str, wp.array]]:
    """The control arrays a recorded step's backward writes gradients into, by name."""
    if control is None:
        return []
    named = (("control.body_target", control.body_target), ("control.joint_target", control.joint_target), ("control.ball_target", control.ball_target))
    # A model without joints (or ball joints) has empty target arrays, without gradients.
    return [(label, array) for label, array in named if isinstance(array, wp.array) and array.requires_grad and array.size]


# The friction-exact model is minimised to this fraction of its step's travel, within this
# many Newton iterations of its own; each costs one friction evaluation per trial.
_FRICTION_MODEL_TOLERANCE = 1e-2
_FRICTION_MODEL_ITERATIONS = 10
_FRICTION_MODEL_HALVINGS = 20
# Nor is it built while conservative advancement holds the steps below this fraction (the
# last Newton step's bound; contact models with ``crawl_skips_friction_model``): only that
# fraction of a step is taken, so the model's exact friction over the whole step changes
# little of it, at one friction evaluation per trial (a pushing rod turning against its box,
# held to 2-5% a step for 15-60 iterations a frame, spent 80% of its time there).
_FRICTION_MODEL_MIN_ALPHA = 0.3

# A Newton direction that conservative advancement cuts below this fraction is blocked by a
# near contact; damped directions (H + lambda diag H) d = -g are then tried, lambda rising
# from the first value by the factor while their bounded model decrease keeps improving.
_BLOCKED_ALPHA = 1e-2
_DAMPING_FIRST = 1e-4
_DAMPING_FACTOR = 10.0
_DAMPING_LAST = 1e2
# A body pair whose centres close in on each other by less than this fraction of the smaller
# body's radius in one step cannot pass through each other within it; the pass-through check
# (``ImplicitSolver._pass_through``) skips it, so resting and pushing contact cost nothing.
_PASS_THROUGH_TRAVEL = 0.5
# The inner balls' test (``ImplicitSolver._pass_through``) takes a pair of round bodies
# (each one's inner ball at least ``_PASS_THROUGH_ROUND`` of its bounding radius: a sphere
# of one or more subdivisions) for passing through only when the direction between their
# centres turns by at least ``_PASS_THROUGH_TURN`` (rad) in the step, the mover ending
# beside or beyond the other. Their inner balls are nearly the bodies, and both ends of the
# step are intersection-free (centres at least the radius sum R apart), so a slide round the
# other's curved surface turning by phi has a straight motion cutting the balls by up to
# R (1 - cos(phi / 2)) (a ball falling 0.1 m past another at dt 0.02 turned 28 degrees, its
# straight motion 1.75 mm, 0.9% of R, inside, and was refused). A flat face has no such
# sagitta: a cube sliding past another's face strip stays refused. Not beyond 45 degrees:
# the straight motion may then cut R (1 - cos 22.5) = 7.6% of R deep, and at 90 degrees a
# sphere shot at 30 m/s through 8 cm of another (its direction turning 87 degrees) passed (a
# review).
_PASS_THROUGH_ROUND = 0.9
_PASS_THROUGH_TURN = 0.25 * np.pi
# A Newton step left untaken moves the solution by its length, which over dt is an error of
# length / dt^2 in the step's accelerations: no converged step is longer than this error
# (m/s^2) allows. With the tolerance alone, a step under 1e-10 of a body's size was the whole
# of a small dt's correction, and dropping it every step lost every force (at dt 1e-6 a
# thrown box felt no gravity, a sliding one no friction, a pendulum never swung).
_CONVERGED_ACCELERATION = 1e-5
# No body's converged step is longer than this fraction of its closest pair's separation,
# across which the barrier's force changes by twice as much.
_CONVERGED_GAP_FRACTION = 1e-2
# 16 units of float64 roundoff, relative. A Newton step cannot resolve a position more finely
# than its coordinates' rounding: a body's steps below this times its largest coordinate count
# as converged (a lone 1 cm box 50 km up took Newton steps of 0.2 ulp against a tolerance of
# 6e-13 m and failed after 500 iterations).
_ROUNDING = 16.0 * np.finfo(np.float64).eps
# Bodies closer than this fraction of the smaller one's radius are named in a failing step's
# error as pressed beyond what Newton resolves in float64 (a box 1e-8 m between walls, 6e-8
# of its radius, did not converge; at 1e-7 m it falls).
_PRESSED_SEPARATION = 1e-7
# Chords per step of a body centre's straight-motion path relative to another body, tested
# for crossing that body's surface (``ImplicitSolver._centre_crossing``).
_PASS_THROUGH_CHORDS = 16
# Along the joints, the centres' paths are followed by a chord per this much swing (rad) of the
# body whose centre swings most, up to _PASS_THROUGH_CHORDS.
_PASS_THROUGH_CHORD_TURN = 0.2
# A closed body whose centre of mass is outside its material (a ring) is followed by a point
# inside it, sought along the inward normals of this many of its largest faces.
_INNER_POINT_FACES = 16


def _is_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether a mesh is closed once coincident vertices are merged: every edge is used as
    often in each direction. An open mesh has no inside: a tray without a lid winds 5/6 about
    its centre, which lies in the air above its floor."""
    faces = welded_face_indices(vertices, faces)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    # Each directed edge as one integer key, compared as sorted multisets (vectorised: a
    # Counter of tuples took 1 s for an 81,920-face ball at every solver's construction).
    count = len(vertices)
    return bool(np.array_equal(np.sort(edges[:, 0] * count + edges[:, 1]), np.sort(edges[:, 1] * count + edges[:, 0])))


def _encloses(triangles: np.ndarray, point: np.ndarray) -> bool:
    """Whether a closed mesh's ``triangles`` (T, 3, 3) wind about ``point`` (3,): a non-zero
    integer winding number (2 inside two overlapping boxes)."""
    winding = winding_numbers(point[None], triangles)[0]
    return bool(round(winding) != 0 and abs(winding - round(winding)) < 1e-3)


def _inner_point(triangles: np.ndarray) -> np.ndarray | None:
    """A point inside a closed, outward-wound mesh ``triangles`` (T, 3, 3) well away from its
    surface, or None: along the inward normals of its largest faces, halfway to the first
    surface each meets, the deepest of them (a ring's or a cup's centre of mass lies in its
    hollow; this finds its tube's or wall's middle)."""
    normal = cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    area = np.linalg.norm(normal, axis=1)
    span = 2.0 * float(np.linalg.norm(triangles.reshape(-1, 3), axis=1).max())
    best, depth = None, 0.0
    for face in np.argsort(-area)[:_INNER_POINT_FACES]:
        if area[face] == 0.0:
            break
        inward = -normal[face] / area[face]
        start = triangles[face].mean(axis=0) + 1e-9 * span * inward  # off its own face
        hit = _segments_cross_triangles(start[None], (start + span * inward)[None], triangles)
        if hit is not None and hit[1] * span > depth:
            depth = hit[1] * span
            best = start + 0.5 * depth * inward
    return best if best is not None and _encloses(triangles, best) else None


def _segments_cross_triangles(start: np.ndarray, end: np.ndarray, triangles: np.ndarray) -> tuple[int, float] | None:
    """(index k, parameter t in [0, 1]) of the first of the segments start[k] -> end[k] (K, 3)
    to cross one of ``triangles`` (T, 3, 3), or None (Moller-Trumbore, all pairs at once)."""
    direction = end - start
    e1 = triangles[:, 1] - triangles[:, 0]
    e2 = triangles[:, 2] - triangles[:, 0]
    h = cross(direction[:, None, :], e2[None, :, :])
    det = np.einsum("tj,ktj->kt", e1, h)
    scale = np.linalg.norm(direction, axis=1)[:, None] * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    # A chord parallel to a face divides by zero; the mask drops it (no warning reaches users).
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / det
        offset = start[:, None, :] - triangles[None, :, 0]
        u = inverse * np.einsum("ktj,ktj->kt", offset, h)
        q = cross(offset, e1[None, :, :])
        v = inverse * np.einsum("kj,ktj->kt", direction, q)
        t = inverse * np.einsum("tj,ktj->kt", e2, q)
        crossing = (np.abs(det) > 1e-14 * scale) & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t >= 0.0) & (t <= 1.0)
    hits = np.argwhere(crossing)
    if not len(hits):
        return None
    first = hits[np.argmin(hits[:, 0] + t[crossing])]
    return int(first[0]), float(t[first[0], first[1]])


def _coordinate_rounding(poses: np.ndarray) -> np.ndarray:
    """Each body's rounding floor (m): ``_ROUNDING`` of its largest position coordinate, the
    step length below which its Newton step counts as converged."""
    return _ROUNDING * np.abs(poses[:, :3]).max(axis=1)


def _closest_on_chords(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each chord of a polyline ``points`` (k + 1, ..., 3) comes closest to the origin:
    the fraction along the chord (unclipped), the distance there (k, ...), and the chords'
    squared lengths (k, ...)."""
    start, closing = points[:-1], points[1:] - points[:-1]
    length2 = np.einsum("...j,...j->...", closing, closing)
    fraction = -np.einsum("...j,...j->...", start, closing) / np.where(length2 > 0.0, length2, 1.0)
    distance = np.linalg.norm(start + np.clip(fraction, 0.0, 1.0)[..., None] * closing, axis=-1)
    return fraction, distance, length2


def _described(value) -> str:
    """What a wrong argument is, for an error message: a wp.array's dtype and shape, else its type."""
    return f"{value.dtype.__name__} array of shape {value.shape}" if isinstance(value, wp.array) else type(value).__name__


def _check_pose_array(poses, count: int, label: str, expected: str) -> None:
    """ValueError naming ``label`` unless ``poses`` is a wp.array of ``count`` wp.transformd."""
    if not isinstance(poses, wp.array) or poses.shape != (count,) or poses.dtype != wp.transformd:
        raise ValueError(f"{label}: expected a wp.array of {count} wp.transformd, {expected}, got {_described(poses)}")


def _check_quaternion_norms(quaternions: np.ndarray, checked: np.ndarray, label: str, names, *, whose: str = "body") -> None:
    """ValueError naming the body (``whose`` it is) unless each ``checked`` row's (x, y, z, w)
    norm lies in SCALE_RANGE (the step normalises them; zero is no rotation): the kernels
    normalise from their squares, and a previous rotation given at 1e160 was read as another
    one."""
    norms = quat_norm(quaternions)
    low, high = SCALE_RANGE
    bad = np.flatnonzero(checked & ~((norms >= low) & (norms <= high)))
    if bad.size:
        b = int(bad[0])
        if norms[b] == 0.0:
            raise ValueError(f"{label}: {whose} {names[b]!r} (index {b}) has a zero rotation quaternion")
        raise ValueError(f"{label}: {whose} {names[b]!r} (index {b}) has a rotation quaternion of norm {norms[b]:.3g}; expected a norm in [{low:g}, {high:g}] (it is normalised)")


def _check_no_shared_arrays(state_in: State, state_out: State) -> None:
    """ValueError naming the arrays if a ``state_out`` array shares memory with a
    ``state_in`` one: the step writes its output while its result and backward still read
    the input (a State sharing another's arrays stopped a moving box dead, silently)."""
    names = ("body_q", "body_q_prev", "joint_q", "joint_q_prev")
    for i, out_name in enumerate(names):
        out = getattr(state_out, out_name, None)
        # Against every input array, and against the output's other arrays (one array as
        # both body_q and body_q_prev held the box where it was).
        others = [("state_in", name) for name in names] + [("state_out", name) for name in names[i + 1 :]]
        for label, name in others:
            state = state_in if label == "state_in" else state_out
            if shares_memory(out, getattr(state, name, None)):
                raise ValueError(
                    f"state_out.{out_name}: shares memory with {label}.{name}; a step writes state_out while it reads "
                    "state_in, so give state_out arrays of its own (model.state()); two States may alternate as input and output"
                )


class _CrossingGeometry(NamedTuple):
    """What the pass-through check reads of a body, in its frame (``ImplicitSolver._crossing_geometry``)."""

    closed: bool  # its mesh has an inside (``_is_closed``)
    centre_inside: bool  # its centre of mass is a material point (a ring's or an open ground's is not)
    # The material point the crossing test follows, in the body's frame: the centre of mass
    # where it is inside, else a point inside a closed mesh (``_inner_point``: a ring's tube),
    # None for an open mesh.
    followed_point: np.ndarray | None
    triangles: np.ndarray  # (T, 3, 3)
    low: np.ndarray  # (T, 3) the triangles' bounding boxes
    high: np.ndarray
    inner_radius: float  # of the ball about its centre inside it (0 for a centre outside)


class _UnsolvedTrials:
    """How many of a step's trial evaluations had leaf pairs whose plane searches failed
    (the trial is then rejected like a contact), and the last such pairs. A step on a 40 km
    two-triangle ground failed after 500 iterations, 1,389 of its 1,451 trials with unsolved
    pairs, and its error said only "no convergence"."""

    def __init__(self):
        self.trials = self.failed = 0
        self.pairs = ()

    def count(self, contact) -> None:
        self.trials += 1
        if contact.unsolved_pairs:
            self.failed += 1
            self.pairs = contact.unsolved_pairs


class SolverError(RuntimeError):
    """The implicit step did not converge; the message carries the diagnostics."""


@dataclass(frozen=True)
class StepInfo:
    """Diagnostics of a step: Newton iterations, final Newton step length (m), L at the
    solution, the smallest body-pair separation bound (m) and the number of friction pairs
    (0 when friction is off: no friction work is done)."""

    iterations: int
    step_length: float
    objective: float
    min_separation: float
    friction_pairs: int


def _pd_error(kp: np.ndarray, coords: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The joint PD's error, coordinates minus targets, and 0 for a coordinate without
    stiffness, which has no target (a far one, 1e160, made its energy 0 x inf)."""
    return np.where(kp != 0.0, coords - target, 0.0)


def retract(poses: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Poses moved by rigid coordinates: p + dp, exp([dtheta]x) R (world axes)."""
    out = poses.copy()
    out[:, :3] += step[:, :3]
    q = quat_mul(quat_from_rotation_vector(step[:, 3:]), poses[:, 3:])
    out[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return out


# Block size of the triangular solves with a Cholesky factor. numpy has no triangular solve,
# and np.linalg.solve on a whole factor factorises it again (LU), twice: at 1,536 unknowns
# (256 dynamic boxes) 0.58 s against 0.057 s by blocks, the Cholesky factorisation itself
# 0.29 s (this 2-core CPU, beside other jobs). By blocks only the diagonal blocks are
# factorised; up to one block (42 bodies) it is the one solve of the whole factor it
# always was.
_TRIANGULAR_BLOCK = 256


def _solve_lower(lower: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x with ``lower`` x = rhs for a lower-triangular ``lower``, by forward substitution over blocks."""
    x = np.empty_like(rhs)
    for start in range(0, len(rhs), _TRIANGULAR_BLOCK):
        stop = start + _TRIANGULAR_BLOCK
        x[start:stop] = np.linalg.solve(lower[start:stop, start:stop], rhs[start:stop] - lower[start:stop, :start] @ x[:start])
    return x


def _solve_upper(upper: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x with ``upper`` x = rhs for an upper-triangular ``upper``, by back substitution over blocks."""
    x = np.empty_like(rhs)
    for stop in range(len(rhs), 0, -_TRIANGULAR_BLOCK):
        start = max(stop - _TRIANGULAR_BLOCK, 0)
        x[start:stop] = np.linalg.solve(upper[start:stop, start:stop], rhs[start:stop] - upper[start:stop, stop:] @ x[stop:])
    return x


def _backtrack_factor(value: float, slope: float, t_value: float, t_slope: float | None, alpha: float) -> float:
    """Factor for the next trial step after a rejected trial at ``alpha``: the minimiser of the
    cubic through L and its slope along the step at 0 and at the trial (Nocedal & Wright,
    eq. 3.59), kept within [0.1, 0.5] of the trial; halving where the trial is not finite.

    Rejections come mostly from friction's smoothed Coulomb kink (curvature lambda N / e
    within e = v_eps dt of sticking, ~0 beyond), which the Newton model overshoots; the
    cubic lands near the kink in one trial where halving took three or four.
    """
    if t_slope is None or not (np.isfinite(t_value) and np.isfinite(t_slope)):
        return 0.5
    # Overflowing terms (slopes near the float64 limit) end in the halving below, silently.
    with np.errstate(over="ignore", invalid="ignore"):
        d1 = slope + t_slope - 3.0 * (t_value - value) / alpha
        radicand = d1 * d1 - slope * t_slope
        if radicand < 0.0:
            return 0.5
        d2 = np.sqrt(radicand)
        denominator = t_slope - slope + 2.0 * d2
        if denominator == 0.0:
            return 0.5
        fraction = 1.0 - (t_slope + d2 - d1) / denominator
    return float(np.clip(fraction, 0.1, 0.5)) if np.isfinite(fraction) else 0.5


@dataclass(frozen=True)
class _StepInputs:
    """What a step's objective depends on besides the iterate."""

    dt: float
    bodies: dynamics_kernels.BodyModel  # per-body terms' model at this dt
    mu: float
    friction: "LaggedFriction | None"
    # A taped step without friction whose coefficient wants a gradient: the friction data at
    # coefficient 1, for d/d friction at 0 (D is linear in it), else None.
    friction_rate: "LaggedFriction | None"
    body_q: wp.array  # poses q^t
    body_target: wp.array  # body PD targets
    joint_q: np.ndarray  # joint coordinates at t
    joint_target: np.ndarray  # joint PD targets
    ball_target: np.ndarray  # (nball, 4) ball-joint target rotations
    ball_start: np.ndarray  # (nball, 4) ball-joint rotations at t


def _check_contact_model(contact) -> None:
    """ValueError unless ``contact`` is a contact model ``finalize`` makes (ipc's only exists
    once ``warpcontact.ipc`` was imported, which is why it is looked up, not imported)."""
    ipc = sys.modules.get("warpcontact.ipc")
    kinds = (ContactModel,) if ipc is None else (ContactModel, ipc.IpcContactModel)
    if not isinstance(contact, kinds):
        raise ValueError(f"model.contact: expected the contact model finalize made (ContactModel or IpcContactModel), got {_described(contact)}")


class ImplicitSolver:
    """Implicit Newton time stepper of a ``Model``.

    Args:
        model: the model.
        tolerance: converged when the Newton step moves no body point farther than
            ``tolerance`` times the largest body radius, nor farther than 1e-5 m/s^2 x dt^2
            (a step's acceleration error).
        max_iterations: Newton iteration cap; exceeding it raises ``SolverError``. Most steps
            take 2-10 iterations; a step in which a faceted body must roll or slide on a
            contact (an unstable equilibrium of the step objective) can take hundreds, each
            bounded by conservative advancement.
        advancement_fraction: fraction of its distance to a separating plane (or of a far
            cluster pair's sphere separation) that one line-search step may close.
        exact_friction_steps: with friction on free bodies, take Newton directions that
            minimise a model of L with the friction term exact (``_friction_exact_direction``)
            while a step is longer than the slip smoothing length, except while conservative
            advancement holds the steps below 30% of their length (the contact model's
            ``crawl_skips_friction_model``; there only that part is taken). On by default, on a CPU
            and on a GPU alike: it takes fewer Newton iterations on every measured scene, and
            over whole runs of frames the friction evaluations it adds cost less than the
            iterations they save (on a GPU's impact frames alone, about as much;
            docs/architecture.md, "Friction-exact Newton steps"). Either way the step
            converges to a minimiser of the same L, within ``tolerance``; where a
            contact-rich step's L has several nearby minima, the two paths can end in
            different ones (docs/architecture.md, "Known limits").
    """

    def __init__(
        self,
        model: Model,
        *,
        tolerance: float = 1e-10,
        max_iterations: int = 500,
        advancement_fraction: float = 0.9,
        exact_friction_steps: bool = True,
    ):
        for label, value in (("tolerance", tolerance), ("advancement_fraction", advancement_fraction)):
            if not (is_real(value) and 0 < value < 1):
                raise ValueError(f"{label}: must be a number in (0, 1), got {value!r}")
        if not (is_whole(max_iterations) and max_iterations >= 1):
            raise ValueError(f"max_iterations: must be a whole number >= 1, got {max_iterations!r}")
        if not isinstance(model, Model):
            raise ValueError(f"model: expected a Model (ModelBuilder.finalize()), got {type(model).__name__}")
        _check_contact_model(model.contact)
        self.model = model
        # The contact model the solver's tables below were made from: one put in its place
        # later failed as an AttributeError deep in the step (a probe, stop 64).
        self._contact = model.contact
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.advancement_fraction = float(advancement_fraction)
        self.exact_friction_steps = checked_flag(exact_friction_steps, "exact_friction_steps")
        self.last_step: StepInfo | None = None
        n = model.num_bodies
        # The contact model's flags, made by finalize: the model's body_dynamic is a writable array.
        self._dynamic = ~model.contact.static
        # The dynamic bodies in index order, and the rows of each one's 6x6 block in the
        # contact Hessians (``ContactEvaluation.hessian``), which hold them alone.
        self._dynamic_bodies = np.flatnonzero(self._dynamic)
        self._unresolved_fall: set[int] = set()  # bodies warned about once: gravity below their rounding at some dt
        self._block_rows = np.arange(6 * len(self._dynamic_bodies)).reshape(-1, 6)
        # The dtype and shape of each model array the step reads back, as the model had them
        # when this solver was made: one replaced by another kind of array failed deep in
        # Warp or numpy.
        for name in _CHECKED_MODEL_ARRAYS:
            if not isinstance(getattr(model, name), wp.array):
                raise ValueError(f"model.{name}: expected a wp.array (as finalize makes it), got {_described(getattr(model, name))}")
        self._model_array_layout = {name: (getattr(model, name).dtype, getattr(model, name).shape) for name in _CHECKED_MODEL_ARRAYS}
        # The body pairs whose separation bounds cap a converged step (``_pressed``).
        self._pair_bodies = np.asarray(model.contact.body_pairs).reshape(-1, 2)
        # Per body, tr of its second moment per unit mass (m^2): the size of the rotational
        # inertia term, which L computes as a difference of such terms (``_solve``); read with
        # the other parameters at every step (``_checked_model_parameters``).
        self._unit_second_moment_trace = None
        self._dofs = np.flatnonzero(np.repeat(self._dynamic, 6))
        # Free bodies only: the reduced coordinates are the rigid coordinates (J = I).
        self._articulation = None if model.articulation.identity else model.articulation
        self._length_scale = float(model.body_radius.max())
        # Per body, what the pass-through check reads (``_crossing_geometry``), made when a
        # suspect pair first needs it: made for every body here, it was most of the solver's
        # construction (1.2 s of 1.3 s at 2,003 bodies, nearly all static and never suspect).
        self._crossing_geometries: dict[int, tuple] = {}
        # The tree (root body) each body's joints tie it to; links of one tree move along joint
        # arcs, which the pass-through check's straight motion does not follow.
        self._joint_tree = connected_labels(n, [(joint.parent, joint.child) for joint in model.articulation.joints if joint.parent >= 0])
        with wp.ScopedDevice(model.device):
            self._predicted_position = wp.zeros(n, dtype=wp.vec3d)
            self._predicted_rotation = wp.zeros(n, dtype=wp.mat33d)
            self._prediction_sensitivity = wp.zeros(n, dtype=wp.mat33d)
            self._predict_status = wp.zeros(n, dtype=wp.int32)
            self._trial_q = wp.zeros(n, dtype=wp.transformd)
            self._energy = wp.zeros(n, dtype=wp.float64)
            self._energy_grad = wp.zeros(n, dtype=vec6d)
            self._energy_hess = wp.zeros(n, dtype=dynamics_kernels.mat66d)
        self._trial_q_host = host_buffer(n, wp.transformd, model.device)
        self._readback = HostReadback(model.device)
        self._launches = LaunchCache(model.device)
        # (poses, value, gradient, Hessian) of the friction term at the last evaluation.
        self._friction_at_evaluation = None
        self._unit_friction = None  # coefficient 1, for _friction_rate_frame
        # (poses, joint coordinates) of the last state_out this solver wrote (_joint_arrays).
        self._last_written = None

    # --- forward ------------------------------------------------------------------------------

    def _body_model(self, dt: float, *, snapshot: bool = False) -> dynamics_kernels.BodyModel:
        """The model's per-body data for a step of ``dt``: its arrays, or with ``snapshot``
        copies of those a user may change between steps (masses, second moments and gains),
        which a taped step's backward reads when it runs; static flags are set by ``finalize``."""
        m = self.model
        take = (lambda array: wp.clone(array, requires_grad=False)) if snapshot else (lambda array: array)
        bodies = dynamics_kernels.BodyModel()
        bodies.mass = take(m.body_mass)
        # Read live by the backward, a second moment changed after the step (a user's, or a
        # second step's) turned its gradients 163x and flipped their signs (a probe, stop 63).
        bodies.unit_second_moment = take(m.body_unit_second_moment)
        bodies.dynamic = m.body_dynamic
        bodies.kp_linear = take(m.body_kp_linear)
        bodies.kd_linear = take(m.body_kd_linear)
        bodies.kp_angular = take(m.body_kp_angular)
        bodies.kd_angular = take(m.body_kd_angular)
        bodies.gravity = wp.vec3d(*m.gravity)
        bodies.dt = float(dt)
        return bodies

    def _checked_model_parameters(self) -> tuple[float, float, np.ndarray]:
        """The contact stiffness mu, the friction coefficient and the body masses, after checking the model parameters a user may change (or
        a gradient step may push) after ``finalize``, the joints' gains and limits included: a
        zero mass sent a resting puck 16 m up and a negative friction spun it, silently; the
        others failed as "no convergence" or blamed dt. ValueError naming the parameter (and
        body or coordinate). The values are those ``_solve`` read back with the step's poses."""
        model = self.model
        read = self._readback.read
        mu = float(read("contact_stiffness")[0])
        friction = float(read("friction")[0])
        for name, value in (("contact_stiffness", mu), ("friction", friction), ("friction_smoothing", model.friction_smoothing)):
            problem = contact_setting_problem(name, value)
            if problem is not None:
                raise ValueError(f"model.{name}: {problem}, got {value!r}")
        problem = gravity_problem(model.gravity)
        if problem is not None:
            # A NaN was blamed on dt and the control's targets, 4 numbers on Warp's vector constructor.
            raise ValueError(f"model.gravity: {problem}, got {model.gravity!r}")
        # Which bodies are static is fixed by finalize (the contact model's lists and this
        # solver's coordinates follow it); changed in the array, a resting box made static
        # was flung up 0.5 m in 3 steps.
        dynamic = read("body_dynamic")
        bad = np.flatnonzero((dynamic != 0) != self._dynamic)
        if bad.size:
            b = int(bad[0])
            raise ValueError(
                f"model.body_dynamic: body {model.body_names[b]!r} has {int(dynamic[b])} where the model was built "
                f"{'dynamic (1)' if self._dynamic[b] else 'static (0)'}; which bodies are static is fixed when the model is built: build it again"
            )
        mass = read("body_mass")
        bad = np.flatnonzero(self._dynamic & ~(np.isfinite(mass) & (mass > 0.0)))
        if bad.size:
            raise ValueError(f"model.body_mass: body {model.body_names[bad[0]]!r} has mass {float(mass[bad[0]])!r}; a dynamic body's mass must be positive and finite")
        # Changed after finalize to NaN, zero or negative, it was blamed on dt ("rotation per
        # step too large") for a body at rest, and the tolerance kept the old one's size.
        # Of the dynamic bodies only: a static body's are never read (1,000 static boxes made
        # this check 0.7 ms a step).
        moment = read("body_unit_second_moment")
        dynamic_bodies = self._dynamic_bodies
        checked = moment[dynamic_bodies]
        with np.errstate(invalid="ignore"):
            symmetric = np.isfinite(checked).all(axis=(1, 2)) & (np.abs(checked - checked.transpose(0, 2, 1)) <= 1e-9 * np.abs(checked).max(axis=(1, 2))[:, None, None]).all(axis=(1, 2))
        eigenvalues = np.zeros((len(checked), 3))
        eigenvalues[symmetric] = np.linalg.eigvalsh(checked[symmetric])
        bad = dynamic_bodies[~(eigenvalues.min(axis=1) > 0.0)]
        if bad.size:
            raise ValueError(f"model.body_unit_second_moment: body {model.body_names[bad[0]]!r} has {moment[bad[0]].tolist()}; a dynamic body's must be finite, symmetric and positive definite (m^2)")
        # add_body's range, for a second moment changed since (1e120 failed as "rotation per
        # step too large"); the inertia over the mass is tr(S) 1 - S.
        unit_inertia = eigenvalues.sum(axis=1)[:, None] - eigenvalues
        bad = np.flatnonzero(unit_inertia_outside(unit_inertia))
        if bad.size:
            b = dynamic_bodies[bad[0]]
            raise ValueError(f"model.body_unit_second_moment: body {model.body_names[b]!r}: its inertia over its mass {unit_inertia_problem(unit_inertia[bad[0]])}")
        self._unit_second_moment_trace = np.trace(moment, axis1=1, axis2=2)
        for name in _GAIN_ARRAYS:
            gains = read(name).reshape(model.num_bodies, -1)
            bad = np.flatnonzero(self._dynamic & ~(np.isfinite(gains) & (gains >= 0.0)).all(axis=1))
            if bad.size:  # a negative gain put energy in, silently
                raise ValueError(f"model.{name}: body {model.body_names[bad[0]]!r} has {gains[bad[0]].tolist()}; PD gains must be finite and >= 0")
        problem = self._articulation.parameter_problem() if self._articulation is not None else None
        if problem is not None:
            raise ValueError(f"model.articulation.{problem}")
        return mu, friction, mass

    def _pressed(self, travel: np.ndarray, evaluation, rounding_length: np.ndarray) -> bool:
        """Whether a body's step ``travel`` (m) exceeds _CONVERGED_GAP_FRACTION of the
        separation bound of its closest pair at ``evaluation`` (and its coordinates'
        ``rounding_length``, per body; ipc's per pair where it matters, ``ipc.PAIR_DISTANCE_FRACTION``).
        Asked only of steps short enough to converge otherwise."""
        a, b = self._pair_bodies.T
        limit = _CONVERGED_GAP_FRACTION * evaluation.pair_separation
        return bool(np.any((travel[a] > np.maximum(limit, rounding_length[a])) | (travel[b] > np.maximum(limit, rounding_length[b]))))

    def _friction_frame(self, mu: float, friction: float, dt: float) -> "LaggedFriction | None":
        """Lagged friction data at the configuration the contact model evaluated last (q^t);
        None when the friction coefficient is 0, so that no friction work is done."""
        model = self.model
        if friction == 0.0:
            return None
        return model.contact.friction_frame(mu, model.friction, model.friction_smoothing * dt, coefficient=friction)

    def _friction_rate_frame(self, mu: float, dt: float) -> "LaggedFriction":
        """The lagged friction data at q^t with coefficient 1: D is linear in the coefficient,
        so d/d friction at 0 (one-sided: it cannot be negative) is the adjoint of this D. The
        step itself stays frictionless; without it that gradient was silently 0."""
        model = self.model
        if self._unit_friction is None:
            self._unit_friction = wp.array([1.0], dtype=wp.float64, device=model.device)
        return model.contact.friction_frame(mu, self._unit_friction, model.friction_smoothing * dt, coefficient=1.0)

    def _evaluate(self, poses: np.ndarray, coords: np.ndarray, step_in: "_StepInputs", contact=None):
        """L, its gradient and Hessian over the reduced coordinates, the contact evaluation and
        the articulation Jacobian at ``poses`` (None for free bodies only); ``contact``: the
        contact model's evaluation at ``poses`` when the caller already has it."""
        # The body terms are launched first, so that the contact evaluation's wait covers them.
        self._trial_q_host.numpy()[:] = poses
        wp.copy(self._trial_q, self._trial_q_host)
        self._launches.launch(
            "body energy",
            dynamics_kernels.body_energy_kernel,
            dim=self.model.num_bodies,
            inputs=[step_in.bodies, self._trial_q, step_in.body_q, self._predicted_position, self._predicted_rotation, step_in.body_target],
            outputs=[self._energy, self._energy_grad, self._energy_hess],
        )
        self._readback.enqueue(energy=self._energy, energy_grad=self._energy_grad, energy_hess=self._energy_hess)
        # A lagged frame without pairs adds zeros (0.9 ms an evaluation at 64 bodies).
        friction = step_in.friction if step_in.friction is not None and step_in.friction.pairs else None
        if contact is None:
            # With the friction terms queued behind the evaluation's wait: on a GPU a wait of
            # their own was one more synchronisation an evaluation.
            contact = self.model.contact.evaluate(poses, friction=friction)
        self._readback.wait()
        if not contact.ok:
            return np.inf, None, None, contact, None
        read = self._readback.read
        mu = step_in.mu
        value = float(read("energy").sum()) + mu * contact.value
        grad = read("energy_grad").reshape(-1) + mu * contact.grad.reshape(-1)
        hess = mu * contact.hessian
        if friction is not None:
            f_value, f_grad, f_hess = self.model.contact.friction_terms(friction)
            self._friction_at_evaluation = (poses.copy(), f_value, f_grad, f_hess)
            value += f_value
            grad += f_grad
            hess += f_hess
        # The k-th dynamic body's terms are the k-th diagonal 6x6 block.
        rows = self._block_rows
        hess[rows[:, :, None], rows[:, None, :]] += read("energy_hess")[self._dynamic_bodies]
        art = self._articulation
        if art is None:
            return value, grad[self._dofs], hess, contact, None
        J, reduced_grad, reduced_hess = art.reduce(poses, grad, hess)
        if art.cones:
            c_value, c_grad, c_hess = art.cone_terms(poses)
            if not np.isfinite(c_value):
                return np.inf, None, None, contact, None
            value += c_value
            reduced_grad += c_grad
            reduced_hess += c_hess
        if art.has_ball_drives:
            b_value, b_grad, b_hess = art.ball_drive_terms(poses, step_in.ball_target, step_in.ball_start, step_in.dt)
            value += b_value
            reduced_grad += b_grad
            reduced_hess += b_hess
        if art.num_coordinates:
            j_value, j_grad, j_hess = self._joint_terms(coords, step_in)
            c = art.coordinate_dof
            value += j_value
            reduced_grad[c] += j_grad
            reduced_hess[c, c] += j_hess
        return value, reduced_grad, reduced_hess, contact, J

    def _joint_terms(self, coords: np.ndarray, step_in: "_StepInputs"):
        """Joint-space PD (implicit, like the body PD) and limit barriers: value, gradient, diagonal Hessian."""
        art = self._articulation
        dt = step_in.dt
        error = _pd_error(art.kp, coords, step_in.joint_target)
        velocity = coords - step_in.joint_q
        with np.errstate(over="ignore"):  # a target beyond float64's reach: _solve names it
            value = 0.5 * float(np.sum(art.kp * error**2 + art.kd / dt * velocity**2))
        grad = art.kp * error + art.kd / dt * velocity
        hess = art.kp + art.kd / dt
        if art.has_limits:
            l_value, l_grad, l_hess = joint_limit_energy(coords, art.lower, art.upper, art.limit_margins(), art.limit_stiffness)
            value += float(l_value.sum())
            grad = grad + l_grad
            hess = hess + l_hess
        return value, grad, hess

    def _limit_step(self, poses: np.ndarray, coords: np.ndarray, direction: np.ndarray) -> float:
        """Largest step fraction that closes at most ``advancement_fraction`` of any joint
        coordinate's distance to its limits, or of any ball joint's room to its cone limit."""
        art = self._articulation
        if art is None:
            return 1.0
        cone_alpha = art.cone_step_limit(poses, direction, self.advancement_fraction) if art.cones else 1.0
        if not art.has_limits:
            return cone_alpha
        delta = direction[art.coordinate_dof]
        room = np.where(delta < 0, coords - art.lower, art.upper - coords)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(delta != 0, self.advancement_fraction * room / np.abs(delta), np.inf)
        return float(min(1.0, cone_alpha, ratio.min(initial=np.inf)))

    def _newton_direction(self, hess: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Descent direction from H d = -g (``_saddle_free_direction``'s first part)."""
        return self._saddle_free_direction(hess, grad)[0]

    def _saddle_free_direction(self, hess: np.ndarray, grad: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Descent direction from H d = -g, and the part of it that a floor cut short.

        The contact potential is not convex, so H can be indefinite away from the minimum;
        then its negative eigenvalues are replaced by their magnitudes (floored at 1e-10 of
        the largest), which keeps the curvature of every other direction, unlike a uniform
        diagonal shift that degrades Newton to gradient descent. The second part is None,
        or, where the floor raised eigenvalues, the direction along those eigenvectors with
        their own magnitudes: a step the floor shortened below the tolerance is no
        convergence (a box between walls 1e-9 m away, stiffness ~1e23 against its inertia's
        ~1e4, stood still in free fall, "converged" at every step).
        """
        try:
            chol = np.linalg.cholesky(hess)
            return -_solve_upper(chol.T, _solve_lower(chol, grad)), None
        except np.linalg.LinAlgError:
            values, vectors = np.linalg.eigh(hess)
            magnitude = np.abs(values)
            floor = 1e-10 * magnitude.max()
            if not np.isfinite(floor) or floor == 0.0:
                raise SolverError(f"Newton system is singular or not finite (eigenvalues {values.min():.3e} .. {values.max():.3e})") from None
            along = vectors.T @ grad
            direction = -vectors @ (along / np.maximum(magnitude, floor))
            floored = magnitude < floor
            if not floored.any():
                return direction, None
            return direction, -vectors[:, floored] @ (along[floored] / np.maximum(magnitude[floored], np.finfo(float).tiny))

    def _friction_exact_direction(self, q: np.ndarray, grad: np.ndarray, hess: np.ndarray, direction: np.ndarray, friction: LaggedFriction) -> np.ndarray:
        """Minimiser d of m(d) = g_o.d + 1/2 d^T H_o d + D(q + d) - D(q) over the free bodies'
        rigid coordinates, where g_o and H_o are L's gradient and Hessian at q without the
        friction D (from the last ``_evaluate``, at q), and D is evaluated exactly at the
        retracted poses.

        m shares L's gradient at q, and its first Newton step from d = 0 is ``direction``
        (the plain Newton direction), so d only improves on it where D's quadratic model
        fails: slips crossing the smoothing scale, where plain Newton steps overshoot and
        backtrack. D's gradient at q + d is taken in that pose's chart, which is exact for
        translations and first-order for rotations; the outer iteration, with L exact,
        decides acceptance. Returns ``direction`` when H_o is not positive definite or d is
        not a descent direction of L.
        """
        dofs = self._dofs
        contact = self.model.contact
        evaluated_at, f_value, f_grad, f_hess = self._friction_at_evaluation
        if not np.array_equal(evaluated_at, q):  # a rejected warm start was evaluated last
            f_value, f_grad, f_hess = contact.friction_terms(friction, poses=q)
        f_grad = f_grad[dofs]
        g_other, h_other = grad - f_grad, hess - f_hess
        try:
            np.linalg.cholesky(h_other)
        except np.linalg.LinAlgError:
            return direction

        def travel(d):
            return float(self._step_travel(d)[1].max())

        def friction_at(d):
            value, g, h = contact.friction_terms(friction, poses=retract(q, self._step_travel(d)[0]))
            return value - f_value, g[dofs], h

        # Steps longer than the slip smoothing length leave the friction's quadratic model
        # (``_solve``'s converged length).
        tol = min(self.tolerance * self._length_scale, friction.slip_smoothing)
        d = np.zeros_like(grad)
        model_value, model_grad, step = 0.0, grad, direction
        for _ in range(_FRICTION_MODEL_ITERATIONS):
            if travel(step) <= max(tol, _FRICTION_MODEL_TOLERANCE * travel(d)):
                break
            slope = float(model_grad @ step)
            t = 1.0
            for _ in range(_FRICTION_MODEL_HALVINGS):
                trial = d + t * step
                friction_change, t_grad, t_hess = friction_at(trial)
                trial_value = float(g_other @ trial + 0.5 * trial @ h_other @ trial) + friction_change
                if trial_value <= model_value + 1e-4 * t * slope:
                    break
                t *= 0.5
            else:
                break
            d, model_value = trial, trial_value
            model_grad = g_other + h_other @ d + t_grad
            step = self._newton_direction(h_other + t_hess, model_grad)
        return d if float(grad @ d) < 0.0 else direction

    def _unblocked_direction(self, grad: np.ndarray, hess: np.ndarray, direction: np.ndarray, alpha: float, frame=None) -> tuple[np.ndarray, float]:
        """A direction and its advancement bound for a Newton step that a near contact blocks.

        A body struck from almost touching can be asked to turn or slide far in one step;
        conservative advancement then admits ~1e-3 of the Newton direction per iteration, the
        pose hardly changes, and Newton proposes the same direction again (hundreds of
        iterations). Levenberg-Marquardt directions (H + lambda diag H) d = -g shorten and
        turn the step towards -g; each is cut by its own advancement bound, and the one whose
        bounded step lowers the quadratic model of L most is taken (the Newton direction
        itself when none does better). Rigid bodies only (joints keep plain Newton).
        ``frame``: q's term lists when the contact model last evaluated elsewhere.
        """

        def model_change(d: np.ndarray, a: float) -> float:
            return a * float(grad @ d) + 0.5 * a * a * float(d @ hess @ d)

        best_change, best_direction, best_alpha = model_change(direction, alpha), direction, alpha
        scaling = np.diag(np.maximum(np.diag(hess), np.finfo(float).tiny))
        damping = _DAMPING_FIRST
        while damping <= _DAMPING_LAST:
            d = self._newton_direction(hess + damping * scaling, grad)
            a = self.model.contact.advancement_limit(self._step_travel(d)[0], fraction=self.advancement_fraction, frame=frame)
            change = model_change(d, a)
            if change < best_change:
                best_change, best_direction, best_alpha = change, d, a
            elif best_direction is not direction:
                break  # past the best damping
            damping *= _DAMPING_FACTOR
        return best_direction, best_alpha

    def _step_travel(self, direction: np.ndarray, jacobian: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The (nbodies, 6) rigid-coordinate step (dp, dtheta) of a Newton direction (over the
        free bodies' dofs, or mapped by an articulation's ``jacobian``) and how far any point
        of each body moves under it (m)."""
        if jacobian is None:
            step = np.zeros((self.model.num_bodies, 6))
            step.reshape(-1)[self._dofs] = direction
        else:
            step = (jacobian @ direction).reshape(-1, 6)
        return step, rigid_step_travel(step, self.model.body_radius)

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> StepInfo:
        """Advance one time step of ``dt`` seconds from ``state_in`` into ``state_out``.

        Raises ValueError before writing anything if dt is not a positive number, a state's
        arrays are not one pose per body of this model, ``state_in`` holds non-finite poses
        or a zero quaternion, or bodies intersect in it; raises SolverError with diagnostics
        if Newton does not converge, or if its solution moves one body through another
        (``_pass_through``: dt too large for the impact). Nothing is written then.
        Inside ``with wp.Tape()``, records the step's implicit-function-theorem backward, which
        consumes ``state_out``'s gradients (zeroes them once read, as Warp's adjoints of array
        writes do: intermediate states hold none after ``tape.backward()``); the
        states must then have gradient arrays, and no model array other than body_mass,
        contact_stiffness and friction may have requires_grad set (ValueError before anything
        is written).
        """
        if not self.model.step_lock.acquire(blocking=False):
            # Two threads stepping one model: one failed naming an internal function, the
            # other's trajectory moved by 2.5e-9 m (a probe).
            raise RuntimeError("model: another thread is stepping this model; a Model serves one thread at a time (its contact model keeps each step's evaluations): build one model per thread")
        try:
            with paused_tape() as tape:
                if tape is not None:
                    self._check_taped_step(tape, state_in, state_out, control)
                info, record = self._solve(state_in, state_out, control, dt, taped=tape is not None)
        finally:
            self.model.step_lock.release()
        if tape is not None:
            backward, arrays, control_values = record()
            tape.record_func(backward, arrays)
            noted = _taped_step_arrays(tape)
            for _, array in self._taped_state_arrays(state_in, state_out):
                noted[id(array)] = None
            noted.update(control_values)
        return info

    def _check_taped_step(self, tape: wp.Tape, state_in: State, state_out: State, control: Control | None):
        """Refuse, before anything is written, a step whose recorded backward would be wrong."""
        for label, array in self._taped_state_arrays(state_in, state_out):
            if isinstance(array, wp.array) and not array.requires_grad:
                raise ValueError(
                    f"{label}: has no gradient array, but the step is recorded on a wp.Tape; make the states with "
                    "model.state(requires_grad=True), or step outside the tape"
                )
        for name in _UNDIFFERENTIATED_MODEL_ARRAYS:
            if getattr(self.model, name).requires_grad:
                raise ValueError(
                    f"model.{name}: requires_grad is set, but the step's backward does not differentiate it (its gradient "
                    f"would stay zero); gradients reach {', '.join('model.' + n for n in _DIFFERENTIATED_MODEL_ARRAYS)}"
                )
        # A backward reads the adjoint its output's gradient holds when it runs; an output
        # buffer that an earlier recorded step also read or wrote (two states swapped back
        # and forth) mixes their adjoints: the gradient came out 4x too large, silently.
        noted = _taped_step_arrays(tape)
        for label, array in self._taped_state_arrays(state_in, state_out):
            if label.startswith("state_out") and id(array) in noted:
                raise ValueError(
                    f"{label}: an earlier step recorded on this wp.Tape already uses this array, and its backward would read "
                    "this step's adjoints; make a new State for every time step (model.state()) while recording"
                )
        # A control shared by several recorded steps gets the sum of their adjoints: right for
        # a target held constant, but not for one rewritten in place between steps. A state's
        # array (noted None) as a target, the poses a step starts from, was refused as changed.
        for label, array in _taped_control_arrays(control):
            if noted.get(id(array)) is not None and not np.array_equal(_host(noted[id(array)]), array.numpy()):
                raise ValueError(
                    f"{label}: its values changed since an earlier step recorded on this wp.Tape used it, and its gradient "
                    "would add up both steps' adjoints; make a new Control for every time step (model.control()) while recording"
                )

    def _joint_arrays(self, state_in: State, state_out: State, control: Control | None, poses: np.ndarray):
        """Current joint coordinates and joint targets (numpy); checks the joint buffers and
        that the coordinates agree with the current ``poses`` (normalised state_in.body_q)."""
        count = self.model.num_joint_coordinates
        buffers = (("state_in.joint_q", state_in.joint_q), ("state_out.joint_q", state_out.joint_q), ("state_out.joint_q_prev", state_out.joint_q_prev))
        if count == 0:
            supplied = None if control is None else control.joint_target
            if supplied is not None and not (isinstance(supplied, wp.array) and supplied.shape == (0,)):
                # Ignored before: targets for joints the model does not have.
                raise ValueError(f"control.joint_target: this model has no joint coordinates; expected None or model.control()'s empty array, got {_described(supplied)}")
            for label, arr in buffers:
                # Ignored before: coordinates for joints the model does not have.
                if arr is not None and not (isinstance(arr, wp.array) and arr.shape == (0,)):
                    raise ValueError(f"{label}: this model has no joint coordinates; expected None or model.state()'s empty array, got {_described(arr)}")
            return np.zeros(0), np.zeros(0)
        for label, arr in buffers:
            # An int32 output stored the coordinates truncated, silently, and the next step
            # blamed the state's consistency.
            if not isinstance(arr, wp.array) or arr.shape != (count,) or arr.dtype != wp.float64:
                raise ValueError(f"{label}: expected a float64 wp.array of the model's {count} joint coordinates (use model.state())")
        coords = state_in.joint_q.numpy()
        art = self._articulation
        bad = np.flatnonzero(~np.isfinite(coords))
        if bad.size:
            # Named like a body target's: "contains non-finite values" named no coordinate.
            raise ValueError(f"state_in.joint_q: coordinate {art.coordinate_names[bad[0]]!r} is {float(coords[bad[0]])!r}; expected finite values")
        # The state holds each configuration twice; the step reads the poses for contact and
        # the coordinates for drives and limits, so they must agree. The check (~0.3 ms a joint)
        # is skipped for what this solver's last step wrote, which agrees by construction.
        written = self._last_written
        problem = None if written is not None and np.array_equal(written[0], poses) and np.array_equal(written[1], coords) else art.state_problem(poses, coords)
        if problem:
            raise ValueError(f"state_in: {problem}; set both from one configuration (model.state() gives a consistent one)")
        outside = np.flatnonzero((coords <= art.lower) | (coords >= art.upper))
        if outside.size:
            i = outside[0]
            raise ValueError(f"state_in.joint_q: coordinate {art.coordinate_names[i]!r} = {coords[i]:.6g} is not strictly inside its limits ({art.lower[i]:.6g}, {art.upper[i]:.6g})")
        # The limit barrier divides by the square of the distance to the limit, which
        # underflows closer than this: a hinge at 0 with limits (-1e-200, 1) stayed at 0.
        touching = np.flatnonzero((coords - art.lower < MIN_LIMIT_MARGIN) | (art.upper - coords < MIN_LIMIT_MARGIN))
        if touching.size:
            i = touching[0]
            raise ValueError(
                f"state_in.joint_q: coordinate {art.coordinate_names[i]!r} = {coords[i]:.6g} is within {MIN_LIMIT_MARGIN:g} of its limits "
                f"({art.lower[i]:.6g}, {art.upper[i]:.6g}), where the limit barrier's square of the distance underflows; start it farther inside"
            )
        supplied = None if control is None else control.joint_target
        if supplied is not None and not (isinstance(supplied, wp.array) and supplied.dtype == wp.float64):
            raise ValueError(f"control.joint_target: expected a float64 wp.array of {count} joint targets (use model.control()), got {_described(supplied)}")
        target = coords if supplied is None else supplied.numpy()
        if target.shape != (count,):
            raise ValueError(f"control.joint_target: expected {count} finite joint targets, got shape {target.shape}")
        bad = np.flatnonzero(~np.isfinite(target))
        if bad.size:
            raise ValueError(f"control.joint_target: the target of coordinate {art.coordinate_names[bad[0]]!r} is {float(target[bad[0]])!r}; expected {count} finite joint targets")
        return coords, target

    def _ball_arrays(self, control: Control | None, poses: np.ndarray):
        """Ball-joint target rotations and rotations at ``poses`` (nball, 4); checks the targets."""
        art = self.model.articulation
        start = art.ball_rotations(poses)
        supplied = None if control is None else control.ball_target
        if supplied is None:
            return start, start
        count = art.num_ball_joints
        if not isinstance(supplied, wp.array) or supplied.dtype != wp.quatd or supplied.shape != (count,):
            raise ValueError(f"control.ball_target: expected a wp.array of {count} wp.quatd (x, y, z, w), one per ball joint {art.ball_joint_names} (use model.control()), got {_described(supplied)}")
        target = supplied.numpy()
        bad = np.flatnonzero(~np.isfinite(target).all(axis=1))
        if bad.size:
            raise ValueError(f"control.ball_target: the target of ball joint {art.ball_joint_names[bad[0]]!r} is {target[bad[0]].tolist()}; expected a finite rotation quaternion")
        # Normalised as body targets are, with the same norms accepted: an optimiser's step on
        # a target (or a finite difference of 1e-5) leaves the unit sphere, and was refused.
        _check_quaternion_norms(target, np.ones(count, dtype=bool), "control.ball_target", art.ball_joint_names, whose="the target of ball joint")
        return target / np.linalg.norm(target, axis=1)[:, None], start

    def _solve(self, state_in: State, state_out: State, control: Control | None, dt: float, *, taped: bool = False):
        check_time_step(dt)
        dt = float(dt)  # an np.float32 dt made float32 of every product with it
        model = self.model
        for label, given in (("state_in", state_in), ("state_out", state_out)):
            if not isinstance(given, State):
                raise ValueError(f"{label}: expected a State (model.state()), got {type(given).__name__}")
        if control is not None and not isinstance(control, Control):
            raise ValueError(f"control: expected a Control (model.control()) or None, got {type(control).__name__}")
        if state_out is state_in:
            raise ValueError("state_out: must be a different State from state_in (one buffer per time step)")
        for label, state in (("state_in", state_in), ("state_out", state_out)):
            for name in ("body_q", "body_q_prev"):
                _check_pose_array(getattr(state, name, None), model.num_bodies, f"{label}.{name}", "one per body of this model (use model.state())")
        _check_no_shared_arrays(state_in, state_out)
        if model.contact is not self._contact:
            raise ValueError(f"model.contact: replaced after this solver was made (now {_described(model.contact)}); the solver's tables belong to the model's own contact model: make a new ImplicitSolver, or restore it")
        for name, (dtype, shape) in self._model_array_layout.items():
            value = getattr(model, name)
            if not isinstance(value, wp.array) or value.dtype != dtype or value.shape != shape or value.device != model.device:
                got = f"{_described(value)} on {value.device}" if isinstance(value, wp.array) else _described(value)
                raise ValueError(f"model.{name}: expected a {dtype.__name__} wp.array of shape {shape} on {model.device}, as the model was built, got {got}")
        # One wait for the poses and every model parameter the step checks: each read of its
        # own was a synchronisation of a GPU.
        self._readback.enqueue(body_q=state_in.body_q, body_q_prev=state_in.body_q_prev, **{name: getattr(model, name) for name in _CHECKED_MODEL_ARRAYS})
        self._readback.wait()
        # Copies: the reads are views of the state's memory (CPU) or of reused host buffers.
        q_now = self._readback.read("body_q").copy()
        q_prev = self._readback.read("body_q_prev").copy()
        for label, arr in (("state_in.body_q", q_now), ("state_in.body_q_prev", q_prev)):
            check_finite_poses(arr, label, model.body_names)
            # Checked here by name: beyond it the previous pose (a velocity of 1e300 m/s given
            # to set_body_velocity) was blamed on dt and the control's targets.
            far = beyond_coordinates(arr[:, :3])
            if far is not None:
                b = far[0]
                raise ValueError(f"{label}: body {model.body_names[b]!r} (index {b}) is at {arr[b, :3].tolist()}, beyond the +-{MAX_COORDINATE:g} m of a body's coordinates")
            _check_quaternion_norms(arr[:, 3:], np.ones(len(arr), dtype=bool), label, model.body_names)
        if control is not None:
            _check_pose_array(control.body_target, len(q_now), "control.body_target", "one per body (use model.control())")
        q = normalized_poses(q_now)
        # Before the joint arrays, which are checked against the limits.
        mu, friction_coefficient, mass = self._checked_model_parameters()
        fall = float(np.abs(model.gravity).max()) * dt * dt
        if fall > MAX_COORDINATE:
            # The step's free fall g dt^2 then overflowed the kernels' coordinates: the error
            # named an internal argument of the advancement bound.
            raise ValueError(f"model.gravity and dt: gravity {np.asarray(model.gravity, dtype=np.float64).tolist()} m/s^2 falls {fall:.3g} m in dt={dt} s, beyond the +-{MAX_COORDINATE:g} m of a body's coordinates; reduce dt or gravity")
        if fall > 0.0 and len(self._dynamic_bodies):
            # A step no longer than the rounding of a body's coordinates counts as converged
            # (the rounding floor): at z = 100 m and dt 1e-7 s a box hung in the air, its fall
            # of 1e-13 m a step dropped every step, without a word (a probe).
            reach = _coordinate_rounding(q[self._dynamic_bodies])
            for stuck in np.flatnonzero(fall <= reach):
                body = int(self._dynamic_bodies[stuck])
                if body not in self._unresolved_fall:
                    self._unresolved_fall.add(body)
                    warnings.warn(
                        f"dt: {dt:g} s is too short for body {model.body_names[body]!r} {np.abs(q[body, :3]).max():.3g} m from the origin: its free fall in a step, "
                        f"{fall:.3g} m, is below the float64 rounding of its coordinates ({reach[stuck]:.3g} m), which the steps take for convergence, so "
                        "gravity will not move it; use a longer dt or place the scene nearer the origin",
                        stacklevel=3,
                    )
        coords_now, joint_target = self._joint_arrays(state_in, state_out, control, q)
        if self._articulation is not None and self._articulation.cones:
            # A swing on or past its cone made the start's energy infinite, blamed on dt,
            # inertia and gravity.
            problem = self._articulation.cone_problem(q)
            if problem is not None:
                raise ValueError(f"state_in.body_q: {problem}")
        ball_target, ball_start = self._ball_arrays(control, q_now)
        dynamic = self._dynamic
        art = self._articulation

        q_start = q.copy()
        start = model.contact.evaluate(q, reuse=True)
        if start.contact_pairs:
            names = ", ".join(f"{a} and {b}" for a, b in start.contact_pairs)
            raise ValueError(f"state_in: bodies intersect or touch at the start of the step: {names}")
        # Gaps of a few units of roundoff: a box set exactly on a plate (z = half height + top,
        # 1.7e-17 m apart) took one Newton iteration a step and hardly moved, silently.
        touching = self._touching_pair(start)
        if touching is not None:
            a, b, gap = touching
            raise ValueError(
                f"state_in: bodies {a!r} and {b!r} start {gap:.3g} m apart, "
                "within the rounding of their coordinates (they touch to float64): start them farther apart (a resting gap is ~sqrt(100 mu / (m g)))"
            )
        friction = self._friction_frame(mu, friction_coefficient, dt)
        step_in = _StepInputs(
            dt=float(dt),
            bodies=self._body_model(dt),
            mu=mu,
            friction=friction,
            friction_rate=self._friction_rate_frame(mu, dt) if taped and friction is None and model.friction.requires_grad else None,
            body_q=state_in.body_q,
            body_target=control.body_target if control is not None else state_in.body_q,
            joint_q=coords_now,
            joint_target=joint_target,
            ball_target=ball_target,
            ball_start=ball_start,
        )

        wp.launch(
            dynamics_kernels.predict_kernel,
            dim=model.num_bodies,
            inputs=[model.body_unit_second_moment, model.body_dynamic, state_in.body_q, state_in.body_q_prev],
            outputs=[self._predicted_position, self._predicted_rotation, self._prediction_sensitivity, self._predict_status],
            device=model.device,
        )
        # One wait for the status and the prediction the warm start reads: three reads of their
        # own were three synchronisations of a GPU a step.
        self._readback.enqueue(predict_status=self._predict_status, predicted_position=self._predicted_position, predicted_rotation=self._predicted_rotation)
        self._readback.wait()
        failed = np.flatnonzero(self._readback.read("predict_status"))
        if failed.size:
            raise SolverError(f"rotation prediction failed for {[model.body_names[i] for i in failed]}: rotation per step too large for dt={dt}")

        coords = coords_now.copy()
        value, grad, hess, contact, jacobian = self._evaluate(q, coords, step_in, start)
        # The term lists that bound the next Newton step when the contact model's last
        # evaluation was elsewhere (None: its lists are those of q).
        q_lists = None
        if art is None and np.isfinite(value):
            q, value, grad, hess, contact, q_lists = self._warm_start(q, value, grad, hess, contact, coords, step_in)
        if not np.isfinite(value):
            if control is not None:
                # Read back only on failure: a non-finite PD target, or a zero rotation for a
                # body with rotational PD stiffness, is the caller's error.
                targets = control.body_target.numpy()
                # Only targets with gains count (an unactuated axis ignores its target).
                kp_linear = model.body_kp_linear.numpy()
                kp_angular = model.body_kp_angular.numpy()
                used = np.concatenate([kp_linear != 0.0, np.repeat((kp_angular != 0.0)[:, None], 4, axis=1)], axis=1)
                bad = np.flatnonzero((~np.isfinite(targets) & used).any(axis=1) & self._dynamic)
                if bad.size:
                    raise ValueError(f"control.body_target: the target of body {self.model.body_names[bad[0]]!r} (index {bad[0]}) is not finite")
                _check_quaternion_norms(targets[:, 3:], (kp_angular != 0.0) & self._dynamic, "control.body_target", self.model.body_names, whose="the target of body")
            # Joint coordinates outside their limits were refused with the state (_joint_arrays).
            if art is not None and art.num_coordinates:
                with np.errstate(over="ignore"):
                    overflow = np.flatnonzero(~np.isfinite(art.kp * _pd_error(art.kp, coords_now, joint_target) ** 2))
                if overflow.size:
                    c = overflow[0]
                    raise ValueError(f"control.joint_target: the PD energy of coordinate {art.coordinate_names[c]!r} overflows float64 (target {joint_target[c]:.6g}, coordinate {coords_now[c]:.6g}, kp {art.kp[c]:.6g})")
            if contact.unsolved_pairs:
                pairs = ", ".join(f"{a} and {b}" for a, b in contact.unsolved_pairs)
                raise SolverError(f"objective is not finite at the start pose: {pairs}: {UNSOLVED_HINT}")
            if not np.isfinite(contact.value):
                # Blamed on inertia, gravity and PD terms (a probe, stop 65: the ipc model's
                # potential between two touching static bodies, before it dropped those terms).
                raise SolverError(
                    f"objective is not finite at the start pose: the contact potential is {contact.value}, though no body pair was found "
                    f"touching, intersecting or unsolved; bodies may be pressed closer than float64 resolves, or the contact stiffness (mu {mu:g}) overflows it"
                )
            # Every contact term is finite: it was blamed on the leaf searches of no pair.
            raise SolverError(
                f"objective is not finite at the start pose, though its contact terms are: the bodies' inertia (over dt={dt}), "
                "gravity or PD terms overflow float64; check dt and the control's targets"
            )
        # Steps this short are in Newton's quadratic regime, where Armijo tests only rounding
        # noise; the cap keeps that true for loose tolerances (1e3 x 1e-6 would let full steps
        # cycle at millimetres).
        rounding_step = min(1e3 * self.tolerance, 1e-7) * self._length_scale
        # Nor does Armijo resolve a decrease below L's rounding, which its rotational inertia
        # term sets: (tr S - tr(R_hat S R^T)) / dt^2 is a difference of terms of this size, so
        # L moves in quanta of about eps times it, and an increase within them is no increase
        # (Armijo's slack). A rod spinning in free flight near a post (the warm start refused)
        # ended each step with decrements of 1.7e-14 against quanta of 5.7e-14, and its line
        # search failed.
        rounding_energy = _ROUNDING * float(np.sum((mass * self._unit_second_moment_trace)[dynamic])) / dt**2
        # Nor is a step converged that slips farther than the friction term's smoothing length,
        # beyond which its quadratic model is no measure of the distance to the solution: its
        # curvature (mu N / the slip smoothing) made a box's fall of 1 cm a Newton step of 2.6e-10
        # m at a smoothing of 1e-12 m/s, under the tolerance, and the box hung in the air.
        slip_length = step_in.friction.slip_smoothing if step_in.friction is not None and step_in.friction.pairs else np.inf
        # Every iteration's converged length but the coordinates' rounding, which moves with q.
        converged_step = min(self.converged_step(dt), slip_length)
        converged = False
        iterations = 0
        step_length = np.inf
        # Trial evaluations whose leaf searches failed: a failing step names them.
        unsolved = _UnsolvedTrials()
        last_alpha = None  # the last Newton step's advancement bound
        for iterations in range(1, self.max_iterations + 1):
            direction, floored = self._saddle_free_direction(hess, grad)
            full, travel = self._step_travel(direction, None if art is None else jacobian)
            step_length = float(travel.max())
            # Over slips much shorter than the smoothing length the friction term's quadratic
            # model holds, and plain Newton converges quadratically.
            friction = step_in.friction
            crawling = model.contact.crawl_skips_friction_model and last_alpha is not None and last_alpha < _FRICTION_MODEL_MIN_ALPHA
            if self.exact_friction_steps and art is None and friction is not None and friction.pairs and step_length > friction.slip_smoothing and not crawling:
                direction = self._friction_exact_direction(q, grad, hess, direction, friction)
                full, travel = self._step_travel(direction)
                step_length = float(travel.max())
            # Per body, from its own coordinates: from the largest dynamic coordinate of the scene,
            # a second box 10 km away made a box's whole step at dt 1e-6 (gravity's 1e-11 m)
            # "converged" at its first iteration, and the box never fell.
            rounding_length = _coordinate_rounding(q)
            converged_length = np.maximum(converged_step, rounding_length)
            # A step the saddle-free floor made short is no convergence (_saddle_free_direction).
            hidden_travel = np.zeros(len(travel)) if floored is None else self._step_travel(floored, None if art is None else jacobian)[1]
            hidden = float(hidden_travel.max())
            # Beside a 1/x barrier Newton's step is about half the gap, however unbalanced the
            # force: a box started 4e-11 m above another "converged" at its first step of 2e-11
            # m, pressed by 2e17 N, and stayed there. So no body's step may exceed a fraction
            # of its closest pair's separation (its own: one pressed pair held every body of a
            # scene to its gap).
            if np.all(travel <= converged_length) and not self._pressed(travel, contact, rounding_length) and not (art is not None and art.pressed_limit(q, coords, direction, fraction=_CONVERGED_GAP_FRACTION, rounding=_ROUNDING)):
                if np.any(hidden_travel > converged_length):
                    raise SolverError(self._diagnostics("no convergence", iterations, step_length, value, travel, q_start, dt, unsolved, hess, contact, hidden=hidden, converged_length=converged_length))
                converged = True
                break
            decrement = -float(grad @ direction)
            # The contact model holds the term lists of q (or q_lists does, after a rejected
            # warm start): trials come after this.
            frame = model.contact.advancement_frame() if art is not None else q_lists
            q_lists = None
            alpha = min(model.contact.advancement_limit(full, fraction=self.advancement_fraction, frame=frame), self._limit_step(q, coords, direction))
            if art is None and alpha < _BLOCKED_ALPHA:
                direction, alpha = self._unblocked_direction(grad, hess, direction, alpha, frame)
                full, travel = self._step_travel(direction)
                step_length = float(travel.max())
                decrement = -float(grad @ direction)
            last_alpha = alpha
            # L's rounding scales with its terms, not with L, which is ~0 in free flight under
            # a locally supported contact model (ipc, sdrs): short steps are taken in full.
            quadratic_regime = (decrement <= 1e-10 * max(abs(value), 1e-300) or step_length <= rounding_step) and alpha == 1.0
            accepted = False
            for _ in range(60):
                if art is None:
                    trial, t_coords = retract(q, alpha * full), coords
                else:
                    # Bodies move along products of exponentials, not along the straight
                    # rigid-coordinate paths that conservative advancement bounds, so certify
                    # the straight path to each body's actual trial pose.
                    trial = art.retract(q, alpha * direction)
                    t_coords = coords + alpha * direction[art.coordinate_dof]
                    path = rigid_step_between(q, trial)
                    # An unchanged turned pose gives a rotation of rounding (1e-17), which the
                    # bound refuses from a static body: any scene with joints and a turned
                    # static body failed its first step (a probe, stop 63).
                    path[~dynamic] = 0.0
                    certified = model.contact.advancement_limit(path, fraction=self.advancement_fraction, frame=frame)
                    if certified < 1.0:
                        alpha *= min(max(certified, 0.1), 0.9)
                        continue
                t_value, t_grad, t_hess, t_contact, t_jacobian = self._evaluate(trial, t_coords, step_in)
                unsolved.count(t_contact)
                # Below the rounding of L an Armijo test is noise; full steps are safe there.
                if np.isfinite(t_value) and (quadratic_regime or t_value <= value - 1e-4 * alpha * decrement + rounding_energy):
                    accepted = True
                    break
                alpha *= _backtrack_factor(value, -decrement, t_value, None if t_grad is None else float(t_grad @ direction), alpha)
            if not accepted:
                if step_length <= rounding_step and np.all(hidden_travel <= converged_length):
                    converged = True  # stalled at the rounding floor of L
                    break
                raise SolverError(self._diagnostics("line search failed", iterations, step_length, value, travel, q_start, dt, unsolved, hess, contact, hidden=hidden, converged_length=converged_length))
            q, coords, value, grad, hess, contact, jacobian = trial, t_coords, t_value, t_grad, t_hess, t_contact, t_jacobian
        if not converged:
            # The move the saddle-free floor hid at the last iterate, as where steps converge:
            # steps capped by a pressed pair's gap iterate on to here.
            raise SolverError(self._diagnostics("no convergence", iterations, step_length, value, travel, q_start, dt, unsolved, hess, contact, hidden=hidden, converged_length=converged_length))

        # A solution the next step would refuse as its start: a simulation ended there with
        # "start them farther apart" and wrote none of its frames (mu 1e-30, a probe).
        touching = self._touching_pair(contact)
        if touching is not None:
            a, b, gap = touching
            raise SolverError(
                f"the step's solution leaves bodies {a!r} and {b!r} {gap:.3g} m apart, within the rounding of their coordinates (they touch to float64), "
                f"so no step could start from it: the contact stiffness (mu {mu:g}) is too small for these bodies' weight and size (a resting gap is ~sqrt(100 mu / (m g)))"
            )
        # The friction adjoint needs the poses the friction terms saw: unit quaternions for the
        # static bodies too, whose user-given values (of any norm) go back into state_out.
        q_solved = q.copy()
        q[~dynamic] = q_now[~dynamic]
        passed = self._pass_through(q_start, q, dt, None if art is None else art.step_between(q_start, q_solved, coords_now, coords))
        if passed is not None:
            raise SolverError(passed)
        state_out.body_q.assign(q)
        state_out.body_q_prev.assign(q_now)
        if len(coords):
            state_out.joint_q.assign(coords)
            state_out.joint_q_prev.assign(coords_now)
            self._last_written = (normalized_poses(q), coords.copy())
        friction = step_in.friction
        self.last_step = StepInfo(
            iterations,
            step_length,
            value,
            float(contact.pair_separation.min()) if len(contact.pair_separation) else np.inf,
            friction.pairs if friction is not None else 0,
        )
        return self.last_step, lambda: self._backward_function(state_in, state_out, control, step_in, hess, jacobian, contact.grad, q, q_now, q_prev, (q_solved, q_start))

    def _touching_pair(self, evaluation) -> tuple[str, str, float] | None:
        """(name, name, separation) of the first body pair of an evaluation within the rounding
        of the coordinates, or None. Unsolved pairs have their own error; ipc's barrier refuses
        a zero distance itself (and its separations are its pairs' own only below
        ``ipc.PAIR_DISTANCE_FRACTION`` of dhat: above it one global distance, which named the
        first pair, not the touching one)."""
        contact = self.model.contact
        if evaluation.unsolved_pairs or not isinstance(contact, ContactModel):
            return None
        touching = np.flatnonzero(evaluation.pair_separation <= _ROUNDING * self._length_scale)
        if not touching.size:
            return None
        a, b = contact.body_pairs[touching[0]]
        return self.model.body_names[a], self.model.body_names[b], float(evaluation.pair_separation[touching[0]])

    def converged_step(self, dt: float) -> float:
        """The Newton step length (m) under which a step of ``dt`` (s) converges: ``tolerance``
        times the largest body radius, capped at 1e-5 m/s^2 x dt^2 (a step's acceleration
        error), before the per-body rounding floor and friction's slip smoothing length.
        Tolerances above the cap's converge alike: at dt 0.04 s beside a 2.5 m table every
        tolerance above ~6e-9."""
        return min(self.tolerance * self._length_scale, _CONVERGED_ACCELERATION * dt * dt)

    def _warm_start(self, q, value, grad, hess, contact, coords, step_in):
        """Start Newton from the inertial prediction (``predict_kernel``: where each body would
        coast to, the minimiser of the inertia term) when conservative advancement certifies
        the whole path to it and L is lower there.

        Returns the start (q, value, grad, hess, contact) and, when the prediction was
        evaluated and rejected, an ``AdvancementFrame`` of q's term lists for the first
        Newton step's bound (else None), instead of evaluating q again."""
        model = self.model
        dynamic = self._dynamic_bodies
        # As read back with the prediction's status (``_solve``).
        position = self._readback.read("predicted_position")
        rotation = self._readback.read("predicted_rotation")
        predicted = q[dynamic].copy()
        predicted[:, :3] = position[dynamic]
        predicted[:, 3:] = np.array([quat_from_matrix(rotation[b]) for b in dynamic]).reshape(-1, 4)
        velocity = np.zeros((model.num_bodies, 6))
        velocity[dynamic] = rigid_step_between(q[dynamic], predicted)
        if not np.any(velocity):
            return q, value, grad, hess, contact, None
        if model.contact.advancement_limit(velocity, fraction=self.advancement_fraction) < 1.0:
            # A contact closes within the step: the impact will change the velocities, and a
            # start pressed against the barrier costs Newton more than it saves.
            return q, value, grad, hess, contact, None
        q_lists = model.contact.advancement_frame()  # copies, far cheaper than evaluating q again
        trial = retract(q, velocity)
        t_value, t_grad, t_hess, t_contact, _ = self._evaluate(trial, coords, step_in)
        if np.isfinite(t_value) and t_value < value:
            return trial, t_value, t_grad, t_hess, t_contact, None
        return q, value, grad, hess, contact, q_lists

    def _pass_through(self, q_from: np.ndarray, q_to: np.ndarray, dt: float, joint_step: np.ndarray | None = None) -> str | None:
        """Why the step from ``q_from`` to its solution ``q_to`` moved one body through
        another, or None.

        Every Newton iterate is intersection-free and so is the path through them, but with a
        step too large for the bodies' speed that path can lead around a body: a cube at 30
        m/s (1.2 m a step) met a resting cube 0.2 m ahead, the iterates slid the two past
        each other sideways, and the step ended with the cube beyond the other one, which
        never moved (docs/architecture.md, "Pass-through"). The frames, and any playback
        interpolating them, then show one body passing through the other. A body pair is
        suspect when its centres move by at least ``_PASS_THROUGH_TRAVEL`` of the smaller
        body's radius relative to each other and their bounding spheres meet in the step.
        Its step is refused when, along the step's motion from ``q_from`` to ``q_to`` (straight,
        or with ``joint_step``, the articulation's DOF increments from one to the other, along
        the joints), either body's centre of mass crosses the other's surface
        (``_centre_crossing``), or when the contact model finds the pair intersecting where
        the centres come closest.
        """
        pairs = self.model.contact.body_pairs
        if not len(pairs):
            return None
        a, b = pairs[:, 0], pairs[:, 1]
        radius = self.model.body_radius
        if joint_step is None:
            # A pair's relative travel is at most twice the largest centre shift (and the
            # rounding of centres differenced below): well under the threshold of the
            # smallest body, no pair is moving and the scan (0.4-0.7 ms a step) is skipped.
            # Twice the bound (4 shifts) and 16 roundings leave slack for the rounding of the
            # scan's own sums (a review found cases at exactly one rounding of 2 shifts).
            shift = float(np.linalg.norm(q_to[:, :3] - q_from[:, :3], axis=1).max())
            rounding = 16.0 * float(np.spacing(max(np.abs(q_from[:, :3]).max(), np.abs(q_to[:, :3]).max())))
            if 4.0 * shift + rounding < _PASS_THROUGH_TRAVEL * float(radius.min()):
                return None
            chords, step = 1, rigid_step_between(q_from, q_to)

            def move(f):
                return retract(q_from, f * step)

        else:
            # Articulated bodies move along their joints (a hinged paddle's centre on an arc
            # about the hinge), not straight: followed straight, a paddle turning 3 rad in a
            # step swept around a ball lying on its arc, and nothing was refused.
            art = self._articulation
            chords = int(np.clip(np.ceil(art.swing_bounds(joint_step).max(initial=0.0) / _PASS_THROUGH_CHORD_TURN), 1, _PASS_THROUGH_CHORDS))

            def move(f):
                return art.retract(q_from, f * joint_step)

        sampled = {}

        def path(s):
            """Poses (len(s), nbodies, 7) at fractions ``s`` of the step's motion, each computed
            once: every suspect pair's crossing test walks the same fractions."""
            for f in s:
                if f not in sampled:
                    sampled[f] = move(f)
            return np.stack([sampled[f] for f in s])

        centres = path(np.linspace(0.0, 1.0, chords + 1))[:, :, :3] if chords > 1 else np.stack([q_from[:, :3], q_to[:, :3]])
        relative = centres[:, b] - centres[:, a]  # (chords + 1, pairs, 3)
        # Each chord of the centres' relative path, and where it comes closest to zero.
        chord_fraction, chord_distance, length2 = _closest_on_chords(relative)
        travel = np.sqrt(length2).sum(axis=0)
        moving = travel > _PASS_THROUGH_TRAVEL * np.minimum(radius[a], radius[b])
        nearest = chord_distance.argmin(axis=0)
        pair = np.arange(len(a))
        fraction = (nearest + np.clip(chord_fraction[nearest, pair], 0.0, 1.0)) / chords if chords > 1 else chord_fraction[0]
        clipped = np.clip(fraction, 0.0, 1.0)
        closest_distance = chord_distance[nearest, pair]
        # How far the direction between the centres turns along the relative path (the angle
        # between its ends for a straight motion; summed over the chords along joints).
        turn = np.arctan2(np.linalg.norm(np.cross(relative[:-1], relative[1:]), axis=2), np.einsum("kij,kij->ki", relative[:-1], relative[1:])).sum(axis=0)
        meet = closest_distance < radius[a] + radius[b]
        # Two links of one articulation are not followed: a 3-link chain folding at 10 m/s was
        # refused though its joint path is contact-free (its straight path cuts 30-90%).
        suspect = np.flatnonzero(moving & meet & (self._joint_tree[a] != self._joint_tree[b]))
        if not suspect.size:
            return None
        names = self.model.body_names

        how_moving = "moving straight" if joint_step is None else "moving along their joints"

        def refusal(i: int, how: str) -> str:
            return (
                f"bodies {names[a[i]]!r} and {names[b[i]]!r} pass through each other: {how_moving} to this step's solution, {how} "
                f"(relative speed {travel[i] / dt:.3g} m/s, {travel[i]:.3g} m in dt={dt} s, "
                f"radii {radius[a[i]]:.3g} and {radius[b[i]]:.3g} m); the time step is too large for this impact, reduce dt"
            )

        # A body inside a closed one (a ball in a closed box) moves in the container's hollow,
        # not through its material: only its own centre leaving the container passes through.
        # Taken as solid, a ball falling in a closed box was refused at its second step.
        containers = {i: self._container(a[i], b[i], q_from) for i in suspect}
        # Per pair, (body whose centre is followed, body whose surface it must not cross).
        movers = {i: ((a[i], b[i]), (b[i], a[i])) if containers[i] is None else (containers[i],) for i in suspect}
        for i in suspect:
            for mover, other in movers[i]:
                geometry = self._crossing_geometry(mover)
                where = self._centre_crossing(mover, other, path) if geometry.followed_point is not None else None
                if where is not None:
                    point = f"{names[mover]!r}'s centre of mass" if geometry.centre_inside else f"a point inside {names[mover]!r}"
                    return refusal(i, f"{point} crosses {names[other]!r}'s surface at {where:.0%} of it")
        # Two bodies whose centres come closer than the sum of their inner balls' radii overlap
        # there however they turn: a cube passing beside another, its centre never inside it.
        # Sampling the contact model on the straight motion is left to pairs with a dynamic
        # open mesh, which has no inside to follow (below): its turning is not the bodies'
        # and clips a tumbling corner (random piles of boxes and balls at dt 0.02 were
        # refused in 4 of 8 seeds, though sub-steps showed nothing passing).
        inner = {body: self._crossing_geometry(body).inner_radius for body in np.unique(np.concatenate([a[suspect], b[suspect]]))}
        for i in suspect:
            sliding = inner[a[i]] >= _PASS_THROUGH_ROUND * radius[a[i]] and inner[b[i]] >= _PASS_THROUGH_ROUND * radius[b[i]] and turn[i] < _PASS_THROUGH_TURN
            reach = inner[a[i]] + inner[b[i]]
            # Followed in either body's own frame as well: a ball pressed on the face of a slab it
            # set spinning (70-100 degrees in a step at 20 m/s, dt 0.01) stays on that face, but
            # the straight motion in world axes cuts the arc the face swings through.
            if containers[i] is None and closest_distance[i] < reach and not sliding and self._closest_in_own_frames(a[i], b[i], path, chords) < reach:
                return refusal(i, f"their centres come {closest_distance[i]:.3g} m apart at {clipped[i]:.0%} of it, inside both bodies (the balls about their centres inside them have radii {inner[a[i]]:.3g} and {inner[b[i]]:.3g} m; the direction between the centres turns {np.degrees(turn[i]):.0f} degrees)")
        # A static open body (a two-triangle ground) has no centre to follow: its side of the
        # other body is told by the other's centre alone, which the first test follows. Sampled
        # here as well, an ant's leg sliding on the ground with its joints turning was refused
        # as passing through it: the replayed joint path dipped its tip below the ground, which
        # neither the iterates nor the same gait at half the step did (a probe, stop 59).
        followed = np.array([all(self._crossing_geometry(mover).followed_point is not None or not self._dynamic[mover] for mover, _ in movers[i]) for i in suspect], dtype=bool)
        suspect = suspect[~followed]
        closest = suspect[(fraction[suspect] > 0.0) & (fraction[suspect] < 1.0)]
        for s in np.unique(np.round(fraction[closest], 3)):
            hits = self.model.contact.evaluate(path([s])[0]).contact_pairs
            for i in closest:
                if (names[a[i]], names[b[i]]) in hits:
                    return refusal(i, f"they intersect at {s:.0%} of it")
        return None

    def _closest_in_own_frames(self, a: int, b: int, path, chords: int) -> float:
        """The larger, over the frames of bodies ``a`` and ``b``, of the closest approach of
        their centres when the relative path is followed by ``chords`` straight chords in that
        body's frame (``path``: fractions (k,) -> poses (k, nbodies, 7)). A body in contact
        with the face of one that spins keeps to the face in that body's frame, where the
        straight motion in world axes cuts the arc the face swings through by its sagitta."""
        poses = path(np.linspace(0.0, 1.0, chords + 1))[:, [a, b]]
        relative = poses[:, 1, :3] - poses[:, 0, :3]
        return max(float(_closest_on_chords(np.einsum("kji,kj->ki", quat_to_matrix(poses[:, k, 3:]), relative))[1].min()) for k in (0, 1))

    def _crossing_geometry(self, body: int) -> "_CrossingGeometry":
        """What the pass-through check reads of a body (``_CrossingGeometry``), made once."""
        geometry = self._crossing_geometries.get(body)
        if geometry is None:
            vertices, faces = self.model.body_meshes[body]
            triangles = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
            closed = _is_closed(vertices, faces)
            centre_inside = closed and _encloses(triangles, np.zeros(3))
            inner = float(np.linalg.norm(trimesh.triangles.closest_point(triangles, np.zeros((len(triangles), 3))), axis=1).min()) if centre_inside else 0.0
            followed = np.zeros(3) if centre_inside else _inner_point(triangles) if closed else None
            geometry = _CrossingGeometry(closed, centre_inside, followed, triangles, triangles.min(axis=1), triangles.max(axis=1), inner)
            self._crossing_geometries[body] = geometry
        return geometry

    def _container(self, a: int, b: int, q: np.ndarray) -> tuple[int, int] | None:
        """(inner, container) when one of bodies ``a``, ``b`` lies inside the other's closed
        mesh at poses ``q`` (a ball in a closed box), else None. The step's start is free of
        intersections, so one vertex of the smaller body decides."""
        radius = self.model.body_radius
        inner, outer = (a, b) if radius[a] <= radius[b] else (b, a)
        if np.linalg.norm(q[inner, :3] - q[outer, :3]) + radius[inner] > radius[outer] or not self._crossing_geometry(outer).closed:
            return None
        vertex = quat_to_matrix(q[inner, 3:]) @ self._crossing_geometry(inner).triangles[0, 0] + q[inner, :3]
        local = quat_to_matrix(q[outer, 3:]).T @ (vertex - q[outer, :3])
        return (inner, outer) if _encloses(self._crossing_geometry(outer).triangles, local) else None

    def _centre_crossing(self, mover: int, other: int, path) -> float | None:
        """The fraction of the step's motion (``path``: fractions (k,) -> poses (k, nbodies, 7);
        straight, p + s dp, exp(s [dtheta]x) R, or along the joints) at which body
        ``mover``'s centre of mass crosses body ``other``'s surface, or None. The centre's
        path in ``other``'s frame is followed by ``_PASS_THROUGH_CHORDS`` chords.

        Chosen over testing the straight motion of every point, which dips a tilting facet
        below the surface it rests on (a faceted ball rolling 0.26 m a step, a box sliding off
        a table's edge), and over sampling the contact model along it, which sees the same
        dips: a centre reaches another body's surface only by passing into it.
        """
        s = np.linspace(0.0, 1.0, _PASS_THROUGH_CHORDS + 1)
        poses = path(s)[:, [mover, other]]
        rotation = quat_to_matrix(poses[:, 1, 3:])
        point = poses[:, 0, :3] + quat_to_matrix(poses[:, 0, 3:]) @ self._crossing_geometry(mover).followed_point
        centre = np.einsum("kji,kj->ki", rotation, point - poses[:, 1, :3])
        # Only triangles whose boxes meet the path's: a ball over a 49,152-face ground tested
        # every face, half its step time.
        geometry = self._crossing_geometry(other)
        triangles, low, high = geometry.triangles, geometry.low, geometry.high
        near = np.flatnonzero(np.all((low <= centre.max(axis=0)) & (high >= centre.min(axis=0)), axis=1))
        if not near.size:
            return None
        hit = _segments_cross_triangles(centre[:-1], centre[1:], triangles[near])
        if hit is None:
            return None
        chord, t = hit
        return float(s[chord] + t / _PASS_THROUGH_CHORDS)

    def _diagnostics(self, what: str, iterations: int, step_length: float, value: float, travel: np.ndarray, q_start: np.ndarray, dt: float, unsolved: "_UnsolvedTrials", hess: np.ndarray, evaluation, *, hidden: float = 0.0, converged_length) -> str:
        worst = np.argsort(-travel)[:3]
        # Per body: the length the body moving most had to fall below.
        converged_length = float(np.broadcast_to(converged_length, travel.shape)[worst[0]]) if len(travel) else float(np.max(converged_length))
        names = self.model.body_names
        bodies = ", ".join(f"{names[i]} ({travel[i]:.3e} m)" for i in worst if travel[i] > 0)
        # A body that coasts, or falls, several of its radii in one step (a 1 um cube falls
        # 2 mm in 0.02 s) meets its contacts deep inside the step, which Newton may not resolve.
        free = self._predicted_position.numpy() + np.asarray(self.model.gravity) * dt * dt - q_start[:, :3]
        coast = np.linalg.norm(free, axis=1) / self.model.body_radius
        coast[~self._dynamic] = 0.0
        fastest = int(np.argmax(coast))
        hint = f"; {names[fastest]} would move {coast[fastest]:.3g} times its radius in free flight in this step of {dt:g} s: reduce dt" if coast[fastest] > 1.0 else ""
        contact = self.model.contact
        if steep_blend(getattr(contact, "eps", np.inf), contact.mode):
            hint += f"; eps {contact.eps:g} is below {STEEP_BLEND_EPS:g}, where the blend is steep and Newton slow: a larger eps converges"
        pressed = self._pressed_pair(evaluation)
        if hidden or pressed:
            values = np.abs(np.linalg.eigvalsh(hess)) if np.isfinite(hess).all() else np.array([np.nan])
            hidden_move = f"; eigenvalues floored at 1e-10 of the largest hid a move of {hidden:.1e} m" if hidden else ""
            span = f"; the Newton system's eigenvalue magnitudes span {values.min():.1e} .. {values.max():.1e}{hidden_move}: "
            if pressed:
                hint += (
                    f"{span}{pressed} pressed this close is far stiffer than the bodies' inertia, beyond what float64 resolves; start the bodies farther apart, "
                    f"or, where their weight presses them this close, raise the contact stiffness ({PRESSED_GAP_HINT})"
                )
            else:
                # No pair is pressed: it blamed a contact where a drive held a ball joint on
                # its cone's rim (a probe, stop 58).
                hint += (
                    f"{span}a barrier pressed this close (a joint's limit or cone, or a contact) is far stiffer than the bodies' inertia, beyond what "
                    "float64 resolves; soften the drive or force that presses against it, or damp it (a drive's kd helps Newton along a cone's rim)"
                )
        if unsolved.failed:
            pairs = ", ".join(f"{a} and {b}" for a, b in unsolved.pairs)
            hint += f"; {unsolved.failed} of {unsolved.trials} trial poses had unsolved leaf pairs (last: {pairs}): {UNSOLVED_HINT}"
        # A step below that length that still failed read as a contradiction (a probe, stop 64).
        short = (
            "; this one is shorter, but a body pressed close to a contact, eigenvalues floored in the Newton system or another body's own smaller "
            "length kept it from counting as converged"
            if what == "no convergence" and step_length <= converged_length
            else ""
        )
        return (
            f"implicit step: {what} after {iterations} Newton iterations; last Newton step moves points "
            # The length the step had to fall below, not tolerance x the largest radius alone: a
            # 4e10 m ground made that 2.8 m, which a step of 1e-6 m "missed".
            f"up to {step_length:.3e} m (converged below {converged_length:.3e} m: the least of tolerance x the largest body radius, "
            f"1e-5 m/s^2 x dt^2 and the friction smoothing length, or the coordinates' rounding{short}), L = {value:.9e}; "
            f"largest moves: {bodies}{hint}"
        )

    def _pressed_pair(self, evaluation) -> str:
        """The closest body pair of ``evaluation`` (of this model's ContactModel) when closer
        than _PRESSED_SEPARATION of the smaller body's radius, as "contact between a and b (d m
        apart)", else ""."""
        if not isinstance(self.model.contact, ContactModel) or not len(evaluation.pair_separation):
            return ""
        k = int(np.argmin(evaluation.pair_separation))
        a, b = self.model.contact.body_pairs[k]
        gap = float(evaluation.pair_separation[k])
        if gap > _PRESSED_SEPARATION * min(self.model.body_radius[a], self.model.body_radius[b]):
            return ""
        names = self.model.body_names
        return f"contact between {names[a]} and {names[b]} ({gap:.1e} m apart)"

    # --- backward -----------------------------------------------------------------------------

    def _taped_state_arrays(self, state_in: State, state_out: State) -> list[tuple[str, wp.array]]:
        """The state arrays whose gradients a recorded step's backward reads or writes, by name."""
        names = [("state_out", "body_q"), ("state_out", "body_q_prev"), ("state_in", "body_q"), ("state_in", "body_q_prev")]
        if self.model.num_joint_coordinates:
            names += [("state_out", "joint_q"), ("state_out", "joint_q_prev"), ("state_in", "joint_q")]
        states = {"state_in": state_in, "state_out": state_out}
        return [(f"{label}.{name}", getattr(states[label], name)) for label, name in names]

    def _backward_function(self, state_in, state_out, control, step_in, hess, jacobian, contact_grad, q_next, q_now, q_prev, friction_poses):
        """The step's backward and the arrays it touches, for ``tape.record_func``, and the
        values of its taped control arrays at this step ({id(array): values}, the backward's
        own snapshots where it keeps the raw values), which ``_check_taped_step`` compares
        with a later step's. ``friction_poses``: the step's solution and start as the friction
        terms saw them (unit quaternions; a start quaternion of norm 1.01 made the friction
        adjoint's rotations 2% too large and every start-pose gradient 15% off)."""
        model = self.model
        dev = model.device
        n = model.num_bodies
        dt, friction = step_in.dt, step_in.friction
        dynamic = self._dynamic
        art = self._articulation
        hess = hess.copy()
        # The arrays this step read and wrote, bound now: a Control, State or model array
        # replaced between taped steps (one target or friction array per step) sent every
        # step's adjoint into the array held when tape.backward ran (the earlier arrays' gradients
        # zero, the last one's their sum).
        state_in, state_out = dataclasses.replace(state_in), dataclasses.replace(state_out)
        control = None if control is None else dataclasses.replace(control)
        parameters = {name: getattr(model, name) for name in _DIFFERENTIATED_MODEL_ARRAYS}
        # The model's masses, gains and friction coefficient as they were in this step: changed
        # between two taped steps, the first step's backward read the new values (gradients off
        # by 2.6x the gradient itself).
        bodies = self._body_model(dt, snapshot=True)
        if friction is not None:
            friction = dataclasses.replace(friction, friction=wp.clone(friction.friction, requires_grad=False))
        contact_grad = contact_grad.copy()
        with wp.ScopedDevice(dev):
            # Snapshots: the backward must see this step's values, not later contents.
            q_next_arr = wp.array(q_next, dtype=wp.transformd)
            q_now_arr = wp.array(q_now, dtype=wp.transformd)
            q_prev_arr = wp.array(q_prev, dtype=wp.transformd)
            target_arr = wp.clone(step_in.body_target, requires_grad=False)
            predicted_position = wp.clone(self._predicted_position)
            predicted_rotation = wp.clone(self._predicted_rotation)
            sensitivity = wp.clone(self._prediction_sensitivity)
        arrays = [array for _, array in self._taped_state_arrays(state_in, state_out)] + [array for array in parameters.values() if array.requires_grad]
        arrays += [array for _, array in _taped_control_arrays(control)]
        joints = art is not None and art.num_coordinates > 0
        if joints:
            joint_kp, joint_kd = art.kp.copy(), art.kd.copy()  # as this step used them
        balls = art is not None and art.has_ball_drives
        if balls:
            ball_gains = (art.ball_kp.copy(), art.ball_kd.copy())
        # Targets a step is not given hold the joints where the step starts (_joint_arrays,
        # _ball_arrays): their adjoints belong to the start.
        joint_target_is_start = control is None or control.joint_target is None
        ball_target_is_start = control is None or control.ball_target is None
        ball_target_grad = balls and not ball_target_is_start and control.ball_target.requires_grad
        if ball_target_grad:
            # As given, not normalised: the adjoint of the normalisation divides by the norm.
            ball_target_arr = wp.clone(control.ball_target, requires_grad=False)
        # step_in.joint_target may be a view of the control's memory (.numpy() on a CPU): it
        # gets a copy of its own.
        own = {"control.body_target": target_arr, "control.joint_target": step_in.joint_target.copy()}
        control_values = {id(array): own[label] if label in own else wp.clone(array, requires_grad=False) for label, array in _taped_control_arrays(control)}

        def backward():
            with wp.ScopedDevice(dev):
                out_adj = state_out.body_q.grad
                rigid_out = wp.zeros(n, dtype=vec6d)
                wp.launch(dynamics_kernels.pose_adjoint_to_rigid_kernel, dim=n, inputs=[q_next_arr, out_adj], outputs=[rigid_out])
                adj = rigid_out.numpy().reshape(-1)
                if art is None:
                    lam_full = np.zeros(6 * n)
                    lam_full[self._dofs] = np.linalg.solve(hess, -adj[self._dofs])
                else:
                    reduced_adj = jacobian.T @ adj
                    if joints:
                        reduced_adj[art.coordinate_dof] += state_out.joint_q.grad.numpy()
                    lam_reduced = np.linalg.solve(hess, -reduced_adj)
                    lam_full = jacobian @ lam_reduced
                lam = wp.array(lam_full.reshape(n, 6), dtype=vec6d)
                adj_now = wp.zeros(n, dtype=vec6d)
                adj_prev = wp.zeros(n, dtype=vec6d)
                adj_target = wp.zeros(n, dtype=vec6d)
                adj_mass = wp.zeros(n, dtype=wp.float64)
                wp.launch(
                    dynamics_kernels.body_adjoint_kernel,
                    dim=n,
                    inputs=[bodies, q_next_arr, q_now_arr, predicted_position, predicted_rotation, sensitivity, target_arr, lam],
                    outputs=[adj_now, adj_prev, adj_target, adj_mass],
                )
                mu_adj = float(lam_full @ contact_grad.reshape(-1))
                if friction is not None and friction.pairs:
                    adj_q, adj_friction, adj_mu = model.contact.friction_adjoint(friction, *friction_poses, lam_full.reshape(n, 6))
                    adj_now.assign(adj_now.numpy() + adj_q)
                    _accumulate(parameters["friction"], adj_friction)
                    mu_adj += adj_mu
                elif step_in.friction_rate is not None and step_in.friction_rate.pairs:
                    # At coefficient 0 the step has no friction: only its coefficient moves it.
                    _, adj_friction, _ = model.contact.friction_adjoint(step_in.friction_rate, *friction_poses, lam_full.reshape(n, 6))
                    _accumulate(parameters["friction"], adj_friction)
                if balls:
                    target_adj, start_adj = art.ball_drive_adjoint(q_next, q_now, lam_reduced, step_in.ball_target, dt, target_is_start=ball_target_is_start, gains=ball_gains)
                    adj_now.assign(adj_now.numpy() + start_adj)
                    if ball_target_grad:
                        wp.launch(dynamics_kernels.rotation_adjoint_to_quat_kernel, dim=art.num_ball_joints, inputs=[ball_target_arr, wp.array(target_adj, dtype=wp.vec3d)], outputs=[control.ball_target.grad])
                wp.launch(dynamics_kernels.rigid_adjoint_to_pose_kernel, dim=n, inputs=[q_now_arr, adj_now], outputs=[state_in.body_q.grad])
                wp.launch(dynamics_kernels.rigid_adjoint_to_pose_kernel, dim=n, inputs=[q_prev_arr, adj_prev], outputs=[state_in.body_q_prev.grad])
                # Without a control each body's PD target is its start pose q^t (target_arr is a
                # copy of state_in.body_q), so the target's adjoint is the start's.
                target_grad = state_in.body_q.grad if control is None else control.body_target.grad if control.body_target.requires_grad else None
                if target_grad is not None:
                    wp.launch(dynamics_kernels.rigid_adjoint_to_pose_kernel, dim=n, inputs=[target_arr, adj_target], outputs=[target_grad])
                _accumulate(parameters["body_mass"], adj_mass.numpy())
                _accumulate(parameters["contact_stiffness"], mu_adj)
                # state_out.body_q_prev is a copy of state_in.body_q; static bodies stay put.
                passthrough = state_out.body_q_prev.grad.numpy().copy()  # a view on a CPU: never the state's own
                static_adj = out_adj.numpy()
                passthrough[~dynamic] += static_adj[~dynamic]
                state_in.body_q.grad.assign(state_in.body_q.grad.numpy() + passthrough)
                if joints:
                    # d(grad)/d(target) = -kp and d(grad)/d(q^t) = -kd/dt on each coordinate;
                    # state_out.joint_q_prev is a copy of state_in.joint_q.
                    lam_coords = lam_reduced[art.coordinate_dof]
                    adj_coords = -joint_kd / dt * lam_coords + state_out.joint_q_prev.grad.numpy()
                    if joint_target_is_start:
                        adj_coords -= joint_kp * lam_coords
                    state_in.joint_q.grad.assign(state_in.joint_q.grad.numpy() + adj_coords)
                    if not joint_target_is_start and control.joint_target.requires_grad:
                        control.joint_target.grad.assign(control.joint_target.grad.numpy() - joint_kp * lam_coords)
                # The step's outputs' adjoints are consumed, as Warp's adjoints of array writes
                # consume theirs: a second tape.backward() without tape.zero() then adds its
                # gradient to the first instead of passing this step's adjoints through again.
                # An array marked retain_grad keeps its adjoint, as Warp's writes leave it (they
                # were zeroed regardless, a probe, stop 63).
                outputs = (state_out.body_q, state_out.body_q_prev) + ((state_out.joint_q, state_out.joint_q_prev) if model.num_joint_coordinates else ())
                for output in outputs:
                    if not output.retain_grad:
                        output.grad.zero_()

        return backward, arrays, control_values
