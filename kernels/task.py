"""Task kernels, differentiated by Warp's autodiff: control parameterisations and the loss.

Degree-of-freedom codes of a controlled body: 0 x, 1 y, 2 z (translations, m),
3 rx, 4 ry, 5 rz (rotation vector about world axes, rad), 6 vx, 7 vy, 8 vz (initial
velocity, m/s). A task's ``yaw`` is the rotation about the stage's up axis, rz or ry
(``warpcontact.tasks``).
"""

import warp as wp

from .state import quat_from_rotation_vector

__all__ = ["DOF_CODES", "initial_state_kernel", "joint_sine_target_kernel", "pd_target_kernel", "target_loss_kernel"]

DOF_CODES = {"x": 0, "y": 1, "z": 2, "rx": 3, "ry": 4, "rz": 5, "vx": 6, "vy": 7, "vz": 8}


@wp.func
def _offsets(values: wp.array2d(dtype=wp.float64), row: int, dof_codes: wp.array(dtype=wp.int32)):
    """(translation, rotation vector, velocity) from one row of decision variables."""
    dp = wp.vec3d()
    rv = wp.vec3d()
    dv = wp.vec3d()
    for k in range(dof_codes.shape[0]):
        code = dof_codes[k]
        v = values[row, k]
        if code < 3:
            dp[code] = dp[code] + v
        elif code < 6:
            rv[code - 3] = rv[code - 3] + v
        else:
            dv[code - 6] = dv[code - 6] + v
    return dp, rv, dv


@wp.func
def _moved_pose(base_pose: wp.transformd, dp: wp.vec3d, rv: wp.vec3d):
    """``base_pose`` moved by ``dp`` and turned by the rotation vector ``rv`` about world axes."""
    rot = quat_from_rotation_vector(rv) * wp.transform_get_rotation(base_pose)
    return wp.transformd(wp.transform_get_translation(base_pose) + dp, rot)


@wp.kernel
def pd_target_kernel(
    # Model:
    body: int,
    base_pose: wp.transformd,
    dof_codes: wp.array(dtype=wp.int32),
    # Data in:
    values: wp.array2d(dtype=wp.float64),
    row: int,
    # Data out:
    target_out: wp.array(dtype=wp.transformd),
):
    """Target of ``body`` = base pose moved by the row's offsets (rotation about world axes)."""
    dp, rv, dv = _offsets(values, row, dof_codes)
    target_out[body] = _moved_pose(base_pose, dp, rv)


@wp.kernel
def initial_state_kernel(
    # Model:
    body: int,
    base_pose: wp.transformd,
    base_velocity: wp.vec3d,
    dof_codes: wp.array(dtype=wp.int32),
    # Data in:
    values: wp.array2d(dtype=wp.float64),
    # Data out:
    body_q_out: wp.array(dtype=wp.transformd),
    linear_velocity_out: wp.array(dtype=wp.vec3d),
):
    """Initial pose and velocity of ``body`` from the decision variables (row 0): offsets from
    its base pose and base (authored) velocity."""
    dp, rv, dv = _offsets(values, 0, dof_codes)
    body_q_out[body] = _moved_pose(base_pose, dp, rv)
    linear_velocity_out[body] = base_velocity + dv


@wp.kernel
def joint_sine_target_kernel(
    # Model:
    coordinate: wp.array(dtype=wp.int32),
    rest: wp.array(dtype=wp.float64),
    # Data in:
    values: wp.array2d(dtype=wp.float64),
    time: wp.float64,
    # Data out:
    target_out: wp.array(dtype=wp.float64),
):
    """Joint PD target of actuated coordinate ``coordinate[i]`` at ``time`` (s): its rest value
    plus sum_j A_j sin(omega_j t + phi_j), row i of ``values`` = (A_1, omega_1, phi_1, A_2, ...)
    (rad, rad/s, rad), the paper's accumulated sine waves (after ChainQueen)."""
    i = wp.tid()
    c = coordinate[i]
    total = rest[c]
    for j in range(values.shape[1] // 3):
        total += values[i, 3 * j] * wp.sin(values[i, 3 * j + 1] * time + values[i, 3 * j + 2])
    target_out[c] = total


@wp.kernel
def target_loss_kernel(
    # Model:
    target_body: wp.array(dtype=wp.int32),
    target_position: wp.array(dtype=wp.vec3d),
    target_tolerance: wp.array(dtype=wp.float64),
    # Data in:
    body_q: wp.array(dtype=wp.transformd),
    # Data out:
    loss_out: wp.array(dtype=wp.float64),
):
    """sum over targets of ReLU(|x_com - x*|^2 - tolerance^2) (paper, "Benchmark Details")."""
    i = wp.tid()
    d = wp.transform_get_translation(body_q[target_body[i]]) - target_position[i]
    tol = target_tolerance[i]
    wp.atomic_add(loss_out, 0, wp.max(wp.dot(d, d) - tol * tol, wp.float64(0.0)))
