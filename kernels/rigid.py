"""Rigid-body coordinates: body transforms and the projection of point derivatives.

A body's 6 coordinates (dp, dtheta) move a body point as x = exp([dtheta]x) r + p + dp with
r = R X its world-oriented offset (rotation about the body origin, world axes). For a
scalar f of points with point gradient g and point Hessian blocks H_kl:

    df/d(dp, dtheta)  = (g, r x g)
    d2f               = J_k^T H_kl J_l,  J = [I, -[r]x]
                        + on the (dtheta, dtheta) block of each point's body:
                          1/2 (g r^T + r g^T) - (g . r) I     (curvature of exp)
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = [
    "vec6d",
    "mat66d",
    "body_transforms_kernel",
    "rigid_point_gradient",
    "rigid_point_pair_block",
    "rigid_point_curvature",
    "rigid_separation_derivatives",
    "upper_entry",
    "world_triangle",
]

vec6d = wp.types.vector(length=6, dtype=wp.float64)
mat66d = wp.types.matrix(shape=(6, 6), dtype=wp.float64)


@wp.func
def rigid_point_gradient(g: wp.vec3d, r: wp.vec3d):
    c = wp.cross(r, g)
    return vec6d(g[0], g[1], g[2], c[0], c[1], c[2])


@wp.func
def rigid_point_pair_block(h: wp.mat33d, rk: wp.vec3d, rl: wp.vec3d):
    """J_k^T H J_l for points with offsets rk (row body) and rl (column body)."""
    sk = wp.skew(rk)
    sl = wp.skew(rl)
    top_right = -(h * sl)
    bottom_left = sk * h
    bottom_right = -(sk * h * sl)
    out = mat66d()
    for i in range(3):
        for j in range(3):
            out[i, j] = h[i, j]
            out[i, j + 3] = top_right[i, j]
            out[i + 3, j] = bottom_left[i, j]
            out[i + 3, j + 3] = bottom_right[i, j]
    return out


@wp.func
def rigid_point_curvature(g: wp.vec3d, r: wp.vec3d):
    """(dtheta, dtheta) block added by the curvature of the exponential map."""
    half = wp.float64(0.5)
    return half * (wp.outer(g, r) + wp.outer(r, g)) - wp.dot(g, r) * wp.identity(n=3, dtype=wp.float64)


@wp.func
def rigid_separation_derivatives(g: wp.vec3d, h: wp.mat33d, ra: wp.vec3d, rb: wp.vec3d):
    """A function of the separation x_a - x_b of a point of body a (offset ra) and one of
    body b (offset rb), with gradient g and Hessian h in that separation: its rigid gradients
    (a, b) and Hessian blocks (a a), (a b), (b b), curvature included."""
    hess_aa = rigid_point_pair_block(h, ra, ra)
    hess_ab = rigid_point_pair_block(-h, ra, rb)
    hess_bb = rigid_point_pair_block(h, rb, rb)
    curv_a = rigid_point_curvature(g, ra)
    curv_b = rigid_point_curvature(-g, rb)
    for i in range(3):
        for j in range(3):
            hess_aa[3 + i, 3 + j] = hess_aa[3 + i, 3 + j] + curv_a[i, j]
            hess_bb[3 + i, 3 + j] = hess_bb[3 + i, 3 + j] + curv_b[i, j]
    return rigid_point_gradient(g, ra), rigid_point_gradient(-g, rb), hess_aa, hess_ab, hess_bb


@wp.func
def upper_entry(body_r: int, body_c: int, i: int, j: int):
    """Where entry (i, j) of block (body_r, body_c) of a symmetric Hessian of 6 x 6 blocks
    (indexed by body, or by a body's Hessian slot) is kept in its upper triangle: (row,
    column), or (-1, -1) for the lower triangle of a diagonal block, which is not kept (its
    mirror is)."""
    row = 6 * body_r + i
    col = 6 * body_c + j
    if body_r == body_c and j < i:
        return -1, -1
    if row > col:
        return col, row
    return row, col


@wp.func
def world_triangle(local: wp.mat33d, rotation: wp.mat33d, position: wp.vec3d):
    """A triangle's vertices (rows) moved from its body frame to the world."""
    out = wp.mat33d()
    for k in range(3):
        out[k] = rotation * local[k] + position
    return out


@wp.kernel
def body_transforms_kernel(
    # Data in:
    pose_in: wp.array(dtype=wp.transformd),
    # Data out:
    rotation_out: wp.array(dtype=wp.mat33d),
    position_out: wp.array(dtype=wp.vec3d),
):
    b = wp.tid()
    pose = pose_in[b]
    rotation_out[b] = wp.quat_to_matrix(wp.transform_get_rotation(pose))
    position_out[b] = wp.transform_get_translation(pose)
