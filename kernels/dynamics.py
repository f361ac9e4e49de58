"""Per-body terms of the implicit step: inertia, gravity and implicit PD control.

Coordinates are the rigid-body coordinates of ``kernels/rigid.py`` (dp, dtheta; rotation
about the body origin = centre of mass, world axes). For a body of mass m and second
moment S = sum m_v X_v X_v^T (body frame, about the centre of mass):

    inertia  m/(2 dt^2) |p - p_hat|^2 + 1/dt^2 (tr S - tr(R_hat S R^T))
             = sum_v m_v/(2 dt^2) |x_v - y_v|^2,   y_v = R_hat X_v + p_hat
    gravity  -m <g, p>
    PD       1/2 sum_i kp_i (p_i - p*_i)^2 + kp_ang/2 (3 - tr(R* R^T))
             + 1/(2 dt) [sum_i kd_i (p_i - p_i^t)^2 + kd_ang (3 - tr(R^t R^T))]

p_hat = 2 p^t - p^{t-1}. The rotational prediction R_hat = R^t F is the free step of the
Lie-group variational integrator (Lee, Leok, McClamroch):
F S - S F^T = S F_prev - F_prev^T S with F_prev = (R^{t-1})^T R^t, so free bodies conserve
angular momentum exactly, while the inertial term keeps the paper's vertex-based form
centred on that prediction.

Every term of the form c - tr(C R^T) with M = C R^T has gradient -axial(M) and Hessian
tr(M) I - sym(M); perturbing C's left factor by exp([zeta]x) changes the gradient by
-(tr(M) I - M) zeta.
"""

import warp as wp

from .rigid import mat66d, vec6d

wp.set_module_options({"enable_backward": False})

__all__ = [
    "PREDICT_OK",
    "PREDICT_FAILED",
    "axial",
    "exp_so3",
    "BodyModel",
    "predict_kernel",
    "body_energy_kernel",
    "body_adjoint_kernel",
    "pose_adjoint_to_rigid_kernel",
    "rigid_adjoint_to_pose_kernel",
    "rotation_adjoint_to_quat_kernel",
]

PREDICT_OK = wp.constant(0)
PREDICT_FAILED = wp.constant(1)

_LGVI_MAX_ITERATIONS = wp.constant(50)
_LGVI_TOL = wp.constant(wp.float64(1.0e-15))
_LGVI_MAX_BACKTRACKS = wp.constant(30)


@wp.func
def axial(m: wp.mat33d):
    """vee(M - M^T): the axial vector of twice the skew part."""
    return wp.vec3d(m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1])


@wp.func
def _trace(m: wp.mat33d):
    return m[0, 0] + m[1, 1] + m[2, 2]


@wp.func
def _sym(m: wp.mat33d):
    return wp.float64(0.5) * (m + wp.transpose(m))


@wp.func
def exp_so3(w: wp.vec3d):
    """Rotation matrix exp([w]x) (Rodrigues, with series near zero)."""
    theta2 = wp.dot(w, w)
    k = wp.skew(w)
    one = wp.float64(1.0)
    a = one
    b = wp.float64(0.5)
    if theta2 < wp.float64(1.0e-12):
        a = one - theta2 / wp.float64(6.0)
        b = wp.float64(0.5) - theta2 / wp.float64(24.0)
    else:
        theta = wp.sqrt(theta2)
        a = wp.sin(theta) / theta
        b = (one - wp.cos(theta)) / theta2
    return wp.identity(n=3, dtype=wp.float64) + a * k + b * (k * k)


@wp.func
def _pose_rotation(q: wp.transformd):
    """The rotation of a pose whose quaternion may have any norm whose square is a float64;
    beyond that NaN, so that the step fails and names it (normalised, a PD target of norm
    1e160 became the identity rotation, silently)."""
    r = wp.transform_get_rotation(q)
    norm = wp.length(r)
    if not (norm > wp.float64(1.0e-150) and norm < wp.float64(1.0e150)):
        return wp.mat33d(wp.float64(wp.nan))
    return wp.quat_to_matrix(wp.normalize(r))


@wp.func
def _twist_matrix(m: wp.mat33d):
    """tr(M) I - M: maps zeta to d axial([zeta]x M)."""
    return _trace(m) * wp.identity(n=3, dtype=wp.float64) - m


@wp.struct
class BodyModel:
    """Per-body model data of the step's inertia, gravity and PD terms (one entry per body)."""

    mass: wp.array(dtype=wp.float64)
    unit_second_moment: wp.array(dtype=wp.mat33d)
    dynamic: wp.array(dtype=wp.int32)
    kp_linear: wp.array(dtype=wp.vec3d)
    kd_linear: wp.array(dtype=wp.vec3d)
    kp_angular: wp.array(dtype=wp.float64)
    kd_angular: wp.array(dtype=wp.float64)
    gravity: wp.vec3d
    dt: wp.float64


@wp.kernel
def predict_kernel(
    # Model:
    body_unit_second_moment: wp.array(dtype=wp.mat33d),
    body_dynamic: wp.array(dtype=wp.int32),
    # Data in:
    body_q: wp.array(dtype=wp.transformd),
    body_q_prev: wp.array(dtype=wp.transformd),
    # Data out:
    predicted_position_out: wp.array(dtype=wp.vec3d),
    predicted_rotation_out: wp.array(dtype=wp.mat33d),
    prediction_sensitivity_out: wp.array(dtype=wp.mat33d),
    status_out: wp.array(dtype=wp.int32),
):
    b = wp.tid()
    status_out[b] = PREDICT_OK
    q = body_q[b]
    qp = body_q_prev[b]
    predicted_position_out[b] = wp.float64(2.0) * wp.transform_get_translation(q) - wp.transform_get_translation(qp)
    r_t = _pose_rotation(q)
    if body_dynamic[b] == 0:
        predicted_rotation_out[b] = r_t
        prediction_sensitivity_out[b] = wp.mat33d()
        return
    s = body_unit_second_moment[b]  # the prediction is invariant to scaling S
    f_prev = wp.transpose(_pose_rotation(qp)) * r_t
    target = axial(s * f_prev)
    f = f_prev
    converged = bool(False)
    scale = _trace(s)
    a = wp.mat33d()
    for _it in range(_LGVI_MAX_ITERATIONS):
        fs = f * s
        residual = target - axial(fs)
        a = _twist_matrix(fs) * f
        norm = wp.length(residual)
        if norm <= _LGVI_TOL * scale:
            converged = True
            break
        # Full Newton steps cycled for turns of 1.5-2 rad a step (a thin plate spun about a
        # diagonal): steps are halved until the residual falls.
        xi = wp.inverse(a) * residual
        trial = f * exp_so3(xi)
        for _bt in range(_LGVI_MAX_BACKTRACKS):
            if wp.length(target - axial(trial * s)) < norm:
                break
            xi = wp.float64(0.5) * xi
            trial = f * exp_so3(xi)
        f = trial
    if not converged or wp.abs(wp.determinant(a)) <= wp.float64(1.0e-12) * scale * scale * scale:
        status_out[b] = PREDICT_FAILED
    r_hat = r_t * f
    predicted_rotation_out[b] = r_hat
    # d R_hat = [zeta]x R_hat with zeta = (I + K) a - K c for perturbations a of R^t and c of
    # R^{t-1} (left, world axes); K = R_hat A^-1 B R^t^T from the implicit function theorem.
    bmat = _twist_matrix(wp.transpose(f_prev) * s)
    prediction_sensitivity_out[b] = r_hat * wp.inverse(a) * bmat * wp.transpose(r_t)


@wp.func
def _alignment_terms(c: wp.mat33d, r: wp.mat33d, weight: wp.float64):
    """weight * (-tr(C R^T)): value, gradient, Hessian in dtheta."""
    m = c * wp.transpose(r)
    hess = weight * (_trace(m) * wp.identity(n=3, dtype=wp.float64) - _sym(m))
    return -weight * _trace(m), -weight * axial(m), hess


@wp.kernel
def body_energy_kernel(
    # Model:
    bodies: BodyModel,
    # Data in:
    body_q: wp.array(dtype=wp.transformd),
    body_q_current: wp.array(dtype=wp.transformd),
    predicted_position: wp.array(dtype=wp.vec3d),
    predicted_rotation: wp.array(dtype=wp.mat33d),
    body_target: wp.array(dtype=wp.transformd),
    # Data out:
    energy_out: wp.array(dtype=wp.float64),
    grad_out: wp.array(dtype=vec6d),
    hess_out: wp.array(dtype=mat66d),
):
    b = wp.tid()
    if bodies.dynamic[b] == 0:
        energy_out[b] = wp.float64(0.0)
        grad_out[b] = vec6d()
        hess_out[b] = mat66d()
        return
    m = bodies.mass[b]
    s = m * bodies.unit_second_moment[b]
    inv_dt2 = wp.float64(1.0) / (bodies.dt * bodies.dt)
    p = wp.transform_get_translation(body_q[b])
    r = _pose_rotation(body_q[b])
    p_now = wp.transform_get_translation(body_q_current[b])
    r_now = _pose_rotation(body_q_current[b])
    p_target = wp.transform_get_translation(body_target[b])
    r_target = _pose_rotation(body_target[b])
    kp = bodies.kp_linear[b]
    kd = bodies.kd_linear[b]

    dp = p - predicted_position[b]
    energy = wp.float64(0.5) * m * inv_dt2 * wp.dot(dp, dp) - m * wp.dot(bodies.gravity, p)
    g_lin = m * inv_dt2 * dp - m * bodies.gravity
    h_lin = wp.vec3d(m * inv_dt2, m * inv_dt2, m * inv_dt2)
    for i in range(3):
        # An axis without a gain ignores its target, which may then be anything (NaN too).
        e_p = wp.float64(0.0)
        if kp[i] != wp.float64(0.0):
            e_p = p[i] - p_target[i]
        e_d = p[i] - p_now[i]
        energy += wp.float64(0.5) * (kp[i] * e_p * e_p + kd[i] * e_d * e_d / bodies.dt)
        g_lin[i] = g_lin[i] + kp[i] * e_p + kd[i] * e_d / bodies.dt
        h_lin[i] = h_lin[i] + kp[i] + kd[i] / bodies.dt

    e_rot, g_rot, h_rot = _alignment_terms(predicted_rotation[b] * s, r, inv_dt2)
    energy += e_rot + inv_dt2 * _trace(s)
    half = wp.float64(0.5)
    kp_ang = bodies.kp_angular[b]
    if kp_ang != wp.float64(0.0):
        e_a, g_a, h_a = _alignment_terms(r_target, r, half * kp_ang)
        energy += e_a + wp.float64(1.5) * kp_ang
        if wp.length(wp.transform_get_rotation(body_target[b])) == wp.float64(0.0):
            # No rotation to drive to (it normalises to zero, and drove nothing): the step
            # reports a non-finite objective, and the solver names the target.
            energy = wp.float64(wp.inf)
        g_rot += g_a
        h_rot += h_a
    kd_ang = bodies.kd_angular[b]
    if kd_ang != wp.float64(0.0):
        e_b, g_b, h_b = _alignment_terms(r_now, r, half * kd_ang / bodies.dt)
        energy += e_b + wp.float64(1.5) * kd_ang / bodies.dt
        g_rot += g_b
        h_rot += h_b

    energy_out[b] = energy
    grad_out[b] = vec6d(g_lin[0], g_lin[1], g_lin[2], g_rot[0], g_rot[1], g_rot[2])
    h = mat66d()
    for i in range(3):
        h[i, i] = h_lin[i]
        for j in range(3):
            h[3 + i, 3 + j] = h_rot[i, j]
    hess_out[b] = h


@wp.kernel
def body_adjoint_kernel(
    # Model:
    bodies: BodyModel,
    # Data in:
    body_q: wp.array(dtype=wp.transformd),
    body_q_current: wp.array(dtype=wp.transformd),
    predicted_position: wp.array(dtype=wp.vec3d),
    predicted_rotation: wp.array(dtype=wp.mat33d),
    prediction_sensitivity: wp.array(dtype=wp.mat33d),
    body_target: wp.array(dtype=wp.transformd),
    multiplier: wp.array(dtype=vec6d),
    # Data out:
    adj_current_out: wp.array(dtype=vec6d),
    adj_previous_out: wp.array(dtype=vec6d),
    adj_target_out: wp.array(dtype=vec6d),
    adj_mass_out: wp.array(dtype=wp.float64),
):
    """lambda^T d(grad_q L)/dy for y = q^t, q^{t-1}, the PD target and the mass (per body)."""
    b = wp.tid()
    adj_current_out[b] = vec6d()
    adj_previous_out[b] = vec6d()
    adj_target_out[b] = vec6d()
    adj_mass_out[b] = wp.float64(0.0)
    if bodies.dynamic[b] == 0:
        return
    lam = multiplier[b]
    lam_p = wp.vec3d(lam[0], lam[1], lam[2])
    lam_r = wp.vec3d(lam[3], lam[4], lam[5])
    m = bodies.mass[b]
    s = m * bodies.unit_second_moment[b]
    inv_dt2 = wp.float64(1.0) / (bodies.dt * bodies.dt)
    r = _pose_rotation(body_q[b])
    r_now = _pose_rotation(body_q_current[b])
    r_target = _pose_rotation(body_target[b])
    p = wp.transform_get_translation(body_q[b])
    kp = bodies.kp_linear[b]
    kd = bodies.kd_linear[b]

    # Translation: grad = m/dt^2 (p - 2 p^t + p^{t-1}) - m g + kp (p - p*) + kd/dt (p - p^t).
    a_now_p = wp.vec3d()
    a_prev_p = m * inv_dt2 * lam_p
    a_tgt_p = wp.vec3d()
    for i in range(3):
        a_now_p[i] = -(wp.float64(2.0) * m * inv_dt2 + kd[i] / bodies.dt) * lam_p[i]
        a_tgt_p[i] = -kp[i] * lam_p[i]

    # Rotation, inertia: grad = -axial(R_hat S R^T) / dt^2, R_hat moved by zeta = (I+K) a - K c.
    k = prediction_sensitivity[b]
    t_in = _twist_matrix(predicted_rotation[b] * s * wp.transpose(r))
    w = -inv_dt2 * (wp.transpose(t_in) * lam_r)
    a_now_r = w + wp.transpose(k) * w
    a_prev_r = -(wp.transpose(k) * w)
    # PD target and rotational damping: grad = -(k/2) axial(C R^T) with C = R* or R^t.
    half = wp.float64(0.5)
    a_tgt_r = wp.vec3d()
    if bodies.kp_angular[b] != wp.float64(0.0):
        t_tgt = _twist_matrix(r_target * wp.transpose(r))
        a_tgt_r = -(half * bodies.kp_angular[b]) * (wp.transpose(t_tgt) * lam_r)
    t_now = _twist_matrix(r_now * wp.transpose(r))
    a_now_r += -(half * bodies.kd_angular[b] / bodies.dt) * (wp.transpose(t_now) * lam_r)

    adj_current_out[b] = vec6d(a_now_p[0], a_now_p[1], a_now_p[2], a_now_r[0], a_now_r[1], a_now_r[2])
    adj_previous_out[b] = vec6d(a_prev_p[0], a_prev_p[1], a_prev_p[2], a_prev_r[0], a_prev_r[1], a_prev_r[2])
    adj_target_out[b] = vec6d(a_tgt_p[0], a_tgt_p[1], a_tgt_p[2], a_tgt_r[0], a_tgt_r[1], a_tgt_r[2])
    # Inertia scales with the mass (S = m S_unit, and R_hat does not depend on m); gravity is -m g.
    g_inertia_rot = -inv_dt2 * axial(predicted_rotation[b] * s * wp.transpose(r))
    d_lin_dm = inv_dt2 * (p - predicted_position[b]) - bodies.gravity
    adj_mass_out[b] = wp.dot(lam_p, d_lin_dm) + wp.dot(lam_r, g_inertia_rot) / m


@wp.kernel
def pose_adjoint_to_rigid_kernel(
    # Data in:
    body_q: wp.array(dtype=wp.transformd),
    pose_adjoint: wp.array(dtype=wp.transformd),
    # Data out:
    rigid_adjoint_out: wp.array(dtype=vec6d),
):
    """Adjoint of a pose (p, quaternion components) as a rigid cotangent (dp, dtheta)."""
    b = wp.tid()
    q = wp.normalize(wp.transform_get_rotation(body_q[b]))
    g = pose_adjoint[b]
    gq = wp.transform_get_rotation(g)
    gp = wp.transform_get_translation(g)
    out = vec6d(gp[0], gp[1], gp[2], wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for i in range(3):
        e = wp.quatd(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        e[i] = wp.float64(0.5)
        dq = e * q  # d q / d theta_i for q -> exp(theta) q
        out[3 + i] = gq[0] * dq[0] + gq[1] * dq[1] + gq[2] * dq[2] + gq[3] * dq[3]
    rigid_adjoint_out[b] = out


@wp.func
def _quat_adjoint(q: wp.quatd, a: wp.vec3d):
    """Quaternion-component adjoint of a cotangent a of a left turn exp([theta]x) R(q/|q|),
    through theta = 2 vec(dq q*) / |q|^2 (norm changes give 0)."""
    out = wp.quatd(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if a[0] == wp.float64(0.0) and a[1] == wp.float64(0.0) and a[2] == wp.float64(0.0):
        return out  # also for a q the step ignores (a PD target without a rotational gain may be NaN)
    qc = wp.quat_inverse(wp.normalize(q)) / wp.length(q)
    for j in range(4):
        e = wp.quatd(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        e[j] = wp.float64(1.0)
        v = e * qc
        out[j] = wp.float64(2.0) * (a[0] * v[0] + a[1] * v[1] + a[2] * v[2])
    return out


@wp.kernel
def rigid_adjoint_to_pose_kernel(
    # Data in:
    body_q: wp.array(dtype=wp.transformd),
    rigid_adjoint: wp.array(dtype=vec6d),
    # Data out:
    pose_adjoint_out: wp.array(dtype=wp.transformd),
):
    """Add a rigid cotangent to a pose adjoint, through theta = 2 vec(dq q*) / |q|^2 (norm changes give 0)."""
    b = wp.tid()
    a = rigid_adjoint[b]
    out = pose_adjoint_out[b]
    dq = _quat_adjoint(wp.transform_get_rotation(body_q[b]), wp.vec3d(a[3], a[4], a[5]))
    for i in range(3):
        out[i] = out[i] + a[i]
    for j in range(4):
        out[3 + j] = out[3 + j] + dq[j]
    pose_adjoint_out[b] = out


@wp.kernel
def rotation_adjoint_to_quat_kernel(
    # Data in:
    rotations: wp.array(dtype=wp.quatd),
    rotation_adjoint: wp.array(dtype=wp.vec3d),
    # Data out:
    quat_adjoint_out: wp.array(dtype=wp.quatd),
):
    """Add a left-turn cotangent to a quaternion adjoint (as ``rigid_adjoint_to_pose_kernel``)."""
    i = wp.tid()
    quat_adjoint_out[i] = quat_adjoint_out[i] + _quat_adjoint(rotations[i], rotation_adjoint[i])
