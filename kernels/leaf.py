"""Separating-plane potential between two triangles (paper eq. potential-slow, Lemma lem:slow).

    P(A, B) = min_p L(p),  p = (n, d),
    L(p)    = 12 / (1 - |n|) + sum_k 1 / g_k,   g_k = sigma_k (<x_k, n> + d)

over the six vertices x_k (k < 3: triangle A with sigma = +1; k >= 3: triangle B with
sigma = -1). L is strictly convex on its feasible set, so P is the value at the unique
minimiser p*. With b(g) = 1/g, derivatives with respect to the vertices are

    dP/dx_k      = sigma_k b'(g_k) n                           (envelope theorem)
    d2P/dx_k dx_l = delta_kl b''(g_k) n n^T - B_k L_pp^-1 B_l^T  (implicit function theorem)
    B_k = d2L/dx_k dp = sigma_k b'(g_k) [I 0] + b''(g_k) n (x_k, 1)^T

SDRS baseline (Ye et al. 2024, ``sdrs_solve``): the same plane problem with IPC's locally
supported log barrier b(g) = -(g - dhat)^2 log(g / dhat) / dhat^3 for g < dhat, 0 beyond
(``leaf_barrier``), on unit normals |n| = 1, so that g_k is the vertex's distance to the
plane:

    P_sdrs(A, B) = min_{|n| = 1, d} sum_k b(g_k)

b is convex and decreasing, so this equals the minimum over |n| <= 1 (a convex problem;
scaling a plane up only lowers L while a gap is below dhat), whose minimiser is unique
when P > 0. P = 0 exactly, with zero derivatives, when the triangles are at least 2 dhat
apart (the best plane, the closest points' bisector, then leaves every gap >= dhat). b is
C2 at dhat, so P is twice differentiable; it is +inf on contact. The solve is Newton on
the sphere: steps tangent to |n| = 1 with the Riemannian Hessian
P Lnn P + lam P (lam = -sum_k b'(g_k) g_k, the multiplier of |n| = 1) plus a radial block
c n n^T that only fixes the gauge (c = the mean tangent curvature, for conditioning),
retracted by normalising n. The same formulas give the
derivatives with B_k's normal columns projected on the tangent plane, B_k T with
T = diag(P, 1); the solution stores T L_pp^-1 T, which applies that projection once per pair.

All work happens in a local frame centred on the midpoint of the closest points and
turned so that its z axis is the start normal e (``LeafSolution.frame``): the potential is
invariant under both (d absorbs the shift; gaps are dot products), the centre keeps the
small gaps g_k free of cancellation when the triangles sit far from the world origin, and
the turn keeps the plane Hessian's stiff directions (the tilts and the offset, held by
gaps far below the triangles' size) apart from its soft one (the normal's length) in
every orientation. Solved in world axes, a near-touching pair turned off the axes mixed
them, and the 4x4 solve lost the soft direction's digits: Hessians off by 1e-2 at 1e-7 m
gaps, and pairs unsolved at 1e-8 m. Where the optimal plane tilts off e near contact (a face
over a perpendicular face's edge), the search goes on in a frame along it (``_solve_from``).
The plane search and L_pp^-1 stay in the turned frame;
the solution's n and every derivative a caller reads are in world axes, so B_k's rows are
world coordinates and its plane columns the frame's:

    B_k = sigma_k b'(g_k) [R^T 0] + b''(g_k) n (R x_k, 1)^T,  R = ``frame`` (rows: its axes)

The plane search (``_plane_newton``) is generic over the float type: ``leaf_solve`` with
``float32_search`` runs it in float32 and finishes it in float64 (``_solve_from_float32``).
Everything the derivatives read (``LeafSolution``) is float64.
"""

from typing import Any

import warp as wp

from .geometry import triangle_closest_points, triangle_separating_axis
from .linalg import spd4_inverse, spd4_solve

wp.set_module_options({"enable_backward": False})

__all__ = [
    "LEAF_OK",
    "LEAF_CONTACT",
    "LEAF_NOT_CONVERGED",
    "LEAF_NONFINITE",
    "MAX_LEAF_SEPARATION",
    "LeafSolution",
    "leaf_barrier",
    "leaf_solve",
    "sdrs_solve",
    "pair_solve",
    "pair_solve_from_plane",
    "leaf_vertex",
    "leaf_vertex_barrier",
    "leaf_vertex_gradient",
    "leaf_mixed_block",
    "leaf_hessian_block",
    "leaf_plane_sensitivity",
    "leaf_potential_kernel",
]

LEAF_OK = wp.constant(0)
LEAF_CONTACT = wp.constant(1)  # touching or intersecting: P = +inf
LEAF_NOT_CONVERGED = wp.constant(2)  # iteration cap or line-search failure
LEAF_NONFINITE = wp.constant(3)  # non-finite input coordinates

mat34d = wp.types.matrix(shape=(3, 4), dtype=wp.float64)

# Converged when the squared Newton decrement, relative to L, falls below this; about
# two Newton steps past the point where L itself stops changing in float64.
_DECREMENT_TOL = wp.constant(wp.float64(1.0e-24))
# If the line search stalls, the iterate is accepted only below this decrement relative
# to _energy_scale (the precision floor of L's evaluation); otherwise the pair is flagged.
_STALL_TOL = wp.constant(wp.float64(1.0e-14))
# Below this decrement relative to _energy_scale the Newton step is taken in full.
_FULL_STEP_TOL = wp.constant(wp.float64(1.0e-10))
_ARMIJO = wp.constant(1.0e-4)
# The same three tests for a plane search in float32 (unit roundoff 6e-8 against 1.1e-16),
# scaled to its rounding as the float64 ones are to float64's.
_DECREMENT_TOL_F32 = wp.constant(wp.float32(1.0e-12))
_STALL_TOL_F32 = wp.constant(wp.float32(1.0e-5))
_FULL_STEP_TOL_F32 = wp.constant(wp.float32(1.0e-2))
# SDRS pairs whose widest-margin plane misses dhat by less than this fraction count as
# beyond the support (see sdrs_solve).
_SUPPORT_TOL = wp.constant(wp.float64(1.0e-8))
_MAX_BACKTRACKS = wp.constant(60)
# Farthest separation (m) a leaf plane search resolves: beyond ~1e29 m the barrier terms
# (1/g ~ 1e-29) vanish against the plane term's 12 in float64, and pairs converged to planes
# tilted up to 80 degrees from the separation (forces of ~1e-44 N in wrong directions) or
# read as contact. Such pairs are reported not converged. A body-level potential never
# solves them (they are far terms there unless eps is huge); ten times the size of the
# observable universe is no limit on a scene.
MAX_LEAF_SEPARATION = wp.constant(wp.float64(1.0e27))
# A plane whose normal leaves the search frame's z axis by more than this (radians) is
# searched on in a frame along it, at most _MAX_REFRAMES times.
_REFRAME_TILT = wp.constant(wp.float64(1.0e-8))
# ... when some vertex is nearer to it than this fraction of the pair's extent (farther,
# the plane Hessian's terms are within 1e9 of each other, and no digits are at stake).
_REFRAME_GAP = wp.constant(wp.float64(1.0e-3))
_MAX_REFRAMES = wp.constant(2)


@wp.struct
class LeafSolution:
    status: wp.int32
    iterations: wp.int32
    value: wp.float64
    # Optimal plane in world axes about origin; world offset is d - <n, origin>.
    n: wp.vec3d
    d: wp.float64
    origin: wp.vec3d
    # Rows: the axes of the frame the plane is solved in, z along the start normal, or along
    # the optimal plane's where the search was re-framed (``_solve_from``).
    frame: wp.mat33d
    # Vertices relative to origin in world axes (rows) and their gaps g_k.
    ta: wp.mat33d
    tb: wp.mat33d
    gap_a: wp.vec3d
    gap_b: wp.vec3d
    # Barrier slopes b'(g_k) and curvatures b''(g_k), stored once: the derivative blocks
    # read them many times per pair.
    slope_a: wp.vec3d
    slope_b: wp.vec3d
    curv_a: wp.vec3d
    curv_b: wp.vec3d
    # Inverse plane Hessian L_pp^-1 at the optimum, in the frame's plane coordinates
    # (R n, d); for SDRS T L_pp^-1 T with T = diag(I - (R n)(R n)^T, 1), which restricts
    # every use to unit-normal plane variations.
    lpp_inv: wp.mat44d
    # Barrier support: 0 for the paper's 1/g, > 0 for SDRS's log barrier on unit normals.
    dhat: wp.float64


@wp.func
def leaf_barrier(g: Any, dhat: Any):
    """Barrier b(g) of one gap g > 0 and its derivatives (b, b', b''), in g's float type.

    dhat <= 0: the paper's global b = 1/g. dhat > 0: SDRS's (IPC's) locally supported
    log barrier, b = -(s - 1)^2 log(s) / dhat with s = g / dhat < 1, exactly 0 beyond; b, b'
    and b'' all vanish at dhat, so b is C2 there. It is IPC's -(g - dhat)^2 log(g / dhat)
    divided by dhat^3: a shape independent of dhat, in units of 1/length like 1/g, so the
    contact stiffness mu means the same in both models (b' = -1/g^2 and -1/(dhat g) for
    g << dhat).
    """
    one = type(g)(1.0)
    two = type(g)(2.0)
    if dhat <= type(g)(0.0):
        ig = one / g
        return ig, -ig * ig, two * ig * ig * ig
    if g >= dhat:
        zero = type(g)(0.0)
        return zero, zero, zero
    s = g / dhat
    r = s - one
    lg = wp.log(s)
    b = -r * r * lg / dhat
    b1 = (-two * r * lg - r * r / s) / (dhat * dhat)
    b2 = (-two * lg - type(g)(4.0) * r / s + r * r / (s * s)) / (dhat * dhat * dhat)
    return b, b1, b2


@wp.func
def leaf_vertex(sol: LeafSolution, k: int):
    """Local coordinates, sign sigma and gap g of vertex k (0..2: A, 3..5: B)."""
    if k < 3:
        return sol.ta[k], wp.float64(1.0), sol.gap_a[k]
    return sol.tb[k - 3], wp.float64(-1.0), sol.gap_b[k - 3]


@wp.func
def leaf_vertex_barrier(sol: LeafSolution, k: int):
    """b'(g_k) and b''(g_k) of vertex k."""
    if k < 3:
        return sol.slope_a[k], sol.curv_a[k]
    return sol.slope_b[k - 3], sol.curv_b[k - 3]


@wp.func
def _barrier_sum(ta: Any, tb: Any, p: Any, dhat: Any):
    """sum_k b(g_k) at plane p; +inf if p does not separate the triangles strictly."""
    zero = p.dtype(0.0)
    n = wp.vector(p[0], p[1], p[2])
    energy = zero
    for k in range(3):
        ga = wp.dot(ta[k], n) + p[3]
        gb = -(wp.dot(tb[k], n) + p[3])
        if ga <= zero or gb <= zero:
            return p.dtype(wp.inf)
        ba, _ba1, _ba2 = leaf_barrier(ga, dhat)
        bb, _bb1, _bb2 = leaf_barrier(gb, dhat)
        energy += ba + bb
    return energy


@wp.func
def _plane_energy(ta: Any, tb: Any, p: Any):
    r = wp.length(wp.vector(p[0], p[1], p[2]))
    one = p.dtype(1.0)
    if r >= one:
        return p.dtype(wp.inf)
    return p.dtype(12.0) / (one - r) + _barrier_sum(ta, tb, p, p.dtype(0.0))


@wp.func
def _add_vertex_terms(x: Any, sigma: Any, p: Any, dhat: Any, grad: Any, hess: Any, lam: Any):
    """Adds vertex x's barrier term to grad and hess of L in p, and -b'(g) g to lam."""
    g = sigma * (wp.dot(x, wp.vector(p[0], p[1], p[2])) + p[3])
    _b, b1, b2 = leaf_barrier(g, dhat)
    v = wp.vector(x[0], x[1], x[2], p.dtype(1.0))
    return grad + (sigma * b1) * v, hess + b2 * wp.outer(v, v), lam - b1 * g


@wp.func
def _plane_derivatives(ta: Any, tb: Any, p: Any):
    """Gradient and Hessian of L in p (p must be feasible)."""
    zero = p.dtype(0.0)
    n = wp.vector(p[0], p[1], p[2])
    r = wp.length(n)
    one = p.dtype(1.0)
    om = one - r
    f1 = p.dtype(12.0) / (om * om)
    f2 = p.dtype(24.0) / (om * om * om)
    u = n / r
    grad = wp.vector(f1 * u[0], f1 * u[1], f1 * u[2], zero)
    hess = wp.matrix(shape=(4, 4), dtype=p.dtype)
    for i in range(3):
        for j in range(3):
            hess[i, j] = (f2 - f1 / r) * u[i] * u[j]
        hess[i, i] = hess[i, i] + f1 / r
    lam = zero
    for k in range(3):
        grad, hess, lam = _add_vertex_terms(ta[k], one, p, zero, grad, hess, lam)
        grad, hess, lam = _add_vertex_terms(tb[k], -one, p, zero, grad, hess, lam)
    return grad, hess


@wp.func
def _max_feasible_step(ta: Any, tb: Any, p: Any, dp: Any):
    """Largest alpha with p + alpha dp strictly inside the feasible set (may be +inf)."""
    zero = p.dtype(0.0)
    alpha = p.dtype(wp.inf)
    for k in range(3):
        for side in range(2):
            x = ta[k]
            sigma = p.dtype(1.0)
            if side == 1:
                x = tb[k]
                sigma = p.dtype(-1.0)
            g = sigma * (wp.dot(x, wp.vector(p[0], p[1], p[2])) + p[3])
            rate = sigma * (wp.dot(x, wp.vector(dp[0], dp[1], dp[2])) + dp[3])
            if rate < zero:
                alpha = wp.min(alpha, -g / rate)
    # |n + alpha dn| < 1: positive root of a alpha^2 + 2 b alpha + c, c < 0.
    n = wp.vector(p[0], p[1], p[2])
    dn = wp.vector(dp[0], dp[1], dp[2])
    a = wp.dot(dn, dn)
    if a > zero:
        b = wp.dot(n, dn)
        c = wp.dot(n, n) - p.dtype(1.0)
        disc = wp.sqrt(wp.max(b * b - a * c, zero))
        root = zero
        if b >= zero:
            root = -c / (b + disc)
        else:
            root = (disc - b) / a
        alpha = wp.min(alpha, root)
    return alpha


@wp.func
def _tangent_projector(n: Any):
    """diag(I - n n^T, 1): restricts plane variations to unit normals."""
    t = wp.identity(n=4, dtype=n.dtype)
    for i in range(3):
        for j in range(3):
            t[i, j] = t[i, j] - n[i] * n[j]
    return t


@wp.func
def _sdrs_derivatives(ta: Any, tb: Any, p: Any, dhat: Any):
    """Riemannian gradient and Hessian of the SDRS plane energy on |n| = 1 (see module docstring)."""
    grad = wp.vector(length=4, dtype=p.dtype)
    hess = wp.matrix(shape=(4, 4), dtype=p.dtype)
    lam = p.dtype(0.0)
    one = p.dtype(1.0)
    for k in range(3):
        grad, hess, lam = _add_vertex_terms(ta[k], one, p, dhat, grad, hess, lam)
        grad, hess, lam = _add_vertex_terms(tb[k], -one, p, dhat, grad, hess, lam)
    n = wp.vector(p[0], p[1], p[2])
    t = _tangent_projector(n)
    hess = t * hess * t
    # The sphere's curvature adds lam on the tangent plane. The radial direction is a gauge
    # (no gradient, no step, projected out of every derivative), so its curvature is free:
    # the mean tangent curvature keeps H well conditioned where lam -> 0 at the support.
    gauge = lam + p.dtype(0.5) * (hess[0, 0] + hess[1, 1] + hess[2, 2])
    for i in range(3):
        for j in range(3):
            hess[i, j] = hess[i, j] + (gauge - lam) * n[i] * n[j]
        hess[i, i] = hess[i, i] + lam
    return t * grad, hess


@wp.func
def _energy(ta: Any, tb: Any, p: Any, dhat: Any):
    if dhat > p.dtype(0.0):
        return _barrier_sum(ta, tb, p, dhat)
    return _plane_energy(ta, tb, p)


@wp.func
def _derivatives(ta: Any, tb: Any, p: Any, dhat: Any):
    if dhat > p.dtype(0.0):
        return _sdrs_derivatives(ta, tb, p, dhat)
    return _plane_derivatives(ta, tb, p)


@wp.func
def _step_bound(ta: Any, tb: Any, p: Any, dp: Any, dhat: Any):
    # A retracted (SDRS) step leaves the linear constraint set along a curve; its
    # infeasible trials have infinite energy and are backtracked instead.
    if dhat > p.dtype(0.0):
        return p.dtype(wp.inf)
    return _max_feasible_step(ta, tb, p, dp)


@wp.func
def _energy_scale(ta: Any, tb: Any, p: Any, dhat: Any, energy: Any):
    """The scale of L's rounding error, which the full-step and stall tests compare
    decrements with: L itself for the paper's model (L >= 12), but for SDRS also
    sum_k |b'(g_k)| (|x_k| + |d|), E's slope times the size of its gaps' rounding: near
    the support E -> 0 far faster than its rounding error, and an Armijo test on E, or a
    stall test relative to E, resolves nothing there."""
    if dhat <= p.dtype(0.0):
        return energy
    n = wp.vector(p[0], p[1], p[2])
    scale = energy
    for k in range(3):
        _ba, ba1, _ba2 = leaf_barrier(wp.dot(ta[k], n) + p[3], dhat)
        _bb, bb1, _bb2 = leaf_barrier(-(wp.dot(tb[k], n) + p[3]), dhat)
        scale += -ba1 * (wp.length(ta[k]) + wp.abs(p[3])) - bb1 * (wp.length(tb[k]) + wp.abs(p[3]))
    return scale


@wp.func
def _advance(p: Any, step: Any, alpha: Any, dhat: Any):
    trial = p + alpha * step
    if dhat > p.dtype(0.0):
        # Retraction onto unit normals (the step is tangent, so |n + alpha dn| >= 1).
        n = wp.normalize(wp.vector(trial[0], trial[1], trial[2]))
        trial = wp.vector(n[0], n[1], n[2], trial[3])
    return trial


@wp.func
def _is_finite_mat(m: wp.mat33d):
    for i in range(3):
        for j in range(3):
            if not wp.isfinite(m[i, j]):
                return False
    return True


@wp.func
def _frame_from_normal(e: wp.vec3d):
    """Rows: an orthonormal frame whose z axis is the unit vector e (Duff et al. 2017); the
    identity, up to signs, for e on a world axis (``_contact_frame`` then turns it about z)."""
    sign = wp.float64(1.0)
    if e[2] < wp.float64(0.0):
        sign = wp.float64(-1.0)
    a = wp.float64(-1.0) / (sign + e[2])
    b = e[0] * e[1] * a
    return wp.mat33d(
        wp.float64(1.0) + sign * e[0] * e[0] * a, sign * b, -sign * e[0],
        b, sign + e[1] * e[1] * a, -e[1],
        e[0], e[1], e[2],
    )  # fmt: skip


@wp.func
def _contact_frame(ta: wp.mat33d, tb: wp.mat33d, e: wp.vec3d, offset: wp.float64):
    """Rows: the frame of a pair's plane search, z along the unit normal e of a separating
    plane <x, e> + offset = 0 and x along the widest spread of the vertices nearest it
    (weights (g_min / g)^3, as b'' at its gaps). Near vertices along one line (parallel edges) hold the tilt
    towards that line stiffly and leave the tilt about it soft: only with the line on an
    axis does the plane Hessian keep the soft tilt's digits."""
    base = _frame_from_normal(e)
    gap_min = wp.float64(wp.inf)
    for k in range(3):
        gap_min = wp.min(gap_min, wp.min(wp.dot(ta[k], e) + offset, -(wp.dot(tb[k], e) + offset)))
    weight_sum = wp.float64(0.0)
    first = wp.vec2d()
    second = wp.vec3d()  # xx, xy, yy
    for k in range(6):
        x = ta[k % 3]
        if k >= 3:
            x = tb[k - 3]
        local = base * x
        ratio = gap_min / wp.abs(local[2] + offset)
        weight = ratio * ratio * ratio
        weight_sum += weight
        first += weight * wp.vec2d(local[0], local[1])
        second += weight * wp.vec3d(local[0] * local[0], local[0] * local[1], local[1] * local[1])
    mean = first / weight_sum
    xx = second[0] / weight_sum - mean[0] * mean[0]
    xy = second[1] / weight_sum - mean[0] * mean[1]
    yy = second[2] / weight_sum - mean[1] * mean[1]
    angle = wp.float64(0.5) * wp.atan2(wp.float64(2.0) * xy, xx - yy)
    c = wp.cos(angle)
    s = wp.sin(angle)
    return wp.matrix_from_rows(c * base[0] + s * base[1], c * base[1] - s * base[0], base[2])


@wp.func
def _frame_triangles(sol: LeafSolution):
    """A's and B's vertices (rows) in the solution's frame."""
    ta = wp.mat33d()
    tb = wp.mat33d()
    for k in range(3):
        ta[k] = sol.frame * sol.ta[k]
        tb[k] = sol.frame * sol.tb[k]
    return ta, tb


@wp.func
def _leaf_start(ta_world: wp.mat33d, tb_world: wp.mat33d, dhat: wp.float64):
    """Local frame and unit start normal e, the closest points' bisector plane (n = e, d = 0),
    which is (0, 0, 1, 0) in the frame (its z axis is e).

    Sets status CONTACT when no such plane separates the triangles strictly (they touch or
    intersect) and NONFINITE for non-finite input.
    """
    sol = LeafSolution()
    sol.status = LEAF_OK
    sol.iterations = 0
    sol.value = wp.float64(wp.inf)
    sol.dhat = dhat
    e = wp.vec3d()
    if not (_is_finite_mat(ta_world) and _is_finite_mat(tb_world)):
        sol.status = LEAF_NONFINITE
        return sol, e

    ca, cb = triangle_closest_points(ta_world, tb_world)
    sep = ca - cb
    dist = wp.length(sep)
    origin = wp.float64(0.5) * (ca + cb)
    sol.origin = origin
    ta = wp.mat33d()
    tb = wp.mat33d()
    for k in range(3):
        ta[k] = ta_world[k] - origin
        tb[k] = tb_world[k] - origin
    sol.ta = ta
    sol.tb = tb
    if dist <= wp.float64(0.0):
        sol.status = LEAF_CONTACT
        return sol, e

    # The plane through the midpoint, normal to the closest-point direction, separates
    # disjoint triangles strictly.
    e = sep / dist
    if _separates(ta, tb, e):
        sol.frame = _contact_frame(ta, tb, e, wp.float64(0.0))
        return sol, e
    # At gaps far below the triangles' size that direction, rounded, can tilt the plane
    # across a large triangle's far vertices; a separating axis of the pair (face normals,
    # edge cross products) is exact there. With none, the triangles touch or intersect.
    axis, offset, found = triangle_separating_axis(ta, tb)
    if not found:
        sol.status = LEAF_CONTACT
        return sol, e
    origin = origin + offset * axis
    for k in range(3):
        ta[k] = ta[k] - offset * axis
        tb[k] = tb[k] - offset * axis
    sol.origin = origin
    sol.ta = ta
    sol.tb = tb
    sol.frame = _contact_frame(ta, tb, axis, wp.float64(0.0))
    return sol, axis


@wp.func
def _separates(ta: wp.mat33d, tb: wp.mat33d, e: wp.vec3d):
    """Whether the plane through the local origin with normal e leaves A strictly on its
    positive side and B strictly on its negative side."""
    for k in range(3):
        if wp.dot(ta[k], e) <= wp.float64(0.0) or wp.dot(tb[k], e) >= wp.float64(0.0):
            return False
    return True


@wp.func
def _store_plane(sol: LeafSolution, p: wp.vec4d):
    """Stores the plane p, given in the frame, with n in world axes, and its gaps."""
    n = wp.vec3d(p[0], p[1], p[2])
    sol.n = wp.transpose(sol.frame) * n
    sol.d = p[3]
    ta, tb = _frame_triangles(sol)
    sol.gap_a = wp.vec3d(wp.dot(ta[0], n) + p[3], wp.dot(ta[1], n) + p[3], wp.dot(ta[2], n) + p[3])
    sol.gap_b = wp.vec3d(-(wp.dot(tb[0], n) + p[3]), -(wp.dot(tb[1], n) + p[3]), -(wp.dot(tb[2], n) + p[3]))
    slope_a = wp.vec3d()
    slope_b = wp.vec3d()
    curv_a = wp.vec3d()
    curv_b = wp.vec3d()
    for k in range(3):
        _ba, ba1, ba2 = leaf_barrier(sol.gap_a[k], sol.dhat)
        _bb, bb1, bb2 = leaf_barrier(sol.gap_b[k], sol.dhat)
        slope_a[k] = ba1
        curv_a[k] = ba2
        slope_b[k] = bb1
        curv_b[k] = bb2
    sol.slope_a = slope_a
    sol.slope_b = slope_b
    sol.curv_a = curv_a
    sol.curv_b = curv_b
    return sol


@wp.func
def _plane_newton(ta: Any, tb: Any, start: Any, dhat: Any, max_iterations: int, decrement_tol: Any, stall_tol: Any, full_step_tol: Any):
    """Damped Newton on the plane from ``start`` (see the module docstring), in the float
    type of its arguments; returns (plane, L, Hessian at the plane, converged, iterations).
    Converged: decrement <= decrement_tol L, or, where the decrement stops shrinking,
    decrement <= stall_tol times L's rounding scale. A start that does not separate the
    triangles strictly inside |n| < 1 returns at once with L = +inf (iterates never do)."""
    p = start
    energy = _energy(ta, tb, p, dhat)
    one = p.dtype(1.0)
    converged = bool(False)
    previous_decrement = p.dtype(wp.inf)
    # Every exit with converged = True leaves p where hess was taken, so the caller's
    # inverse reuses it.
    hess = wp.matrix(shape=(4, 4), dtype=p.dtype)
    it = int(0)
    if not wp.isfinite(energy):
        return p, energy, hess, converged, it
    while it < max_iterations:
        grad, hess = _derivatives(ta, tb, p, dhat)
        step, ok = spd4_solve(hess, -grad)
        if not ok:
            break
        decrement = -wp.dot(grad, step)
        scale = _energy_scale(ta, tb, p, dhat, energy)
        if decrement <= decrement_tol * energy:
            converged = True
            break
        max_step = _step_bound(ta, tb, p, step, dhat)
        if decrement <= full_step_tol * scale and max_step > one:
            # Quadratic regime: the expected decrease is below what an Armijo test on L
            # can resolve, so take the full (feasible) step; a decrement that stops
            # shrinking means L's rounding floor is reached, or, above the stall level,
            # that L is not quadratic here after all (SDRS near its support, where
            # vertices leave it as the plane tilts): then the damped step below.
            if decrement >= previous_decrement:
                if decrement <= stall_tol * scale:
                    converged = True
                    break
            else:
                previous_decrement = decrement
                trial = _advance(p, step, one, dhat)
                trial_energy = _energy(ta, tb, trial, dhat)
                if wp.isfinite(trial_energy):
                    it += 1
                    p = trial
                    energy = trial_energy
                    continue
        it += 1
        alpha = wp.min(one, p.dtype(0.99) * max_step)
        accepted = bool(False)
        for _bt in range(_MAX_BACKTRACKS):
            trial = _advance(p, step, alpha, dhat)
            trial_energy = _energy(ta, tb, trial, dhat)
            if trial_energy <= energy - p.dtype(_ARMIJO) * alpha * decrement:
                p = trial
                energy = trial_energy
                accepted = True
                break
            alpha = alpha * p.dtype(0.5)
        if not accepted:
            converged = decrement <= stall_tol * scale
            break
    return p, energy, hess, converged, it


@wp.func
def _finish_solution(sol: LeafSolution, p: wp.vec4d, energy: wp.float64, hess: wp.mat44d, converged: bool, iterations: int):
    """Stores the plane p, L and the inverse plane Hessian (all in the frame) in ``sol``."""
    sol.iterations = iterations
    if wp.isnan(energy):
        # No iterate at all: rounding lost the start plane of a pair ~1e-16 of its size
        # apart (1/0 - 1/0 in its scale). Unsolved, at +inf and with no plane: NaN was
        # written as the value and the plane.
        sol.value = wp.float64(wp.inf)
        sol.status = LEAF_NOT_CONVERGED
        return sol
    sol = _store_plane(sol, p)
    sol.value = energy
    if not converged:
        sol.status = LEAF_NOT_CONVERGED
        return sol
    inv, inv_ok = spd4_inverse(hess)
    if not inv_ok:
        sol.status = LEAF_NOT_CONVERGED
        return sol
    if sol.dhat > wp.float64(0.0):
        # B_k T H^-1 T B_l^T: the plane moves on unit normals (module docstring). The
        # radial block of H is decoupled, so T H^-1 T is also the exact dp*/dx operator.
        t = _tangent_projector(wp.vec3d(p[0], p[1], p[2]))
        inv = t * inv * t
    sol.lpp_inv = inv
    return sol


@wp.func
def _near_contact(ta: wp.mat33d, tb: wp.mat33d, p: wp.vec4d):
    """Whether plane p (in the frame) leaves some vertex closer to it than _REFRAME_GAP of
    the pair's extent about the local origin: the stiff terms that mix with soft ones."""
    gap_min = wp.float64(wp.inf)
    extent = wp.float64(0.0)
    n = wp.vec3d(p[0], p[1], p[2])
    for k in range(3):
        gap_min = wp.min(gap_min, wp.min(wp.dot(ta[k], n) + p[3], -(wp.dot(tb[k], n) + p[3])))
        extent = wp.max(extent, wp.max(wp.length(ta[k]), wp.length(tb[k])))
    return gap_min < _REFRAME_GAP * wp.length(n) * extent


@wp.func
def _solve_from(sol: LeafSolution, start: wp.vec4d, fallback: wp.vec4d, max_iterations: int):
    """Newton on the plane in float64 from ``start``, or from ``fallback`` (a start known to
    be feasible) where ``start`` is not (planes in the frame); fills the solution."""
    ta, tb = _frame_triangles(sol)
    p, energy, hess, converged, it = _plane_newton(ta, tb, start, sol.dhat, max_iterations, _DECREMENT_TOL, _STALL_TOL, _FULL_STEP_TOL)
    if not wp.isfinite(energy):
        p, energy, hess, converged, it = _plane_newton(ta, tb, fallback, sol.dhat, max_iterations, _DECREMENT_TOL, _STALL_TOL, _FULL_STEP_TOL)
    for _turn in range(_MAX_REFRAMES):
        # A near-contact plane tilted off the frame's z axis is searched on, and its Hessian
        # taken, in a frame along it, where the stiff and soft directions part again.
        r = wp.length(wp.vec3d(p[0], p[1], p[2]))
        if not wp.isfinite(energy) or wp.length(wp.vec2d(p[0], p[1])) <= _REFRAME_TILT * r or not _near_contact(ta, tb, p):
            break
        search_frame = sol.frame
        n = wp.transpose(sol.frame) * wp.vec3d(p[0], p[1], p[2])
        sol.frame = _contact_frame(sol.ta, sol.tb, n / r, p[3] / r)
        turned = sol.frame * n
        ta, tb = _frame_triangles(sol)
        p_turned, energy_turned, hess_turned, converged_turned, it_turned = _plane_newton(
            ta, tb, wp.vec4d(turned[0], turned[1], turned[2], p[3]), sol.dhat, max_iterations, _DECREMENT_TOL, _STALL_TOL, _FULL_STEP_TOL
        )
        it += it_turned
        if not wp.isfinite(energy_turned) or (converged and not converged_turned):
            # Rounding left the plane infeasible in the new frame, or the search there did
            # not converge where the first one had: the previous frame's solution stands.
            sol.frame = search_frame
            break
        p, energy, hess, converged = p_turned, energy_turned, hess_turned, converged_turned
    return _finish_solution(sol, p, energy, hess, converged, it)


@wp.func
def _solve_from_float32(sol: LeafSolution, start: wp.vec4d, max_iterations: int):
    """Newton on the plane from ``start`` with the search in float32, finished in float64
    (``_solve_from``) from its plane: the float64 stage usually takes one or two steps, and
    the solution meets the float64 tolerances. The iteration cap applies to each stage."""
    ta, tb = _frame_triangles(sol)
    p32, energy32, _hess32, _converged32, it32 = _plane_newton(
        wp.mat33f(ta), wp.mat33f(tb), wp.vec4f(start), wp.float32(sol.dhat), max_iterations, _DECREMENT_TOL_F32, _STALL_TOL_F32, _FULL_STEP_TOL_F32
    )
    # Rounding may leave a near-touching start plane infeasible in float32, and the float32
    # optimum infeasible in float64: either stage then starts from the float64 start.
    p = start
    if wp.isfinite(energy32):
        p = wp.vec4d(p32)
    sol = _solve_from(sol, p, start, max_iterations)
    sol.iterations = sol.iterations + it32
    return sol


@wp.func
def _scaled_bisector(sol: LeafSolution, e: wp.vec3d):
    """The start plane of ``leaf_solve`` in the frame: the bisector (normal e, the frame's z
    axis, through the local origin) at its best scale r, the minimiser of
    12/(1-r) + coupling/r along it."""
    coupling = wp.float64(0.0)
    for k in range(3):
        coupling += wp.float64(1.0) / wp.dot(sol.ta[k], e) - wp.float64(1.0) / wp.dot(sol.tb[k], e)
    q = wp.sqrt(coupling / wp.float64(12.0))
    r0 = q / (wp.float64(1.0) + q)
    return wp.vec4d(wp.float64(0.0), wp.float64(0.0), r0, wp.float64(0.0))


@wp.func
def _separation_lower_bound(ta: wp.mat33d, tb: wp.mat33d):
    """A lower bound on the distance between triangles A and B: their centroids' distance
    less each one's farthest vertex from its centroid."""
    third = wp.float64(1.0) / wp.float64(3.0)
    ca = (ta[0] + ta[1] + ta[2]) * third
    cb = (tb[0] + tb[1] + tb[2]) * third
    ra = wp.max(wp.length(ta[0] - ca), wp.max(wp.length(ta[1] - ca), wp.length(ta[2] - ca)))
    rb = wp.max(wp.length(tb[0] - cb), wp.max(wp.length(tb[1] - cb), wp.length(tb[2] - cb)))
    return wp.length(ca - cb) - ra - rb


@wp.func
def leaf_solve(ta_world: wp.mat33d, tb_world: wp.mat33d, max_iterations: int, float32_search: bool):
    """Solve the leaf plane problem for triangles A, B (rows = vertices, world frame);
    ``float32_search`` runs the plane search in float32 (``_solve_from_float32``)."""
    sol, e = _leaf_start(ta_world, tb_world, wp.float64(0.0))
    if sol.status != LEAF_OK:
        return sol
    if _separation_lower_bound(ta_world, tb_world) > MAX_LEAF_SEPARATION:
        sol.status = LEAF_NOT_CONVERGED
        return sol
    start = _scaled_bisector(sol, e)
    if float32_search:
        return _solve_from_float32(sol, start, max_iterations)
    return _solve_from(sol, start, start, max_iterations)


@wp.func
def sdrs_solve(ta_world: wp.mat33d, tb_world: wp.mat33d, dhat: wp.float64, max_iterations: int):
    """Solve the SDRS plane problem (support ``dhat`` > 0, m) for triangles A, B (world frame)."""
    sol, e = _leaf_start(ta_world, tb_world, dhat)
    if sol.status != LEAF_OK:
        return sol
    start = wp.vec4d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))
    # The bisector is the widest-margin plane (margin = half the distance): if it leaves
    # every gap at or beyond dhat, P = 0 and all derivatives vanish. So it does when the
    # deficit is below _SUPPORT_TOL dhat: there P < 1e-24 / dhat and the plane problem
    # degenerates (its rotation about the active vertices is held only by the multiplier,
    # ~ deficit^2, against curvatures ~ deficit), past what float64 Newton resolves.
    margin = wp.float64(wp.inf)
    for k in range(3):
        margin = wp.min(margin, wp.min(wp.dot(sol.ta[k], e), -wp.dot(sol.tb[k], e)))
    if margin >= dhat * (wp.float64(1.0) - _SUPPORT_TOL):
        sol = _store_plane(sol, start)
        sol.slope_a = wp.vec3d()
        sol.slope_b = wp.vec3d()
        sol.curv_a = wp.vec3d()
        sol.curv_b = wp.vec3d()
        sol.value = wp.float64(0.0)
        return sol
    return _solve_from(sol, start, start, max_iterations)


@wp.func
def pair_solve(ta_world: wp.mat33d, tb_world: wp.mat33d, dhat: wp.float64, max_iterations: int, float32_search: bool):
    """``leaf_solve`` for dhat <= 0 (the paper's model), ``sdrs_solve`` otherwise (always
    float64: its support test and the degenerate planes near it need float64)."""
    if dhat > wp.float64(0.0):
        return sdrs_solve(ta_world, tb_world, dhat, max_iterations)
    return leaf_solve(ta_world, tb_world, max_iterations, float32_search)


@wp.func
def pair_solve_from_plane(ta_world: wp.mat33d, tb_world: wp.mat33d, plane: wp.vec4d, dhat: wp.float64, max_iterations: int):
    """``pair_solve`` started from a plane (n, d) in world coordinates, e.g. this pair's
    optimum at the same or a nearby configuration, where Newton needs a step or none.
    The paper's model only, from the usual start if that plane does not separate the
    triangles strictly inside |n| < 1; SDRS (dhat > 0) solves from its own start."""
    if dhat > wp.float64(0.0):
        return sdrs_solve(ta_world, tb_world, dhat, max_iterations)
    sol, e = _leaf_start(ta_world, tb_world, dhat)
    if sol.status != LEAF_OK:
        return sol
    n = wp.vec3d(plane[0], plane[1], plane[2])
    turned = sol.frame * n
    start = wp.vec4d(turned[0], turned[1], turned[2], plane[3] + wp.dot(n, sol.origin))
    return _solve_from(sol, start, _scaled_bisector(sol, e), max_iterations)


@wp.func
def leaf_vertex_gradient(sol: LeafSolution, k: int):
    """dP/dx_k (the contact force on vertex k is its negative)."""
    _x, sigma, _g = leaf_vertex(sol, k)
    b1, _b2 = leaf_vertex_barrier(sol, k)
    return (sigma * b1) * sol.n


@wp.func
def leaf_mixed_block(sol: LeafSolution, k: int):
    """B_k = d2L / dx_k dp (3x4): rows world coordinates of x_k, columns the frame's plane
    coordinates, those of ``lpp_inv`` (module docstring)."""
    x, sigma, _g = leaf_vertex(sol, k)
    b1, b2 = leaf_vertex_barrier(sol, k)
    turned = sol.frame * x
    m = mat34d()
    for i in range(3):
        for j in range(3):
            m[i, j] = b2 * sol.n[i] * turned[j] + sigma * b1 * sol.frame[j, i]
        m[i, 3] = b2 * sol.n[i]
    return m


@wp.func
def leaf_hessian_block(sol: LeafSolution, k: int, l: int):
    """d2P / dx_k dx_l (3x3)."""
    bk = leaf_mixed_block(sol, k)
    bl = leaf_mixed_block(sol, l)
    block = -(bk * sol.lpp_inv * wp.transpose(bl))
    if k == l:
        _b1, b2 = leaf_vertex_barrier(sol, k)
        block = block + b2 * wp.outer(sol.n, sol.n)
    return block


@wp.func
def leaf_plane_sensitivity(sol: LeafSolution, k: int):
    """d p* / d x_k (4x3) of the optimal local plane p* = (n, d), n in world axes:
    -L_pp^-1 B_k^T in the frame, its normal rows turned to world axes."""
    to_world = wp.identity(n=4, dtype=wp.float64)
    for i in range(3):
        for j in range(3):
            to_world[i, j] = sol.frame[j, i]
    return -(to_world * sol.lpp_inv * wp.transpose(leaf_mixed_block(sol, k)))


@wp.func
def _write_pair(
    tid: int,
    sol: LeafSolution,
    compute_derivatives: bool,
    value_out: wp.array(dtype=wp.float64),
    plane_out: wp.array(dtype=wp.vec4d),
    status_out: wp.array(dtype=wp.int32),
    iterations_out: wp.array(dtype=wp.int32),
    grad_out: wp.array2d(dtype=wp.vec3d),
    hess_out: wp.array3d(dtype=wp.mat33d),
):
    value_out[tid] = sol.value
    status_out[tid] = sol.status
    iterations_out[tid] = sol.iterations
    plane_out[tid] = wp.vec4d(sol.n[0], sol.n[1], sol.n[2], sol.d - wp.dot(sol.n, sol.origin))
    if not compute_derivatives:
        return
    for k in range(6):
        if sol.status == LEAF_OK:
            grad_out[tid, k] = leaf_vertex_gradient(sol, k)
        else:
            grad_out[tid, k] = wp.vec3d()
        for l in range(6):
            if sol.status == LEAF_OK:
                hess_out[tid, k, l] = leaf_hessian_block(sol, k, l)
            else:
                hess_out[tid, k, l] = wp.mat33d()


@wp.kernel
def leaf_potential_kernel(
    # Model:
    dhat: wp.float64,
    # Data in:
    tri_a_in: wp.array(dtype=wp.mat33d),
    tri_b_in: wp.array(dtype=wp.mat33d),
    max_iterations: int,
    float32_search: bool,
    compute_derivatives: bool,
    # Data out:
    value_out: wp.array(dtype=wp.float64),
    plane_out: wp.array(dtype=wp.vec4d),
    status_out: wp.array(dtype=wp.int32),
    iterations_out: wp.array(dtype=wp.int32),
    grad_out: wp.array2d(dtype=wp.vec3d),
    hess_out: wp.array3d(dtype=wp.mat33d),
):
    """One triangle pair per thread: the paper's potential for dhat <= 0, SDRS's otherwise."""
    tid = wp.tid()
    sol = pair_solve(tri_a_in[tid], tri_b_in[tid], dhat, max_iterations, float32_search)
    _write_pair(tid, sol, compute_derivatives, value_out, plane_out, status_out, iterations_out, grad_out, hess_out)
