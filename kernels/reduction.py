"""Term evaluation and the bottom-up blend reduction of P_BSH, in rigid-body coordinates.

Every term of a body pair (a, b) is differentiated with respect to the 12 coordinates
(dp_a, dtheta_a, dp_b, dtheta_b). Its value and gradient are added to its record
(``Targets``): the accumulator of its enclosing blend record, or, at top level, one of its
body pair's replicated top-level records, which ``top_level_kernel`` finally sums into the
scene totals (value, (nbodies, 6) gradient and dense Hessian over the non-static bodies;
static bodies receive nothing). Blend records are resolved from the deepest nesting level up, each
applying

    B       = (1 - phi) S + phi P_c
    grad B  = (1 - phi) grad S + phi grad P_c + (P_c - S) grad phi
    hess B  = (1 - phi) hess S + phi hess P_c + grad phi (grad P_c - grad S)^T
              + (grad P_c - grad S) grad phi^T + (P_c - S) hess phi

to the exact sum S of its children, and adding B to its own target. hess B is linear in
hess S, so Hessians skip the blend records: a term's Hessian reaches the total multiplied
by the product of (1 - phi) over its enclosing blend records (``blend_weight_kernel``,
``record_weight``), and each blend record adds the rest of hess B (its own terms) with its
parent's weight. Every Hessian therefore goes straight into a top-level record, and blend
records carry 13 numbers instead of 157. A static body's Hessian blocks are not even
formed: entry (i, j) of every formula above reads only entries i and j, so a static row or
column only ever flows into static rows and columns. Hessians are symmetric, so only their
upper triangles are accumulated (78 of 144 atomic adds per term; atomic adds bound these
kernels on a GPU); the reader mirrors the scene total
(``warpcontact.contact.symmetric_from_upper``).

Centred weights: every centred term (a far term, or P_c inside a blend) of the node pair
(I, J) is multiplied by ``node_weight[I] * node_weight[J]``. The paper's model uses weight 1
for every node; ``ContactModel(centred_weight="pairs")`` uses the number of triangles under
each node, so that a centred term stands for as many leaf pairs as the exact sum it replaces
(docs/architecture.md, "Centred weights").

Locally supported models (SDRS) have no far or blend terms: their far list holds the
cluster pairs the traversal pruned, which contribute only their separation bound
(``far_term_kernel`` with ``potential`` off), and their leaf terms use ``pair_solve``'s
SDRS barrier (``dhat`` > 0).
"""

import warp as wp

from .geometry import triangle_closest_points, triangle_separating_axis
from .blend import centered_potential, shell_blend
from .leaf import LEAF_CONTACT, LEAF_OK, LeafSolution, leaf_mixed_block, leaf_vertex_barrier, leaf_vertex_gradient, pair_solve
from .rigid import mat66d, rigid_point_curvature, rigid_point_gradient, rigid_separation_derivatives, upper_entry, vec6d, world_triangle
from .traversal import COUNTER_BLEND, COUNTER_FAR, COUNTER_LEAF, listed

wp.set_module_options({"enable_backward": False})

__all__ = ["PAIR_CONTACT", "RECORD_ENTRIES", "Targets", "add_record_gradient", "add_term_hessian_block", "add_record_value", "target_record", "blend_weight_kernel", "far_term_kernel", "leaf_term_kernel", "blend_level_kernel", "top_level_kernel", "advancement_kernel"]


# A body pair's merged leaf status (``leaf_term_kernel``'s max) when any of its triangle
# pairs touches: it outranks the leaf statuses, so contact is never hidden by an unsolved
# pair (one triangle pair touching to rounding, unsolved, hid 15 intersecting ones, and an
# intersecting start was blamed on float64's resolution).
PAIR_CONTACT = wp.constant(8)


@wp.func
def _pair_status_rank(status: int):
    if status == LEAF_CONTACT:
        return PAIR_CONTACT
    return status


@wp.struct
class Targets:
    """Accumulator records that terms add to. Value and gradient records below
    ``top_record`` are the blend records (same index as the blend list); from ``top_record``
    on, each body pair (seed) owns ``top_replicas`` records for its top-level terms, which
    ``top_level_kernel`` sums into the scene totals. Hessian records exist at top level only
    (``record_hess[seed * top_replicas + replica]``); ``record_weight[r]`` is the product of
    (1 - phi) over blend record r and its enclosing ones. Replicas spread the atomic adds of
    a body pair's terms (e.g. 113k top-level blend records over 136 body pairs at 6,208
    triangles), which would otherwise all contend for the same few hundred addresses on a
    GPU."""

    record_value: wp.array(dtype=wp.float64)
    record_grad: wp.array2d(dtype=wp.float64)
    record_hess: wp.array3d(dtype=wp.float64)
    record_weight: wp.array(dtype=wp.float64)
    top_record: int
    top_replicas: int
    body_dynamic: wp.array(dtype=wp.int32)
    # Each body's block of the scene Hessian, which holds the non-static bodies only (in
    # index order); -1 for a static body.
    hessian_slot: wp.array(dtype=wp.int32)


@wp.func
def target_record(t: Targets, parent: int, seed: int, tid: int):
    """The record a term adds to: its enclosing blend record, or one of its body pair's
    top-level replicas (chosen by thread, so neighbouring threads use different ones)."""
    if parent >= 0:
        return parent
    return t.top_record + seed * t.top_replicas + tid % t.top_replicas


@wp.func
def _record_dropped(t: Targets, parent: int):
    """True for a term whose blend record did not fit the blend list (the traversal
    overflowed; the host grows the lists and evaluates again, discarding this pass)."""
    return parent >= t.top_record


@wp.func
def add_record_value(t: Targets, record: int, value: wp.float64):
    wp.atomic_add(t.record_value, record, value)


@wp.func
def add_record_gradient(t: Targets, record: int, pair: wp.vec2i, side: int, g: vec6d):
    """Adds a side's gradient; a static side's is never read, so it is not added."""
    if t.body_dynamic[pair[side]] != 0:
        for i in range(6):
            wp.atomic_add(t.record_grad, record, 6 * side + i, g[i])


@wp.func
def add_term_hessian_block(t: Targets, parent: int, seed: int, tid: int, side_r: int, side_c: int, h: mat66d):
    """Adds block (side_r, side_c) of the symmetric 12x12 Hessian of a term inside blend
    record ``parent`` (-1: top level), times the weight it keeps up to the top level, to the
    upper triangle (``upper_entry``, the two sides in place of bodies) of one of its body
    pair's top-level Hessian records (chosen by thread, as ``target_record``). Callers pass
    the dynamic sides' diagonal blocks and block (0, 1); block (1, 0) is its transpose and
    is never added."""
    weight = wp.float64(1.0)
    if parent >= 0:
        weight = t.record_weight[parent]
    record = seed * t.top_replicas + tid % t.top_replicas
    for i in range(6):
        for j in range(6):
            row, col = upper_entry(side_r, side_c, i, j)
            if row >= 0:
                wp.atomic_add(t.record_hess, record, row, col, weight * h[i, j])


@wp.func
def _centre_distance_derivatives(ci: wp.vec3d, cj: wp.vec3d, pos_a: wp.vec3d, pos_b: wp.vec3d):
    """Distance r = |ci - cj| of two body points, its rigid gradient (per side) and Hessian blocks."""
    delta = ci - cj
    dist = wp.length(delta)
    u = delta / dist
    ri = ci - pos_a
    rj = cj - pos_b
    h = (wp.identity(n=3, dtype=wp.float64) - wp.outer(u, u)) / dist
    grad_a, grad_b, hess_aa, hess_ab, hess_bb = rigid_separation_derivatives(u, h, ri, rj)
    return dist, grad_a, grad_b, hess_aa, hess_ab, hess_bb


@wp.func
def _pick12(va: vec6d, vb: vec6d, i: int):
    if i < 6:
        return va[i]
    return vb[i - 6]


@wp.func
def _pick1212(haa: mat66d, hab: mat66d, hbb: mat66d, i: int, j: int):
    """Entry (i, j), i <= j, of the 12x12 matrix with blocks haa, hab (upper) and hbb."""
    if j < 6:
        return haa[i, j]
    if i < 6:
        return hab[i, j - 6]
    return hbb[i - 6, j - 6]


@wp.func
def _world_centres(
    node_center: wp.array(dtype=wp.vec3d),
    ni: int,
    nj: int,
    pair: wp.vec2i,
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
):
    ci = body_rotation[pair[0]] * node_center[ni] + body_position[pair[0]]
    cj = body_rotation[pair[1]] * node_center[nj] + body_position[pair[1]]
    return ci, cj


@wp.func
def _weighted_centred_potential(node_weight: wp.array(dtype=wp.float64), ni: int, nj: int, dist: wp.float64):
    """w_I w_J P_c(r) and its first two r-derivatives (module docstring, "Centred weights")."""
    w = node_weight[ni] * node_weight[nj]
    value, first, second = centered_potential(dist)
    return w * value, w * first, w * second


@wp.kernel
def far_term_kernel(
    # Model:
    node_center: wp.array(dtype=wp.vec3d),
    node_radius: wp.array(dtype=wp.float64),
    node_weight: wp.array(dtype=wp.float64),
    potential: bool,
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    far_items: wp.array(dtype=wp.vec4i),
    counters: wp.array(dtype=wp.int32),
    seed_chunk: wp.array(dtype=wp.int32),
    chunk: int,
    # Data out:
    targets: Targets,
    seed_separation_out: wp.array(dtype=wp.float64),
):
    if wp.tid() >= listed(counters, COUNTER_FAR, far_items.shape[0]):
        return
    item = far_items[wp.tid()]
    if _record_dropped(targets, item[2]) or seed_chunk[item[3]] != chunk:
        return
    pair = seed_body_pair[item[3]]
    ci, cj = _world_centres(node_center, item[0], item[1], pair, body_rotation, body_position)
    # The clusters lie inside their spheres, which are this far apart at least.
    wp.atomic_min(seed_separation_out, item[3], wp.length(ci - cj) - node_radius[item[0]] - node_radius[item[1]])
    if not potential:
        return
    dist, ga, gb, haa, hab, hbb = _centre_distance_derivatives(ci, cj, body_position[pair[0]], body_position[pair[1]])
    value, first, second = _weighted_centred_potential(node_weight, item[0], item[1], dist)
    record = target_record(targets, item[2], item[3], wp.tid())
    add_record_value(targets, record, value)
    add_record_gradient(targets, record, pair, 0, first * ga)
    add_record_gradient(targets, record, pair, 1, first * gb)
    dynamic_a = targets.body_dynamic[pair[0]] != 0
    dynamic_b = targets.body_dynamic[pair[1]] != 0
    if dynamic_a:
        add_term_hessian_block(targets, item[2], item[3], wp.tid(), 0, 0, second * wp.outer(ga, ga) + first * haa)
    if dynamic_a and dynamic_b:
        cross = second * wp.outer(ga, gb) + first * hab
        add_term_hessian_block(targets, item[2], item[3], wp.tid(), 0, 1, cross)
    if dynamic_b:
        add_term_hessian_block(targets, item[2], item[3], wp.tid(), 1, 1, second * wp.outer(gb, gb) + first * hbb)


mat64d = wp.types.matrix(shape=(6, 4), dtype=wp.float64)


@wp.func
def _leaf_rigid_side(sol: LeafSolution, side: int, triangle: wp.mat33d, position: wp.vec3d):
    """One triangle's leaf derivatives in its body's rigid coordinates.

    With J_k the rigid Jacobian of vertex k (offset r_k = x_k - p), the leaf Hessian
    delta_kl b''_k n n^T - B_k L_pp^-1 B_l^T projects to the body blocks

        H_ss' = delta_ss' D_s - C_s L_pp^-1 C_s'^T,  C_s = sum_k J_k^T B_k (6x4),
        D_s = sum_k b''_k (J_k^T n)(J_k^T n)^T + the exponential map's curvature,

    so each vertex's mixed block is formed once, instead of once per vertex pair.
    Returns the gradient (6), C_s and D_s.
    """
    g = vec6d()
    coupling = mat64d()
    own = mat66d()
    curvature = wp.mat33d()
    for m in range(3):
        k = 3 * side + m
        r = triangle[m] - position
        gk = leaf_vertex_gradient(sol, k)
        g += rigid_point_gradient(gk, r)
        curvature += rigid_point_curvature(gk, r)
        _b1, b2 = leaf_vertex_barrier(sol, k)
        u = rigid_point_gradient(sol.n, r)
        own += b2 * wp.outer(u, u)
        bk = leaf_mixed_block(sol, k)
        for j in range(4):
            column = rigid_point_gradient(wp.vec3d(bk[0, j], bk[1, j], bk[2, j]), r)
            for i in range(6):
                coupling[i, j] = coupling[i, j] + column[i]
    for i in range(3):
        for j in range(3):
            own[3 + i, 3 + j] = own[3 + i, 3 + j] + curvature[i, j]
    return g, coupling, own


@wp.kernel
def leaf_term_kernel(
    # Model:
    triangle_vertices: wp.array(dtype=wp.mat33d),
    dhat: wp.float64,
    max_iterations: int,
    float32_search: bool,
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    leaf_items: wp.array(dtype=wp.vec4i),
    counters: wp.array(dtype=wp.int32),
    seed_chunk: wp.array(dtype=wp.int32),
    chunk: int,
    # Data out:
    targets: Targets,
    seed_status_out: wp.array(dtype=wp.int32),
    seed_separation_out: wp.array(dtype=wp.float64),
    leaf_iterations_out: wp.array(dtype=wp.int32),
    leaf_plane_out: wp.array(dtype=wp.vec4d),
):
    tid = wp.tid()
    if tid >= listed(counters, COUNTER_LEAF, leaf_items.shape[0]):
        return
    item = leaf_items[tid]
    if _record_dropped(targets, item[2]) or seed_chunk[item[3]] != chunk:
        return
    seed = item[3]
    pair = seed_body_pair[seed]
    rot_a = body_rotation[pair[0]]
    rot_b = body_rotation[pair[1]]
    pos_a = body_position[pair[0]]
    pos_b = body_position[pair[1]]
    ta = world_triangle(triangle_vertices[item[0]], rot_a, pos_a)
    tb = world_triangle(triangle_vertices[item[1]], rot_b, pos_b)
    sol = pair_solve(ta, tb, dhat, max_iterations, float32_search)
    leaf_iterations_out[tid] = sol.iterations
    leaf_plane_out[tid] = wp.vec4d(sol.n[0], sol.n[1], sol.n[2], sol.d - wp.dot(sol.n, sol.origin))
    record = target_record(targets, item[2], seed, tid)
    if sol.status != LEAF_OK:
        wp.atomic_max(seed_status_out, seed, _pair_status_rank(sol.status))
        wp.atomic_min(seed_separation_out, seed, wp.float64(0.0))
        add_record_value(targets, record, wp.float64(wp.inf))
        return
    add_record_value(targets, record, sol.value)
    # The optimal plane separates the triangles; each lies at least min gap / |n| from it.
    gap_a = wp.min(wp.min(sol.gap_a[0], sol.gap_a[1]), sol.gap_a[2])
    gap_b = wp.min(wp.min(sol.gap_b[0], sol.gap_b[1]), sol.gap_b[2])
    wp.atomic_min(seed_separation_out, seed, (gap_a + gap_b) / wp.length(sol.n))
    if sol.value == wp.float64(0.0):
        return  # SDRS beyond its support: zero derivatives too
    dynamic_a = targets.body_dynamic[pair[0]] != 0
    dynamic_b = targets.body_dynamic[pair[1]] != 0
    coupling_a = mat64d()
    coupling_b = mat64d()
    if dynamic_a:
        g, coupling_a, own = _leaf_rigid_side(sol, 0, ta, pos_a)
        add_record_gradient(targets, record, pair, 0, g)
        add_term_hessian_block(targets, item[2], seed, tid, 0, 0, own - coupling_a * sol.lpp_inv * wp.transpose(coupling_a))
    if dynamic_b:
        g, coupling_b, own = _leaf_rigid_side(sol, 1, tb, pos_b)
        add_record_gradient(targets, record, pair, 1, g)
        add_term_hessian_block(targets, item[2], seed, tid, 1, 1, own - coupling_b * sol.lpp_inv * wp.transpose(coupling_b))
    if dynamic_a and dynamic_b:
        add_term_hessian_block(targets, item[2], seed, tid, 0, 1, -(coupling_a * sol.lpp_inv * wp.transpose(coupling_b)))


@wp.func
def _blend_keep(
    node_center: wp.array(dtype=wp.vec3d),
    node_radius: wp.array(dtype=wp.float64),
    eps: wp.float64,
    item: wp.vec4i,
    pair: wp.vec2i,
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
):
    """1 - phi of a blend record: the share of its children's sum S that B keeps."""
    ci, cj = _world_centres(node_center, item[0], item[1], pair, body_rotation, body_position)
    phi, _, _ = shell_blend(wp.length(ci - cj), node_radius[item[0]] + node_radius[item[1]], eps)
    return wp.float64(1.0) - phi


@wp.kernel
def blend_weight_kernel(
    # Model:
    node_center: wp.array(dtype=wp.vec3d),
    node_radius: wp.array(dtype=wp.float64),
    eps: wp.float64,
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    blend_items: wp.array(dtype=wp.vec4i),
    counters: wp.array(dtype=wp.int32),
    seed_chunk: wp.array(dtype=wp.int32),
    chunk: int,
    # Data out:
    targets: Targets,
):
    """record_weight[r]: the product of 1 - phi over blend record r and the records that
    enclose it (walked up the parent links; a chain is as long as the blend nesting)."""
    record = wp.tid()
    if record >= listed(counters, COUNTER_BLEND, blend_items.shape[0]):
        return
    if seed_chunk[blend_items[record][3]] != chunk:
        return
    pair = seed_body_pair[blend_items[record][3]]
    weight = wp.float64(1.0)
    current = record
    while current >= 0 and current < targets.top_record:
        item = blend_items[current]
        weight *= _blend_keep(node_center, node_radius, eps, item, pair, body_rotation, body_position)
        current = item[2]
    targets.record_weight[record] = weight


@wp.kernel
def blend_level_kernel(
    # Model:
    node_center: wp.array(dtype=wp.vec3d),
    node_radius: wp.array(dtype=wp.float64),
    node_weight: wp.array(dtype=wp.float64),
    eps: wp.float64,
    level: int,
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    blend_items: wp.array(dtype=wp.vec4i),
    blend_level: wp.array(dtype=wp.int32),
    counters: wp.array(dtype=wp.int32),
    seed_chunk: wp.array(dtype=wp.int32),
    chunk: int,
    # Data out:
    targets: Targets,
):
    record = wp.tid()
    if record >= listed(counters, COUNTER_BLEND, blend_items.shape[0]):
        return
    if blend_level[record] != level:
        return
    item = blend_items[record]
    if seed_chunk[item[3]] != chunk:
        return
    pair = seed_body_pair[item[3]]
    ci, cj = _world_centres(node_center, item[0], item[1], pair, body_rotation, body_position)
    dist, ga, gb, haa, hab, hbb = _centre_distance_derivatives(ci, cj, body_position[pair[0]], body_position[pair[1]])
    pc, pc1, pc2 = _weighted_centred_potential(node_weight, item[0], item[1], dist)
    phi, phi1, phi2 = shell_blend(dist, node_radius[item[0]] + node_radius[item[1]], eps)
    s = targets.record_value[record]
    target = target_record(targets, item[2], item[3], record)
    one = wp.float64(1.0)
    add_record_value(targets, target, (one - phi) * s + phi * pc)
    if not wp.isfinite(s):
        return
    ga_out = vec6d()
    gb_out = vec6d()
    for i in range(12):
        gd = _pick12(ga, gb, i)
        gs = targets.record_grad[record, i]
        gi = (one - phi) * gs + phi * pc1 * gd + (pc - s) * phi1 * gd
        if i < 6:
            ga_out[i] = gi
        else:
            gb_out[i - 6] = gi
    add_record_gradient(targets, target, pair, 0, ga_out)
    add_record_gradient(targets, target, pair, 1, gb_out)
    for side_r in range(2):
        for side_c in range(side_r, 2):
            if targets.body_dynamic[pair[side_r]] == 0 or targets.body_dynamic[pair[side_c]] == 0:
                continue
            block = mat66d()
            for ii in range(6):
                i = 6 * side_r + ii
                gdi = _pick12(ga, gb, i)
                dgi = pc1 * gdi - targets.record_grad[record, i]
                for jj in range(6):
                    if side_r == side_c and jj < ii:
                        continue  # the lower triangle of a diagonal block is not added
                    j = 6 * side_c + jj
                    gdj = _pick12(ga, gb, j)
                    dgj = pc1 * gdj - targets.record_grad[record, j]
                    hd = _pick1212(haa, hab, hbb, i, j)
                    # (1 - phi) hess S reached the top level with the children's weights.
                    block[ii, jj] = phi * (pc2 * gdi * gdj + pc1 * hd) + phi1 * (gdi * dgj + dgi * gdj) + (pc - s) * (phi2 * gdi * gdj + phi1 * hd)
            add_term_hessian_block(targets, item[2], item[3], record, side_r, side_c, block)


# Entries of an accumulator record: the value, 12 gradient entries, the 12x12 Hessian.
RECORD_ENTRIES = wp.constant(1 + 12 + 144)


@wp.func
def _add_top_level_entry(
    seed: int,
    entry: int,
    pair: wp.vec2i,
    targets: Targets,
    total_value_out: wp.array(dtype=wp.float64),
    total_grad_out: wp.array2d(dtype=wp.float64),
    total_hess_out: wp.array2d(dtype=wp.float64),
):
    first = targets.top_record + seed * targets.top_replicas
    total = wp.float64(0.0)
    if entry == 0:
        for r in range(targets.top_replicas):
            total += targets.record_value[first + r]
        wp.atomic_add(total_value_out, 0, total)
        return
    if entry <= 12:
        i = entry - 1
        body = pair[i / 6]
        if targets.body_dynamic[body] == 0:
            return
        for r in range(targets.top_replicas):
            total += targets.record_grad[first + r, i]
        wp.atomic_add(total_grad_out, body, i % 6, total)
        return
    i = (entry - 13) / 12
    j = (entry - 13) % 12
    slot_r = targets.hessian_slot[pair[i / 6]]
    slot_c = targets.hessian_slot[pair[j / 6]]
    if j < i or slot_r < 0 or slot_c < 0:
        return  # records hold upper triangles only; static bodies have no block
    for r in range(targets.top_replicas):
        total += targets.record_hess[seed * targets.top_replicas + r, i, j]
    row, col = upper_entry(slot_r, slot_c, i % 6, j % 6)
    wp.atomic_add(total_hess_out, row, col, total)


@wp.kernel
def top_level_kernel(
    # Model:
    seed_body_pair: wp.array(dtype=wp.vec2i),
    entries_per_thread: int,
    # Data in:
    targets: Targets,
    # Data out:
    total_value_out: wp.array(dtype=wp.float64),
    total_grad_out: wp.array2d(dtype=wp.float64),
    total_hess_out: wp.array2d(dtype=wp.float64),
):
    """Sums entries [group * entries_per_thread, (group + 1) * entries_per_thread) of
    RECORD_ENTRIES of a body pair's top-level replicas into the scene totals (value,
    (nbodies, 6) gradient, upper triangle of the (6 ndynamic)^2 Hessian over the non-static
    bodies, ``Targets.hessian_slot``); static bodies' entries are dropped. Launched over (body pairs, entry groups): on a GPU one entry a
    thread; on a CPU, whose threads run one after another, all of a body pair's entries in
    one thread, since a thread each made the launch cost more than its sums. Each total
    receives the body pairs in the same order either way."""
    seed, group = wp.tid()
    pair = seed_body_pair[seed]
    if entries_per_thread == RECORD_ENTRIES:
        # A whole body pair in one thread: its entries in the same order, but only those that
        # reach a total. Walking all 157 to drop a static body's and the records' empty lower
        # triangle made this sum 7x the far terms it adds beside many static bodies (a probe).
        _add_top_level_entry(seed, 0, pair, targets, total_value_out, total_grad_out, total_hess_out)
        for i in range(12):
            if targets.body_dynamic[pair[i / 6]] != 0:
                _add_top_level_entry(seed, 1 + i, pair, targets, total_value_out, total_grad_out, total_hess_out)
        for i in range(12):
            if targets.hessian_slot[pair[i / 6]] >= 0:
                for j in range(i, 12):
                    if targets.hessian_slot[pair[j / 6]] >= 0:
                        _add_top_level_entry(seed, 13 + 12 * i + j, pair, targets, total_value_out, total_grad_out, total_hess_out)
        return
    first_entry = group * entries_per_thread
    for entry in range(first_entry, wp.min(first_entry + entries_per_thread, RECORD_ENTRIES)):
        _add_top_level_entry(seed, entry, pair, targets, total_value_out, total_grad_out, total_hess_out)


_ADVANCEMENT_HALVINGS = wp.constant(60)
_ADVANCEMENT_BISECTIONS = wp.constant(30)
_ADVANCEMENT_RESTARTS = wp.constant(3)
# Candidate corners of a triangle clipped to a box: 3 vertices + 3 edges x 4 sides + 4 box edges.
corners19 = wp.types.matrix(shape=(19, 3), dtype=wp.float64)


@wp.func
def _path_travel(r: wp.vec3d, direction: wp.vec3d, dp: wp.vec3d, k: wp.vec3d, alpha: wp.float64, phi: wp.float64):
    """Upper bound on how far a point at offset ``r`` from its body's origin moves along
    ``direction`` under any alpha' <= alpha of a rigid step (dp, phi k), phi = alpha |dtheta|.

    The point moves along d by alpha dp.d + sin(phi) (k x r).d + (1 - cos(phi)) ((k.r)(k.d) - r.d).
    Bounding sin(phi) by phi (or phi - phi^3/6 where its factor is negative) and 1 - cos(phi)
    by phi^2/2 gives a bound convex and non-decreasing in phi beyond its linear part, so it is
    convex in alpha and zero at alpha = 0; it is also convex in r (a sum of affine terms and
    positive parts of affine terms), so over a convex polygon its maximum is at a corner.
    """
    zero = wp.float64(0.0)
    b = wp.dot(wp.cross(k, r), direction)
    c = wp.dot(k, r) * wp.dot(k, direction) - wp.dot(r, direction)
    travel = alpha * wp.dot(dp, direction) + phi * b + wp.float64(0.5) * phi * phi * wp.max(c, zero)
    if b < zero:
        travel += phi * phi * phi * (-b) / wp.float64(6.0)
    return travel


@wp.func
def _within(value: wp.float64, low: wp.float64, high: wp.float64, slack: wp.float64):
    return value >= low - slack and value <= high + slack


@wp.func
def _lateral_box(tri: wp.mat33d, u: wp.vec3d, w: wp.vec3d, margin: wp.float64):
    """The triangle's extents along u and w, each widened by ``margin`` on both sides."""
    box = wp.vec4d(wp.dot(tri[0], u), wp.dot(tri[0], u), wp.dot(tri[0], w), wp.dot(tri[0], w))
    for v in range(1, 3):
        box[0] = wp.min(box[0], wp.dot(tri[v], u))
        box[1] = wp.max(box[1], wp.dot(tri[v], u))
        box[2] = wp.min(box[2], wp.dot(tri[v], w))
        box[3] = wp.max(box[3], wp.dot(tri[v], w))
    return box + wp.vec4d(-margin, margin, -margin, margin)


@wp.func
def _clipped_corners(tri: wp.mat33d, direction: wp.vec3d, u: wp.vec3d, w: wp.vec3d, box: wp.vec4d):
    """Corners of the part of a triangle whose (u, w) coordinates lie in ``box`` (u, w and
    ``direction`` orthonormal): the triangle's vertices inside the box, its edges' crossings of
    the box's four sides inside the box, and the box's four edges along ``direction`` where they
    cross the triangle. Returns (corners, count); count 0 when no part lies in the box.

    Rounding must not drop a corner lying on the box's or the triangle's boundary (it may be
    the highest), so membership is tested with a slack; a point kept in error lies within the
    slack of the part.
    """
    corners = corners19()
    count = int(0)
    slack = wp.float64(1.0e-9) * (wp.abs(box[0]) + wp.abs(box[1]) + wp.abs(box[2]) + wp.abs(box[3]))
    for v in range(3):
        if _within(wp.dot(tri[v], u), box[0], box[1], slack) and _within(wp.dot(tri[v], w), box[2], box[3], slack):
            corners[count] = tri[v]
            count += 1
    for e in range(3):
        p = tri[e]
        q = tri[(e + 1) % 3]
        for side in range(4):
            axis = u
            across = w
            low = box[2]
            high = box[3]
            if side >= 2:
                axis = w
                across = u
                low = box[0]
                high = box[1]
            sp = wp.dot(p, axis) - box[side]
            sq = wp.dot(q, axis) - box[side]
            if (sp < wp.float64(0.0) and sq > wp.float64(0.0)) or (sp > wp.float64(0.0) and sq < wp.float64(0.0)):
                x = p + (sp / (sp - sq)) * (q - p)  # on the side by construction: test the other axis only
                if _within(wp.dot(x, across), low, high, slack):
                    corners[count] = x
                    count += 1
    face = wp.cross(tri[1] - tri[0], tri[2] - tri[0])
    tilt = wp.dot(face, direction)
    if tilt != wp.float64(0.0):
        for corner in range(4):
            base = box[corner / 2] * u + box[2 + corner % 2] * w
            x = base + (wp.dot(face, tri[0] - base) / tilt) * direction
            inside = True
            for e in range(3):
                edge = tri[(e + 1) % 3] - tri[e]
                offset = x - tri[e]
                if wp.dot(wp.cross(edge, offset), face) < -wp.float64(1.0e-9) * wp.length(edge) * wp.length(offset) * wp.length(face):
                    inside = False
            if inside:
                corners[count] = x
                count += 1
    return corners, count


@wp.func
def _spin_axis(step: vec6d):
    """Unit axis (zero without rotation) and angle |dtheta| of a rigid step's rotation."""
    dtheta = wp.vec3d(step[3], step[4], step[5])
    spin = wp.length(dtheta)
    if spin > wp.float64(0.0):
        return dtheta / spin, spin
    return wp.vec3d(), spin


@wp.func
def _front_reach(corners: corners19, count: int, pos: wp.vec3d, direction: wp.vec3d, step: vec6d, alpha: wp.float64):
    """Upper bound on the largest height along ``direction`` that any point of the convex
    polygon ``corners[:count]`` reaches under alpha' <= alpha of its body's rigid step (height
    plus ``_path_travel`` is convex, so the maximum is at a corner)."""
    dp = wp.vec3d(step[0], step[1], step[2])
    k, spin = _spin_axis(step)
    reach = wp.float64(-1.0e308)
    for i in range(count):
        x = corners[i]
        reach = wp.max(reach, wp.dot(x, direction) + _path_travel(x - pos, direction, dp, k, alpha, alpha * spin))
    return reach


@wp.func
def _relative_front_reach(corners: corners19, count: int, pos: wp.vec3d, step: vec6d, frame_pos: wp.vec3d, frame_step: vec6d, direction: wp.vec3d, alpha: wp.float64):
    """Upper bound on the largest height along ``direction`` that any point of a body's convex
    polygon ``corners[:count]`` reaches in the frame of another body (held at its start pose)
    under alpha' <= alpha of both bodies' rigid steps.

    With E = exp(alpha [dtheta]), subscript F for the frame body, dp the translation step less
    the frame body's, s = x - p_F and r = x - p, the point x moves in that frame by
    (E_F^T - I) s + (E - I) r + alpha dp + alpha (E_F^T - I) dp + (E_F^T - I)(E - I) r. The
    first two are bounded by ``_path_travel`` (the frame's rotation reversed, the body's
    rotation), the last two by alpha phi_F |dp| and phi_F phi |r|, phi = alpha |dtheta| (a
    rotation's chord is at most its arc). Each bound is convex in alpha and
    in x and zero at alpha = 0, so the maximum is at a corner. Bodies turning together then
    close only what their centres' paths differ by, where the world-frame bound adds up
    each body's own swing across the whole face.
    """
    dp = wp.vec3d(step[0] - frame_step[0], step[1] - frame_step[1], step[2] - frame_step[2])
    k, spin = _spin_axis(step)
    frame_k, frame_spin = _spin_axis(frame_step)
    frame_k = -frame_k  # the frame's rotation reversed
    still = wp.vec3d()
    phi = alpha * spin
    frame_phi = alpha * frame_spin
    shared = alpha * wp.dot(dp, direction) + alpha * frame_phi * wp.length(dp)
    reach = wp.float64(-1.0e308)
    for i in range(count):
        x = corners[i]
        r = x - pos
        travel = _path_travel(x - frame_pos, direction, still, frame_k, alpha, frame_phi) + _path_travel(r, direction, still, k, alpha, phi) + frame_phi * phi * wp.length(r)
        reach = wp.max(reach, wp.dot(x, direction) + travel)
    return reach + shared


@wp.func
def _closing_reach(
    in_frame_of_a: bool,
    corners_a: corners19,
    count_a: int,
    pos_a: wp.vec3d,
    step_a: vec6d,
    corners_b: corners19,
    count_b: int,
    pos_b: wp.vec3d,
    step_b: vec6d,
    normal: wp.vec3d,
    lead_a: wp.float64,
    alpha: wp.float64,
):
    """Bound on what the parts' fronts reach towards each other at alpha, A on the positive
    side of ``normal`` (they stay apart while it stays below their gap): along a world axis,
    the sum of both parts' ``_front_reach``, or along an axis fixed in A, where A's front
    stays at its height ``lead_a`` now."""
    if in_frame_of_a:
        return lead_a + _relative_front_reach(corners_b, count_b, pos_b, step_b, pos_a, step_a, normal, alpha)
    return _front_reach(corners_a, count_a, pos_a, -normal, step_a, alpha) + _front_reach(corners_b, count_b, pos_b, normal, step_b, alpha)


@wp.func
def _path_reach(tri: wp.mat33d, pos: wp.vec3d, step: vec6d):
    """Upper bound on how far any point of the triangle moves along the whole rigid step
    (alpha <= 1) of a body centred at ``pos``: |dp| + |dtheta| max |r| (a rotation's chord is
    at most its arc)."""
    lever = wp.max(wp.max(wp.length(tri[0] - pos), wp.length(tri[1] - pos)), wp.length(tri[2] - pos))
    return wp.length(wp.vec3d(step[0], step[1], step[2])) + wp.length(wp.vec3d(step[3], step[4], step[5])) * lever


@wp.func
def _clipped_advancement(
    in_frame_of_a: bool,
    ta: wp.mat33d,
    tb: wp.mat33d,
    pos_a: wp.vec3d,
    pos_b: wp.vec3d,
    step_a: vec6d,
    step_b: vec6d,
    normal: wp.vec3d,
    u: wp.vec3d,
    w: wp.vec3d,
    margin: wp.float64,
    fraction: wp.float64,
    floor: wp.float64,
):
    """``_axis_advancement`` along ``normal`` (A on its positive side; u, w across it) in the
    world or in A's frame, with each triangle cut to the other's extents widened by ``margin``,
    the most a point can move against the other triangle in that frame: the largest alpha in
    [0, 1] (to within 1e-9 of it) whose ``_closing_reach`` stays within ``fraction`` of the gap
    and leaves at least ``floor`` of it."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    corners_a, count_a = _clipped_corners(ta, normal, u, w, _lateral_box(tb, u, w, margin))
    corners_b, count_b = _clipped_corners(tb, normal, u, w, _lateral_box(ta, u, w, margin))
    if count_a == 0 or count_b == 0:
        return one  # no point of one triangle can reach the other
    # Each front's height now (its reach at alpha = 0); the gap is what separates them.
    lead_a = _front_reach(corners_a, count_a, pos_a, -normal, step_a, zero)
    lead_b = _front_reach(corners_b, count_b, pos_b, normal, step_b, zero)
    if not (-lead_a - lead_b > floor):
        return zero
    room = wp.min(fraction * (-lead_a - lead_b) + lead_a + lead_b, -floor)
    # The reach is convex in alpha, so the admissible alphas are an interval.
    if _closing_reach(in_frame_of_a, corners_a, count_a, pos_a, step_a, corners_b, count_b, pos_b, step_b, normal, lead_a, one) <= room:
        return one
    # Halve until the closure fits, then refine by bisection to within 1e-9 of alpha. A coarser
    # alpha (1%) was cheaper, but it made the Newton path, and with it the converged state
    # within its tolerance, jump with the simulation's parameters, which finite-difference
    # checks of task gradients then saw (1.3e-5 relative on the ant's).
    lo = zero
    hi = one
    halvings = int(0)
    while lo == zero and halvings < _ADVANCEMENT_HALVINGS:
        mid = wp.float64(0.5) * hi
        if _closing_reach(in_frame_of_a, corners_a, count_a, pos_a, step_a, corners_b, count_b, pos_b, step_b, normal, lead_a, mid) <= room:
            lo = mid
        else:
            hi = mid
        halvings += 1
    if lo == zero:
        return zero
    for _it in range(_ADVANCEMENT_BISECTIONS):
        mid = wp.float64(0.5) * (lo + hi)
        if _closing_reach(in_frame_of_a, corners_a, count_a, pos_a, step_a, corners_b, count_b, pos_b, step_b, normal, lead_a, mid) <= room:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def _axis_advancement(
    ta: wp.mat33d,
    tb: wp.mat33d,
    pos_a: wp.vec3d,
    pos_b: wp.vec3d,
    step_a: vec6d,
    step_b: vec6d,
    axis: wp.vec3d,
    fraction: wp.float64,
    floor: wp.float64,
):
    """Largest alpha in [0, 1] (to within 1e-9 of it) for which the parts of the triangles that can
    meet along the step keep a gap along ``axis``, closing at most ``fraction`` of it and
    leaving at least ``floor``; 0 if those parts' extents along it are not ``floor`` apart now.

    While that gap stays positive no point of one triangle meets a point of the other. Two
    points can only meet if they start within their relative travel of each other across
    ``axis``, so each triangle is cut to the other's extents across it, widened by that travel
    (at alpha = 1, so the parts do not depend on alpha): a long face resting on a small one is
    held back by the motion of its part above the small face, not by its far end's swing. The
    gap is bounded by what both parts close, each corner credited with how far behind its
    part's leading corner it starts, so it is the relative motion that counts: bodies moving
    together are not held back, a static side takes none of the room, and a face may tilt
    about a vertex or edge resting close to the other triangle. Where the world axis holds
    the step back, the axis is also tried fixed in either body (``_relative_front_reach``): a
    pair in face contact turning together (a pusher and what it pushes, a struck cube spun
    off the striker's face) then closes only what the turn moves the faces apart, not each
    face's swing about its own centre.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    if wp.length(axis) == zero:
        return zero
    normal = wp.normalize(axis)
    if wp.dot(normal, ta[0] + ta[1] + ta[2] - tb[0] - tb[1] - tb[2]) < zero:
        normal = -normal
    # Lateral axes along the pair's longest edge across the normal, so that a long sliver's
    # cut is tight along its length.
    longest = wp.vec3d()
    for e in range(6):
        edge = tb[(e + 1) % 3] - tb[e % 3]
        if e < 3:
            edge = ta[(e + 1) % 3] - ta[e]
        edge = edge - wp.dot(edge, normal) * normal
        if wp.length_sq(edge) > wp.length_sq(longest):
            longest = edge
    if wp.length(longest) == zero:
        return zero
    u = wp.normalize(longest)
    w = wp.cross(normal, u)
    reach_a = _path_reach(ta, pos_a, step_a)
    reach_b = _path_reach(tb, pos_b, step_b)
    alpha = _clipped_advancement(False, ta, tb, pos_a, pos_b, step_a, step_b, normal, u, w, reach_a + reach_b, fraction, floor)
    # The same axis fixed in either body: in the frame of the one that turns more, the other's
    # points move least. There a triangle's points also carry the frame body's motion reversed.
    if alpha < one:
        alpha = wp.max(alpha, _clipped_advancement(True, ta, tb, pos_a, pos_b, step_a, step_b, normal, u, w, reach_b + _path_reach(tb, pos_a, step_a), fraction, floor))
    if alpha < one:
        alpha = wp.max(alpha, _clipped_advancement(True, tb, ta, pos_b, pos_a, step_b, step_a, -normal, u, w, reach_a + _path_reach(ta, pos_b, step_b), fraction, floor))
    return alpha


@wp.func
def _best_axis_advancement(
    ta: wp.mat33d,
    tb: wp.mat33d,
    pos_a: wp.vec3d,
    pos_b: wp.vec3d,
    step_a: vec6d,
    step_b: vec6d,
    first_axis: wp.vec3d,
    fraction: wp.float64,
    floor: wp.float64,
):
    """``_axis_advancement`` along the best of ``first_axis`` and the two face normals."""
    one = wp.float64(1.0)
    alpha = _axis_advancement(ta, tb, pos_a, pos_b, step_a, step_b, first_axis, fraction, floor)
    if alpha < one:
        alpha = wp.max(alpha, _axis_advancement(ta, tb, pos_a, pos_b, step_a, step_b, wp.cross(ta[1] - ta[0], ta[2] - ta[0]), fraction, floor))
    if alpha < one:
        alpha = wp.max(alpha, _axis_advancement(ta, tb, pos_a, pos_b, step_a, step_b, wp.cross(tb[1] - tb[0], tb[2] - tb[0]), fraction, floor))
    return alpha


@wp.func
def _moved_triangle(tri: wp.mat33d, pos: wp.vec3d, step: vec6d, alpha: wp.float64):
    """The triangle of a body centred at ``pos`` after alpha of its rigid step."""
    k, spin = _spin_axis(step)
    turn = wp.identity(3, dtype=wp.float64)
    if spin > wp.float64(0.0):
        turn = wp.quat_to_matrix(wp.quat_from_axis_angle(k, alpha * spin))
    shift = alpha * wp.vec3d(step[0], step[1], step[2])
    moved = wp.mat33d()
    for v in range(3):
        moved[v] = pos + shift + turn * (tri[v] - pos)
    return moved


@wp.func
def _leaf_advancement(
    ta: wp.mat33d,
    tb: wp.mat33d,
    pos_a: wp.vec3d,
    pos_b: wp.vec3d,
    step_a: vec6d,
    step_b: vec6d,
    plane_normal: wp.vec3d,
    fraction: wp.float64,
):
    """Largest alpha (to within 1e-9 of it) that keeps two triangles apart along the step.

    Any axis along which the pair stays apart certifies the path. The potential's plane sits
    between the triangles' orientations, so a face resting on another face (a body on the
    ground) nearly meets it at its raised end; the face normals let it tilt much further.
    Where they hold the step back, the bound restarts from where it stopped, as conservative
    advancement does: the rest of the path from alpha has the same form (each body's
    remaining (1 - alpha) step from its pose there), and the triangles' gap along a fresh axis
    there (the widest separating one, or a face normal) is measured, not bounded. A bound
    loose for a contact that opens along the step (an edge turning and sliding over another)
    then admits what the true motion does, while the parts of the triangles that can meet
    keep a gap of at least 1 - ``fraction`` of the pair's distance now along each restart's
    axis (the rest cannot meet at all): a pair that really closes stops about where it did.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    alpha = _best_axis_advancement(ta, tb, pos_a, pos_b, step_a, step_b, plane_normal, fraction, zero)
    if alpha == zero or alpha == one:
        return alpha
    closest_a, closest_b = triangle_closest_points(ta, tb)
    floor = (one - fraction) * wp.length(closest_a - closest_b)
    for _restart in range(_ADVANCEMENT_RESTARTS):
        moved_a = _moved_triangle(ta, pos_a, step_a, alpha)
        moved_b = _moved_triangle(tb, pos_b, step_b, alpha)
        axis, middle, separated = triangle_separating_axis(moved_a, moved_b)
        if not separated:
            return alpha
        more = _best_axis_advancement(
            moved_a,
            moved_b,
            pos_a + alpha * wp.vec3d(step_a[0], step_a[1], step_a[2]),
            pos_b + alpha * wp.vec3d(step_b[0], step_b[1], step_b[2]),
            (one - alpha) * step_a,
            (one - alpha) * step_b,
            axis,
            fraction,
            floor,
        )
        if more == zero:
            return alpha
        alpha = alpha + more * (one - alpha)
        if more == one:
            return one
    return alpha


@wp.func
def _pair_keeps_clear(step_a: vec6d, step_b: vec6d, reach_a: wp.float64, reach_b: wp.float64, separation: wp.float64, fraction: wp.float64):
    """True when two bodies' whole travel along the step is at most half of ``fraction`` of
    the separation of their closest term (sphere gap or gap along a leaf plane).

    No point of a body moves farther than |dp| + |dtheta| reach (a chord is shorter than its
    arc), so no term of the pair closes more than that sum, and each term's own bound
    (far: sphere separation over approach; leaf: the same along its plane normal, the first
    axis tried) is then at least 1. The factor 2 keeps the skip clear of those bounds'
    rounding, so skipped terms are exactly those that would not lower alpha.
    """
    travel_a = wp.length(wp.vec3d(step_a[0], step_a[1], step_a[2])) + wp.length(wp.vec3d(step_a[3], step_a[4], step_a[5])) * reach_a
    travel_b = wp.length(wp.vec3d(step_b[0], step_b[1], step_b[2])) + wp.length(wp.vec3d(step_b[3], step_b[4], step_b[5])) * reach_b
    return wp.float64(2.0) * (travel_a + travel_b) <= fraction * separation


@wp.kernel
def advancement_kernel(
    # Model:
    node_center: wp.array(dtype=wp.vec3d),
    node_radius: wp.array(dtype=wp.float64),
    triangle_vertices: wp.array(dtype=wp.mat33d),
    body_reach: wp.array(dtype=wp.float64),
    fraction: wp.float64,
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    seed_separation: wp.array(dtype=wp.float64),
    far_items: wp.array(dtype=wp.vec4i),
    num_far: int,
    leaf_items: wp.array(dtype=wp.vec4i),
    leaf_plane: wp.array(dtype=wp.vec4d),
    body_step: wp.array(dtype=vec6d),
    # Data out:
    alpha_out: wp.array(dtype=wp.float64),
):
    """Largest alpha in (0, 1] keeping every term's geometry apart along alpha * step (atomic min).

    Far terms: the clusters stay inside their spheres, so their points approach by at most
    alpha (|dp_a - dp_b| + |dtheta_a| rho_a + |dtheta_b| rho_b), rho = |c - p| + R.
    Leaf terms: the two triangles (or the parts of them that can meet along the step) may close
    at most ``fraction`` of their gap along a fixed axis, so a plane normal to it keeps
    separating them along the whole path; the axis is the best of the potential's plane normal
    and the two triangles' face normals, and where that holds the step back the bound restarts
    from where it stopped (``_leaf_advancement``).
    Body pairs whose travel is far inside their closest term's separation (``_pair_keeps_clear``)
    are skipped: none of their terms can cut the step.
    """
    tid = wp.tid()
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    if tid < num_far:
        item = far_items[tid]
        pair = seed_body_pair[item[3]]
        if _pair_keeps_clear(body_step[pair[0]], body_step[pair[1]], body_reach[pair[0]], body_reach[pair[1]], seed_separation[item[3]], fraction):
            return
        pos_a = body_position[pair[0]]
        pos_b = body_position[pair[1]]
        ci = body_rotation[pair[0]] * node_center[item[0]] + pos_a
        cj = body_rotation[pair[1]] * node_center[item[1]] + pos_b
        separation = wp.length(ci - cj) - node_radius[item[0]] - node_radius[item[1]]
        sa = body_step[pair[0]]
        sb = body_step[pair[1]]
        relative = wp.vec3d(sa[0] - sb[0], sa[1] - sb[1], sa[2] - sb[2])
        spin_a = wp.length(wp.vec3d(sa[3], sa[4], sa[5])) * (wp.length(ci - pos_a) + node_radius[item[0]])
        spin_b = wp.length(wp.vec3d(sb[3], sb[4], sb[5])) * (wp.length(cj - pos_b) + node_radius[item[1]])
        approach = wp.length(relative) + spin_a + spin_b
        if approach > zero:
            wp.atomic_min(alpha_out, 0, wp.min(one, fraction * separation / approach))
        return
    item = leaf_items[tid - num_far]
    pair = seed_body_pair[item[3]]
    if _pair_keeps_clear(body_step[pair[0]], body_step[pair[1]], body_reach[pair[0]], body_reach[pair[1]], seed_separation[item[3]], fraction):
        return
    plane = leaf_plane[tid - num_far]
    ta = world_triangle(triangle_vertices[item[0]], body_rotation[pair[0]], body_position[pair[0]])
    tb = world_triangle(triangle_vertices[item[1]], body_rotation[pair[1]], body_position[pair[1]])
    pos_a = body_position[pair[0]]
    pos_b = body_position[pair[1]]
    step_a = body_step[pair[0]]
    step_b = body_step[pair[1]]
    alpha = _leaf_advancement(ta, tb, pos_a, pos_b, step_a, step_b, wp.vec3d(plane[0], plane[1], plane[2]), fraction)
    if alpha < one:
        wp.atomic_min(alpha_out, 0, alpha)

