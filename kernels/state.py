"""State initialisation kernels, differentiated by Warp's autodiff (recorded on the tape)."""

import warp as wp

__all__ = ["quat_from_rotation_vector", "previous_pose_from_velocity_kernel"]


@wp.func
def quat_from_rotation_vector(w: wp.vec3d):
    """exp of a rotation vector (rad) as a quaternion; differentiable at zero."""
    angle = wp.length(w)
    if angle < wp.float64(1.0e-8):
        # Series keeps the adjoint finite at zero angular velocity.
        return wp.normalize(wp.quatd(wp.float64(0.5) * w[0], wp.float64(0.5) * w[1], wp.float64(0.5) * w[2], wp.float64(1.0)))
    s = wp.sin(wp.float64(0.5) * angle) / angle
    return wp.quatd(s * w[0], s * w[1], s * w[2], wp.cos(wp.float64(0.5) * angle))


@wp.kernel
def previous_pose_from_velocity_kernel(
    # Data in:
    body_q: wp.array(dtype=wp.transformd),
    linear_velocity: wp.array(dtype=wp.vec3d),
    angular_velocity: wp.array(dtype=wp.vec3d),
    dt: wp.float64,
    # Data out:
    body_q_prev_out: wp.array(dtype=wp.transformd),
):
    b = wp.tid()
    q = body_q[b]
    p_prev = wp.transform_get_translation(q) - dt * linear_velocity[b]
    r_prev = quat_from_rotation_vector(-dt * angular_velocity[b]) * wp.transform_get_rotation(q)
    body_q_prev_out[b] = wp.transformd(p_prev, r_prev)
