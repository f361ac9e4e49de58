"""Separating-plane potential between two triangles (paper eq. potential-slow, Lemma lem:slow).

    P(A, B) = min_p L(p),  p = (n, d),
    L(p)    = 12 / (1 - |n|) + sum_k 1 / g_k,   g_k = sigma_k (<x_k, n> + d)

over the six vertices x_k (k < 3: triangle A with sigma = +1; k >= 3: triangle B with
sigma = -1). L is strictly convex on its feasible set, so P is the value at the unique
minimiser p*. Derivatives with respect to the vertices:

    dP/dx_k      = -sigma_k n / g_k^2                          (envelope theorem)
    d2P/dx_k dx_l = delta_kl 2/g_k^3 n n^T - B_k L_pp^-1 B_l^T  (implicit function theorem)
    B_k = d2L/dx_k dp = -sigma_k [I 0] / g_k^2 + 2/g_k^3 n (x_k, 1)^T

All work happens in a local frame centred on the midpoint of the closest points: the
potential is translation invariant (d absorbs the shift), and the local frame keeps the
small gaps g_k free of cancellation when the triangles sit far from the world origin.
"""

import warp as wp

from .geometry import triangle_closest_points
from .linalg import spd4_inverse, spd4_solve

wp.set_module_options({"enable_backward": False})

__all__ = [
    "LEAF_OK",
    "LEAF_CONTACT",
    "LEAF_NOT_CONVERGED",
    "LEAF_NONFINITE",
    "LeafSolution",
    "leaf_solve",
    "leaf_vertex",
    "leaf_vertex_gradient",
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
# If the line search stalls, the iterate is accepted only below this decrement (the
# precision floor of L's evaluation); otherwise the pair is flagged.
_STALL_TOL = wp.constant(wp.float64(1.0e-14))
# Below this relative decrement the Newton step is taken in full (see leaf_solve).
_FULL_STEP_TOL = wp.constant(wp.float64(1.0e-10))
_ARMIJO = wp.constant(wp.float64(1.0e-4))
_MAX_BACKTRACKS = wp.constant(60)


@wp.struct
class LeafSolution:
    status: wp.int32
    iterations: wp.int32
    value: wp.float64
    # Optimal plane in the local frame; world offset is d - <n, origin>.
    n: wp.vec3d
    d: wp.float64
    origin: wp.vec3d
    # Vertices relative to origin (rows) and their gaps g_k.
    ta: wp.mat33d
    tb: wp.mat33d
    gap_a: wp.vec3d
    gap_b: wp.vec3d
    # Inverse plane Hessian L_pp^-1 at the optimum.
    lpp_inv: wp.mat44d


@wp.func
def leaf_vertex(sol: LeafSolution, k: int):
    """Local coordinates, sign sigma and gap g of vertex k (0..2: A, 3..5: B)."""
    if k < 3:
        return sol.ta[k], wp.float64(1.0), sol.gap_a[k]
    return sol.tb[k - 3], wp.float64(-1.0), sol.gap_b[k - 3]


@wp.func
def _plane_energy(ta: wp.mat33d, tb: wp.mat33d, p: wp.vec4d):
    n = wp.vec3d(p[0], p[1], p[2])
    r = wp.length(n)
    one = wp.float64(1.0)
    if r >= one:
        return wp.float64(wp.inf)
    energy = wp.float64(12.0) / (one - r)
    for k in range(3):
        ga = wp.dot(ta[k], n) + p[3]
        gb = -(wp.dot(tb[k], n) + p[3])
        if ga <= wp.float64(0.0) or gb <= wp.float64(0.0):
            return wp.float64(wp.inf)
        energy += one / ga + one / gb
    return energy


@wp.func
def _add_vertex_terms(x: wp.vec3d, sigma: wp.float64, n: wp.vec3d, d: wp.float64, grad: wp.vec4d, hess: wp.mat44d):
    g = sigma * (wp.dot(x, n) + d)
    v = wp.vec4d(x[0], x[1], x[2], wp.float64(1.0))
    ig = wp.float64(1.0) / g
    return grad - (sigma * ig * ig) * v, hess + (wp.float64(2.0) * ig * ig * ig) * wp.outer(v, v)


@wp.func
def _plane_derivatives(ta: wp.mat33d, tb: wp.mat33d, p: wp.vec4d):
    """Gradient and Hessian of L in p (p must be feasible)."""
    n = wp.vec3d(p[0], p[1], p[2])
    r = wp.length(n)
    one = wp.float64(1.0)
    om = one - r
    f1 = wp.float64(12.0) / (om * om)
    f2 = wp.float64(24.0) / (om * om * om)
    u = n / r
    grad = wp.vec4d(f1 * u[0], f1 * u[1], f1 * u[2], wp.float64(0.0))
    hess = wp.mat44d()
    for i in range(3):
        for j in range(3):
            hess[i, j] = (f2 - f1 / r) * u[i] * u[j]
        hess[i, i] = hess[i, i] + f1 / r
    for k in range(3):
        grad, hess = _add_vertex_terms(ta[k], one, n, p[3], grad, hess)
        grad, hess = _add_vertex_terms(tb[k], -one, n, p[3], grad, hess)
    return grad, hess


@wp.func
def _max_feasible_step(ta: wp.mat33d, tb: wp.mat33d, p: wp.vec4d, dp: wp.vec4d):
    """Largest alpha with p + alpha dp strictly inside the feasible set (may be +inf)."""
    zero = wp.float64(0.0)
    alpha = wp.float64(wp.inf)
    for k in range(3):
        for side in range(2):
            x = ta[k]
            sigma = wp.float64(1.0)
            if side == 1:
                x = tb[k]
                sigma = wp.float64(-1.0)
            g = sigma * (wp.dot(x, wp.vec3d(p[0], p[1], p[2])) + p[3])
            rate = sigma * (wp.dot(x, wp.vec3d(dp[0], dp[1], dp[2])) + dp[3])
            if rate < zero:
                alpha = wp.min(alpha, -g / rate)
    # |n + alpha dn| < 1: positive root of a alpha^2 + 2 b alpha + c, c < 0.
    n = wp.vec3d(p[0], p[1], p[2])
    dn = wp.vec3d(dp[0], dp[1], dp[2])
    a = wp.dot(dn, dn)
    if a > zero:
        b = wp.dot(n, dn)
        c = wp.dot(n, n) - wp.float64(1.0)
        disc = wp.sqrt(wp.max(b * b - a * c, zero))
        root = wp.float64(0.0)
        if b >= zero:
            root = -c / (b + disc)
        else:
            root = (disc - b) / a
        alpha = wp.min(alpha, root)
    return alpha


@wp.func
def _is_finite_mat(m: wp.mat33d):
    for i in range(3):
        for j in range(3):
            if not wp.isfinite(m[i, j]):
                return False
    return True


@wp.func
def leaf_solve(ta_world: wp.mat33d, tb_world: wp.mat33d, max_iterations: int):
    """Solve the leaf plane problem for triangles A, B (rows = vertices, world frame)."""
    sol = LeafSolution()
    sol.status = LEAF_OK
    sol.iterations = 0
    sol.value = wp.float64(wp.inf)
    if not (_is_finite_mat(ta_world) and _is_finite_mat(tb_world)):
        sol.status = LEAF_NONFINITE
        return sol

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
        return sol

    # The plane through the midpoint, normal to the closest-point direction, separates
    # disjoint triangles strictly; if it does not, the triangles touch or intersect.
    e = sep / dist
    coupling = wp.float64(0.0)
    for k in range(3):
        ga = wp.dot(ta[k], e)
        gb = -wp.dot(tb[k], e)
        if ga <= wp.float64(0.0) or gb <= wp.float64(0.0):
            sol.status = LEAF_CONTACT
            return sol
        coupling += wp.float64(1.0) / ga + wp.float64(1.0) / gb
    # Best scale along that plane: minimise 12/(1-r) + coupling/r.
    q = wp.sqrt(coupling / wp.float64(12.0))
    r0 = q / (wp.float64(1.0) + q)
    p = wp.vec4d(r0 * e[0], r0 * e[1], r0 * e[2], wp.float64(0.0))
    energy = _plane_energy(ta, tb, p)

    converged = bool(False)
    previous_decrement = wp.float64(wp.inf)
    it = int(0)
    while it < max_iterations:
        grad, hess = _plane_derivatives(ta, tb, p)
        step, ok = spd4_solve(hess, -grad)
        if not ok:
            break
        decrement = -wp.dot(grad, step)
        if decrement <= _DECREMENT_TOL * energy:
            converged = True
            break
        max_step = _max_feasible_step(ta, tb, p, step)
        if decrement <= _FULL_STEP_TOL * energy and max_step > wp.float64(1.0):
            # Quadratic regime: the expected decrease is below what an Armijo test on L
            # can resolve, so take the full (feasible) step; a decrement that stops
            # shrinking means L's rounding floor is reached.
            if decrement >= previous_decrement:
                converged = decrement <= _STALL_TOL * energy
                break
            previous_decrement = decrement
            trial = p + step
            trial_energy = _plane_energy(ta, tb, trial)
            if wp.isfinite(trial_energy):
                it += 1
                p = trial
                energy = trial_energy
                continue
        it += 1
        alpha = wp.min(wp.float64(1.0), wp.float64(0.99) * max_step)
        accepted = bool(False)
        for _bt in range(_MAX_BACKTRACKS):
            trial = p + alpha * step
            trial_energy = _plane_energy(ta, tb, trial)
            if trial_energy <= energy - _ARMIJO * alpha * decrement:
                p = trial
                energy = trial_energy
                accepted = True
                break
            alpha = alpha * wp.float64(0.5)
        if not accepted:
            converged = decrement <= _STALL_TOL * energy
            break

    sol.iterations = it
    n = wp.vec3d(p[0], p[1], p[2])
    sol.n = n
    sol.d = p[3]
    sol.gap_a = wp.vec3d(wp.dot(ta[0], n) + p[3], wp.dot(ta[1], n) + p[3], wp.dot(ta[2], n) + p[3])
    sol.gap_b = wp.vec3d(-(wp.dot(tb[0], n) + p[3]), -(wp.dot(tb[1], n) + p[3]), -(wp.dot(tb[2], n) + p[3]))
    sol.value = energy
    if not converged:
        sol.status = LEAF_NOT_CONVERGED
        return sol
    grad, hess = _plane_derivatives(ta, tb, p)
    inv, inv_ok = spd4_inverse(hess)
    if not inv_ok:
        sol.status = LEAF_NOT_CONVERGED
        return sol
    sol.lpp_inv = inv
    return sol


@wp.func
def leaf_vertex_gradient(sol: LeafSolution, k: int):
    """dP/dx_k (the contact force on vertex k is its negative)."""
    x, sigma, g = leaf_vertex(sol, k)
    return (-sigma / (g * g)) * sol.n


@wp.func
def _mixed_block(sol: LeafSolution, k: int):
    """B_k = d2L / dx_k dp (3x4)."""
    x, sigma, g = leaf_vertex(sol, k)
    ig = wp.float64(1.0) / g
    c = wp.float64(2.0) * ig * ig * ig
    b = mat34d()
    for i in range(3):
        for j in range(3):
            b[i, j] = c * sol.n[i] * x[j]
        b[i, 3] = c * sol.n[i]
        b[i, i] = b[i, i] - sigma * ig * ig
    return b


@wp.func
def leaf_hessian_block(sol: LeafSolution, k: int, l: int):
    """d2P / dx_k dx_l (3x3)."""
    bk = _mixed_block(sol, k)
    bl = _mixed_block(sol, l)
    block = -(bk * sol.lpp_inv * wp.transpose(bl))
    if k == l:
        x, sigma, g = leaf_vertex(sol, k)
        block = block + (wp.float64(2.0) / (g * g * g)) * wp.outer(sol.n, sol.n)
    return block


mat43d = wp.types.matrix(shape=(4, 3), dtype=wp.float64)


@wp.func
def leaf_plane_sensitivity(sol: LeafSolution, k: int):
    """d p* / d x_k (4x3) of the optimal local plane p* = (n, d): -L_pp^-1 B_k^T."""
    return -(sol.lpp_inv * wp.transpose(_mixed_block(sol, k)))


@wp.kernel
def leaf_potential_kernel(
    # Data in:
    tri_a_in: wp.array(dtype=wp.mat33d),
    tri_b_in: wp.array(dtype=wp.mat33d),
    max_iterations: int,
    compute_derivatives: bool,
    # Data out:
    value_out: wp.array(dtype=wp.float64),
    plane_out: wp.array(dtype=wp.vec4d),
    status_out: wp.array(dtype=wp.int32),
    iterations_out: wp.array(dtype=wp.int32),
    grad_out: wp.array2d(dtype=wp.vec3d),
    hess_out: wp.array3d(dtype=wp.mat33d),
):
    tid = wp.tid()
    sol = leaf_solve(tri_a_in[tid], tri_b_in[tid], max_iterations)
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
