"""Sphere-tree traversal: node pairs of two bodies into far / blend / leaf term lists.

For a node pair (I, J) at centre distance r, with d1 = R_I + R_J and d2 = (1 + eps) d1
(paper eq. BSH-potential):

    r >= d2        far:     the centred term P_c(r) alone
    d1 < r < d2    blend:   (1 - phi) * (children's sum) + phi * P_c(r)
    r <= d1        descend: the children's sum

where the children's sum of two leaves is their exact leaf potential. Every emitted item
records its enclosing blend record (`parent`, -1 at top level), so the reduction can apply
each blend to the exact sum below it. Blend records also store their nesting `level`
(0 = outermost) so the reduction runs from the deepest level up.

Locally supported models (SDRS, `support` > 0: no leaf pair farther apart than `support`
has any potential) use the same walk as a broad phase: a node pair whose spheres are at
least `support` apart goes to the far list as a pruned pair (no potential; the reduction
only takes its separation bound, and conservative advancement its motion bound), closer
pairs descend, and leaf pairs are leaf terms without blend records.

One thread walks one body pair with an explicit stack in global scratch memory. Lists are
filled through atomic counters that keep counting past capacity, so one launch reports the
exact sizes needed; the host grows the buffers and relaunches on overflow.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = [
    "COUNTER_FAR",
    "COUNTER_BLEND",
    "COUNTER_LEAF",
    "COUNTER_MAX_LEVEL",
    "COUNTER_STACK_OVERFLOW",
    "NUM_COUNTERS",
    "traverse_kernel",
]

COUNTER_FAR = wp.constant(0)
COUNTER_BLEND = wp.constant(1)
COUNTER_LEAF = wp.constant(2)
COUNTER_MAX_LEVEL = wp.constant(3)
COUNTER_STACK_OVERFLOW = wp.constant(4)
NUM_COUNTERS = 5


@wp.func
def _emit(counters: wp.array(dtype=wp.int32), slot: int, items: wp.array(dtype=wp.vec4i), item: wp.vec4i):
    index = wp.atomic_add(counters, slot, 1)
    if index < items.shape[0]:
        items[index] = item
    return index


@wp.kernel
def traverse_kernel(
    # Model:
    node_center: wp.array(dtype=wp.vec3d),
    node_radius: wp.array(dtype=wp.float64),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_triangle: wp.array(dtype=wp.int32),
    body_root: wp.array(dtype=wp.int32),
    eps: wp.float64,
    support: wp.float64,
    # Data in:
    body_rotation: wp.array(dtype=wp.mat33d),
    body_position: wp.array(dtype=wp.vec3d),
    seed_body_pair: wp.array(dtype=wp.vec2i),
    # Scratch:
    stack: wp.array2d(dtype=wp.vec4i),
    # Data out:
    counters_out: wp.array(dtype=wp.int32),
    far_out: wp.array(dtype=wp.vec4i),
    blend_out: wp.array(dtype=wp.vec4i),
    blend_level_out: wp.array(dtype=wp.int32),
    leaf_out: wp.array(dtype=wp.vec4i),
):
    seed = wp.tid()
    pair = seed_body_pair[seed]
    rot_a = body_rotation[pair[0]]
    pos_a = body_position[pair[0]]
    rot_b = body_rotation[pair[1]]
    pos_b = body_position[pair[1]]
    capacity = stack.shape[1]
    # (node on A, node on B, enclosing blend record, nesting level)
    stack[seed, 0] = wp.vec4i(body_root[pair[0]], body_root[pair[1]], -1, 0)
    top = int(1)
    while top > 0:
        top -= 1
        entry = stack[seed, top]
        ni = entry[0]
        nj = entry[1]
        parent = entry[2]
        level = entry[3]
        ci = rot_a * node_center[ni] + pos_a
        cj = rot_b * node_center[nj] + pos_b
        dist = wp.length(ci - cj)
        d1 = node_radius[ni] + node_radius[nj]
        d2 = (wp.float64(1.0) + eps) * d1
        local = support > wp.float64(0.0)
        far = dist >= d2
        if local:
            far = dist - d1 >= support
        if far:
            _emit(counters_out, COUNTER_FAR, far_out, wp.vec4i(ni, nj, parent, seed))
            continue
        if dist > d1 and not local:
            record = _emit(counters_out, COUNTER_BLEND, blend_out, wp.vec4i(ni, nj, parent, seed))
            if record < blend_level_out.shape[0]:
                blend_level_out[record] = level
            wp.atomic_max(counters_out, COUNTER_MAX_LEVEL, level)
            parent = record
            level = level + 1
        leaf_i = node_left[ni] < 0
        leaf_j = node_left[nj] < 0
        if leaf_i and leaf_j:
            _emit(counters_out, COUNTER_LEAF, leaf_out, wp.vec4i(node_triangle[ni], node_triangle[nj], parent, seed))
            continue
        if top + 4 > capacity:
            wp.atomic_add(counters_out, COUNTER_STACK_OVERFLOW, 1)
            continue
        # Children sets: C(I) = {I_l, I_r} for internal nodes, {I} for leaves.
        li = ni
        ri = ni
        if not leaf_i:
            li = node_left[ni]
            ri = node_right[ni]
        lj = nj
        rj = nj
        if not leaf_j:
            lj = node_left[nj]
            rj = node_right[nj]
        stack[seed, top] = wp.vec4i(li, lj, parent, level)
        top += 1
        if not leaf_j:
            stack[seed, top] = wp.vec4i(li, rj, parent, level)
            top += 1
        if not leaf_i:
            stack[seed, top] = wp.vec4i(ri, lj, parent, level)
            top += 1
            if not leaf_j:
                stack[seed, top] = wp.vec4i(ri, rj, parent, level)
                top += 1
