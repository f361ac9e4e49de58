"""Friction in the ipc and sdrs baselines: the same lagged, smoothed Coulomb law as ours, with
normal forces from each model's own barrier (zero beyond its support) and exact gradients."""

import numpy as np
import pytest
import warp as wp
from helpers_rigid import box, perturbed, quat, quat_mul, skew
from test_solver import assert_frictional_gradients, grid_ground, incline_model, position_loss_kernel, record, rollout

import warpcontact as wc
from warpcontact import scenes
from warpcontact.tasks import TaskProblem, TaskSettings

# Barrier stiffness per mode: ipctk's barrier is not normalised by dhat^3 like sdrs's
# (on squared distances, b' ~ -2 dhat^4 / d instead of -1 / (dhat d)): it needs a far larger mu
# for gaps of ~1e-4 m under a box's weight (tiny gaps make ipctk's CCD very slow).
STIFFNESS = {"bsh": 1e-6, "sdrs": 1e-6, "ipc": 1e5}


def box_on_ground(mode, *, gap, friction=0.5, friction_smoothing=1e-4, contact_stiffness=None, yaw=0.3):
    """A 0.4 m box ``gap`` above a tessellated ground, yawed so no box edge is parallel to a
    ground edge (parallel edge-edge pairs are degenerate for IPC's tangent bases)."""
    b = wc.ModelBuilder(
        gravity=(0.0, 0.0, -9.81),
        contact_stiffness=contact_stiffness or STIFFNESS[mode],
        friction=friction,
        friction_smoothing=friction_smoothing,
        contact_mode=mode,
    )
    b.add_body(grid_ground(2.0, 0.5), static=True, name="ground", pose=(0.03, 0.07, 0.0, 0.0, 0.0, 0.0, 1.0))
    b.add_box((0.4, 0.4, 0.4), density=500.0, name="box", pose=(0.0, 0.0, 0.2 + gap, 0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)))
    return b.finalize()


@pytest.mark.parametrize("mode", ["sdrs", "ipc"])
@pytest.mark.parametrize("angle, friction", [(0.3, 0.5), (0.4, 0.2)])
def test_box_on_incline_sticks_below_and_slides_above_the_coulomb_threshold(mode, angle, friction):
    model, R = incline_model(angle, friction, contact_mode=mode, contact_stiffness=STIFFNESS[mode])
    dt = 0.02
    q, solver = rollout(model, 40, dt)
    assert solver.last_step.friction_pairs > 0
    along = (q[1:, 1, :3] @ R)[:, 0]
    t = np.arange(1, 41) * dt
    late = t > 0.3
    acceleration = abs(2 * np.polyfit(t[late], along[late], 2)[0])
    if np.tan(angle) < friction:
        assert np.ptp(along[late]) < 1e-3  # stuck, like ours (tests/test_solver.py)
    else:
        assert acceleration == pytest.approx(9.81 * (np.sin(angle) - friction * np.cos(angle)), rel=0.02)


def lagged_friction(model, poses):
    contact = model.contact
    contact.evaluate(poses)
    return contact.friction_frame(float(model.contact_stiffness.numpy()[0]), model.friction, 1e-4)


def slid(poses, dx):
    out = poses.copy()
    out[1, 0] += dx
    return out


@pytest.mark.parametrize("mode, dhat", [("sdrs", 0.01), ("ipc", 0.01)])
def test_no_friction_beyond_the_support_and_friction_inside(mode, dhat):
    # sdrs triangles interact below 2 dhat, ipc's primitives below dhat.
    support = 2 * dhat if mode == "sdrs" else dhat
    for gap, acts in ((1.2 * support, False), (0.5 * support, True)):
        model = box_on_ground(mode, gap=gap)
        poses = model.initial_q
        lagged = lagged_friction(model, poses)
        model.contact.evaluate(slid(poses, 0.01))
        value, grad, _ = model.contact.friction_terms(lagged)
        if acts:
            assert lagged.pairs > 0 and value > 0 and grad[6] > 0  # resists the slide along +x
        else:
            assert value == 0.0 and np.all(grad == 0.0)
            if mode == "sdrs":  # listed by the broad phase, yet no normal force
                assert lagged.pairs > 0 and np.all(lagged.data.vertex_force.numpy() == 0.0)


@pytest.mark.parametrize("mode", ["bsh", "sdrs", "ipc"])
@pytest.mark.parametrize("slip", [3e-5, 1e-2])
def test_friction_terms_match_finite_differences(mode, slip):
    """The friction term's gradient and Hessian in rigid coordinates against central
    differences of its value and gradient, at a slip within the smoothing length (1e-4 m,
    where the smoothed law is curved most) and beyond it, the box also turned. As in
    helpers_rigid.fd_check, the gradient at a turned pose is taken about that pose, so
    differences of it carry the exponential map's bracket -1/2 [g_theta]x."""
    model = box_on_ground(mode, gap=0.004)
    poses = model.initial_q
    lagged = lagged_friction(model, poses)
    contact = model.contact
    at = poses.copy()
    at[1, :2] += (slip, -0.4 * slip)
    at[1, 3:] = quat_mul(quat([0.2, -0.1, 1.0], 20.0 * slip), poses[1, 3:])
    value, grad, hess = contact.friction_terms(lagged, poses=at)
    assert lagged.pairs > 0 and value > 0
    h = 1e-7 if slip < 1e-3 else 1e-6
    fd_grad, fd_hess = np.zeros(6), np.zeros((6, 6))
    for k in range(6):
        plus = contact.friction_terms(lagged, poses=perturbed(at, 1, k, h))
        minus = contact.friction_terms(lagged, poses=perturbed(at, 1, k, -h))
        fd_grad[k] = (plus[0] - minus[0]) / (2 * h)
        fd_hess[:, k] = (plus[1][6:] - minus[1][6:]) / (2 * h)
    fd_hess[3:, 3:] += 0.5 * skew(grad[9:12])
    assert np.abs(fd_grad - grad[6:]).max() <= 2e-6 * np.abs(grad[6:]).max()
    assert np.abs(fd_hess - hess).max() <= 2e-6 * np.abs(hess).max()


@pytest.mark.parametrize("mode", ["bsh", "sdrs"])
def test_friction_replicas_give_the_same_terms(mode):
    # GPUs spread each body pair's friction adds over replicated records, as they do the
    # potential's top-level terms (CPU default: 1); any count gives the same terms, with
    # no static rows and an exactly symmetric Hessian.
    meshes = [grid_ground(2.0, 0.5), box((0.4, 0.4, 0.4))]
    poses = np.array([[0.03, 0.07, 0.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.204, 0.0, 0.0, np.sin(0.15), np.cos(0.15)]])
    friction = wp.array([0.5], dtype=wp.float64)
    terms = []
    for replicas in (1, 5):
        contact = wc.ContactModel(meshes, mode=mode, static=[True, False], top_replicas=replicas)
        contact.evaluate(poses)
        lagged = contact.friction_frame(1e-6, friction, 1e-4)
        contact.evaluate(slid(poses, 0.01))
        terms.append(contact.friction_terms(lagged))
    (ref_value, ref_grad, ref_hess), (value, grad, hess) = terms
    assert lagged.pairs > 0 and ref_value > 0
    assert value == pytest.approx(ref_value, rel=1e-13)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-12, atol=1e-13 * np.abs(ref_grad).max())
    np.testing.assert_allclose(hess, ref_hess, rtol=1e-12, atol=1e-13 * np.abs(ref_hess).max())
    assert np.all(grad[:6] == 0) and hess.shape == (6, 6)  # the static ground has no rows
    np.testing.assert_array_equal(hess, hess.T)


@pytest.mark.parametrize("mode", ["bsh", "sdrs", "ipc"])
def test_friction_terms_at_given_poses_leave_the_last_evaluation_alone(mode):
    # The solver's friction-exact Newton model evaluates friction at trial poses between
    # contact evaluations; later advancement bounds and friction terms still need q's.
    model = box_on_ground(mode, gap=0.004)
    poses = model.initial_q
    lagged = lagged_friction(model, poses)
    contact = model.contact
    contact.evaluate(slid(poses, 0.01))
    at_evaluation = contact.friction_terms(lagged)
    elsewhere = contact.friction_terms(lagged, poses=slid(poses, 0.02))
    after = contact.friction_terms(lagged)
    contact.evaluate(slid(poses, 0.02))
    evaluated_there = contact.friction_terms(lagged)
    assert lagged.pairs > 0 and 0 < at_evaluation[0] < elsewhere[0]
    # ipctk sums on worker threads: its last bits vary from call to call.
    for a, b in (*zip(at_evaluation, after), *zip(elsewhere, evaluated_there)):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13 * np.abs(b).max())


def test_sdrs_normal_forces_are_the_barrier_forces():
    model = box_on_ground("sdrs", gap=0.004)
    poses = model.initial_q
    lagged = lagged_friction(model, poses)
    contact = model.contact.evaluate(poses)
    mu = float(model.contact_stiffness.numpy()[0])
    frame = lagged.data
    # Per pair N n^ (the sum of its carrying triangle's N_k; the box's, which the plane's
    # balance makes equal to the force on the ground's triangle A, n^ pointing to A's side,
    # down) balances the force on the box: minus the gradient of its translation.
    total = (frame.vertex_force.numpy().reshape(-1, 3).sum(axis=1)[:, None] * frame.normal.numpy()).sum(axis=0)
    np.testing.assert_allclose(total, mu * contact.grad[1, :3], rtol=1e-9)
    assert total[2] < 0


def sliding_box(mode, *, velocity, friction, mu, start_x=0.0, tape=None, steps=6, dt=0.02):
    """Loss after a box, launched sideways just above the ground, slides and settles for
    ``steps`` steps; wide friction smoothing keeps finite differences well conditioned."""
    model = box_on_ground(mode, gap=0.004, friction=friction, friction_smoothing=0.05, contact_stiffness=mu)
    solver = wc.ImplicitSolver(model, tolerance=1e-13)
    states = [model.state() for _ in range(steps + 1)]
    q0 = states[0].body_q.numpy()
    q0[1, 0] += start_x
    states[0].body_q.assign(q0)
    states[0].body_q_prev.assign(q0)
    vel = wp.array([[0.0, 0.0, 0.0], velocity], dtype=wp.vec3d, requires_grad=True)
    ang = wp.zeros(2, dtype=wp.vec3d, requires_grad=True)
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)

    def forward():
        wc.set_body_velocity(states[0], vel, ang, dt)
        for t in range(steps):
            solver.step(states[t], states[t + 1], None, dt)
        wp.launch(position_loss_kernel, dim=1, inputs=[states[-1].body_q, 1, wp.vec3d(1.0, 0.5, 0.2)], outputs=[loss])

    record(forward, tape)
    return dict(model=model, vel=vel, loss=loss, states=states, solver=solver)


@pytest.mark.parametrize("mode", ["sdrs", "ipc"])
def test_tape_gradients_with_baseline_friction_match_finite_differences(mode):
    """Exact gradients: the lagged normal forces, normals (sdrs) and ipctk's tangent bases and
    closest points (ipc) are differentiated by q^t, not held fixed."""
    v0 = np.array([0.3, 0.1, 0.0])
    mu, lam = STIFFNESS[mode], 0.5
    tape = wp.Tape()
    out = sliding_box(mode, velocity=v0, friction=lam, mu=mu, tape=tape)
    assert out["solver"].last_step.friction_pairs > 0
    tape.backward(out["loss"])
    loss = lambda **kw: sliding_box(mode, **{"velocity": v0, "friction": lam, "mu": mu, **kw})["loss"].numpy()[0]  # noqa: E731
    free = sliding_box(mode, velocity=v0, friction=0.0, mu=mu)["states"][-1].body_q.numpy()[1, 0]
    assert out["states"][-1].body_q.numpy()[1, 0] < free - 1e-3  # friction slows the slide
    # Central differences in mu are stable from steps of mu * 1e-3 (sdrs: 2e-9 from the tape
    # there, but 1e-5 at mu * 1e-5, where solver rounding dominates).
    assert_frictional_gradients(out, loss, body=1, velocity=v0, friction=lam, mu=mu, mu_step=1e-3)


def test_push_task_runs_the_sdrs_baseline_with_friction():
    scene = scenes.build_scene("push")
    assert scene.settings.friction > 0
    problem = TaskProblem(scene, model="sdrs", settings=TaskSettings(horizon=4, receding_horizon=0, iterations=1, learning_rate=scene.task.learning_rate))
    assert problem.model.contact.mode == "sdrs" and problem.model.friction.numpy()[0] == scene.settings.friction
    result = problem.optimize()
    assert len(result.loss_history) >= 1 and np.isfinite(result.final_loss)
    assert problem.solver.last_step.friction_pairs > 0


def test_without_friction_no_baseline_friction_work_is_done():
    for mode in ("sdrs", "ipc"):
        model = box_on_ground(mode, gap=0.004, friction=0.0)
        _, solver = rollout(model, 2, 0.02)
        assert solver.last_step.friction_pairs == 0
