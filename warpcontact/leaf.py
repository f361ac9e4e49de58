"""Host API of the leaf contact potential and its closed-form building blocks (numpy in, numpy out)."""

from dataclasses import dataclass

import numpy as np
import warp as wp

from .kernels import blend as blend_kernels
from .kernels import leaf as leaf_kernels
from ._runtime import resolve_device
from ._validate import MIN_EXTENT, as_float64_array, check_barrier_support, check_coordinates, check_count, checked_flag, extent_problem, gap_problem

__all__ = [
    "LEAF_PRECISIONS",
    "LeafStatus",
    "TrianglePairPotential",
    "triangle_pair_potential",
    "leaf_solve_buffers",
    "leaf_solve_bytes_per_pair",
    "centered_potential",
    "quintic_blend",
]

DEFAULT_MAX_ITERATIONS = 100
# Float types of the leaf's plane search (docs/architecture.md, "The leaf potential").
LEAF_PRECISIONS = ("float64", "float32")


def float32_search(precision: str, *, mode: str = "bsh") -> bool:
    """The kernels' ``float32_search`` flag for a leaf precision name under contact ``mode``;
    ValueError for an unknown name, or for float32 with a baseline (``"sdrs"``, ``"ipc"``),
    whose solves are float64 only."""
    if precision not in LEAF_PRECISIONS:
        raise ValueError(f"leaf precision: must be one of {', '.join(LEAF_PRECISIONS)}, got {precision!r}")
    if precision != "float64" and mode in ("sdrs", "ipc"):
        raise ValueError(f"leaf precision: {precision!r} applies to the paper's potential; contact mode {mode!r} solves in float64")
    return precision == "float32"


class LeafStatus:
    """Per-pair status codes of the leaf solve (``TrianglePairPotential.status``)."""

    OK = int(leaf_kernels.LEAF_OK)
    CONTACT = int(leaf_kernels.LEAF_CONTACT)  # touching or intersecting: value = +inf, zero derivatives
    NOT_CONVERGED = int(leaf_kernels.LEAF_NOT_CONVERGED)  # Newton hit the iteration cap or the line search stalled
    NONFINITE = int(leaf_kernels.LEAF_NONFINITE)  # non-finite coordinates (the host API rejects these before launch)


@dataclass(frozen=True)
class TrianglePairPotential:
    """Leaf potentials of N triangle pairs.

    Attributes:
        value: (N,) potential P (1/m); +inf where the triangles touch or intersect.
        grad: (N, 2, 3, 3) dP/dx; [:, 0] for A's vertices, [:, 1] for B's (1/m^2: P is 1/m).
        hessian: (N, 18, 18) d2P/dx2 (1/m^3) in the order of ``grad.reshape(N, 18)``.
        plane: (N, 4) optimal plane (n, d) in world coordinates; |n| < 1, not normalised.
        ok: (N,) True where the solve converged to a finite value.
        status: (N,) ``LeafStatus`` code.
        iterations: (N,) Newton iterations taken.
    """

    value: np.ndarray
    grad: np.ndarray
    hessian: np.ndarray
    plane: np.ndarray
    ok: np.ndarray
    status: np.ndarray
    iterations: np.ndarray


def triangle_pair_potential(
    A,
    B,
    *,
    device="cpu",
    derivatives: bool = True,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    dhat: float | None = None,
    precision: str = "float64",
) -> TrianglePairPotential:
    """Separating-plane potential of triangle pairs, with exact first and second derivatives.

    Args:
        A, B: (N, 3, 3) triangles (pair i, vertex k, xyz) in metres; float32 input is
            accepted and computed in float64.
        device: Warp device to run on.
        derivatives: compute ``grad`` and ``hessian`` (zeros otherwise).
        max_iterations: Newton iteration cap per pair; pairs hitting it get ``ok = False``.
        dhat: None for the paper's potential (global 1/x barrier); a support distance (m)
            for the SDRS baseline: log barrier on vertex-to-plane distances below ``dhat``,
            unit normals, exactly 0 (with zero derivatives) for triangles 2 dhat apart or
            more. ``plane`` then has a unit normal.
        precision: float type of the plane search, "float64" or "float32" (the paper's
            potential only). With "float32" the search runs in float32 and float64 finishes
            it from its plane to the same tolerances; values, gradients and Hessians are
            always evaluated in float64 at the final plane.

    Zero-area triangles are valid: the potential is defined on convex hulls, so a collapsed
    triangle acts as the segment or point it is. A pair spanning less than
    ``_validate.MIN_EXTENT`` (1e-75 m) without collapsing to one point is refused (its
    search's fourth powers of length underflow: disjoint such triangles read as touching).
    """
    a = as_float64_array(A, "A", trailing_shape=(3, 3))
    b = as_float64_array(B, "B", trailing_shape=(3, 3))
    check_coordinates(a, "A")
    check_coordinates(b, "B")
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"A and B: pair counts differ ({a.shape[0]} vs {b.shape[0]})")
    if len(a):
        extents = np.ptp(np.concatenate([a, b], axis=1), axis=1).max(axis=1)
        small = np.flatnonzero((extents > 0.0) & (extents < MIN_EXTENT))
        if small.size:  # such disjoint triangles read as touching
            raise ValueError(f"A and B: pair {small[0]} {extent_problem(float(extents[small[0]]))}")
    check_count(max_iterations, "max_iterations")
    derivatives = checked_flag(derivatives, "derivatives")
    if dhat is not None:
        check_barrier_support(dhat)
    search32 = float32_search(precision, mode="bsh" if dhat is None else "sdrs")
    n = a.shape[0]
    dev = resolve_device(device)
    ncols = 6 if derivatives else 0
    with wp.ScopedDevice(dev):
        tri_a, tri_b, value, plane, status, iterations, grad, hess = leaf_solve_buffers(a, b, ncols)
        if n:
            wp.launch(
                leaf_kernels.leaf_potential_kernel,
                dim=n,
                inputs=[0.0 if dhat is None else float(dhat), tri_a, tri_b, int(max_iterations), search32, bool(derivatives)],
                outputs=[value, plane, status, iterations, grad, hess],
            )
    status_np = status.numpy()
    if derivatives:
        grad_np = grad.numpy().reshape(n, 2, 3, 3)
        hess_np = hess.numpy().transpose(0, 1, 3, 2, 4).reshape(n, 18, 18)
    else:
        grad_np = np.zeros((n, 2, 3, 3))
        hess_np = np.zeros((n, 18, 18))
    return TrianglePairPotential(
        value=value.numpy(),
        grad=grad_np,
        hessian=hess_np,
        plane=plane.numpy(),
        ok=status_np == LeafStatus.OK,
        status=status_np,
        iterations=iterations.numpy(),
    )


def _leaf_solve_layout(columns: int) -> tuple:
    """(dtype, shape per pair) of each array of ``leaf_solve_buffers``."""
    return (
        (wp.mat33d, ()),
        (wp.mat33d, ()),
        (wp.float64, ()),
        (wp.vec4d, ()),
        (wp.int32, ()),
        (wp.int32, ()),
        (wp.vec3d, (columns,)),
        (wp.mat33d, (columns, columns)),
    )


def leaf_solve_buffers(a: np.ndarray, b: np.ndarray, columns: int) -> tuple:
    """The arrays of a batched ``leaf_potential_kernel`` launch on the current device: the
    (n, 3, 3) triangles ``a`` and ``b`` as mat33d, then its outputs: value, plane, status,
    iterations, gradient (n, ``columns``) vec3d and Hessian (n, ``columns``, ``columns``)
    mat33d blocks (``columns`` 6 with derivatives, else 0); the outputs are zeroed."""
    n = len(a)
    (a_type, _), (b_type, _), *outputs = _leaf_solve_layout(columns)
    return (wp.array(a, dtype=a_type), wp.array(b, dtype=b_type), *(wp.zeros((n, *shape), dtype=dtype) for dtype, shape in outputs))


def leaf_solve_bytes_per_pair(columns: int) -> int:
    """The bytes ``leaf_solve_buffers`` takes per triangle pair."""
    return sum(wp.types.type_size_in_bytes(dtype) * int(np.prod(shape)) for dtype, shape in _leaf_solve_layout(columns))


def leaf_gap_problem(gap: float, extent: float) -> str | None:
    """Why surfaces ``gap`` (m) apart beside ``extent`` (m) of body are no gap a benchmark can
    place and solve leaf planes across (``gap_problem``, and beyond ``MAX_LEAF_SEPARATION``),
    or None: one rule for ``bench contact`` and ``demo``, whose gaps past it were reported
    after the finished ones as triangle pairs that did not solve."""
    problem = gap_problem(gap, extent)
    if problem is None and gap > float(leaf_kernels.MAX_LEAF_SEPARATION):
        problem = f"{gap:g} m is beyond the {float(leaf_kernels.MAX_LEAF_SEPARATION):g} m up to which leaf planes are solved"
    return problem


def _evaluate_scalar_kernel(kernel, x: np.ndarray, device):
    flat = x.reshape(-1)
    dev = resolve_device(device)
    with wp.ScopedDevice(dev):
        x_in = wp.array(flat, dtype=wp.float64)
        outs = [wp.empty(flat.shape[0], dtype=wp.float64) for _ in range(3)]
        if flat.shape[0]:
            wp.launch(kernel, dim=flat.shape[0], inputs=[x_in], outputs=outs)
    return tuple(o.numpy().reshape(x.shape) for o in outs)


def _scalar_input(x, name: str) -> np.ndarray:
    raw = np.asarray(x)
    if not (np.issubdtype(raw.dtype, np.floating) or np.issubdtype(raw.dtype, np.integer)):
        raise ValueError(f"{name}: expected real numbers, got {x!r}")
    arr = raw.astype(np.float64, copy=False)
    if np.isnan(arr).any():
        raise ValueError(f"{name}: contains NaN")
    return arr


def centered_potential(r, *, derivatives: bool = False, device="cpu"):
    """Centred potential P_c(r) = 12 (1 + r^-1/2)^2 of two cluster centres at distance r (m).

    Returns the values (same shape as ``r``), or ``(P_c, dP_c/dr, d2P_c/dr2)`` when
    ``derivatives`` is set. r = 0 gives +inf; negative distances raise ValueError, and so
    do, with ``derivatives``, distances so small (below ~5e-103 m) that a derivative
    overflows float64 where the value does not.
    """
    derivatives = checked_flag(derivatives, "derivatives")
    arr = _scalar_input(r, "r")
    if (arr < 0).any():
        raise ValueError(f"r: distances must be >= 0, got {arr[arr < 0].flat[0]}")
    out = _evaluate_scalar_kernel(blend_kernels.centered_potential_kernel, arr, device)
    if not derivatives:
        return out[0]
    # A finite value beside an infinite derivative was returned for r = 1e-150 (a probe).
    overflow = np.flatnonzero(((arr > 0) & ~(np.isfinite(out[1]) & np.isfinite(out[2]))).reshape(-1))
    if overflow.size:
        i = int(overflow[0])
        raise ValueError(f"r: {arr.reshape(-1)[i]:g} m (flat index {i}) is too small for derivatives of the centred potential: d2P_c/dr2 ~ 24 r^-3 overflows float64 below ~5e-103 m")
    return out


def quintic_blend(s, *, derivatives: bool = False, device="cpu"):
    """Quintic blend Phi(s) = 6 s^5 - 15 s^4 + 10 s^3, clamped to [0, 1] outside [0, 1].

    Returns the values, or ``(Phi, Phi', Phi'')`` when ``derivatives`` is set.
    """
    derivatives = checked_flag(derivatives, "derivatives")
    arr = _scalar_input(s, "s")
    out = _evaluate_scalar_kernel(blend_kernels.quintic_blend_kernel, arr, device)
    return out if derivatives else out[0]
