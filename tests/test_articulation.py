"""Articulations in reduced coordinates: derivatives, physics, limits, the ant, gradients, bad input."""

import contextlib

import numpy as np
import pytest
import warp as wp

import warpcontact as wc
from warpcontact.articulation import joint_limit_energy
from warpcontact.kernels import task as task_kernels
from warpcontact.robots import add_ant
from warpcontact.scenes import ground_rectangle

# --- helpers ---------------------------------------------------------------------------------


def chain_model(**builder_options):
    """A base (x, y, z, yaw) carrying universal -> revolute -> ball -> prismatic links, a free
    sphere and a static triangle: every DOF kind, every joint kind."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0), **builder_options)
    base = b.add_box((0.4, 0.3, 0.1), mass=2.0, pose=(0, 0, 1.0, 0, 0, 0, 1), name="base")
    l1 = b.add_box((0.3, 0.06, 0.06), mass=0.5, pose=(0.42, 0, 1.0, 0, 0, 0, 1), name="l1")
    l2 = b.add_box((0.3, 0.06, 0.06), mass=0.5, pose=(0.78, 0, 1.0, 0, 0, 0, 1), name="l2")
    l3 = b.add_box((0.06, 0.06, 0.3), mass=0.5, pose=(0.78, 0, 0.78, 0, 0, 0, 1), name="l3")
    l4 = b.add_box((0.05, 0.05, 0.2), mass=0.3, pose=(0.78, 0, 0.52, 0, 0, 0, 1), name="l4")
    b.add_sphere(0.1, density=500.0, pose=(0.3, 0.5, 0.6, 0, 0, 0, 1), name="ball")
    b.add_body((np.array([[-2, -2, 0], [2, -2, 0], [0, 2, 0.0]]), np.array([[0, 1, 2]])), static=True, name="ground")
    b.add_joint("base", child=base, dofs=("x", "y", "z", "rz"))
    b.add_joint("universal", child=l1, parent=base, anchor=(0.23, 0, 1.0), axis=[(0, 0, 1), (0, 1, 0)])
    b.add_joint("revolute", child=l2, parent=l1, anchor=(0.6, 0, 1.0), axis=(0, 1, 0))
    b.add_joint("ball", child=l3, parent=l2, anchor=(0.78, 0, 0.95))
    b.add_joint("prismatic", child=l4, parent=l3, anchor=(0.78, 0, 0.62), axis=(0, 0, 1))
    return b.finalize()


def pendulum(length=1.0, angle=0.05, *, links=1, limits=None, kp=0.0, kd=0.0):
    """A chain of ``links`` thin rods hanging from a world hinge about y, the first at ``angle``."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    parent = None
    for i in range(links):
        rod = b.add_box((0.02, 0.02, length), mass=1.0, pose=(0, 0, -(i + 0.5) * length, 0, 0, 0, 1), name=f"rod{i}")
        b.add_joint("revolute", child=rod, parent=parent, anchor=(0, 0, -i * length), axis=(0, 1, 0), limits=limits, kp=kp, kd=kd, name=f"hinge{i}")
        parent = rod
    model = b.finalize()
    state = model.state(requires_grad=False)
    start = np.zeros(model.articulation.num_dofs)
    start[0] = angle
    q = model.articulation.retract(model.initial_q, start)
    for arr in (state.body_q, state.body_q_prev):
        arr.assign(q)
    for arr in (state.joint_q, state.joint_q_prev):
        arr.assign(model.articulation.initial_coordinates + start)
    return model, state


def simulate(model, state, steps, dt, control=None):
    solver = wc.ImplicitSolver(model)
    states = [state]
    for _ in range(steps):
        nxt = model.state(requires_grad=False)
        solver.step(states[-1], nxt, control, dt)
        states.append(nxt)
    return states, solver


def reduced_terms(model, q):
    art = model.articulation
    ev = model.contact.evaluate(q)
    _, grad, hess = art.reduce(q, ev.grad.reshape(-1), ev.hessian)
    return ev.value, grad, hess


# --- kinematics and derivatives ----------------------------------------------------------------


def test_reduced_gradient_and_hessian_match_finite_differences():
    model = chain_model()
    art = model.articulation
    assert art.num_dofs == 4 + 2 + 1 + 3 + 1 + 6
    rng = np.random.default_rng(0)
    q = art.retract(model.initial_q, 0.2 * rng.standard_normal(art.num_dofs))
    value, grad, hess = reduced_terms(model, q)
    m = art.num_dofs

    def f(delta):
        return model.contact.evaluate(art.retract(q, delta)).value

    h1, h2 = 1e-6, 1e-4
    fd_grad = np.array([(f(h1 * e) - f(-h1 * e)) / (2 * h1) for e in np.eye(m)])
    fd_hess = np.zeros((m, m))
    for k in range(m):
        for j in range(k, m):
            ek, ej = h2 * np.eye(m)[k], h2 * np.eye(m)[j]
            fd_hess[k, j] = fd_hess[j, k] = (f(ek + ej) - f(ek - ej) - f(ej - ek) + f(-ek - ej)) / (4 * h2 * h2)
    assert np.abs(fd_grad - grad).max() <= 1e-7 * np.abs(grad).max()
    assert np.abs(fd_hess - hess).max() <= 1e-4 * np.abs(hess).max()
    # The forward-kinematics curvature matters here (about 10% of the Hessian).
    curvature = art.curvature(q, model.contact.evaluate(q).grad)
    assert np.abs(fd_hess - (hess - curvature)).max() > 1e-2 * np.abs(hess).max()


def test_free_bodies_beside_joints_take_the_per_body_arithmetic_bit_for_bit():
    """Free bodies in a scene with joints elsewhere ("loose" bodies) are retracted and
    reduced together, not body by body and through dense products by their identity block
    (one hinge made a step over 16 free boxes 1.7x slower, a probe): the same poses, Jacobian
    and gradient, bit for bit, as the per-body loops, which the chain's bodies still take,
    and the same Hessian to BLAS's rounding of sums over fewer rows."""
    import copy

    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    base = b.add_box((0.4, 0.3, 0.1), mass=2.0, pose=(0, 0, 1.0, 0, 0, 0, 1), name="base")
    l1 = b.add_box((0.3, 0.06, 0.06), mass=0.5, pose=(0.42, 0, 1.0, 0, 0, 0, 1), name="l1")
    b.add_joint("base", child=base, dofs=("x", "y", "z", "rz"))
    b.add_joint("ball", child=l1, parent=base, anchor=(0.23, 0, 1.0))
    for i in range(5):
        b.add_box((0.2, 0.2, 0.2), density=300.0, pose=(2.0 + 0.5 * i, 0.3 * i, 0.5, 0, 0, 0, 1), name=f"box{i}")
    b.add_body((np.array([[-9, -9, 0], [9, -9, 0], [0, 9, 0.0]]), np.array([[0, 1, 2]])), static=True, name="ground")
    model = b.finalize()
    art = model.articulation
    assert list(art._loose_bodies) == [model.body_names.index(f"box{i}") for i in range(5)]
    loops = copy.copy(art)
    loops._loose_bodies, loops._joined_joints, loops._joined_bodies = np.zeros(0, dtype=np.int64), list(range(len(art.joints))), art.dynamic_bodies
    rng = np.random.default_rng(4)
    q = art.retract(model.initial_q, 0.3 * rng.standard_normal(art.num_dofs))
    assert np.array_equal(q, loops.retract(model.initial_q, 0.3 * np.random.default_rng(4).standard_normal(art.num_dofs)))
    step = rng.standard_normal(art.num_dofs)
    assert np.array_equal(art.retract(q, step), loops.retract(q, step))
    grad = rng.standard_normal(6 * model.num_bodies)
    hess = rng.standard_normal((6 * 7, 6 * 7))
    hess = hess + hess.T
    (J, reduced_grad, reduced_hess), (J_loops, grad_loops, hess_loops) = art.reduce(q, grad, hess), loops.reduce(q, grad, hess)
    assert np.array_equal(J, J_loops) and np.array_equal(reduced_grad, grad_loops)
    assert np.abs(reduced_hess - hess_loops).max() <= 4 * np.finfo(float).eps * np.abs(hess_loops).max()
    loose = art._loose_dofs.reshape(-1)
    assert np.array_equal(reduced_hess[np.ix_(loose, loose)], hess_loops[np.ix_(loose, loose)])


def test_a_turned_static_body_beside_joints_steps():
    """The articulated line search bounds the straight path to each trial pose; for a static
    body turned about a general axis that path held a rotation of rounding (1.4e-17), which
    the bound refuses from a static body, so every scene with joints and such a body (a tilted
    ramp, a turned wall) failed its first step (a probe, stop 63)."""
    hinge = {}
    for turn in ((0.0, 0.0, 0.0), (0.2, -0.3, 0.5)):
        b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
        b.add_box((1.0, 1.0, 0.1), static=True, pose=np.r_[5.0, 0.0, 0.0, wc.rotation.quat_from_rotation_vector(np.array(turn))], name="ramp")
        rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, 1.5, 0, 0, 0, 1), name="rod")
        b.add_joint("revolute", child=rod, anchor=(0, 0, 2.0), axis=(0, 1, 0), name="hinge")
        model = b.finalize()
        solver = wc.ImplicitSolver(model)
        state = model.state(requires_grad=False)
        state.body_q_prev.assign(model.articulation.retract(model.initial_q, np.array([-0.02])))
        for _ in range(5):
            following = model.state(requires_grad=False)
            solver.step(state, following, None, 0.01)
            state = following
        hinge[turn] = float(state.joint_q.numpy()[0])
    assert hinge[(0.2, -0.3, 0.5)] == pytest.approx(hinge[(0.0, 0.0, 0.0)], abs=1e-6)


def test_moving_a_joints_static_parent_is_refused():
    """A static parent's built pose is folded into the joint frame, so a post slid 5 mm a
    step by writing its pose left its arm hinged where it was built: the joint came 0.1 m
    apart over 20 accepted steps (a probe, stop 63). Refused, as for a dynamic parent."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    post = b.add_box((0.2, 0.2, 0.2), static=True, pose=(0, 0, 1.0, 0, 0, 0, 1), name="post")
    arm = b.add_box((0.6, 0.04, 0.04), mass=1.0, pose=(0.4, 0, 1.0, 0, 0, 0, 1), name="arm")
    b.add_joint("revolute", child=arm, parent=post, anchor=(0.1, 0, 1.0), axis=(0, 1, 0), kp=50.0, kd=1.0, name="hinge")
    model = b.finalize()
    solver = wc.ImplicitSolver(model)
    state = model.state(requires_grad=False)
    following = model.state(requires_grad=False)
    solver.step(state, following, None, 0.02)  # where it was built: steps
    for pose in (following.body_q, following.body_q_prev):
        q = pose.numpy()
        q[post, 1] += 0.005
        pose.assign(q)
    with pytest.raises(ValueError, match=r"joint 'hinge': its parent, static body 'post', is 0.005 m and 0 rad from where the joint was built"):
        solver.step(following, model.state(requires_grad=False), None, 0.02)


def test_free_bodies_have_identity_coordinates():
    b = wc.ModelBuilder()
    b.add_box((1, 1, 1), density=1.0, pose=(0, 0, 2, 0, 0, 0, 1))
    b.add_sphere(0.5, density=1.0)
    art = b.finalize().articulation
    assert art.identity and art.num_dofs == 12 and art.num_coordinates == 0


def test_retract_keeps_joints_together_and_coordinates_additive():
    model = chain_model()
    art = model.articulation
    rng = np.random.default_rng(1)
    q = model.initial_q
    coords = art.initial_coordinates.copy()
    for _ in range(50):
        step = 0.3 * rng.standard_normal(art.num_dofs)
        q = art.retract(q, step)
        coords += step[art.coordinate_dof]
    assert art.anchor_gaps(q).max() < 1e-13
    between = [c for c, name in enumerate(art.coordinate_names) if not name.startswith("joint0:")]
    wrapped = np.angle(np.exp(1j * (art.coordinates(q)[between] - coords[between])))
    assert np.abs(wrapped).max() < 1e-10


# --- physics ----------------------------------------------------------------------------------


def test_pendulum_small_angle_period():
    length, dt = 1.0, 0.01
    model, state = pendulum(length, 0.05)
    states, solver = simulate(model, state, 500, dt)
    angle = np.array([s.joint_q.numpy()[0] for s in states])
    downward = [i - angle[i] / (angle[i + 1] - angle[i]) for i in range(len(angle) - 1) if angle[i] > 0 >= angle[i + 1]]
    period = np.diff(downward).mean() * dt
    inertia = (length**2 + 0.02**2) / 12 + (length / 2) ** 2  # about the hinge, m = 1
    expected = 2 * np.pi * np.sqrt(inertia / (9.81 * length / 2))
    assert period == pytest.approx(expected, rel=0.01)
    assert solver.last_step.iterations <= 5


def mechanical_energy(model, q_prev, q_next, dt):
    """Kinetic (midpoint velocities) plus potential energy of the rods (m = 1 each)."""
    energy = 0.0
    rot_prev, rot_next = wc.rotation.quat_to_matrix(q_prev[:, 3:]), wc.rotation.quat_to_matrix(q_next[:, 3:])
    second = model.body_unit_second_moment.numpy()
    for b in range(model.num_bodies):
        v = (q_next[b, :3] - q_prev[b, :3]) / dt
        dr = (rot_next[b] - rot_prev[b]) / dt
        energy += 0.5 * v @ v + 0.5 * np.trace(dr @ second[b] @ dr.T)
        energy += 9.81 * 0.5 * (q_next[b, 2] + q_prev[b, 2])
    return energy


def test_double_pendulum_energy_bounded_and_joints_never_separate():
    dt = 0.01
    model, state = pendulum(0.5, 1.2, links=2)
    states, _ = simulate(model, state, 400, dt)
    q = np.array([s.body_q.numpy() for s in states])
    energy = np.array([mechanical_energy(model, q[t], q[t + 1], dt) for t in range(len(q) - 1)])
    rest = -9.81 * (0.25 + 0.75)  # both rods hanging straight down, at rest
    # The implicit (incremental-potential) step dissipates (here ~65% in 4 s at dt = 0.01)
    # and never gains energy.
    assert np.all(np.diff(energy) <= 1e-6 * (energy[0] - rest))
    assert energy.min() >= rest
    art = model.articulation
    assert max(art.anchor_gaps(qt).max() for qt in q) < 1e-12
    assert np.allclose(art.coordinates(q[-1]), states[-1].joint_q.numpy(), atol=1e-9)


def test_joint_limit_is_never_crossed():
    # Released from horizontal, the rod swings down into a limit at -0.3 rad from vertical.
    model, state = pendulum(1.0, np.pi / 2, limits=[(-0.3, 1.7)])
    states, _ = simulate(model, state, 150, 0.01)
    angles = np.array([s.joint_q.numpy()[0] for s in states])
    assert angles.min() > -0.3
    assert angles.min() < -0.25  # it did reach the barrier


def test_joint_pd_holds_target():
    model, state = pendulum(1.0, 0.0, kp=200.0, kd=20.0)
    control = model.control(requires_grad=False)
    control.joint_target.assign(np.array([0.4]))
    states, _ = simulate(model, state, 300, 0.01, control)
    # static equilibrium of a PD spring against gravity: kp (t - a) = m g l/2 sin(a)
    a = states[-1].joint_q.numpy()[0]
    assert 200.0 * (0.4 - a) == pytest.approx(9.81 * 0.5 * np.sin(a), rel=1e-3)


# --- the ant ----------------------------------------------------------------------------------


def ant_model(friction=0.5, friction_smoothing=1e-4):
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81), contact_stiffness=1e-6, friction=friction, friction_smoothing=friction_smoothing)
    ant = add_ant(b)
    ground = ground_rectangle(3.0, 3.0, cell=0.5)
    b.add_body((ground.vertices, ground.faces), static=True, name="ground")
    return b.finalize(), ant


def test_ant_layout_matches_the_paper():
    model, ant = ant_model()
    art = model.articulation
    assert len(ant["bodies"]) == 9
    assert art.num_dofs == 16 and art.num_coordinates == 16
    assert len(ant["actuated"]) == 12 and set(ant["actuated"]) <= set(art.coordinate_names)


def test_ant_stands_without_penetration_or_drift():
    model, ant = ant_model()
    states, solver = simulate(model, model.state(requires_grad=False), 500, 0.02, model.control(requires_grad=False))
    torso = ant["bodies"]["torso"]
    path = np.array([s.body_q.numpy()[torso, :3] for s in states])
    settled = path[100:]
    assert np.abs(settled - settled[0]).max() < 1e-3  # m over 400 steps (8 s)
    assert np.abs(path[:, :2] - path[0, :2]).max() < 1e-4
    feet = [ant["bodies"][f"lower{i}"] for i in range(4)]
    lowest = min(
        (wc.rotation.quat_rotate(s.body_q.numpy()[f, 3:], model.body_meshes[f][0]) + s.body_q.numpy()[f, :3])[:, 2].min() for s in states for f in feet
    )
    assert lowest > 0.0  # never below the ground plane
    assert solver.last_step.min_separation > 0.0
    assert model.articulation.anchor_gaps(states[-1].body_q.numpy()).max() < 1e-12


def test_ant_tape_gradient_of_sine_parameters_matches_finite_differences():
    # A wider friction smoothing and a tight solver tolerance keep the finite differences
    # themselves accurate to ~1e-6 (at 1e-4 m/s smoothing, sticking feet make the loss so
    # stiff that central differences scatter by ~1e-4).
    model, ant = ant_model(friction_smoothing=0.01)
    art = model.articulation
    actuated = np.array([art.coordinate_names.index(n) for n in ant["actuated"]], dtype=np.int32)
    torso = ant["bodies"]["torso"]
    dt, steps, waves = 0.02, 20, 2
    coordinate = wp.array(actuated, dtype=wp.int32)
    rest = wp.array(art.initial_coordinates, dtype=wp.float64)
    solver = wc.ImplicitSolver(model, tolerance=1e-13)
    goal = model.initial_q[torso, :3] + np.array([0.3, 0.1, 0.0])

    def loss_and_grad(values, gradient=True):
        params = wp.array(values, dtype=wp.float64, requires_grad=True)
        states = [model.state() for _ in range(steps + 1)]
        controls = [model.control() for _ in range(steps)]
        tape = wp.Tape()
        with tape:
            for f in range(steps):
                wp.launch(task_kernels.joint_sine_target_kernel, dim=len(actuated), inputs=[coordinate, rest, params, wp.float64((f + 1) * dt)], outputs=[controls[f].joint_target])
                solver.step(states[f], states[f + 1], controls[f], dt)
        position = states[-1].body_q.numpy()[torso, :3]
        loss = float(np.sum((position - goal) ** 2))
        if not gradient:
            return loss, None
        adj = np.zeros((model.num_bodies, 7))
        adj[torso, :3] = 2 * (position - goal)
        states[-1].body_q.grad.assign(adj)
        tape.backward()
        return loss, params.grad.numpy().copy()

    rng = np.random.default_rng(3)
    values = np.zeros((len(actuated), 3 * waves))
    values[:, 0::3] = 0.3 * rng.standard_normal((len(actuated), waves))
    values[:, 1::3] = 2 * np.pi * np.array([1.0, 2.0])
    values[:, 2::3] = rng.uniform(0, 2 * np.pi, (len(actuated), waves))
    loss, grad = loss_and_grad(values)
    assert np.abs(grad).max() > 0
    h = 1e-4
    for index in [(0, 0), (7, 2), (2, 5)]:
        plus, minus = values.copy(), values.copy()
        plus[index] += h
        minus[index] -= h
        fd = (loss_and_grad(plus, False)[0] - loss_and_grad(minus, False)[0]) / (2 * h)
        assert grad[index] == pytest.approx(fd, rel=1e-5, abs=1e-9 * np.abs(grad).max())


# --- bad input --------------------------------------------------------------------------------


def two_boxes():
    b = wc.ModelBuilder()
    a = b.add_box((0.2, 0.2, 0.2), density=100.0, pose=(0, 0, 1, 0, 0, 0, 1), name="a")
    c = b.add_box((0.2, 0.2, 0.2), density=100.0, pose=(0.5, 0, 1, 0, 0, 0, 1), name="c")
    return b, a, c


def test_a_joint_target_is_the_default_control_and_is_checked():
    """``add_joint(target=...)`` (a USD drive's targetPosition) is what Model.control() drives
    to: the pendulum settles where a control target of 0.4 rad took it; NaN keeps a
    coordinate's initial value."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    b.add_joint("revolute", child=rod, anchor=(0, 0, 0), axis=(0, 1, 0), kp=200.0, kd=20.0, target=0.4)
    model = b.finalize()
    np.testing.assert_array_equal(model.control(requires_grad=False).joint_target.numpy(), [0.4])
    states, _ = simulate(model, model.state(requires_grad=False), 300, 0.01, model.control(requires_grad=False))
    a = states[-1].joint_q.numpy()[0]
    assert 200.0 * (0.4 - a) == pytest.approx(9.81 * 0.5 * np.sin(a), rel=1e-3)
    b, a_body, c = two_boxes()
    b.add_joint("universal", child=a_body, anchor=(0, 0, 1.2), axis=[(1, 0, 0), (0, 1, 0)], target=[np.nan, 0.2])
    np.testing.assert_allclose(b.finalize().articulation.default_targets, [0.0, 0.2], atol=1e-12)
    # A coordinate without gains has no target: one of 1e160 was refused as an overflowing
    # energy of kp 0 (0 x inf), while 1e100 was taken.
    control = model.control(requires_grad=False)
    model.articulation.kp[:] = 0.0
    model.articulation.kd[:] = 0.0
    control.joint_target.assign(np.array([1e160]))
    free, _ = simulate(model, model.state(requires_grad=False), 3, 0.01, control)
    control.joint_target.assign(np.array([0.0]))
    held, _ = simulate(model, model.state(requires_grad=False), 3, 0.01, control)
    np.testing.assert_array_equal(free[-1].joint_q.numpy(), held[-1].joint_q.numpy())
    for kind, target, match in (("revolute", [0.1, 0.2], r"target needs 1 value, got shape \(2,\)"), ("revolute", np.inf, r"target must be finite"), ("ball", 0.1, r"ball joints have no coordinates to target")):
        b, a_body, c = two_boxes()
        with pytest.raises(ValueError, match=match):
            b.add_joint(kind, child=a_body, anchor=(0, 0, 1.2), axis=(0, 1, 0), target=target)


def test_bad_joints_get_clear_errors():
    b, a, c = two_boxes()
    with pytest.raises(ValueError, match="unknown joint type 'hinge'"):
        b.add_joint("hinge", child=a, anchor=(0, 0, 0), axis=(0, 0, 1))
    with pytest.raises(ValueError, match="zero length"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 0), axis=(0, 0, 0))
    # Its norm overflowed: the axis was stored as zero, a hinge that never turned.
    b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(1e300, 1e300, 0), name="huge")
    np.testing.assert_allclose(b.finalize().articulation.joints[0].axes[0], [np.sqrt(0.5), np.sqrt(0.5), 0.0], rtol=1e-15)
    b, a, c = two_boxes()
    with pytest.raises(ValueError, match="orthogonal"):
        b.add_joint("universal", child=a, anchor=(0, 0, 0), axis=[(0, 0, 1), (0, 1, 1)])
    with pytest.raises(ValueError, match="same body"):
        b.add_joint("revolute", child=a, parent=a, anchor=(0, 0, 0), axis=(0, 0, 1))
    with pytest.raises(ValueError, match="subset"):
        b.add_joint("base", child=a, dofs=("x", "q"))
    # Wrong counts used to surface as numpy reshape errors naming no joint.
    with pytest.raises(ValueError, match=r"joint 'tilted': expected 1 axis vector\(s\) of 3 values"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 0), axis=(0, 1, 0, 0), name="tilted")
    # Found by a tester: an anchor at 1e200 m was taken, and the hinged box never fell.
    with pytest.raises(ValueError, match=r"joint 'far': anchor: 1e\+200 at index \(0,\) is beyond the \+-1e\+150 m"):
        b.add_joint("revolute", child=a, anchor=(1e200, 0, 0), axis=(0, 1, 0), name="far")
    with pytest.raises(ValueError, match=r"joint 'far': child_frame position: -1e\+200 at index \(2,\) is beyond the \+-1e\+150 m"):
        b.add_joint("revolute", child=a, parent_frame=(0, 0, 0, 0, 0, 0, 1), child_frame=(0, 0, -1e200, 0, 0, 0, 1), axis=(0, 1, 0), name="far")
    with pytest.raises(ValueError, match="joint 'odd': limits must be 1 .lower, upper. pairs"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 0), axis=(0, 1, 0), limits=[0.0, 1.0, 2.0], name="odd")
    b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), name="first")
    with pytest.raises(ValueError, match="already has parent joint 'first'"):
        b.add_joint("ball", child=a, parent=c, anchor=(0.25, 0, 1))
    b.add_joint("revolute", child=c, parent=a, anchor=(0.25, 0, 1), axis=(0, 1, 0), name="first")
    with pytest.raises(ValueError, match=r"joint names must be unique; used more than once: \['first'\]"):
        b.finalize()
    b, a, c = two_boxes()
    b.add_box((0.2, 0.2, 0.2), density=100.0, pose=(2, 0, 1, 0, 0, 0, 1), name="a")
    with pytest.raises(ValueError, match=r"body names must be unique; used more than once: \['a'\]"):
        b.finalize()
    # Defaults skip the names given ("joint1" given, the next unnamed joint is "joint2", not
    # a duplicate), and an empty name, replaced by the default before, is refused.
    b, a, c = two_boxes()
    b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), name="joint1")
    b.add_joint("revolute", child=c, parent=a, anchor=(0.25, 0, 1), axis=(0, 1, 0))
    assert [joint.name for joint in b.finalize().articulation.joints] == ["joint1", "joint2"]
    with pytest.raises(ValueError, match=r"joint 0: name must not be empty, got ''"):
        two_boxes()[0].add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), name="")


def test_joint_cycle_is_refused():
    b, a, c = two_boxes()
    b.add_joint("revolute", child=a, parent=c, anchor=(0.25, 0, 1), axis=(0, 1, 0), name="j1")
    b.add_joint("revolute", child=c, parent=a, anchor=(0.25, 0, 1), axis=(0, 1, 0), name="j2")
    with pytest.raises(ValueError, match="cycle"):
        b.finalize()


def test_articulation_contact_modes_exclude_the_right_pairs_with_a_static_parent():
    """A static pedestal is a link of each arm hinged to it (a fixed robot base), but does not
    join the two arms into one articulation."""

    def pairs(mode):
        b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0), articulation_contact=mode)
        pedestal = b.add_box((0.2, 0.2, 0.2), static=True, name="pedestal", pose=(0, 0, 1.0, 0, 0, 0, 1))
        upper_left = b.add_box((0.3, 0.05, 0.05), mass=0.2, pose=(0.26, 0, 1.0, 0, 0, 0, 1), name="upper_left")
        lower_left = b.add_box((0.3, 0.05, 0.05), mass=0.2, pose=(0.58, 0, 1.0, 0, 0, 0, 1), name="lower_left")
        right = b.add_box((0.3, 0.05, 0.05), mass=0.2, pose=(-0.26, 0, 1.0, 0, 0, 0, 1), name="right")
        b.add_sphere(0.1, density=100.0, pose=(0, 0, 2.0, 0, 0, 0, 1), name="loose")
        b.add_joint("revolute", child=upper_left, parent=pedestal, anchor=(0.1, 0, 1.0), axis=(0, 1, 0))
        b.add_joint("revolute", child=lower_left, parent=upper_left, anchor=(0.42, 0, 1.0), axis=(0, 1, 0))
        b.add_joint("revolute", child=right, parent=pedestal, anchor=(-0.1, 0, 1.0), axis=(0, 1, 0))
        model = b.finalize()
        return {tuple(model.body_names[i] for i in pair) for pair in model.contact.body_pairs}

    every = {(a, b) for i, a in enumerate(["pedestal", "upper_left", "lower_left", "right", "loose"]) for b in ["pedestal", "upper_left", "lower_left", "right", "loose"][i + 1 :]}
    assert pairs("all") == every
    # Before 2026-11-26 a static parent was dropped with the world: its links touched it.
    assert pairs("nonadjacent") == every - {("pedestal", "upper_left"), ("upper_left", "lower_left"), ("pedestal", "right")}
    assert pairs("none") == every - {("pedestal", "upper_left"), ("pedestal", "lower_left"), ("upper_left", "lower_left"), ("pedestal", "right")}


def test_an_arm_hinged_to_a_static_block_swings_as_on_a_held_one():
    """The arm's inner corner sweeps into its parent block as it falls: a static parent used
    to hold it at 0.002 rad after 0.4 s."""

    def swing(static):
        b = wc.ModelBuilder()
        if static:
            block = b.add_box((0.2, 0.2, 0.2), static=True, name="block", pose=(0, 0, 1.0, 0, 0, 0, 1))
        else:
            block = b.add_box((0.2, 0.2, 0.2), mass=100.0, name="block", pose=(0, 0, 1.0, 0, 0, 0, 1))
            b.add_joint("base", child=block, dofs=("z",), kp=1e6, kd=1e3)
        arm = b.add_box((0.5, 0.05, 0.05), mass=0.2, pose=(0.351, 0, 1.0, 0, 0, 0, 1), name="arm")
        b.add_joint("revolute", child=arm, parent=block, anchor=(0.1, 0, 1.0), axis=(0, 1, 0), name="hinge")
        model = b.finalize()
        states, _ = simulate(model, model.state(requires_grad=False), 40, 0.01, model.control(requires_grad=False))
        return states[-1].joint_q.numpy()[-1]

    held, fixed = swing(False), swing(True)
    assert held > 1.5
    assert fixed == pytest.approx(held, abs=2e-3)


def test_violated_joint_and_limits_are_refused():
    b, a, c = two_boxes()
    frame = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    b.add_joint("revolute", child=c, parent=a, parent_frame=(0.25, 0, 0, 0, 0, 0, 1), child_frame=frame, axis=(0, 1, 0), name="apart")
    with pytest.raises(ValueError, match="'apart'.*0.25 m apart"):
        b.finalize()
    b, a, c = two_boxes()
    b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), limits=[(0.1, 0.5)], name="limited")
    with pytest.raises(ValueError, match="limited:0.*not strictly inside"):
        b.finalize()


def test_a_state_outside_the_joint_limits_is_refused_naming_the_coordinate():
    """It used to reach the solver as 'objective is not finite at the start pose'."""
    model, state = pendulum(angle=1.5, limits=[(-1.0, 1.0)])
    nxt = model.state(requires_grad=False)
    before = nxt.joint_q.numpy().copy()
    with pytest.raises(ValueError, match=r"state_in.joint_q: coordinate 'hinge0:0' = 1.5 is not strictly inside its limits \(-1, 1\)"):
        wc.ImplicitSolver(model).step(state, nxt, None, 0.01)
    np.testing.assert_array_equal(nxt.joint_q.numpy(), before)


def test_a_state_whose_coordinates_disagree_with_its_poses_is_refused():
    """The step reads poses for contact and coordinates for drives and limits: a hinge whose
    joint_q said 0.5 rad while its rod hung at 0 was driven and limited as if at 0.5, and the
    output state disagreed with itself. Angles agree modulo 2 pi."""
    model, state = pendulum(angle=0.3, limits=[(-10.0, 10.0)])
    solver = wc.ImplicitSolver(model)
    nxt = model.state(requires_grad=False)
    before = nxt.joint_q.numpy().copy()
    state.joint_q.assign(np.array([0.5]))
    with pytest.raises(ValueError, match=r"state_in: joint 'hinge0' \(world -> rod0\): state_in.joint_q gives it \[0.5\] but state_in.body_q puts it at \[0.3\]"):
        solver.step(state, nxt, None, 0.01)
    np.testing.assert_array_equal(nxt.joint_q.numpy(), before)
    state.joint_q.assign(np.array([0.3 + 2 * np.pi]))  # one more turn: the same configuration
    solver.step(state, nxt, None, 0.01)
    assert nxt.joint_q.numpy()[0] == pytest.approx(0.3 + 2 * np.pi, abs=1e-3)
    # A prismatic coordinate, and poses that break a joint.
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    slider = b.add_box((0.1, 0.1, 0.1), mass=1.0, name="slider")
    b.add_joint("prismatic", child=slider, anchor=(0, 0, 0), axis=(1, 0, 0), name="rail")
    model = b.finalize()
    state = model.state(requires_grad=False)
    state.joint_q.assign(np.array([0.2]))
    with pytest.raises(ValueError, match=r"joint 'rail' .*joint_q gives it \[0.2\] but state_in.body_q puts it at \[0.\]"):
        wc.ImplicitSolver(model).step(state, model.state(), None, 0.01)
    state = model.state(requires_grad=False)
    state.body_q.assign(np.array([[0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match=r"joint 'rail' .*state_in.body_q violate the prismatic joint \(off-axis offset 0.3 m, relative rotation 0 rad; it allows neither\)"):
        wc.ImplicitSolver(model).step(state, model.state(), None, 0.01)
    # A turn alone was reported as "off-axis offset 0 m or relative rotation" (a probe).
    state = model.state(requires_grad=False)
    state.body_q.assign(np.array([[0.0, 0.0, 0.0, 0.0, 0.0, np.sin(0.2), np.cos(0.2)]]))
    with pytest.raises(ValueError, match=r"violate the prismatic joint \(off-axis offset 0 m, relative rotation 0.4 rad; it allows neither\)"):
        wc.ImplicitSolver(model).step(state, model.state(), None, 0.01)


def test_joint_limit_barrier_derivatives_match_finite_differences():
    """Value, gradient and Hessian of the limit barrier at both limits, deep in the margin and
    just inside its edge, against central differences; zero beyond the margin, +inf past a limit."""
    lower, upper = np.array([-1.0, -0.5, 0.0]), np.array([1.0, 0.5, 2.0])
    margin, stiffness = np.array([0.1, 0.05, 0.3]), np.array([2.0, 50.0, 0.7])
    q = np.array([0.999, -0.46, 0.2999])  # near the upper limit, the lower one, the margin's edge
    value, grad, hess = joint_limit_energy(q, lower, upper, margin, stiffness)
    assert np.all(value > 0)
    h = 1e-7
    plus = joint_limit_energy(q + h, lower, upper, margin, stiffness)
    minus = joint_limit_energy(q - h, lower, upper, margin, stiffness)
    np.testing.assert_allclose(grad, (plus[0] - minus[0]) / (2 * h), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(hess, (plus[1] - minus[1]) / (2 * h), rtol=1e-6, atol=1e-9)
    assert grad[0] > 0 > grad[1]  # pushed away from each limit
    clear = joint_limit_energy(np.array([0.5, 0.0, 1.0]), lower, upper, margin, stiffness)
    assert all(np.all(part == 0.0) for part in clear)
    assert np.all(np.isinf(joint_limit_energy(np.array([1.0, 0.0, 1.0]), lower, upper, margin, stiffness)[0]))


def test_start_state_gradient_along_a_consistent_perturbation_matches_finite_differences():
    """body_q, body_q_prev and joint_q hold one configuration; their adjoints together give the
    derivative along a perturbation of all three (a double pendulum with PD and a limit). The
    shoulder starts inside its limit's margin and is driven past the limit, so the limit's
    barrier acts in every step (a start at 0.4 rad never reached it, and a 10% error in the
    barrier's Hessian passed)."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    upper = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="upper")
    lower = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -1.5, 0, 0, 0, 1), name="lower")
    b.add_joint("revolute", child=upper, anchor=(0, 0, 0), axis=(0, 1, 0), kp=30.0, kd=3.0, limits=[(-1.0, 1.0)], name="shoulder")
    b.add_joint("revolute", child=lower, parent=upper, anchor=(0, 0, -1.0), axis=(0, 1, 0), kp=5.0, kd=0.5, name="elbow")
    model = b.finalize()
    art = model.articulation
    solver = wc.ImplicitSolver(model, tolerance=1e-13)
    weights = np.array([[0.3, 0.0, -0.7], [1.1, 0.0, 0.4]])
    angles = np.array([0.95, -0.3])

    def rollout(delta, tape=None):
        state = model.state()
        q = art.retract(model.initial_q, delta)
        for arr in (state.body_q, state.body_q_prev):
            arr.assign(q)
        for arr in (state.joint_q, state.joint_q_prev):
            arr.assign(art.initial_coordinates + delta)
        states = [state] + [model.state() for _ in range(6)]
        control = model.control()
        control.joint_target.assign([1.4, 0.0])
        with tape or contextlib.nullcontext():
            for t in range(6):
                solver.step(states[t], states[t + 1], control, 0.01)
        return states

    tape = wp.Tape()
    states = rollout(angles, tape)
    shoulder = np.array([s.joint_q.numpy()[0] for s in states])
    assert np.all(shoulder > art.upper[0] - art.limit_margins()[0]) and np.all(shoulder < art.upper[0])
    adjoint = np.zeros((2, 7))
    adjoint[:, :3] = weights
    states[-1].body_q.grad.assign(adjoint)
    tape.backward()
    start = states[0]
    h = 1e-6
    for i in range(2):
        e = np.zeros(2)
        e[i] = h
        fd = (np.sum(weights * rollout(angles + e)[-1].body_q.numpy()[:, :3]) - np.sum(weights * rollout(angles - e)[-1].body_q.numpy()[:, :3])) / (2 * h)
        pose_change = (art.retract(model.initial_q, angles + e) - art.retract(model.initial_q, angles - e)) / (2 * h)
        taped = np.sum((start.body_q.grad.numpy() + start.body_q_prev.grad.numpy()) * pose_change) + (start.joint_q.grad.numpy()[i] + start.joint_q_prev.grad.numpy()[i])
        assert taped == pytest.approx(fd, rel=1e-8)


def test_joint_arrays_of_the_wrong_kind_and_overflowing_targets_get_named_errors():
    model, state = pendulum(kp=50.0)
    solver = wc.ImplicitSolver(model)
    control = model.control(requires_grad=False)
    # A numpy array used to raise AttributeError: 'numpy.ndarray' object has no attribute 'numpy'.
    with pytest.raises(ValueError, match="control.joint_target: expected a float64 wp.array of 1 joint targets .* got ndarray"):
        solver.step(state, model.state(), wc.Control(control.body_target, joint_target=np.array([0.3])), 0.01)
    with pytest.raises(ValueError, match=r"control.joint_target: expected a float64 wp.array of 1 joint targets .* got int32 array of shape \(1,\)"):
        solver.step(state, model.state(), wc.Control(control.body_target, joint_target=wp.array([0], dtype=wp.int32)), 0.01)
    with pytest.raises(ValueError, match="state_in.joint_q: expected a float64 wp.array"):
        solver.step(wc.State(state.body_q, state.body_q_prev, np.array([0.05]), state.joint_q_prev), model.state(), None, 0.01)
    # An int32 output stored the coordinate truncated to 0, silently; nothing is written now.
    out = model.state()
    out.joint_q = wp.zeros(1, dtype=wp.int32)
    before = out.body_q.numpy().copy()
    with pytest.raises(ValueError, match="state_out.joint_q: expected a float64 wp.array of the model's 1 joint coordinates"):
        solver.step(state, out, None, 0.01)
    np.testing.assert_array_equal(out.body_q.numpy(), before)
    # A finite target whose PD energy overflows was blamed on leaf plane searches of no pair.
    control.joint_target.assign(np.array([1e160]))
    with pytest.raises(ValueError, match=r"control.joint_target: the PD energy of coordinate 'hinge0:0' overflows float64 \(target 1e\+160"):
        solver.step(state, model.state(), control, 0.01)


def test_static_child_and_missing_joint_state_are_refused():
    b = wc.ModelBuilder()
    s = b.add_box((1, 1, 0.1), static=True, name="floor")
    with pytest.raises(ValueError, match="static"):
        b.add_joint("revolute", child=s, anchor=(0, 0, 0), axis=(0, 0, 1))
    model, state = pendulum()
    broken = wc.State(body_q=state.body_q, body_q_prev=state.body_q_prev)
    with pytest.raises(ValueError, match="joint coordinates"):
        wc.ImplicitSolver(model).step(broken, model.state(), None, 0.01)


def ball_pendulum(swing, *, cone=0.3, **options):
    """A rod hanging from a world ball joint with a swing (cone) limit about the vertical,
    started at ``swing`` rad about x; ``options`` go to ``add_joint``."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    b.add_joint("ball", child=rod, anchor=(0, 0, 0), axis=(0, 0, 1), cone_limit=cone, name="shoulder", **options)
    model = b.finalize()
    q = model.articulation.retract(model.initial_q, np.array([swing, 0.0, 0.0]))
    return model, q


def test_ball_joint_cone_barrier_derivatives_match_finite_differences():
    model, q = ball_pendulum(0.27)
    art = model.articulation
    q = art.retract(q, np.array([0.0, 0.02, 0.05]))  # off-plane, with twist
    value, grad, hess = art.cone_terms(q)
    assert value > 0  # inside the barrier's margin (0.03 rad)

    def f(delta):
        return art.cone_terms(art.retract(q, delta))[0]

    h1, h2, eye = 1e-7, 1e-5, np.eye(3)
    fd_grad = np.array([(f(h1 * e) - f(-h1 * e)) / (2 * h1) for e in eye])
    fd_hess = np.array([[(f(h2 * (ek + ej)) - f(h2 * (ek - ej)) - f(h2 * (ej - ek)) + f(-h2 * (ek + ej))) / (4 * h2 * h2) for ej in eye] for ek in eye])
    assert np.abs(fd_grad - grad).max() <= 1e-6 * np.abs(grad).max()
    assert np.abs(fd_hess - hess).max() <= 1e-4 * np.abs(hess).max()


def test_a_ball_joint_s_cone_barrier_takes_the_given_margin_and_stiffness():
    """Both used to be replaced: the margin by a tenth of the limit, silently."""
    for options, active, value in (({}, False, None), ({"limit_margin": 0.25}, True, None), ({"limit_margin": 0.25, "limit_stiffness": 3.0}, True, 3.0)):
        model, q = ball_pendulum(0.1, **options)
        energy = model.articulation.cone_terms(q)[0]
        assert (energy > 0) == active
        if value:
            assert energy == pytest.approx(value * ball_pendulum(0.1, limit_margin=0.25)[0].articulation.cone_terms(q)[0], rel=1e-12)


def test_ball_joint_swing_never_crosses_its_cone_limit():
    model, q = ball_pendulum(0.2)
    state = model.state(requires_grad=False)
    state.body_q.assign(q)
    state.body_q_prev.assign(model.articulation.retract(q, np.array([-0.04, 0.01, 0.0])))  # swinging outwards
    states, _ = simulate(model, state, 60, 0.01)
    cone = model.articulation.cones[0]
    swings = [model.articulation._cone_angle(cone, s.body_q.numpy())[0] for s in states]
    assert max(swings) < 0.3
    assert max(swings) > 0.27  # it reached the barrier
    assert max(model.articulation.anchor_gaps(s.body_q.numpy()).max() for s in states) < 1e-12


def test_a_rod_whirling_along_its_cone_rim_takes_ordinary_newton_steps():
    # The step bound charged all of the child axis's motion |w x a_c| against the room to the
    # limit, also motion along the rim that opens no swing: at 12 rad/s Newton stalled (no
    # convergence after 500 iterations at step 5).
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_box((0.03, 0.03, 1.0), mass=1.0, pose=(0, 0, -0.52, 0, 0, 0, 1), name="rod")
    b.add_joint("ball", child=rod, anchor=(0, 0, -0.02), axis=(0, 0, -1), cone_limit=0.4, name="b")
    model = b.finalize()
    art = model.articulation
    dt, spin = 0.01, 12.0
    tilted = art.retract(model.initial_q, np.array([0.35, 0.0, 0.0]))
    state = model.state(requires_grad=False)
    state.body_q.assign(tilted)
    state.body_q_prev.assign(art.retract(tilted, np.array([0.0, 0.0, -spin * dt])))
    solver = wc.ImplicitSolver(model)
    swings, iterations = [], []
    for _ in range(30):
        nxt = model.state(requires_grad=False)
        solver.step(state, nxt, None, dt)
        state = nxt
        iterations.append(solver.last_step.iterations)
        swings.append(art._cone_angle(art.cones[0], state.body_q.numpy())[0])
    assert max(swings) < 0.4 and max(swings) > 0.399  # on the rim, never past it
    assert max(iterations) <= 40


def test_hinge_angles_start_on_the_turn_inside_their_limits():
    # Poses give angles in (-pi, pi]: a hinge posed at 3.5 rad read as -2.78 and was refused
    # by its own limits (3, 4).
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    turn = wc.rotation.quat_from_rotation_vector(np.array([0.0, 3.5, 0.0]))
    centre = wc.rotation.quat_rotate(turn, np.array([0.0, 0.0, -0.5]))
    rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(*centre, *turn), name="rod")
    b.add_joint("revolute", child=rod, parent_frame=(0, 0, 0, 0, 0, 0, 1), child_frame=(0, 0, 0.5, 0, 0, 0, 1), axis=(0, 1, 0), limits=[(3.0, 4.0)], name="h")
    model = b.finalize()
    art = model.articulation
    assert art.initial_coordinates[0] == pytest.approx(3.5) and art.default_targets[0] == pytest.approx(3.5)
    states, _ = simulate(model, model.state(requires_grad=False), 40, 0.01)  # gravity swings it away from upright, into its stop at 4
    angles = [s.joint_q.numpy()[0] for s in states]
    assert min(angles) > 3.49 and 3.9 < max(angles) < 4.0


def test_a_joint_s_tolerance_is_its_own_bodies_size():
    # The anchor tolerance was 1e-6 of the scene's largest body: a 2 km ground let a hinge
    # whose anchors stood 1 mm apart load.
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_body((np.array([[-1e3, -1e3, 0], [1e3, -1e3, 0], [0, 1e3, 0.0]]), np.array([[0, 1, 2]])), static=True, name="ground")
    rod = b.add_box((0.05, 0.05, 1.0), mass=1.0, pose=(0, 0, 1.5, 0, 0, 0, 1), name="rod")
    b.add_joint("revolute", child=rod, parent_frame=(0, 0, 2.001, 0, 0, 0, 1), child_frame=(0, 0, 0.5, 0, 0, 0, 1), axis=(0, 1, 0), name="h")
    with pytest.raises(ValueError, match="joint 'h' \\(world -> rod\\): joint anchors are 0.001 m apart"):
        b.finalize()


def test_bad_joint_options_are_named():
    b, a, c = two_boxes()
    for options, match in (
        (dict(kind="base", child=a, dofs=("ry",), anchor=(0, 0, 0)), "a base joint moves its body along world axes through its centre of mass; anchor do not apply"),
        (dict(kind="revolute", child=a, parent=True, anchor=(0, 0, 1.2), axis=(0, 1, 0)), "parent must be a body index in \\[0, 2\\) or None, got True"),
        (dict(kind="revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), kp="10"), "kp must be numbers, got '10'"),
        (dict(kind="revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), name=5), "name must be a string, got 5"),
        (dict(kind="ball", child=a, anchor=(0, 0, 1.2), cone_limit=np.array([0.5, 0.6])), "cone_limit must be in \\(0, pi\\) rad"),
    ):
        with pytest.raises(ValueError, match=match):
            b.add_joint(**options)


def test_a_base_joint_on_a_static_parent_is_refused():
    """It was taken, and the body's contact with that parent dropped as a joint's own: a box
    on a base joint "from" the floor fell through it (0.6 m below after 0.4 s)."""
    b = wc.ModelBuilder()
    floor = b.add_box((2.0, 2.0, 0.2), static=True, pose=(0, 0, -0.1, 0, 0, 0, 1), name="floor")
    box = b.add_box((0.2, 0.2, 0.2), density=100.0, pose=(0, 0, 0.11, 0, 0, 0, 1), name="box")
    with pytest.raises(ValueError, match=r"a base joint connects a body to the world \(parent None\)"):
        b.add_joint("base", child=box, parent=floor, dofs=("x", "y", "z"))


@wp.kernel
def _first_body_x_kernel(q: wp.array(dtype=wp.transformd), loss: wp.array(dtype=wp.float64)):
    loss[0] = wp.transform_get_translation(q[0])[0]


@pytest.mark.parametrize("kind", ["revolute", "ball"])
def test_a_recorded_step_s_backward_uses_the_joint_gains_it_stepped_with(kind):
    """Gains changed after recording: the backward read the joints' gains when it ran (a ball
    joint's target gradient 13x off)."""

    def gradients(change):
        b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
        arm = b.add_box((0.05, 0.05, 0.5), density=800.0, pose=(0, 0, 1.0, 0, 0, 0, 1))
        if kind == "ball":
            b.add_joint("ball", child=arm, anchor=(0, 0, 1.25), kp=5.0, kd=0.5)
        else:
            b.add_joint("revolute", child=arm, anchor=(0, 0, 1.25), axis=(0, 1, 0), kp=5.0, kd=0.5)
        model = b.finalize()
        art, solver = model.articulation, wc.ImplicitSolver(model)
        states = [model.state() for _ in range(3)]
        control = model.control()
        target = control.ball_target if kind == "ball" else control.joint_target
        target.assign([[0.0, np.sin(0.15), 0.0, np.cos(0.15)]] if kind == "ball" else [0.3])
        loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        tape = wp.Tape()
        with tape:
            solver.step(states[0], states[1], control, 0.02)
            solver.step(states[1], states[2], control, 0.02)
            wp.launch(_first_body_x_kernel, dim=1, inputs=[states[2].body_q], outputs=[loss])
        if change:
            for gains in ((art.ball_kp, art.ball_kd) if kind == "ball" else (art.kp, art.kd)):
                gains *= 10.0
        tape.backward(loss)
        return target.grad.numpy().copy(), states[0].body_q.grad.numpy().copy()

    for kept, changed in zip(gradients(False), gradients(True)):
        assert np.abs(kept).max() > 0
        np.testing.assert_array_equal(changed, kept)


def test_bad_cone_limits_are_refused():
    b, a, c = two_boxes()
    with pytest.raises(ValueError, match="cone_limit only applies to ball joints"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), cone_limit=0.5)
    with pytest.raises(ValueError, match=r"cone_limit must be in \(0, pi\)"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), cone_limit=4.0)
    with pytest.raises(ValueError, match="no coordinate limits"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), limits=[(-1.0, 1.0)])
    # The cone barrier's stiffness and margin were not checked, and a given margin was ignored:
    # NaN or 0 ran 500 Newton iterations to "no convergence", -1 pulled the rod onto the limit.
    for value in (np.nan, 0.0, -1.0):
        with pytest.raises(ValueError, match="joint 'cone': limit_stiffness must be finite and positive"):
            b.add_joint("ball", child=a, anchor=(0, 0, 1.2), cone_limit=0.5, limit_stiffness=value, name="cone")
        with pytest.raises(ValueError, match="joint 'cone': limit_margin must be finite and positive"):
            b.add_joint("ball", child=a, anchor=(0, 0, 1.2), cone_limit=0.5, limit_margin=value, name="cone")
    with pytest.raises(ValueError, match="joint 'free': limit_margin applies to a ball joint's cone_limit, and it has none"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), limit_margin=0.1, name="free")
    model_builder = wc.ModelBuilder()
    rod = model_builder.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    tilt = (0.0, np.sin(0.5), 0.0, np.cos(0.5))  # the child's joint frame turned by 1 rad about y
    model_builder.add_joint("ball", child=rod, parent_frame=(0, 0, 0, 0, 0, 0, 1), child_frame=(0, 0, 0.5, *tilt), axis=(1, 0, 0), cone_limit=0.5, name="tilted")
    with pytest.raises(ValueError, match="'tilted'.*not strictly inside its cone limit"):
        model_builder.finalize()



@pytest.mark.parametrize("swing", [1.2, 1.25])
def test_a_state_swung_onto_or_past_a_cone_limit_is_refused_naming_the_joint(swing):
    """Found by a probe: a ball joint's start swing at or past its cone limit made the start's
    energy infinite, and the step blamed dt, the inertia and gravity. A revolute coordinate
    outside its limits was already refused by name."""
    model = _hanging_rod("ball", axis=(0, 0, -1), cone_limit=1.2)
    state = model.state(requires_grad=False)
    q = model.articulation.retract(model.initial_q, np.array([0.0, swing, 0.0]))
    state.body_q.assign(q)
    state.body_q_prev.assign(q)
    with pytest.raises(ValueError, match=rf"state_in.body_q: joint 'hinge' \(world -> rod\): swing {swing:g} rad is not strictly inside its cone limit 1.2 rad"):
        wc.ImplicitSolver(model).step(state, model.state(requires_grad=False), None, 0.01)


# --- ball-joint drives --------------------------------------------------------------------------


def driven_ball_chain(kp=3.0, kd=0.5, *, gravity=(0.0, 0.0, -9.81)):
    """A box on an undriven world ball joint carrying a rod on a driven ball joint."""
    b = wc.ModelBuilder(gravity=gravity)
    base = b.add_box((0.2, 0.2, 0.2), mass=1.0, pose=(0, 0, 0.2, 0, 0, 0, 1), name="base")
    rod = b.add_box((0.3, 0.1, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    b.add_joint("ball", child=base, anchor=(0, 0, 0.3), name="top")
    b.add_joint("ball", child=rod, parent=base, anchor=(0, 0, 0), kp=kp, kd=kd, name="shoulder")
    return b.finalize()


def left_jacobian(phi):
    """d exp(phi + eta) = exp(J_l(phi) eta) exp(phi) to first order (series near zero)."""
    angle = np.linalg.norm(phi)
    K = wc.rotation.skew(phi)
    half_sine = np.sin(0.5 * angle) / angle if angle > 1e-4 else 0.5 - angle**2 / 48.0
    cubic = (angle - np.sin(angle)) / angle**3 if angle > 1e-2 else 1.0 / 6.0 - angle**2 / 120.0
    return np.eye(3) + 2.0 * half_sine**2 * K + cubic * K @ K  # (1 - cos a)/a^2 = 2 (sin(a/2)/a)^2


def turned(q, angle, axis):
    """Quaternion(s) ``q`` turned on the left by ``angle`` about ``axis``."""
    axis = np.asarray(axis, dtype=np.float64)
    return wc.rotation.quat_mul(wc.rotation.quat_from_rotation_vector(angle * axis / np.linalg.norm(axis)), q)


@pytest.mark.parametrize("case", ["generic", "at_target", "near_half_turn", "half_turn"])
def test_ball_drive_derivatives_match_finite_differences(case):
    model = driven_ball_chain()
    art = model.articulation
    rng = np.random.default_rng(4)
    q = art.retract(model.initial_q, rng.standard_normal(art.num_dofs))
    start = art.ball_rotations(art.retract(q, 0.05 * rng.standard_normal(art.num_dofs)))
    now = art.ball_rotations(q)
    dt = 0.01
    target = {
        "generic": wc.rotation.quat_from_rotation_vector(rng.standard_normal((2, 3))),
        "at_target": now,
        "near_half_turn": turned(now, np.pi - 1e-3, (0.3, 0.2, 1.0)),
        "half_turn": turned(now, np.pi, (0.3, 0.2, 1.0)),
    }[case]
    if case != "generic":
        art.ball_kd[:] = 0.0  # the target alone sets the gradient: zero at the target and half a turn from it
    dofs = art.joint_dofs[art.ball_joint_names.index("shoulder")]

    def terms(w):
        delta = np.zeros(art.num_dofs)
        delta[dofs] = w
        value, grad, hess = art.ball_drive_terms(art.retract(q, delta), target, start, dt)
        return value, grad[dofs], hess[np.ix_(dofs, dofs)]

    value, grad, hess = terms(np.zeros(3))
    h, eye = 1e-5, np.eye(3)
    fd_grad = np.array([(terms(h * e)[0] - terms(-h * e)[0]) / (2 * h) for e in eye])
    # The gradient is taken in a chart re-centred at each pose; in the chart at q it is
    # J_l(w)^T times that, whose differences give the Hessian.
    fd_hess = np.array([(left_jacobian(h * e).T @ terms(h * e)[1] - left_jacobian(-h * e).T @ terms(-h * e)[1]) / (2 * h) for e in eye])
    scale = np.abs(hess).max()
    assert np.abs(fd_grad - grad).max() <= 1e-6 * max(np.abs(grad).max(), 1e-3 * scale)
    assert np.abs(fd_hess - hess).max() <= 1e-6 * scale
    if case == "at_target":
        assert value < 1e-30 and np.abs(grad).max() < 1e-14
        np.testing.assert_allclose(hess, 3.0 * eye, atol=1e-12)  # kp I: a hinge PD's stiffness in every direction
    if case == "half_turn":
        assert value == pytest.approx(2 * 3.0) and np.abs(grad).max() < 1e-12


def test_ball_drive_adjoint_matches_finite_differences():
    model = driven_ball_chain()
    art = model.articulation
    rng = np.random.default_rng(5)
    q = art.retract(model.initial_q, rng.standard_normal(art.num_dofs))
    q_start = art.retract(q, 0.1 * rng.standard_normal(art.num_dofs))
    target = wc.rotation.quat_from_rotation_vector(rng.standard_normal((2, 3)))
    lam = rng.standard_normal(art.num_dofs)
    dt = 0.01
    target_adjoint, start_adjoint = art.ball_drive_adjoint(q, q_start, lam, target, dt)

    def contracted(target, q_start):
        return lam @ art.ball_drive_terms(q, target, art.ball_rotations(q_start), dt)[1]

    def turn_target(i, w):
        out = target.copy()
        out[i] = turned(target[i], np.linalg.norm(w), w)
        return out

    def turn_body(b, w):
        out = q_start.copy()
        out[b, 3:] = turned(q_start[b, 3:], np.linalg.norm(w), w)
        return out

    h, eye = 1e-6, np.eye(3)
    fd_target = np.array([[(contracted(turn_target(i, h * e), q_start) - contracted(turn_target(i, -h * e), q_start)) / (2 * h) for e in eye] for i in range(2)])
    fd_start = np.array([[(contracted(target, turn_body(b, h * e)) - contracted(target, turn_body(b, -h * e))) / (2 * h) for e in eye] for b in range(2)])
    assert np.abs(fd_target - target_adjoint).max() <= 1e-7 * np.abs(target_adjoint).max()
    assert np.abs(fd_start - start_adjoint[:, 3:]).max() <= 1e-7 * np.abs(start_adjoint).max()
    assert np.abs(start_adjoint[:, :3]).max() == 0.0  # relative rotations do not depend on positions


def ball_rod(*, gravity, kp=20.0, kd=2.0):
    """A wide rod hanging from a driven world ball joint (twist changes its vertices)."""
    b = wc.ModelBuilder(gravity=gravity)
    rod = b.add_box((0.3, 0.1, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    b.add_joint("ball", child=rod, anchor=(0, 0, 0), kp=kp, kd=kd, name="shoulder")
    return b.finalize()


def rotation_angle(a, b):
    """Angles (rad) of the rotations between quaternion arrays a and b."""
    return np.linalg.norm(wc.rotation.rotation_vector_from_quat(wc.rotation.quat_mul(wc.rotation.quat_conjugate(a), b)), axis=-1)


def test_ball_drive_settles_at_its_target():
    model = ball_rod(gravity=(0.0, 0.0, 0.0))
    control = model.control(requires_grad=False)
    target = turned(model.articulation.initial_ball_rotations, 1.0, (1.0, 0.5, 0.3))  # swing and twist
    control.ball_target.assign(target)
    states, solver = simulate(model, model.state(requires_grad=False), 300, 0.01, control)
    error = rotation_angle(target, model.articulation.ball_rotations(states[-1].body_q.numpy()))[0]
    assert error < 1e-4  # measured 2.2e-5 rad after 3 s from 1 rad
    assert solver.last_step.iterations <= 3


def test_ball_drive_torque_is_kp_sine_against_gravity():
    # Target 0.4 rad about x: the static equilibrium of kp (1 - cos) against gravity is
    # kp sin(0.4 - a) = m g l/2 sin(a), the hinge PD's balance with sin for the error.
    model = ball_rod(gravity=(0.0, 0.0, -9.81))
    control = model.control(requires_grad=False)
    control.ball_target.assign(turned(model.articulation.initial_ball_rotations, 0.4, (1.0, 0.0, 0.0)))
    states, _ = simulate(model, model.state(requires_grad=False), 300, 0.01, control)
    swing = wc.rotation.rotation_vector_from_quat(model.articulation.ball_rotations(states[-1].body_q.numpy()))[0]
    assert np.abs(swing[1:]).max() < 1e-9
    assert 20.0 * np.sin(0.4 - swing[0]) == pytest.approx(9.81 * 0.5 * np.sin(swing[0]), rel=1e-3)


def test_ball_target_tape_gradient_matches_finite_differences():
    model = ball_rod(gravity=(0.0, 0.0, -9.81), kp=5.0, kd=0.5)
    art = model.articulation
    solver = wc.ImplicitSolver(model, tolerance=1e-13)
    dt, steps = 0.02, 15
    goal = np.array([0.2, -0.1, -0.4, 0.3, 0.1, 0.2, 0.9])
    start = model.state(requires_grad=False)
    start.body_q_prev.assign(art.retract(model.initial_q, np.array([0.02, -0.03, 0.01])))  # moving

    def loss_and_grad(target, gradient=True):
        control = model.control()
        control.ball_target.assign(target)
        states = [model.state() for _ in range(steps + 1)]
        states[0].body_q.assign(start.body_q.numpy())
        states[0].body_q_prev.assign(start.body_q_prev.numpy())
        tape = wp.Tape()
        with tape:
            for f in range(steps):
                solver.step(states[f], states[f + 1], control, dt)
        pose = states[-1].body_q.numpy()[0]
        loss = float(np.sum((pose - goal) ** 2))
        if not gradient:
            return loss, None
        states[-1].body_q.grad.assign((2 * (pose - goal))[None])
        tape.backward()
        return loss, control.ball_target.grad.numpy()[0].copy()

    target = turned(art.initial_ball_rotations, 0.7, (0.5, 1.0, 0.2))
    _, grad = loss_and_grad(target)
    h = 1e-5
    for axis in np.eye(3):
        # along a left turn of the target, whose quaternion moves by 1/2 (axis, 0) q*
        direction = 0.5 * wc.rotation.quat_mul(np.r_[axis, 0.0], target[0])
        fd = (loss_and_grad(turned(target, h, axis), False)[0] - loss_and_grad(turned(target, -h, axis), False)[0]) / (2 * h)
        assert grad @ direction == pytest.approx(fd, rel=1e-5, abs=1e-7 * np.abs(grad).max())
    assert abs(grad @ target[0]) < 1e-12 * np.abs(grad).max()  # a target's norm does not matter
    # A target off the unit sphere (an optimiser's step leaves it) is normalised, as body
    # targets are: the same motion, and the gradient of the normalisation, 1/|q| of the unit
    # target's (it refused norms 3e-6 off 1, a probe, stop 62).
    scale = 1.3
    loss_unit, _ = loss_and_grad(target, False)
    loss_scaled, grad_scaled = loss_and_grad(scale * target)
    assert loss_scaled == pytest.approx(loss_unit, rel=1e-12)
    np.testing.assert_allclose(grad_scaled, grad / scale, rtol=1e-9, atol=1e-12 * np.abs(grad).max())
    direction = np.array([0.3, -0.2, 0.5, 0.1])
    fd = (loss_and_grad(scale * target + h * direction, False)[0] - loss_and_grad(scale * target - h * direction, False)[0]) / (2 * h)
    assert grad_scaled @ direction == pytest.approx(fd, rel=1e-5, abs=1e-7 * np.abs(grad).max())


@pytest.mark.parametrize("kind", ["revolute", "ball"])
def test_a_step_without_targets_holds_driven_joints_at_their_start_in_the_gradient(kind):
    # Without a control a joint's PD target is where the step starts; the backward dropped the
    # target's dependence on that start: gradients 37% (revolute) to 95% (ball) off.
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    arm = b.add_box((0.05, 0.05, 0.5), density=800.0, name="arm", pose=(0, 0, 1.0, 0, 0, 0, 1))
    if kind == "revolute":
        b.add_joint("revolute", child=arm, anchor=(0, 0, 1.25), axis=(0, 1, 0), kp=5.0, kd=0.1)
    else:
        b.add_joint("ball", child=arm, anchor=(0, 0, 1.25), kp=5.0, kd=0.1)
    model = b.finalize()
    solver = wc.ImplicitSolver(model, tolerance=1e-13)
    dt, steps = 0.02, 8
    weights = np.random.default_rng(0).normal(size=7)

    def loss_and_grad(spin, gradient=True):
        states = [model.state() for _ in range(steps + 1)]
        angular = wp.array([spin], dtype=wp.vec3d, requires_grad=True)
        tape = wp.Tape()
        with tape:
            wc.set_body_velocity(states[0], wp.zeros(1, dtype=wp.vec3d, requires_grad=True), angular, dt)
            for f in range(steps):
                solver.step(states[f], states[f + 1], None, dt)
        loss = float(states[-1].body_q.numpy()[0] @ weights)
        if gradient:
            states[-1].body_q.grad.assign(weights[None])
            tape.backward()
        return loss, angular.grad.numpy()[0].copy()

    spin = np.array([0.3, 1.5, 0.2])
    _, grad = loss_and_grad(spin)
    h = 1e-6
    for i in range(3):
        e = np.eye(3)[i]
        fd = (loss_and_grad(spin + h * e, False)[0] - loss_and_grad(spin - h * e, False)[0]) / (2 * h)
        assert grad[i] == pytest.approx(fd, rel=1e-4, abs=1e-4 * np.abs(grad).max())


def test_bad_ball_drives_are_refused():
    b, a, c = two_boxes()
    with pytest.raises(ValueError, match="kp must be finite and >= 0"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), kp=-1.0)
    with pytest.raises(ValueError, match="one kp and one kd"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), kp=[1.0, 2.0, 3.0])
    model = ball_rod(gravity=(0.0, 0.0, -9.81))
    solver = wc.ImplicitSolver(model)
    state = model.state(requires_grad=False)
    control = model.control(requires_grad=False)
    control.ball_target = wp.array(np.array([[0.0, 0.0, 0.0, 1.0]] * 2), dtype=wp.quatd)
    with pytest.raises(ValueError, match=r"control.ball_target: expected a wp.array of 1 wp.quatd .*\['shoulder'\].*shape \(2,\)"):
        solver.step(state, model.state(), control, 0.01)
    control.ball_target = wp.array(np.array([0.0, 0.0, 0.0, 1.0]), dtype=wp.float64)
    with pytest.raises(ValueError, match="control.ball_target: expected .*float64"):
        solver.step(state, model.state(), control, 0.01)
    # Normalised like body targets (test_ball_target_tape_gradient_matches_finite_differences),
    # within the same norms.
    control.ball_target = wp.array(np.array([[0.0, 0.0, 0.0, 0.0]]), dtype=wp.quatd)
    with pytest.raises(ValueError, match="control.ball_target: the target of ball joint 'shoulder' \\(index 0\\) has a zero rotation quaternion"):
        solver.step(state, model.state(), control, 0.01)
    control.ball_target = wp.array(np.array([[0.0, 0.0, 0.0, 1e200]]), dtype=wp.quatd)
    with pytest.raises(ValueError, match="control.ball_target: the target of ball joint 'shoulder' \\(index 0\\) has a rotation quaternion of norm 1e\\+200; expected a norm in"):
        solver.step(state, model.state(), control, 0.01)
    control.ball_target = wp.array(np.array([[0.0, np.nan, 0.0, 1.0]]), dtype=wp.quatd)
    with pytest.raises(ValueError, match=r"control.ball_target: the target of ball joint 'shoulder' is \[0.0, nan, 0.0, 1.0\]; expected a finite rotation quaternion"):
        solver.step(state, model.state(), control, 0.01)


def test_non_finite_joint_targets_and_coordinates_are_refused_naming_the_coordinate():
    """Found by a probe: a NaN in control.joint_target (one of the ant's 16) said only
    "expected 16 finite joint targets", and a NaN in state_in.joint_q "contains non-finite
    values", naming neither the coordinate nor the value, where a body target's names its body."""
    model, state = pendulum(links=2, kp=50.0)
    solver = wc.ImplicitSolver(model)
    control = model.control(requires_grad=False)
    control.joint_target.assign(np.array([0.1, np.nan]))
    with pytest.raises(ValueError, match=r"control.joint_target: the target of coordinate 'hinge1:0' is nan; expected 2 finite joint targets"):
        solver.step(state, model.state(requires_grad=False), control, 0.01)
    control.joint_target = wp.array([0.1, 0.2, 0.3], dtype=wp.float64)
    with pytest.raises(ValueError, match=r"control.joint_target: expected 2 finite joint targets, got shape \(3,\)"):
        solver.step(state, model.state(requires_grad=False), control, 0.01)
    state.joint_q.assign(np.array([np.inf, 0.0]))
    with pytest.raises(ValueError, match=r"state_in.joint_q: coordinate 'hinge0:0' is inf; expected finite values"):
        solver.step(state, model.state(requires_grad=False), None, 0.01)


def test_base_joint_settings_follow_the_dofs_as_given():
    """Coordinates run x, y, z, rx, ry, rz whatever order dofs lists them in; the limits, gains
    and targets stayed in the given order: dofs ("rz", "x") put rz's 0.1 rad limit, gain and
    target on x."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    slider = b.add_box((0.2, 0.2, 0.2), density=500.0, name="slider", pose=(0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
    b.add_joint("base", child=slider, dofs=("rz", "x"), limits=[(-0.1, 0.1), (-5.0, 5.0)], kp=[1.0, 50.0], kd=[0.1, 5.0], target=[0.05, 2.0], name="b")
    # A string was split into letters: "xyz" taken as three translations, "rz" refused as ('r', 'z') (a probe).
    other = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    free = other.add_box((0.2, 0.2, 0.2), density=500.0, name="free")
    for text in ("xyz", "rz"):
        with pytest.raises(ValueError, match=rf"dofs must be a sequence of names from .*, such as \('x', 'rz'\), got the string '{text}'"):
            other.add_joint("base", child=free, dofs=text)
    art = b.finalize().articulation
    assert art.coordinate_names == ["b:x", "b:rz"]
    np.testing.assert_array_equal(art.lower, [-5.0, -0.1])
    np.testing.assert_array_equal(art.kp, [50.0, 1.0])
    np.testing.assert_array_equal(art.kd, [5.0, 0.1])
    np.testing.assert_array_equal(art.default_targets, [2.0, 0.05])
    # Three free rotations own no coordinates: the values are the translations', as listed
    # (the reordering raised an IndexError for every base with three rotations).
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    free = b.add_box((0.2, 0.2, 0.2), density=500.0, name="free", pose=(0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
    b.add_joint("base", child=free, dofs=("rz", "z", "ry", "x", "rx", "y"), limits=[(-3.0, 3.0), (-1.0, 1.0), (-2.0, 2.0)], name="f")
    art = b.finalize().articulation
    assert art.coordinate_names == ["f:x", "f:y", "f:z"]
    np.testing.assert_array_equal(art.lower, [-1.0, -2.0, -3.0])


def test_links_of_one_chain_folding_fast_are_not_refused_as_passing_through():
    """Links move along joint arcs: a 3-link chain (articulation_contact="all") driven to fold
    was refused at dt 0.02 ("'l1' and 'l2' pass through each other") though its joint path
    is contact-free; only the straight (position, rotation) path cuts them."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0), articulation_contact="all")
    length = 0.3
    link = b.add_box((length, 0.05, 0.05), density=500.0, name="l0", pose=(0.01 + length / 2, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
    b.add_joint("revolute", child=link, anchor=(0.0, 0.0, 1.0), axis=(0.0, 0.0, 1.0), kp=1e3, kd=10.0, name="j0")
    for i in (1, 2):
        x0 = i * (length + 0.02)
        child = b.add_box((length, 0.05, 0.05), density=500.0, name=f"l{i}", pose=(x0 + 0.01 + length / 2, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
        b.add_joint("revolute", child=child, parent=link, anchor=(x0, 0.0, 1.0), axis=(0.0, 0.0, 1.0), kp=50.0, kd=1.0, limits=[(-3.0, 3.0)], name=f"j{i}")
        link = child
    model = b.finalize()
    control = model.control()
    control.joint_target.assign(np.array([0.0, 2.9, 2.9]))
    out = model.state()
    wc.ImplicitSolver(model).step(model.state(), out, control, 0.02)
    assert model.contact.evaluate(out.body_q.numpy()).ok and out.joint_q.numpy()[2] > 0.1


def test_a_hinged_link_swinging_through_a_ball_in_one_step_is_refused():
    """Found by a probe: a paddle hinged at one end (kp 1e6, target 3 rad, dt 0.01) turned
    3 rad in one step through a ball lying on its arc at 1 rad, and the step succeeded: the
    Newton iterates carried the ball around and back, and the pass-through check followed
    the paddle's centre straight, across the arc's chord, which misses the ball. Followed
    along the joint, the ball's centre crosses the paddle ~1 rad in."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0), contact_stiffness=1e-6)
    paddle = b.add_box((1.0, 0.05, 0.05), mass=1.0, pose=(0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), name="paddle")
    b.add_joint("revolute", child=paddle, anchor=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0), kp=1e6, name="hinge")
    b.add_sphere(0.1, density=100.0, pose=(0.9 * np.cos(1.0), 0.9 * np.sin(1.0), 0.0, 0.0, 0.0, 0.0, 1.0), name="ball")
    model = b.finalize()
    control = model.control(requires_grad=False)
    control.joint_target.assign([3.0])
    with pytest.raises(wc.SolverError, match=r"'paddle' and 'ball' pass through each other: moving along their joints to this step's solution, 'ball''s centre of mass crosses 'paddle''s surface at 3\d% of it"):
        wc.ImplicitSolver(model).step(model.state(requires_grad=False), model.state(requires_grad=False), control, 0.01)
    control.joint_target.assign([0.5])  # short of the ball: a step like any other
    out = model.state(requires_grad=False)
    wc.ImplicitSolver(model).step(model.state(requires_grad=False), out, control, 0.01)
    assert 0.1 < out.joint_q.numpy()[0] < 0.6


def test_step_between_is_what_retract_takes_from_one_configuration_to_another():
    """The joint-space step between two states of the ant (a base joint, hinged legs), a
    free box and a ball joint, which ``retract`` turns back into the second state's poses to
    rounding."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81), contact_stiffness=1e-6)
    add_ant(b)
    ground = ground_rectangle(6.0, 6.0)
    b.add_body((ground.vertices, ground.faces), static=True, name="ground")
    b.add_box((0.2, 0.2, 0.2), density=300.0, pose=(-2.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0), name="free")
    top = b.add_box((0.1, 0.1, 0.4), density=300.0, pose=(2.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), name="top")
    swing = b.add_box((0.1, 0.1, 0.4), density=300.0, pose=(2.0, 0.0, 0.55, 0.0, 0.0, 0.0, 1.0), name="swing")
    b.add_joint("revolute", child=top, anchor=(2.0, 0.0, 1.2), axis=(0.0, 1.0, 0.0), name="hang")
    b.add_joint("ball", child=swing, parent=top, anchor=(2.0, 0.0, 0.78), name="ball")
    model = b.finalize()
    art = model.articulation
    rng = np.random.default_rng(3)
    start = model.state(requires_grad=False)
    velocity = np.zeros((model.num_bodies, 3))
    spin = rng.normal(size=(model.num_bodies, 3))
    wc.set_body_velocity(start, wp.array(velocity, dtype=wp.vec3d), wp.array(spin, dtype=wp.vec3d), 0.04, body_names=model.body_names)
    states = [start]
    solver = wc.ImplicitSolver(model)
    for _ in range(3):
        states.append(model.state(requires_grad=False))
        solver.step(states[-2], states[-1], None, 0.04)
    for before, after in zip(states[:-1], states[1:]):
        q_from, q_to = before.body_q.numpy(), after.body_q.numpy()
        step = art.step_between(q_from, q_to, before.joint_q.numpy(), after.joint_q.numpy())
        assert np.abs(step).max() > 1e-3
        back = art.retract(q_from, step)
        np.testing.assert_allclose(back[:, :3], q_to[:, :3], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", back[:, 3:], q_to[:, 3:])), 1.0, rtol=0, atol=1e-12)


def test_a_base_joint_state_that_disagrees_with_its_poses_is_refused():
    """Found by a probe: a box on an ("x", "z") base moved 0.5 m up in body_q with its
    coordinates left at 0 stayed up there, outside its z limits, and a y shift or a tilt
    the joint cannot make was taken; a hinge's were refused. A base's coordinates are its
    centre's offsets along world axes and its turns about them."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    box = b.add_box((0.2, 0.2, 0.2), mass=1.0, pose=(0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), name="box")
    b.add_joint("base", child=box, dofs=("x", "z", "rz"), limits=[(-0.1, 0.1), (-0.1, 0.1), (-1.0, 1.0)], name="slide")
    model = b.finalize()
    solver = wc.ImplicitSolver(model)
    turned = [0.0, 0.0, np.sin(0.2), np.cos(0.2)]  # 0.4 rad about z
    for change, coordinates, message in (
        ((2, 1.5), [0.0, 0.0, 0.0], r"joint 'slide' \(world -> box\): state_in.joint_q gives z 0 but state_in.body_q moves its centre of mass 0.5 m along z"),
        ((1, 0.3), [0.0, 0.0, 0.0], r"joint 'slide' \(world -> box\): it has no y but state_in.body_q moves its centre of mass 0.3 m along y"),
        ((3, [np.sin(0.25), 0.0, 0.0, np.cos(0.25)]), [0.0, 0.0, 0.0], r"state_in.joint_q gives turns rz 0 but state_in.body_q turns it 0.5 rad"),
        ((3, turned), [0.0, 0.0, 0.4], None),  # the same turn in both: a state like any other
    ):
        state = model.state(requires_grad=False)
        q = state.body_q.numpy().copy()
        index, value = change
        q[0, index if index < 3 else slice(3, 7)] = value
        state.body_q.assign(q)
        state.body_q_prev.assign(q)
        state.joint_q.assign(coordinates)
        state.joint_q_prev.assign(coordinates)
        if message is None:
            solver.step(state, model.state(requires_grad=False), None, 0.01)
        else:
            with pytest.raises(ValueError, match=message):
                solver.step(state, model.state(requires_grad=False), None, 0.01)


def test_joint_order_is_topological_for_long_chains_added_leaf_first():
    """Joints are ordered parent first whatever order they were added in; the recursive
    walk overflowed Python's stack on a chain of ~1,000 joints added leaf first."""
    links = 1050
    builder = wc.ModelBuilder(articulation_contact="none", contact_stiffness=1e-9)
    bodies = [builder.add_box((0.02, 0.02, 0.08), mass=0.1, pose=(0, 0, -0.1 * i - 0.05, 0, 0, 0, 1), name=f"l{i}") for i in range(links)]
    for i in reversed(range(links)):
        builder.add_joint("revolute", child=bodies[i], parent=bodies[i - 1] if i else None, anchor=(0, 0, -0.1 * i), axis=(0, 1, 0), name=f"j{i}")
    art = builder.finalize().articulation
    assert [joint.name for joint in art.joints] == [f"j{i}" for i in range(links)]


def test_the_ant_is_built_only_in_a_z_up_builder():
    """In a Y-up builder the ant was built Z-up all the same, standing in its floor, and only
    "bodies intersect or touch" was said."""
    with pytest.raises(ValueError, match=r"add_ant builds the ant Z-up .*this builder's gravity is \[0.0, -9.81, 0.0\], not along -z"):
        add_ant(wc.ModelBuilder(gravity=(0.0, -9.81, 0.0)))
    add_ant(wc.ModelBuilder(gravity=(0.0, 0.0, 0.0)))  # no up at all: nothing to disagree with


# --- gains and limits changed after finalize ----------------------------------------------------


def _hanging_rod(kind, **joint_options):
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    axis = {"axis": (0, 1, 0)} if kind == "revolute" else {}
    b.add_joint(kind, child=rod, anchor=(0, 0, 0), name="hinge", **axis, **joint_options)
    return b.finalize()


def _stepped(model, state, steps, control=None):
    """``state`` after ``steps`` of 0.01 s, and the first joint coordinate after each."""
    solver, coordinates = wc.ImplicitSolver(model), []
    for _ in range(steps):
        following = model.state(requires_grad=False)
        solver.step(state, following, control, 0.01)
        state = following
        coordinates.append(state.joint_q.numpy()[0] if model.num_joint_coordinates else np.nan)
    return state, coordinates


def _settled_angle(model, steps=200):
    """The rod's angle from the start after ``steps`` of 0.01 s towards 0.5 rad about y."""
    art = model.articulation
    control = model.control(requires_grad=False)
    if art.num_ball_joints:
        control.ball_target.assign([[0.0, np.sin(0.25), 0.0, np.cos(0.25)]])
    else:
        control.joint_target.assign([0.5])
    state, _ = _stepped(model, model.state(requires_grad=False), steps, control)
    turn = art.ball_rotations(state.body_q.numpy())[0] if art.num_ball_joints else None
    return 2.0 * np.arctan2(np.linalg.norm(turn[:3]), turn[3]) if turn is not None else state.joint_q.numpy()[0]


@pytest.mark.parametrize("kind", ["ball", "revolute"])
def test_drives_set_after_finalize_act_as_if_built(kind):
    """Gains set after finalize on a joint built without them were ignored for ball joints
    (the rod stayed at 0 rad, frozen by a flag computed at finalize); they now drive it as
    gains given to add_joint do, to the same digits."""
    built = _settled_angle(_hanging_rod(kind, kp=20.0, kd=2.0))
    model = _hanging_rod(kind)
    gains = (model.articulation.ball_kp, model.articulation.ball_kd) if kind == "ball" else (model.articulation.kp, model.articulation.kd)
    gains[0][:], gains[1][:] = 20.0, 2.0
    assert abs(built - 0.5) < 1e-2
    assert _settled_angle(model) == built


def test_limits_set_after_finalize_hold():
    """Limits set after finalize on a hinge built without any were not enforced: it crossed
    0.2 rad (0.2091) before the next step refused its state."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    b.add_joint("revolute", child=rod, anchor=(0, 0, 0), axis=(0, 1, 0))
    model = b.finalize()
    art = model.articulation
    art.lower[:], art.upper[:], art.limit_margin[:] = -0.2, 0.2, 0.02
    state = model.state(requires_grad=False)
    start = np.array([0.15])
    poses = art.retract(model.initial_q, start)
    state.body_q.assign(poses)
    state.body_q_prev.assign(art.retract(poses, np.array([-0.03])))  # swinging towards +0.2 at 3 rad/s
    state.joint_q.assign(start)
    _, angles = _stepped(model, state, 50)
    assert 0.19 < max(angles) < 0.2


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m.articulation.kp.__setitem__(slice(None), -50.0), r"model.articulation.kp: 'hinge:0' has -50.0; gains must be finite and >= 0"),
        (lambda m: m.articulation.kd.__setitem__(slice(None), np.nan), r"model.articulation.kd: 'hinge:0' has nan"),
        (lambda m: setattr(m.articulation, "kp", np.array([1.0, 2.0])), r"model.articulation.kp: expected a float numpy array of shape \(1,\)"),
        (lambda m: (m.articulation.lower.__setitem__(0, 0.3), m.articulation.upper.__setitem__(0, -0.3)), r"model.articulation.lower, upper: 'hinge:0' has limits \[0.3, -0.3\]"),
        (lambda m: (m.articulation.lower.__setitem__(0, -0.3), m.articulation.limit_margin.__setitem__(0, 0.0)), r"model.articulation.limit_margin: 'hinge:0' has 0.0"),
        (lambda m: m.body_kp_linear.assign([[-1.0, 0.0, 0.0]]), r"model.body_kp_linear: body 'rod' has \[-1.0, 0.0, 0.0\]; PD gains must be finite and >= 0"),
        (lambda m: m.body_kd_angular.assign([np.inf]), r"model.body_kd_angular: body 'rod' has \[inf\]"),
    ],
)
def test_gains_and_limits_changed_after_finalize_are_checked(change, message):
    """A negative kp set after finalize put energy in (a hinge driven to 0.01 rad spun to
    -31.5 rad in 1 s) and a negative body gain likewise; every step now checks the gains and
    limits a user may change."""
    model = _hanging_rod("revolute", kp=50.0, kd=1.0)
    change(model)
    with pytest.raises(ValueError, match=message):
        wc.ImplicitSolver(model).step(model.state(), model.state(), model.control(), 0.01)


def test_base_joint_free_rotation_takes_no_drive():
    """A base joint's three rotations are one rotation vector without coordinates: a single kp,
    kd or target was spread over the translations alone (none with only the rotations), the
    rotation left undriven without a word."""
    for dofs, option in ((("rx", "ry", "rz"), {"kp": 50.0}), (("rx", "ry", "rz"), {"target": 0.3}), (("x", "y", "z", "rx", "ry", "rz"), {"kd": 5.0})):
        b, a, _ = two_boxes()
        with pytest.raises(ValueError, match="joint 'free': a base joint's three free rotations have no coordinates"):
            b.add_joint("base", child=a, dofs=dofs, name="free", **option)
    b, a, _ = two_boxes()
    b.add_joint("base", child=a, dofs=("x", "y", "z", "rx", "ry", "rz"), kp=[50.0, 50.0, 60.0], kd=0.0)
    np.testing.assert_array_equal(b.finalize().articulation.kp, [50.0, 50.0, 60.0])


def test_limit_margin_without_limits_is_refused():
    b, a, _ = two_boxes()
    with pytest.raises(ValueError, match="joint 'hinge': limit_margin applies to limits, and it has none"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), limit_margin=0.05, name="hinge")
    # Found by a probe: a stiffness where nothing is limited was taken and ignored.
    with pytest.raises(ValueError, match="joint 'hinge': limit_stiffness applies to limits, and it has none"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), limit_stiffness=50.0, name="hinge")
    with pytest.raises(ValueError, match="joint 'ball': limit_stiffness applies to a ball joint's cone_limit, and it has none"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), limit_stiffness=50.0, name="ball")
    # Found by a tester: a ball joint's axis is its cone's, and without one it was ignored.
    with pytest.raises(ValueError, match=r"joint 'ball': axis applies to a ball joint's cone_limit \(the swing limit's axis\), and it has none"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), axis=(0, 0, 1), name="ball")


def _hanging_hinge(limits=None):
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0), name="rod")
    b.add_joint("revolute", child=rod, anchor=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0), kd=0.5, limits=limits, name="hinge")
    return b.finalize()


def test_limits_set_after_finalize_get_the_default_margin_of_their_range():
    """Found by a probe: limits (-0.05, 0.15) set after finalize on a hinge built without any
    kept the unlimited coordinate's margin, 0.1 rad, not a tenth of the range as given to
    add_joint: the same rod, hanging from the same limits, swung differently (after 300 steps
    it rested at 0.0127 rad instead of 0). The default margin now follows the range at each
    step."""
    built, later = _hanging_hinge([(-0.05, 0.15)]), _hanging_hinge()
    later.articulation.lower[:], later.articulation.upper[:] = -0.05, 0.15
    np.testing.assert_array_equal(built.articulation.limit_margins(), [0.1 * 0.2])
    np.testing.assert_array_equal(later.articulation.limit_margins(), built.articulation.limit_margins())
    rests = []
    for model in (built, later):
        solver, state = wc.ImplicitSolver(model), model.state(requires_grad=False)
        state.joint_q.assign([0.001])
        state.body_q.assign(model.articulation.retract(state.body_q.numpy(), np.array([0.001])))
        for _ in range(40):
            following = model.state(requires_grad=False)
            solver.step(state, following, None, 0.01)
            state = following
        rests.append(state.joint_q.numpy()[0])
    assert rests[0] == rests[1]  # 0.0193 rad, still swinging after 0.4 s (before: 0.0193 and 0.0278)


def test_a_limit_margin_over_half_the_range_is_refused():
    """Found by a probe: a margin of 0.5 on a 0.2 rad range was taken, and the barrier then
    acted across the whole range (the hanging rod rested at 0.047 rad instead of 0); a cone's
    margin past its limit acts at zero swing (found by a review)."""
    b, a, _ = two_boxes()
    with pytest.raises(ValueError, match=r"joint 'hinge': limit_margin 0.5 exceeds half the range of coordinate 0, 0.1"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), limits=[(-0.05, 0.15)], limit_margin=0.5, name="hinge")
    with pytest.raises(ValueError, match=r"joint 'cone': limit_margin 0.5 exceeds the cone limit, 0.3"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), cone_limit=0.3, limit_margin=0.5, name="cone")
    model = _hanging_hinge([(-0.05, 0.15)])
    model.articulation.limit_margin[:] = 0.15
    with pytest.raises(ValueError, match=r"model.articulation.limit_margin: 'hinge:0' has 0.15, more than half its range \[-0.05, 0.15\]"):
        wc.ImplicitSolver(model).step(model.state(), model.state(), None, 0.01)


def test_limits_too_narrow_for_the_barrier_are_refused():
    """Found by a tester: limits of +-1e-200 rad (default margin 2e-201) were taken, and the
    step ended in a NaN: the limit barrier squares the distance to the limit within its
    margin, which underflows below 1e-150. The range (or cone limit) must leave a margin of
    at least that, and a coordinate must start that far inside its limits (a hinge at 0 with
    limits (-1e-200, 1) stayed at 0, its barrier's Hessian infinite; found by a review);
    1e-148 is taken. A margin given too small is named as such (a first version blamed the
    limits)."""
    b, a, _ = two_boxes()
    with pytest.raises(ValueError, match=r"joint 'hinge': coordinate 0's limits \[-1e-200, 1e-200\]: its limit barrier's default margin, a tenth of the range or cone limit, is 2e-201, below 1e-150"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), limits=(-1e-200, 1e-200), name="hinge")
    with pytest.raises(ValueError, match=r"joint 'hinge': coordinate 0's limits \[-1.0, 1.0\]: limit_margin 1e-160 is below 1e-150, where the barrier's square"):
        b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), limits=(-1.0, 1.0), limit_margin=1e-160, name="hinge")
    with pytest.raises(ValueError, match=r"joint 'cone': cone_limit 1e-200: its limit barrier's default margin, .* is 1e-201, below 1e-150"):
        b.add_joint("ball", child=a, anchor=(0, 0, 1.2), cone_limit=1e-200, name="cone")
    b.add_joint("revolute", child=a, anchor=(0, 0, 1.2), axis=(0, 1, 0), limits=(-1e-148, 1e-148), name="hinge")
    model = _hanging_hinge([(-0.05, 0.15)])
    model.articulation.lower[:], model.articulation.upper[:] = -1e-200, 1e-200  # set after finalize
    with pytest.raises(ValueError, match=r"model.articulation.lower, upper, limit_margin: 'hinge:0' has limits \[-1e-200, 1e-200\]: its limit barrier's default margin, .* is 2e-201"):
        wc.ImplicitSolver(model).step(model.state(), model.state(), None, 0.01)
    model = _hanging_hinge([(-1e-200, 1.0)])
    with pytest.raises(ValueError, match=r"state_in.joint_q: coordinate 'hinge:0' = 0 is within 1e-150 of its limits \(-1e-200, 1\), where the limit barrier's square of the distance underflows"):
        wc.ImplicitSolver(model).step(model.state(), model.state(), None, 0.01)


def test_joint_targets_for_a_model_without_joint_coordinates_are_refused():
    """Targets for coordinates the model does not have were ignored (a ball-only model)."""
    model = _hanging_rod("ball")
    control = model.control()
    control.joint_target = wp.array([0.3, 0.4, 0.5], dtype=wp.float64)
    with pytest.raises(ValueError, match=r"control.joint_target: this model has no joint coordinates; expected None or model.control\(\)'s empty array, got float64 array of shape \(3,\)"):
        wc.ImplicitSolver(model).step(model.state(), model.state(), control, 0.01)
    wc.ImplicitSolver(model).step(model.state(), model.state(), model.control(), 0.01)


@pytest.mark.parametrize("name", ["joint_q", "joint_q_prev"])
def test_joint_coordinates_for_a_model_without_them_are_refused(name):
    """Coordinates given to a model without joint coordinates were ignored (a probe, stop 64)."""
    model = _hanging_rod("ball")
    state_in, state_out = model.state(), model.state()
    for label, state in (("state_in", state_in), ("state_out", state_out)):
        if label == "state_in" and name == "joint_q_prev":
            continue  # state_in's joint_q_prev is not read
        setattr(state, name, wp.array([0.3], dtype=wp.float64))
        with pytest.raises(ValueError, match=rf"{label}.{name}: this model has no joint coordinates; expected None or model.state\(\)'s empty array, got float64 array of shape \(1,\)"):
            wc.ImplicitSolver(model).step(state_in, state_out, None, 0.01)
        setattr(state, name, None)
    wc.ImplicitSolver(model).step(state_in, state_out, None, 0.01)


@pytest.mark.parametrize("position", [(0.0, 0.0, 5.0), 1.0, (np.nan, 0.0)])
def test_ant_position_is_checked(position):
    """A third coordinate was dropped (the ant stood on the ground all the same), a scalar
    failed in indexing."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    with pytest.raises(ValueError, match=r"ant: position must be 2 finite numbers \(x, y; the feet stand at ground_height\)"):
        add_ant(b, position=position)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"name": 5}, r"name: expected a non-empty string to prefix the ant's links and joints, got 5"),
    ({"name": ""}, r"name: expected a non-empty string"),
    ({"spec": None}, r"ant: spec must be an AntSpec, got NoneType"),
    ({"spec": {"gap": 0.02}}, r"ant: spec must be an AntSpec, got dict"),
])
def test_ant_name_and_spec_are_checked_before_anything_is_built(kwargs, message):
    """A TypeError or AttributeError from inside, with the ant's bodies already in the builder (a probe, stop 65)."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    with pytest.raises(ValueError, match=message):
        add_ant(b, **kwargs)
    b.add_box((1.0, 1.0, 1.0), density=1.0, pose=(0.0, 0.0, 5.0, 0.0, 0.0, 0.0, 1.0), name="only")
    assert b.finalize().body_names == ["only"]


def test_base_joint_dofs_given_as_a_set_are_refused():
    """Gains, targets and limits follow dofs' order, which a set's changes with PYTHONHASHSEED (a probe, stop 65)."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    box = b.add_box((0.2, 0.2, 0.2), density=500.0, pose=(0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0), name="box")
    with pytest.raises(ValueError, match=r"dofs must be a sequence \(a list or tuple, in the order of the per-coordinate values\), got the set \['x', 'z'\]"):
        b.add_joint("base", child=box, dofs={"x", "z"}, kp=[10.0, 1000.0], kd=[1.0, 50.0], target=[0.5, -0.2])
    b.add_joint("base", child=box, dofs=["x", "z"], kp=[10.0, 1000.0], kd=[1.0, 50.0], target=[0.5, -0.2])


def test_a_ball_joint_stalled_on_its_cone_is_not_blamed_on_a_contact():
    """A stiff drive holding a ball joint on its cone's rim (a twist in its target) stalls
    Newton (docs/architecture.md, "Measured"); the error blamed a pressed contact, with one
    body and no contact, and told to start the bodies farther apart (a probe, stop 58)."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    rod = b.add_box((0.02, 0.02, 1.0), mass=1.0, pose=(0, 0, -0.5, 0, 0, 0, 1), name="rod")
    b.add_joint("ball", child=rod, anchor=(0, 0, 0), axis=(0, 0, 1), cone_limit=0.3, kp=3e3, kd=0.0, name="shoulder")
    model = b.finalize()
    art = model.articulation
    q = art.retract(model.initial_q, np.array([0.1, 0.0, 0.0]))
    state = model.state(requires_grad=False)
    state.body_q.assign(q)
    state.body_q_prev.assign(q)
    control = model.control(requires_grad=False)
    axis = np.array([1.0, 0.3, 0.2]) / np.linalg.norm([1.0, 0.3, 0.2])
    control.ball_target.assign(wc.rotation.quat_mul(art.initial_ball_rotations, wc.rotation.quat_from_rotation_vector(2.5 * axis)))
    with pytest.raises(wc.SolverError, match=r"a barrier pressed this close \(a joint's limit or cone, or a contact\)") as raised:
        wc.ImplicitSolver(model, max_iterations=300).step(state, model.state(requires_grad=False), control, 0.01)
    assert "farther apart" not in str(raised.value)


def test_a_joint_pressed_against_its_limit_is_not_converged_there():
    """Beside a limit's barrier Newton's step is about the gap, however unbalanced the force:
    a slider 1e-11 m from its limit, driven away from it, "converged" at every step and never
    moved, and a ball joint hit onto its cone (margin 1e-4) stayed on the rim against its drive
    (a probe, stop 65)."""
    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    slider = b.add_box((0.2, 0.2, 0.2), density=500.0, pose=(0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0))
    b.add_joint("prismatic", child=slider, anchor=(0.0, 0.0, 2.0), axis=(0.0, 0.0, 1.0), limits=[(-1e-11, 1.0)], kp=100.0, kd=10.0, target=0.5, name="slide")
    model = b.finalize()
    solver = wc.ImplicitSolver(model)
    states = [model.state(requires_grad=False) for _ in range(2)]
    for t in range(100):
        solver.step(states[t % 2], states[(t + 1) % 2], model.control(), 0.01)
    assert states[0].joint_q.numpy()[0] > 0.4  # 0.5228 (the same drive 1e-9 m from the limit: 0.5228)

    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    rod = b.add_box((1.0, 0.05, 0.05), density=500.0, pose=(0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
    b.add_joint("ball", child=rod, anchor=(0.0, 0.0, 1.0), axis=(1.0, 0.0, 0.0), cone_limit=0.4, kp=30.0, kd=3.0, limit_margin=1e-4)
    model = b.finalize()
    state, nxt = model.state(requires_grad=False), model.state(requires_grad=False)
    wc.set_body_velocity(state, wp.array([[0.0, 10.0, 0.0]], dtype=wp.vec3d), wp.array([[0.0, 0.0, 20.0]], dtype=wp.vec3d), 0.01)
    solver = wc.ImplicitSolver(model)
    cone = model.articulation.cones[0]
    swings = []
    for _ in range(100):
        solver.step(state, nxt, model.control(), 0.01)
        swings.append(model.articulation._cone_angle(cone, nxt.body_q.numpy())[0])
        state, nxt = nxt, state
    assert max(swings) > 0.4 - 1e-9 and swings[-1] < 0.05  # hit the rim, then driven back (0.0107 at step 100)
