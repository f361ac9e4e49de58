"""Input checks shared by the host API: every error names the argument and the problem."""

import numpy as np

from .rotation import normalized_poses, quat_norm

__all__ = [
    "MAX_BARRIER_SUPPORT",
    "MAX_COORDINATE",
    "MAX_COUNT",
    "MAX_FRAMES",
    "MIN_BLEND_EPS",
    "MIN_EXTENT",
    "QUATERNION_TOLERANCE",
    "SCALE_RANGE",
    "as_float64_array",
    "blend_eps_problem",
    "check_barrier_support",
    "check_coordinates",
    "check_count",
    "check_time_step",
    "extent_problem",
    "gap_problem",
    "time_step_problem",
    "checked_flag",
    "is_positive_finite",
    "is_real",
    "is_whole",
    "real_array",
    "real_dtype",
    "scale_problem",
    "shown",
    "validated_poses",
]

# The most frames a task may plan or a simulation run: plans and trajectories are held
# whole, and a horizon of 1e9 frames ended in a numpy MemoryError (44.7 GiB) instead of
# naming the attribute; simulate --frames 1e11 grew until it was killed. A million frames is
# 11 hours at the paper's 0.04 s and ~3 hours of stepping per rollout at 10 ms a frame; the
# paper's longest task plans 700.
MAX_FRAMES = 1_000_000

# Largest barrier support (m) of the locally supported baselines: their barriers overflow
# float64 far beyond it (IPC's from ~1e76 m, SDRS's from ~1e103 m: inf with no named error).
MAX_BARRIER_SUPPORT = 1e6

# Largest coordinate magnitude (m) of vertices and poses: the kernels square world-space
# differences, which overflow float64 from ~1e154 m (the far field's force then read -0.0
# and a leaf solve NaN).
MAX_COORDINATE = 1e150

# Smallest extent (m) of a body, or of a pair of triangles, that is not collapsed to one
# point: the leaf search's fourth powers of length underflow below ~1e-77 m, where disjoint
# triangles 1e-82 m across read as touching (a vertex 0.1 of their size above a face: CONTACT,
# +inf, in the triangle solve and in a body's contact pairs), and squared distances below
# ~1e-154 m, where bounding spheres read radius 0 and missed their triangles.
MIN_EXTENT = 1e-75

# Largest deviation from unit norm of a quaternion given as a rotation (poses, frames,
# targets); within it the quaternion is normalised, beyond it refused.
QUATERNION_TOLERANCE = 1e-6

# Largest count handed to a kernel's int32 argument (iteration caps and the like).
MAX_COUNT = 2**31 - 1


def is_real(value) -> bool:
    """A Python or numpy real scalar, not a bool (which Python counts as an int)."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def shown(value) -> str:
    """A value as an error message shows it: a number as it prints (np.float64(-1.0) as
    -1.0), anything else as its repr (a string quoted, so '0.5' does not read as a number)."""
    return str(value) if is_real(value) else repr(value)


def is_positive_finite(value) -> bool:
    """A real scalar (``is_real``) that is finite and > 0."""
    return is_real(value) and bool(np.isfinite(value)) and value > 0


def is_gain(values) -> bool:
    """Whether PD gains (a float scalar or array) are all finite and >= 0: one rule for the
    builder's arguments, the USD attributes and a task's controlled axes, each of which names
    the value in its caller's terms."""
    values = np.asarray(values, dtype=np.float64)
    return bool(np.isfinite(values).all() and (values >= 0.0).all())


# Magnitudes of the positive scales a step multiplies, divides and squares (dt, quaternion
# norms, the contact settings, gravity): the square and inverse of anything in this range, and
# the product of two such, are finite normal float64 numbers. Beyond it a step overflowed or
# underflowed silently or deep inside (dt = 1e200 s crashed the step and 1e-320 s wrote no
# trajectory at an infinite rate; friction_smoothing 1e-200 m/s gave a NaN step, contact
# stiffness 1e300 numpy's "Eigenvalues did not converge").
SCALE_RANGE = (1e-150, 1e150)


# Range (m^2) of a dynamic body's inertia over its mass (eigenvalues: squared radii of
# gyration): the rotation prediction (kernels/dynamics.py predict_kernel) compares the
# determinant of a matrix of the second moment per unit mass with the cube of its trace,
# which overflow or underflow float64 beyond ~1e+-102 m^2 (inertia eye(3) * 1e120 or 1e-150
# at 1 kg was taken, and the first step of the body at rest failed "rotation per step too
# large").
UNIT_INERTIA_RANGE = (1e-100, 1e100)


def unit_inertia_outside(eigenvalues) -> np.ndarray:
    """Per row of (..., 3) ``eigenvalues`` (m^2) of inertias over masses, whether they leave
    UNIT_INERTIA_RANGE by more than rounding: the step recomputes them from the second
    moment, which rounds an inertia add_body took at 1e100 to just above it."""
    low, high = UNIT_INERTIA_RANGE
    eigenvalues = np.asarray(eigenvalues, dtype=np.float64)
    return (eigenvalues.min(axis=-1) < low * (1.0 - 1e-9)) | (eigenvalues.max(axis=-1) > high * (1.0 + 1e-9))


def unit_inertia_problem(eigenvalues) -> str | None:
    """Why a body whose inertia over its mass has ``eigenvalues`` (m^2) cannot be stepped, or None."""
    low, high = UNIT_INERTIA_RANGE
    eigenvalues = np.asarray(eigenvalues, dtype=np.float64)
    if not unit_inertia_outside(eigenvalues):
        return None
    return (
        f"has eigenvalues {eigenvalues.min():.3g} to {eigenvalues.max():.3g} m^2 (squared radii of gyration), outside [{low:g}, {high:g}] m^2, "
        "where the rotation prediction's cube of them is a float64 number"
    )


# Smallest blend margin eps of P_BSH: the shell d1 < r < (1 + eps) d1 must span many float64
# steps of the centre distance r. Below ~1.1e-16 (1 + eps) d1 rounds to d1, no node pair is
# ever blended, and the potential jumps by S - P_c where a centre distance crosses d1 (two unit
# boxes at eps 1e-17: 212.06 -> 29.13, force 27.5 -> 3.25, a probe); just above, phi moves by
# ~0.2 per rounding step of r. At 1e-12 the shell is ~4,500 steps of r wide.
MIN_BLEND_EPS = 1e-12


def blend_eps_problem(eps) -> str | None:
    """Why ``eps``, a blend margin inside SCALE_RANGE, is too thin for float64 to blend across
    (``MIN_BLEND_EPS``), or None."""
    if float(eps) < MIN_BLEND_EPS:
        return f"must be at least {MIN_BLEND_EPS:g}: a thinner blend shell (1 + eps) d1 is not resolved in float64, and the potential jumps where a node pair crosses it"
    return None


def scale_problem(value, unit: str) -> str | None:
    """Why ``value``, a positive scale in ``unit``, lies outside SCALE_RANGE, or None (it is
    checked positive and finite elsewhere)."""
    low, high = SCALE_RANGE
    if not low <= float(value) <= high:  # float: np.float32 against 1e150 warned of an overflow
        return f"must lie in [{low:g}, {high:g}]{' ' + unit if unit else ''} (its square and inverse must be representable)"
    return None


def time_step_problem(dt) -> str | None:
    """Why ``dt`` is not a time step (s), or None."""
    if not is_positive_finite(dt):
        return "must be a positive finite number of seconds"
    return scale_problem(dt, "s")


def check_time_step(dt) -> None:
    """ValueError naming dt unless it is a time step (``time_step_problem``)."""
    problem = time_step_problem(dt)
    if problem is not None:
        raise ValueError(f"dt: {problem}, got {dt!r}")


def check_barrier_support(dhat, name: str = "dhat") -> None:
    """ValueError naming ``name`` unless ``dhat`` is a positive finite distance (m) of at
    most MAX_BARRIER_SUPPORT."""
    if not is_positive_finite(dhat) or dhat > MAX_BARRIER_SUPPORT:
        raise ValueError(f"{name}: must be a positive finite distance of at most {MAX_BARRIER_SUPPORT:g} m, got {dhat!r}")


def is_whole(value) -> bool:
    """A Python or numpy integer scalar, not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def checked_flag(value, name: str) -> bool:
    """``value`` as a bool, given as True/False (numpy's too) or 1/0; ValueError naming
    ``name`` otherwise: truth-testing read static="False" as True and derivatives="no" as yes."""
    if isinstance(value, (bool, np.bool_)) or (is_whole(value) and value in (0, 1)):
        return bool(value)
    raise ValueError(f"{name}: expected True/False (or 1/0), got {value!r}")


def check_count(value, name: str) -> None:
    """ValueError naming ``name`` unless ``value`` is a whole number in [1, MAX_COUNT]."""
    if not (is_whole(value) and 1 <= value <= MAX_COUNT):
        raise ValueError(f"{name}: must be a whole number from 1 to {MAX_COUNT}, got {value!r}")


def beyond_coordinates(arr) -> tuple | None:
    """The index of the first entry of ``arr`` beyond MAX_COORDINATE in magnitude, or None."""
    big = np.abs(np.asarray(arr, dtype=np.float64)) > MAX_COORDINATE  # float32 against 1e150 warned
    return tuple(int(i) for i in np.argwhere(big)[0]) if big.any() else None


def check_coordinates(arr: np.ndarray, name: str) -> None:
    """ValueError naming ``name`` and the entry if any entry of ``arr`` exceeds MAX_COORDINATE in magnitude."""
    first = beyond_coordinates(arr)
    if first is not None:
        raise ValueError(f"{name}: {arr[first]:g} at index {first} is beyond the +-{MAX_COORDINATE:g} m that float64 distances between such points can represent")


def extent_problem(extent: float) -> str | None:
    """Why points spanning ``extent`` (m, their largest coordinate range) span too little for
    float64 geometry, or None: a span below MIN_EXTENT (collapsed to one point is valid)."""
    if 0.0 < extent < MIN_EXTENT:
        return f"spans {extent:g} m, below the {MIN_EXTENT:g} m that float64 contact geometry resolves (collapsed to one point is valid)"
    return None


def gap_problem(gap: float, extent: float) -> str | None:
    """Why surfaces ``gap`` (m) apart, placed beside ``extent`` (m) of body along the same
    coordinate, are not ``gap`` apart in float64 positions, or None: below ~1e-16 of the extent
    the gap rounds to another (1e-17 m beside a pair of 1 m balls placed them touching,
    and a benchmark wrote rows for a gap it never had)."""
    realised = (extent + gap) - extent
    if abs(realised - gap) > 0.01 * gap:
        return f"{gap:g} m rounds to {realised:g} m beside {extent:.3g} m of body, below what float64 positions resolve"
    return None


def real_array(value) -> np.ndarray | None:
    """``value`` as a float64 array when it holds real numbers (integers or floats), else
    None: text and bools are not numbers, which np.asarray(value, dtype=float) read as such
    ("-9.81" as -9.81, True as 1)."""
    if _holds_text_or_bool(value):
        return None
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):  # ragged nesting
        return None
    return array.astype(np.float64) if real_dtype(array) else None


def _holds_text_or_bool(value) -> bool:
    """Whether a value, or an entry of nested lists and tuples, is text or a bool: numpy
    reads (0.0, 0.0, True) as floats, the bool as 1."""
    if isinstance(value, (str, bool, np.bool_)):
        return True
    return isinstance(value, (list, tuple)) and any(_holds_text_or_bool(v) for v in value)


def real_dtype(array: np.ndarray) -> bool:
    """Whether an array holds real numbers: integers or floats, not bools, text or objects."""
    return array.dtype.kind in "iuf"


def as_float64_array(value, name: str, *, trailing_shape: tuple[int, ...] = ()) -> np.ndarray:
    """Return ``value`` as a C-contiguous float64 array of shape (N, *trailing_shape).

    Raises ValueError naming ``name`` for non-numeric data, a wrong shape, or NaN/inf entries.
    """
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name}: cannot be read as a numeric array ({exc})") from None
    if not real_dtype(arr):
        raise ValueError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    expected = ("N",) + tuple(trailing_shape)
    if arr.ndim != len(expected) or tuple(arr.shape[1:]) != tuple(trailing_shape):
        raise ValueError(f"{name}: expected shape {expected}, got {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        first = np.argwhere(bad)[0]
        raise ValueError(f"{name}: non-finite value {arr[tuple(first)]} at index {tuple(int(i) for i in first)}")
    return arr


def check_finite_poses(poses: np.ndarray, label: str, names) -> None:
    """ValueError naming ``label``, the first body (by name and index) whose row of ``poses``
    is not finite, and its pose ("contains non-finite values" named none)."""
    bad = np.flatnonzero(~np.isfinite(poses).all(axis=1))
    if bad.size:
        b = bad[0]
        raise ValueError(f"{label}: body {names[b]!r} (index {b}) has pose {np.asarray(poses[b]).tolist()}; expected finite values")


def validated_step(step, names, static: np.ndarray) -> np.ndarray:
    """(len(names), 6) float64 rigid-coordinate step (dp, dtheta) of a contact model's
    ``advancement_limit``; ValueError naming the argument, or the static body whose row is
    not zero (such a row was taken, and cut a bound no static body can cut)."""
    step = as_float64_array(step, "step", trailing_shape=(6,))
    check_coordinates(step, "step")
    if step.shape[0] != len(names):
        raise ValueError(f"step: expected {len(names)} rows, got {step.shape[0]}")
    moved = np.flatnonzero(static & (step != 0.0).any(axis=1))
    if moved.size:
        raise ValueError(f"step: static body {names[moved[0]]!r} (row {moved[0]}) has a non-zero row {step[moved[0]].tolist()}; static bodies do not move in a step")
    return step


def validated_poses(poses, names, *, normalize: bool = True, label: str = "poses") -> np.ndarray:
    """(len(names), 7) float64 poses (px, py, pz, qx, qy, qz, qw) with quaternions within
    QUATERNION_TOLERANCE of unit norm, normalised unless ``normalize`` is False; ValueError
    naming the argument (``label``), or the body by index and name, otherwise."""
    poses = as_float64_array(poses, label, trailing_shape=(7,))
    check_coordinates(poses, label)
    if poses.shape[0] != len(names):
        raise ValueError(f"{label}: expected {len(names)} rows (one per body), got {poses.shape[0]}")
    norms = quat_norm(poses[:, 3:])
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{label}: body {i} ({names[i]}) has quaternion norm {norms[i]:.9g}; "
            f"expected unit norm within {QUATERNION_TOLERANCE} (layout px, py, pz, qx, qy, qz, qw)"
        )
    return normalized_poses(poses, norms=norms) if normalize else poses
