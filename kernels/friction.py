"""Frictional damping (paper appendix "Frictional Contact Modeling"), lagged and smoothed.

For every leaf pair (triangles A on body a, B on body b) listed at the step's start q^t, and
each vertex x_k of its carrying triangle C (the moving one against a static body, else the
smaller one; ``_carrying_side``):

    N_k = mu W |n| (-b'(g_k))                the normal force of the pair's leaf potential
                                             on vertex k, |dP/dx_k|, times the local
                                             support weight W (sum_k N_k is the pair's net
                                             force: the plane balances the two sides)
    n^  = n / |n|,   T = I - n^ n^^T          lagged contact normal of the separating plane
    p_k = x_k^t                              the vertex's place at q^t
    u_k = T (x_a(X_A,k; q) - x_b(X_B,k; q))  tangential slip over the step of the two
                                             bodies' material points at p_k at q^t
    D   = lambda sum_k N_k (sqrt(|u_k|^2 + e^2) - e),  e = v_eps dt

as the paper's D = sum_k lambda |dP/dx_k| D_par(x_k), over C's vertices. Until 2026-11-27 a
pair's friction acted at one point, C's centroid, with the whole N: where the normal force
sits on C's vertices at an edge (a box tipping about it), the centroids up to 0.38 m above
the edge slipped as the box turned, and their friction made a couple that held a box 30
degrees over its edge, 12 degrees past its balance (a helper's diagnosis).

The leaf potential is the contact model's (``pair_solve`` with its ``dhat``): for the
paper's model b(g) = 1/g (so -b' = 1/g^2) and W = 1 - Phi((rho - d1)/(d2 - d1)) of P_local
(rho = centroid distance, d1 = R_A + R_B); for the SDRS baseline (dhat > 0) b is the
locally supported log barrier on unit normals and W = 1, so N is exactly zero once every
gap of A reaches dhat: no friction acts beyond the barrier's support.

D is C-infinity in q (a smoothed Coulomb law: the friction force lambda N u / sqrt(|u|^2 + e^2)
saturates at lambda N once slip speeds exceed v_eps). N and n^ depend on q^t; the adjoint
kernel differentiates them exactly through the leaf plane's sensitivity dp*/dx.

Both bodies' material points are at one place, so a rigid motion of the two together is no
slip (with each triangle's own centroid, as until 2026-11-26, a plate and a box on it turning
together at 2 rad/s felt full Coulomb friction against the turn and lost 41% of their angular
momentum in 0.5 s).

The adjoint below is per point (drop the k): it contracts a point's force with ell, the relative displacement of the two
bodies' points under the step's adjoint multiplier (rigid coordinates of both bodies). With w = x_a - x_b,
u = T w, root = sqrt(|u|^2 + e^2), s = u / root and F2 = (I - s s^T) / root
(the derivative of s in u), the contraction C = ell . dD/dx_a = lambda N (ell . s) varies as

    dC = lambda [ (ell.s) dN + N ell . F2 (T dw + dT w) ],   dT w = -dn^ (n^.w) - n^ (dn^.w)

and since F2 and T commute (s is tangent) and n^ . dn^ = 0, with m = F2 T ell:

    dC = lambda [ (ell.s) dN - N ((ell.n^) s + (n^.w) m) . dn^ + N m . dw ]

dN and dn^ go on through the plane's sensitivity dp*/dx (``leaf_plane_sensitivity``), dw
through the rigid motion of the two points at q^t: with the step's rotations dR = R R^t^T,
dw = -dR_A (dp_A^t + dtheta_A x r_A) + dR_B (dp_B^t + dtheta_B x r_B) + (dR_A - dR_B) dp
(r: p from each body's centre; p follows its vertex, the carrying triangle being fixed at
q^t), and through the lever arms of ell. dN_k = mu (f_k (|n| dW + W d|n|) - W |n| b''(g_k)
dg_k) with f_k = -b'(g_k); n^ is the pair's, so the points' cotangents on it add up.

No leaf pair is solved twice for its plane: the setup reads N and n^ off the optimal planes
that the contact evaluation at q^t left (``leaf_term_kernel``), and keeps them; the adjoint
needs the full solution (L_pp^-1) and re-solves from the kept plane, where Newton stops
after at most one step (``pair_solve_from_plane``).
"""

import warp as wp

from .blend import shell_blend
from .leaf import LEAF_OK, leaf_barrier, leaf_plane_sensitivity, leaf_vertex, leaf_vertex_barrier, pair_solve_from_plane
from .reduction import Targets, add_record_gradient, add_record_value, add_term_hessian_block, target_record
from .rigid import mat66d, rigid_point_gradient, rigid_separation_derivatives, vec6d, world_triangle

wp.set_module_options({"enable_backward": False})

__all__ = ["FrictionFrame", "friction_setup_kernel", "friction_energy_kernel", "friction_adjoint_kernel"]


@wp.struct
class FrictionFrame:
    """Lagged friction data of one step, one entry per leaf pair listed at q^t."""

    leaf_items: wp.array(dtype=wp.vec4i)  # (triangle_a, triangle_b, parent, body pair)
    normal: wp.array(dtype=wp.vec3d)  # n^
    plane: wp.array(dtype=wp.vec4d)  # the leaf's optimal plane (n, d) at q^t, world frame
    # Three entries per pair (3 tid + k), one per vertex k of the triangle carrying its points:
    vertex_force: wp.array(dtype=wp.float64)  # N_k (0: no friction from this vertex)
    point_a: wp.array(dtype=wp.vec3d)  # X_A, body frame of a
    point_b: wp.array(dtype=wp.vec3d)  # X_B, body frame of b
    offset: wp.array(dtype=wp.vec3d)  # x_a(X_A) - x_b(X_B) at q^t: 0 up to rounding


@wp.func
def _centroid(t: wp.mat33d):
    return (t[0] + t[1] + t[2]) / wp.float64(3.0)


@wp.func
def _leaf_radius(t: wp.mat33d):
    c = _centroid(t)
    return wp.max(wp.max(wp.length(t[0] - c), wp.length(t[1] - c)), wp.length(t[2] - c))


@wp.func
def _carrying_side(local_a: wp.mat33d, local_b: wp.mat33d, dynamic_a: wp.int32, dynamic_b: wp.int32):
    """The triangle whose vertices carry the pair's points (0: A, 1: B): the moving one where
    the other body is static, else the smaller one (A on a tie). A blend of the two
    centroids put a box's point on a two-triangle ground up to the box triangle's radius off
    its centroid (a sliding box's yaw torque 8x larger). The radii are the body-frame
    triangles', so a pair's choice never changes with the poses (from world triangles, two
    equal balls' rounding flipped it, and the step with it)."""
    if dynamic_b == 0 or (dynamic_a != 0 and _leaf_radius(local_a) <= _leaf_radius(local_b)):
        return 0
    return 1


@wp.func
def _support_weight(ca: wp.vec3d, cb: wp.vec3d, d1: wp.float64, eps: wp.float64, dhat: wp.float64):
    """W = 1 - Phi(s) and dW/drho; (1, 0) for SDRS, whose barrier has its own support."""
    if dhat > wp.float64(0.0):
        return wp.float64(1.0), wp.float64(0.0)
    phi, dphi, _ = shell_blend(wp.length(ca - cb), d1, eps)
    return wp.float64(1.0) - phi, -dphi


@wp.kernel
def friction_setup_kernel(
    # Model:
    triangle_vertices: wp.array(dtype=wp.mat33d),
    eps: wp.float64,
    dhat: wp.float64,
    mu: wp.float64,
    body_dynamic: wp.array(dtype=wp.int32),
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    # Data in (leaf_items, plane) and out (the rest):
    frame: FrictionFrame,
):
    """N needs only the gaps of the plane that the contact evaluation at q^t found, so the
    pair is not solved a second time."""
    tid = wp.tid()
    item = frame.leaf_items[tid]
    pair = seed_body_pair[item[3]]
    local_a = triangle_vertices[item[0]]
    local_b = triangle_vertices[item[1]]
    rot_a = body_rotation[pair[0]]
    rot_b = body_rotation[pair[1]]
    pos_a = body_position[pair[0]]
    pos_b = body_position[pair[1]]
    ta = world_triangle(local_a, rot_a, pos_a)
    tb = world_triangle(local_b, rot_b, pos_b)
    # Each vertex of the carrying triangle is a material point of both bodies at the same
    # place: a rigid motion of the two moves them alike (no slip).
    side = _carrying_side(local_a, local_b, body_dynamic[pair[0]], body_dynamic[pair[1]])
    carrier = ta
    sigma = wp.float64(1.0)
    if side == 1:
        carrier = tb
        sigma = wp.float64(-1.0)
    for k in range(3):
        point_a = wp.transpose(rot_a) * (carrier[k] - pos_a)
        point_b = wp.transpose(rot_b) * (carrier[k] - pos_b)
        frame.point_a[3 * tid + k] = point_a
        frame.point_b[3 * tid + k] = point_b
        frame.offset[3 * tid + k] = (rot_a * point_a + pos_a) - (rot_b * point_b + pos_b)  # 0 up to rounding, so u(q^t) = 0 exactly
        frame.vertex_force[3 * tid + k] = wp.float64(0.0)
    frame.normal[tid] = wp.vec3d()
    plane = frame.plane[tid]
    n = wp.vec3d(plane[0], plane[1], plane[2])
    norm = wp.length(n)
    if not (norm > wp.float64(0.0)):
        return
    forces = wp.vec3d()
    for k in range(3):
        gap = sigma * (wp.dot(carrier[k], n) + plane[3])
        if not (gap > wp.float64(0.0)):
            return
        _b, b1, _b2 = leaf_barrier(gap, dhat)
        forces[k] = -b1
    weight, _ = _support_weight(_centroid(ta), _centroid(tb), _leaf_radius(ta) + _leaf_radius(tb), eps, dhat)
    for k in range(3):
        frame.vertex_force[3 * tid + k] = mu * weight * norm * forces[k]
    frame.normal[tid] = n / norm


@wp.func
def _slip(
    normal: wp.vec3d,
    point_a: wp.vec3d,
    point_b: wp.vec3d,
    offset: wp.vec3d,
    rot_a: wp.mat33d,
    pos_a: wp.vec3d,
    rot_b: wp.mat33d,
    pos_b: wp.vec3d,
):
    """(r_a, r_b, w, u): world offsets of the material points, their separation change, slip."""
    ra = rot_a * point_a
    rb = rot_b * point_b
    w = (ra + pos_a) - (rb + pos_b) - offset
    u = w - wp.dot(w, normal) * normal
    return ra, rb, w, u


@wp.func
def _point_friction(coeff: wp.float64, smoothing: wp.float64, nrm: wp.vec3d, ra: wp.vec3d, rb: wp.vec3d, u: wp.vec3d):
    """One point's D = coeff (sqrt(|u|^2 + e^2) - e), its gradient in both bodies' rigid
    coordinates (a, b) and the Hessian blocks (a a), (a b), (b b)."""
    root = wp.sqrt(wp.dot(u, u) + smoothing * smoothing)
    tangent = wp.identity(n=3, dtype=wp.float64) - wp.outer(nrm, nrm)
    g = (coeff / root) * u  # dD/dx_a at the material point (u is tangent)
    f2 = (wp.identity(n=3, dtype=wp.float64) - wp.outer(u, u) / (root * root)) / root
    h = coeff * (tangent * f2 * tangent)
    ga, gb, haa, hab, hbb = rigid_separation_derivatives(g, h, ra, rb)
    return coeff * (root - smoothing), ga, gb, haa, hab, hbb


@wp.kernel
def friction_energy_kernel(
    # Model:
    friction: wp.array(dtype=wp.float64),
    smoothing: wp.float64,
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    frame: FrictionFrame,
    seed_chunk: wp.array(dtype=wp.int32),
    chunk: int,
    # Data out:
    targets: Targets,
):
    """D of one lagged pair (its three points), its gradient and Hessian, added to one of its
    body pair's records (``targets`` holds top-level records only); ``top_level_kernel`` sums
    them. Only the pairs of body pairs in ``chunk`` (``seed_chunk``) are taken. The points'
    terms are summed here, so a pair adds to the record once, not once per point."""
    tid = wp.tid()
    seed = frame.leaf_items[tid][3]
    if friction[0] == wp.float64(0.0) or seed_chunk[seed] != chunk:
        return
    pair = seed_body_pair[seed]
    nrm = frame.normal[tid]
    value = wp.float64(0.0)
    ga = vec6d()
    gb = vec6d()
    haa = mat66d()
    hab = mat66d()
    hbb = mat66d()
    any_point = bool(False)
    for k in range(3):
        point = 3 * tid + k
        coeff = friction[0] * frame.vertex_force[point]
        if coeff != wp.float64(0.0):
            ra, rb, _w, u = _slip(nrm, frame.point_a[point], frame.point_b[point], frame.offset[point], body_rotation[pair[0]], body_position[pair[0]], body_rotation[pair[1]], body_position[pair[1]])
            d, da, db, daa, dab, dbb = _point_friction(coeff, smoothing, nrm, ra, rb, u)
            value += d
            ga += da
            gb += db
            haa += daa
            hab += dab
            hbb += dbb
            any_point = True
    if not any_point:
        return
    record = target_record(targets, -1, seed, tid)
    add_record_value(targets, record, value)
    add_record_gradient(targets, record, pair, 0, ga)
    add_record_gradient(targets, record, pair, 1, gb)
    dynamic_a = targets.body_dynamic[pair[0]] != 0
    dynamic_b = targets.body_dynamic[pair[1]] != 0
    if dynamic_a:
        add_term_hessian_block(targets, -1, seed, tid, 0, 0, haa)
    if dynamic_a and dynamic_b:
        add_term_hessian_block(targets, -1, seed, tid, 0, 1, hab)
    if dynamic_b:
        add_term_hessian_block(targets, -1, seed, tid, 1, 1, hbb)


@wp.kernel
def friction_adjoint_kernel(
    # Model:
    triangle_vertices: wp.array(dtype=wp.mat33d),
    eps: wp.float64,
    dhat: wp.float64,
    mu: wp.float64,
    friction: wp.array(dtype=wp.float64),
    smoothing: wp.float64,
    max_iterations: int,
    # Data in:
    rotation_next: wp.array(dtype=wp.mat33d),
    position_next: wp.array(dtype=wp.vec3d),
    rotation_now: wp.array(dtype=wp.mat33d),
    position_now: wp.array(dtype=wp.vec3d),
    body_dynamic: wp.array(dtype=wp.int32),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    frame: FrictionFrame,
    multiplier: wp.array(dtype=vec6d),
    first: int,
    # Data out:
    adj_now_out: wp.array2d(dtype=wp.float64),
    adj_friction_out: wp.array(dtype=wp.float64),
    adj_mu_out: wp.array(dtype=wp.float64),
):
    """lambda^T d(grad_q D)/dy for y = q^t (through each point's N_k, n^ and the points'
    places), lambda_f and mu, of the lagged pairs from ``first`` on (one thread each)."""
    tid = first + wp.tid()
    lam_f = friction[0]
    if lam_f == wp.float64(0.0):
        return
    if frame.vertex_force[3 * tid] == wp.float64(0.0) and frame.vertex_force[3 * tid + 1] == wp.float64(0.0) and frame.vertex_force[3 * tid + 2] == wp.float64(0.0):
        return
    item = frame.leaf_items[tid]
    pair = seed_body_pair[item[3]]
    nrm = frame.normal[tid]
    # Time-t geometry and the leaf solution's sensitivities.
    rot_a = rotation_now[pair[0]]
    rot_b = rotation_now[pair[1]]
    pos_a = position_now[pair[0]]
    pos_b = position_now[pair[1]]
    ta = world_triangle(triangle_vertices[item[0]], rot_a, pos_a)
    tb = world_triangle(triangle_vertices[item[1]], rot_b, pos_b)
    sol = pair_solve_from_plane(ta, tb, frame.plane[tid], dhat, max_iterations)
    if sol.status != LEAF_OK:
        return
    side_p = _carrying_side(triangle_vertices[item[0]], triangle_vertices[item[1]], body_dynamic[pair[0]], body_dynamic[pair[1]])
    carrier = ta
    if side_p == 1:
        carrier = tb
    la = multiplier[pair[0]]
    lb = multiplier[pair[1]]
    # Per point k: C_k = ell_k . dD_k/dx_a = lambda N_k ell_k.s_k; its differential (module
    # docstring): dC_k = lambda [ (ell_k.s_k) dN_k - N_k ((ell_k.n^) s_k + (n^.w_k) m_k) . dn^
    # + N_k m_k . dw_k ],  m_k = F2_k T ell_k. n^ is the pair's, so its cotangents add up.
    coeff_n = wp.vec3d()
    v_n = wp.vec3d()
    contraction = wp.float64(0.0)
    # The step's rotations, transposed (dR^T = R^t R^T): the same for the pair's three points.
    step_a = wp.transpose(rotation_next[pair[0]] * wp.transpose(rot_a))
    step_b = wp.transpose(rotation_next[pair[1]] * wp.transpose(rot_b))
    point_cot = wp.mat33d()  # row k: the cotangent of point k's place p_k
    for k in range(3):
        point = 3 * tid + k
        big_n = frame.vertex_force[point]
        if big_n == wp.float64(0.0):
            continue
        ra, rb, w, u = _slip(nrm, frame.point_a[point], frame.point_b[point], frame.offset[point], rotation_next[pair[0]], position_next[pair[0]], rotation_next[pair[1]], position_next[pair[1]])
        ell = wp.vec3d()
        if body_dynamic[pair[0]] != 0:
            ell += wp.vec3d(la[0], la[1], la[2]) + wp.cross(wp.vec3d(la[3], la[4], la[5]), ra)
        if body_dynamic[pair[1]] != 0:
            ell -= wp.vec3d(lb[0], lb[1], lb[2]) + wp.cross(wp.vec3d(lb[3], lb[4], lb[5]), rb)
        root = wp.sqrt(wp.dot(u, u) + smoothing * smoothing)
        s = u / root
        contraction += lam_f * big_n * wp.dot(ell, s)
        t_ell = ell - wp.dot(ell, nrm) * nrm
        m = (t_ell - wp.dot(u, t_ell) / (root * root) * u) / root
        coeff_n[k] = lam_f * wp.dot(ell, s)
        v_n += -(lam_f * big_n) * (wp.dot(ell, nrm) * s + wp.dot(nrm, w) * m)
        # The material points' offsets r_a = R_A X_A, r_b = R_B X_B move with q^t, as p_k's
        # place in each body: d r_a = dR_A (dp_k - dp_A^t - dtheta_A x (p_k - p_A^t)), dR_A =
        # R_A R_A^t^T the step's rotation (likewise b; p_k follows its vertex). C_k = g . ell
        # sees them in w (cotangent lambda N_k m on r_a, minus it on r_b) and in ell's lever
        # arms (g . (l_a x d r_a) = (g x l_a) . d r_a, l_a: the multiplier's rotation).
        slip_cot = (lam_f * big_n) * m
        g = (lam_f * big_n) * s
        cot_a = slip_cot
        cot_b = -slip_cot
        if body_dynamic[pair[0]] != 0:
            cot_a += wp.cross(g, wp.vec3d(la[3], la[4], la[5]))
        if body_dynamic[pair[1]] != 0:
            cot_b -= wp.cross(g, wp.vec3d(lb[3], lb[4], lb[5]))
        turned_a = step_a * cot_a
        turned_b = step_b * cot_b
        point_cot[k] = turned_a + turned_b
        if body_dynamic[pair[0]] != 0:
            g_a = rigid_point_gradient(-turned_a, carrier[k] - pos_a)
            for i in range(6):
                wp.atomic_add(adj_now_out, pair[0], i, g_a[i])
        if body_dynamic[pair[1]] != 0:
            g_b = rigid_point_gradient(-turned_b, carrier[k] - pos_b)
            for i in range(6):
                wp.atomic_add(adj_now_out, pair[1], i, g_b[i])
    wp.atomic_add(adj_friction_out, 0, contraction / lam_f)
    wp.atomic_add(adj_mu_out, 0, contraction / mu)
    ca = _centroid(ta)
    cb = _centroid(tb)
    rho_vec = ca - cb
    rho_hat = rho_vec / wp.length(rho_vec)
    weight, dweight = _support_weight(ca, cb, _leaf_radius(ta) + _leaf_radius(tb), eps, dhat)
    norm = wp.length(sol.n)
    nhat = sol.n / norm
    sigma = wp.float64(1.0)
    if side_p == 1:
        sigma = wp.float64(-1.0)
    third = wp.float64(1.0) / wp.float64(3.0)
    for j in range(6):
        dp = leaf_plane_sensitivity(sol, j)  # 4x3
        dn = wp.mat33d()
        for i in range(3):
            for c in range(3):
                dn[i, c] = dp[i, c]
        dd = wp.vec3d(dp[3, 0], dp[3, 1], dp[3, 2])
        sign = wp.float64(1.0)
        if j >= 3:
            sign = wp.float64(-1.0)
        drho = (sign * third) * rho_hat
        dnorm = wp.transpose(dn) * nhat
        cot = wp.transpose((wp.identity(n=3, dtype=wp.float64) - wp.outer(nhat, nhat)) * dn / norm) * v_n
        # dN_k/dx_j with N_k = mu W |n| f_k, f_k = -b'(g_k), g_k = sigma (<x_k, n> + d) (local
        # frame). For SDRS dn is tangent to |n| = 1 (the sensitivity is projected): d|n| = 0.
        for k in range(3):
            if coeff_n[k] == wp.float64(0.0):
                continue
            x, _sigma_k, _g = leaf_vertex(sol, 3 * side_p + k)
            slope, curvature = leaf_vertex_barrier(sol, 3 * side_p + k)
            dg = wp.transpose(dn) * x + dd
            if j == 3 * side_p + k:
                dg += sol.n
            dbig_n = mu * (-slope * (dweight * norm * drho + weight * dnorm) - weight * norm * curvature * sigma * dg)
            cot += coeff_n[k] * dbig_n
        # Vertex j moves the point it carries.
        if j >= 3 * side_p and j < 3 * side_p + 3:
            cot += point_cot[j - 3 * side_p]
        side = 0
        x = ta[0]
        if j < 3:
            x = ta[j]
        else:
            side = 1
            x = tb[j - 3]
        body = pair[side]
        if body_dynamic[body] == 0:
            continue
        pos = pos_a
        if side == 1:
            pos = pos_b
        g6 = rigid_point_gradient(cot, x - pos)
        for i in range(6):
            wp.atomic_add(adj_now_out, body, i, g6[i])
