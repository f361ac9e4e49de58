"""Closest features between triangles (float64 device functions).

Used to start the leaf solve from a true separating plane: for two disjoint triangles the
closest pair is attained between a vertex and the other triangle or between two edges, so
the 9 edge-edge pairs plus the 6 vertex-face projections cover every case. Degenerate
(zero-area) triangles skip the face projections; their hull is the union of their edges,
which the edge-edge pairs already cover. Where the closest points' direction, rounded at a
gap far below the triangles' size, does not separate them, the separating-axis candidates
(2 face normals, 9 edge cross products, 6 in-plane edge normals for coplanar pairs) give
an exact one.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["segment_closest_points", "triangle_closest_points", "triangle_separating_axis"]


@wp.func
def segment_closest_points(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d):
    """Closest points of segments [p1,q1] and [p2,q2]; robust to zero-length and parallel segments."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = zero
    t = zero
    if a <= zero and e <= zero:
        return p1, p2
    if a <= zero:
        t = wp.clamp(f / e, zero, one)
    else:
        c = wp.dot(d1, r)
        if e <= zero:
            s = wp.clamp(-c / a, zero, one)
        else:
            b = wp.dot(d1, d2)
            denom = a * e - b * b
            # Parallel segments: any s gives a closest pair once t is clamped below.
            if denom > wp.float64(1.0e-14) * a * e:
                s = wp.clamp((b * f - c * e) / denom, zero, one)
            t = (b * s + f) / e
            if t < zero:
                t = zero
                s = wp.clamp(-c / a, zero, one)
            elif t > one:
                t = one
                s = wp.clamp((b - c) / a, zero, one)
    return p1 + s * d1, p2 + t * d2


@wp.func
def _face_projection(p: wp.vec3d, b0: wp.vec3d, b1: wp.vec3d, b2: wp.vec3d):
    """Projection of p onto the plane of (b0,b1,b2) and whether it lies inside the triangle."""
    e1 = b1 - b0
    e2 = b2 - b0
    nrm = wp.cross(e1, e2)
    nn = wp.dot(nrm, nrm)
    scale = wp.max(wp.dot(e1, e1), wp.dot(e2, e2))
    if nn <= wp.float64(1.0e-24) * scale * scale:
        return p, False
    q = p - (wp.dot(p - b0, nrm) / nn) * nrm
    u = wp.dot(wp.cross(b1 - q, b2 - q), nrm)
    v = wp.dot(wp.cross(b2 - q, b0 - q), nrm)
    w = wp.dot(wp.cross(b0 - q, b1 - q), nrm)
    zero = wp.float64(0.0)
    # Exactly, u + v + w = nn. A point ~1e16 of the triangle's size away (beyond it in its
    # plane) rounds b0 - q, b1 - q and b2 - q to one vector: u, v and w are then rounding
    # noise (all 0 for such a point, read as inside: a far vertex "touched" the triangle).
    resolved = wp.abs(u + v + w - nn) <= wp.float64(0.5) * nn
    return q, (u >= zero and v >= zero and w >= zero and resolved)


@wp.func
def triangle_closest_points(ta: wp.mat33d, tb: wp.mat33d):
    """Closest points (on A, on B) of two triangles given as rows of 3x3 matrices."""
    best = wp.float64(1.0e308)
    ca = ta[0]
    cb = tb[0]
    for i in range(3):
        for j in range(3):
            pa, pb = segment_closest_points(ta[i], ta[(i + 1) % 3], tb[j], tb[(j + 1) % 3])
            dd = wp.length_sq(pa - pb)
            if dd < best:
                best = dd
                ca = pa
                cb = pb
    for k in range(3):
        qb, inside_b = _face_projection(ta[k], tb[0], tb[1], tb[2])
        if inside_b:
            dd = wp.length_sq(ta[k] - qb)
            if dd < best:
                best = dd
                ca = ta[k]
                cb = qb
        qa, inside_a = _face_projection(tb[k], ta[0], ta[1], ta[2])
        if inside_a:
            dd = wp.length_sq(tb[k] - qa)
            if dd < best:
                best = dd
                ca = qa
                cb = tb[k]
    return ca, cb


@wp.func
def _projection_range(t: wp.mat33d, u: wp.vec3d):
    """(min, max) of a triangle's vertices projected on u."""
    low = wp.float64(wp.inf)
    high = wp.float64(-wp.inf)
    for k in range(3):
        x = wp.dot(t[k], u)
        low = wp.min(low, x)
        high = wp.max(high, x)
    return low, high


@wp.func
def triangle_separating_axis(ta: wp.mat33d, tb: wp.mat33d):
    """The unit axis among the pair's face normals, edge cross products and in-plane edge
    normals (either sign) along which A lies beyond B with the widest gap, and the gap's
    midpoint along it; found is False when no candidate separates the triangles strictly.

    The in-plane edge normals (a face normal crossed with one of its edges) separate
    coplanar triangles, which every other candidate meets edge on: without them two
    coplanar triangles 1e-8 of their size apart were taken as touching.
    """
    best = wp.vec3d()
    best_gap = wp.float64(0.0)
    best_mid = wp.float64(0.0)
    found = bool(False)
    normal_a = wp.cross(ta[1] - ta[0], ta[2] - ta[0])
    normal_b = wp.cross(tb[1] - tb[0], tb[2] - tb[0])
    for c in range(17):
        u = wp.vec3d()
        if c == 0:
            u = normal_a
        elif c == 1:
            u = normal_b
        elif c < 11:
            i = (c - 2) // 3
            j = (c - 2) % 3
            u = wp.cross(ta[(i + 1) % 3] - ta[i], tb[(j + 1) % 3] - tb[j])
        elif c < 14:
            u = wp.cross(normal_a, ta[(c - 10) % 3] - ta[c - 11])
        else:
            u = wp.cross(normal_b, tb[(c - 13) % 3] - tb[c - 14])
        length = wp.length(u)
        if length > wp.float64(0.0):
            u = u / length
            low_a, high_a = _projection_range(ta, u)
            low_b, high_b = _projection_range(tb, u)
            if low_a - high_b > best_gap:  # A beyond B along u
                best = u
                best_gap = low_a - high_b
                best_mid = wp.float64(0.5) * (low_a + high_b)
                found = True
            if low_b - high_a > best_gap:  # along -u
                best = -u
                best_gap = low_b - high_a
                best_mid = wp.float64(-0.5) * (high_a + low_b)
                found = True
    return best, best_mid, found
