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

Load balancing. A body pair's walk can visit 10^5 node pairs while most body pairs stop at
their roots, so one thread per body pair leaves a GPU nearly idle behind a few long
serial walks. The walk therefore runs in rounds over a task list: a task is one pending
node pair (node on A, node on B, enclosing blend record, nesting level) plus its body pair.
Round 0 has one task per body pair (the root pair). In each round one thread takes one
task and walks depth first from it with a stack in local memory, visiting at most
`visit_budget` node pairs; whatever is still on its stack then is appended to the next
round's task list. Every stack entry carries everything its subtree needs (blend records
are global indices into the blend list), so where a subtree is walked does not change what
it emits: the lists hold the same items as one serial walk, in another order. Busy body
pairs split into more tasks each round, so the thread count grows until the GPU is full.
Measured on an H100 (docs/architecture.md): billiards_6208, 136 body pairs, 671k items,
48.7 ms in one per-body-pair launch before, 0.82 ms in 9 rounds now.

Rounds end: a node pair's children lie one level deeper in both trees, or in the one
that is not at a leaf, so the walk reaches node pair (I, J) after max(depth I, depth J)
steps. A spilled task is at least one step below the task that spilled it, so round r
only holds pairs at least r steps deep and there are at most max_depth + 1 rounds. The
stack never overflows: each visit pops one entry and pushes at most four, so a task's
stack holds at most 3 visit_budget + 1 entries.

Lists and the next round's tasks are filled through atomic counters that keep counting
past capacity, so the host learns the exact sizes needed; it grows the buffers and
reruns the traversal on overflow.

Launch sizes. Every kernel that reads a list (the next round, the term kernels) takes its
length from the counters on the device (`listed`), so it may be launched over the list's
whole capacity: then no launch waits for the host to read a count, and an evaluation
synchronises with the host once, at its end (`ContactModel(sync_free=True)`, the default
on a GPU). Launched over exactly the counted items instead (the default on a CPU, where
reading a counter costs nothing and idle threads run serially), the kernels do the same.
"""

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = [
    "COUNTER_FAR",
    "COUNTER_BLEND",
    "COUNTER_LEAF",
    "COUNTER_MAX_LEVEL",
    "COUNTER_ROUND_TASKS",
    "HOST_SIZED_VISIT_BUDGET",
    "SYNC_FREE_VISIT_BUDGET",
    "listed",
    "traverse_round_kernel",
]

COUNTER_FAR = wp.constant(0)
COUNTER_BLEND = wp.constant(1)
COUNTER_LEAF = wp.constant(2)
COUNTER_MAX_LEVEL = wp.constant(3)
# Slot COUNTER_ROUND_TASKS + r counts the tasks round r hands on to round r + 1.
COUNTER_ROUND_TASKS = wp.constant(4)
# Nodes closer than this (float64 contact geometry resolves no less: ``_validate.MIN_EXTENT``)
# are neither far nor blended but solved as leaves: two point faces 1e-104 m apart (d1 = 0)
# had a far term whose Hessian overflowed, in an evaluation reported ok (a probe, stop 62).
MIN_NODE_DISTANCE = wp.constant(wp.float64(1.0e-75))

# Node pairs one thread visits per round, at most (host-sized launches). Larger means fewer
# rounds (one host read each) but fewer, longer threads with a larger zero-initialised
# local stack.
HOST_SIZED_VISIT_BUDGET = 32
# Sync-free rounds cost no host read, so shorter threads pay: on an NVIDIA H200 a contact
# evaluation (billiards_512 / billiards_6208 / gather) took 1.23 / 2.29 / 0.94 ms at 16,
# 1.08 / 2.04 / 0.83 ms at 8 and 1.06 / 2.01 / 0.77 ms at 4 (stacks sized per budget).
SYNC_FREE_VISIT_BUDGET = 4


@wp.func
def listed(counters: wp.array(dtype=wp.int32), slot: int, capacity: int):
    """Items held by a list whose counter is ``counters[slot]``: the count, or the list's
    capacity where the count ran past it (the host then grows the list and reruns)."""
    return wp.min(counters[slot], capacity)


@wp.func
def _emit(counters: wp.array(dtype=wp.int32), slot: int, items: wp.array(dtype=wp.vec4i), item: wp.vec4i):
    index = wp.atomic_add(counters, slot, 1)
    if index < items.shape[0]:
        items[index] = item
    return index


@functools.cache
def traverse_round_kernel(visit_budget: int):
    """The traversal round kernel whose threads visit at most ``visit_budget`` node pairs.

    A visit pops one stack entry and pushes at most four, so the thread's local stack needs
    3 visit_budget + 1 entries; it is zero-initialised per thread, so it is sized per budget
    (one compiled kernel each) rather than for the largest.
    """
    visit_budget = int(visit_budget)
    if visit_budget < 1:
        raise ValueError(f"visit_budget: must be >= 1, got {visit_budget}")
    stack_capacity = 3 * visit_budget + 1

    @wp.kernel(enable_backward=False, module="unique")
    def traverse_round(
        # Model:
        node_center: wp.array(dtype=wp.vec3d),
        node_radius: wp.array(dtype=wp.float64),
        node_left: wp.array(dtype=wp.int32),
        node_right: wp.array(dtype=wp.int32),
        node_triangle: wp.array(dtype=wp.int32),
        eps: wp.float64,
        support: wp.float64,
        # Data in:
        body_rotation: wp.array(dtype=wp.mat33d),
        body_position: wp.array(dtype=wp.vec3d),
        seed_body_pair: wp.array(dtype=wp.vec2i),
        task: wp.array(dtype=wp.vec4i),
        task_seed: wp.array(dtype=wp.int32),
        task_slot: int,
        round_slot: int,
        # Data out:
        counters_out: wp.array(dtype=wp.int32),
        far_out: wp.array(dtype=wp.vec4i),
        blend_out: wp.array(dtype=wp.vec4i),
        blend_level_out: wp.array(dtype=wp.int32),
        leaf_out: wp.array(dtype=wp.vec4i),
        next_task_out: wp.array(dtype=wp.vec4i),
        next_task_seed_out: wp.array(dtype=wp.int32),
    ):
        t = wp.tid()
        # Round 0 reads the root tasks (task_slot -1), later rounds the tasks counted in task_slot.
        if task_slot >= 0:
            if t >= listed(counters_out, task_slot, task.shape[0]):
                return
        seed = task_seed[t]
        pair = seed_body_pair[seed]
        rot_a = body_rotation[pair[0]]
        pos_a = body_position[pair[0]]
        rot_b = body_rotation[pair[1]]
        pos_b = body_position[pair[1]]
        # (node on A, node on B, enclosing blend record, nesting level)
        stack = wp.zeros(shape=(stack_capacity,), dtype=wp.vec4i)
        stack[0] = task[t]
        top = int(1)
        visits = int(0)
        while top > 0 and visits < visit_budget:
            visits += 1
            top -= 1
            entry = stack[top]
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
            # d1 = 0 (two nodes collapsed to points) at dist 0 is a contact, which only a leaf
            # solve reports: the centred term's direction is undefined there.
            resolved = dist >= MIN_NODE_DISTANCE
            far = dist >= d2 and dist > d1 and resolved
            if local:
                far = dist - d1 >= support
            if far:
                _emit(counters_out, COUNTER_FAR, far_out, wp.vec4i(ni, nj, parent, seed))
                continue
            if dist > d1 and not local and resolved:
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
            stack[top] = wp.vec4i(li, lj, parent, level)
            top += 1
            if not leaf_j:
                stack[top] = wp.vec4i(li, rj, parent, level)
                top += 1
            if not leaf_i:
                stack[top] = wp.vec4i(ri, lj, parent, level)
                top += 1
                if not leaf_j:
                    stack[top] = wp.vec4i(ri, rj, parent, level)
                    top += 1
        if top > 0:
            # Budget spent: hand the pending node pairs on as the next round's tasks.
            first = wp.atomic_add(counters_out, round_slot, top)
            for k in range(top):
                if first + k < next_task_out.shape[0]:
                    next_task_out[first + k] = stack[k]
                    next_task_seed_out[first + k] = seed

    return traverse_round
