"""The IPC baseline (ipctk): derivatives, local support, non-penetration, and its vanishing gradient."""

import numpy as np
import pytest
from helpers_rigid import ball_into_wall, fd_check, icosphere, identity_poses, quat
from test_tasks import space_billiards

from warpcontact import io
from warpcontact.cli import main
from warpcontact.ipc import IpcContactModel
from warpcontact.tasks import TaskProblem, TaskSettings


def test_rigid_derivatives_match_finite_differences():
    model = IpcContactModel([icosphere(1), icosphere(1)], dhat=0.1)
    poses = identity_poses([[0, 0, 0], [1.03, 0.1, 0.05]])
    poses[1, 3:] = quat([1, 2, 3], 0.4)
    base, grad_err, hess_err = fd_check(model, poses, h=1e-7)
    assert base.value > 0 and base.num_leaf > 0
    assert grad_err < 1e-6 and hess_err < 1e-5


def test_static_bodies_have_no_hessian_rows():
    """Three balls, the first and last static: the Hessian holds the middle one only, and
    it matches finite differences (it was (18, 18) with zero static rows)."""
    model = IpcContactModel([icosphere(1)] * 3, dhat=0.1, static=[True, False, True])
    poses = identity_poses([[0, 0, 0], [1.03, 0.1, 0.05], [2.06, 0.0, 0.0]])
    poses[1, 3:] = quat([1, 2, 3], 0.4)
    base, grad_err, hess_err = fd_check(model, poses, h=1e-7)
    assert list(model.hessian_bodies) == [1] and base.hessian.shape == (6, 6) and base.num_leaf > 0
    assert grad_err < 1e-6 and hess_err < 1e-5


def test_potential_vanishes_beyond_dhat_and_is_infinite_on_contact():
    model = IpcContactModel([icosphere(1), icosphere(1)], dhat=0.1, names=["a", "b"])
    far = model.evaluate(identity_poses([[0, 0, 0], [1.2, 0, 0]]))
    assert far.value == 0.0 and np.all(far.grad == 0.0)  # the baseline's vanishing gradient
    hit = model.evaluate(identity_poses([[0, 0, 0], [0.8, 0, 0]]))
    assert np.isposinf(hit.value) and hit.contact_pairs == [("a", "b")]
    with pytest.raises(ValueError, match="CPU only"):
        IpcContactModel([icosphere(0)], device="cuda:0")


def test_implicit_steps_with_ipc_do_not_penetrate():
    x = ball_into_wall(contact_stiffness=1e2, contact_mode="ipc", ipc_dhat=0.02)
    # The ball (radius <= 0.5) stops at the wall face (x = 0.6) and never passes it.
    assert x.max() < 0.1 + 1e-9 and x[-1] < x.max()


def test_from_rest_ipc_has_no_gradient_while_ours_finds_the_shot():
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("vx", "vy")
    settings = TaskSettings(horizon=15, receding_horizon=0, iterations=10, learning_rate=1.0)
    ipc_scene = space_billiards()
    ipc_scene.bodies[0].control_dofs = ("vx", "vy")
    ipc_scene.settings.contact_mode = "ipc"
    ipc = TaskProblem(ipc_scene, settings=settings)
    q0 = ipc.model.initial_q
    _, grad, _ = ipc.rollout(np.zeros((1, 2)), (q0, q0), 15)
    assert np.all(grad == 0.0)  # 0.5 m apart, far beyond dhat: nothing to follow
    ipc_result = ipc.optimize()
    ours = TaskProblem(scene, settings=settings).optimize()
    assert ipc_result.final_loss == pytest.approx(ipc_result.initial_loss)
    assert ours.final_loss < 0.05 * ours.initial_loss


def test_cli_run_with_ipc(tmp_path, capsys):
    path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), path)
    assert main(["run", str(path), "--model", "ipc", "--iters", "2", "--out", str(tmp_path / "out")]) == 0
    scene = space_billiards()
    scene.settings.friction = 0.5
    io.save_scene(scene, tmp_path / "friction.usda")
    assert main(["run", str(tmp_path / "friction.usda"), "--model", "ipc", "--iters", "1", "--out", str(tmp_path / "o")]) == 0


def test_the_ccd_bound_follows_a_turning_body_s_arc():
    """ipctk's CCD follows straight vertex paths: on the one chord of a 0.3 rad turn, a 1 m
    rod's tip passes inside a 4 mm post that stands between the chord and the arc, and the
    whole turn was allowed (the rod spun through the post in a step at 30 rad/s)."""
    import trimesh

    turn = 0.3
    rod = trimesh.creation.box(extents=(1.0, 0.02, 0.02))
    post = trimesh.creation.box(extents=(0.004, 0.004, 0.1))
    radius = 0.25 * (1.0 + np.cos(turn / 2))  # between the tip's chord and its arc
    poses = identity_poses([[0.0, 0.0, 0.0], [radius * np.cos(turn / 2), radius * np.sin(turn / 2), 0.0]])
    model = IpcContactModel([(rod.vertices, rod.faces), (post.vertices, post.faces)], dhat=1e-3, static=[False, True])
    assert np.isfinite(model.evaluate(poses).value)
    step = np.zeros((2, 6))
    step[0, 5] = turn
    alpha = model.advancement_limit(step)
    assert alpha * turn < turn / 2  # stopped before the turn reaches the post
    turned = poses.copy()
    turned[0, 3:] = quat([0.0, 0.0, 1.0], alpha * turn)
    assert np.isfinite(model.evaluate(turned).value)


def test_each_ccd_query_is_capped(monkeypatch):
    """ipctk's default narrow phase splits a query up to 1e7 times: a box sunk through a soft
    barrier (the builder's default mu with ipc) split one query for minutes at 12 GB. Past
    the cap Tight-Inclusion returns its conservative time of impact."""
    import ipctk
    import trimesh

    from warpcontact import ipc

    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    model = IpcContactModel([(box.vertices, box.faces)] * 2, static=[True, False])
    model.evaluate(identity_poses([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]]))
    caps = []
    query = ipctk.compute_collision_free_stepsize

    def recorded(mesh, start, end, **options):
        caps.append(options["narrow_phase_ccd"].max_iterations)
        return query(mesh, start, end, **options)

    monkeypatch.setattr(ipctk, "compute_collision_free_stepsize", recorded)
    step = np.zeros((2, 6))
    step[1, 2] = -0.2
    assert 0.0 < model.advancement_limit(step) < 0.5
    assert caps and set(caps) == {ipc.CCD_MAX_ITERATIONS} and ipc.CCD_MAX_ITERATIONS == 100_000


def test_poses_are_checked_by_the_contact_model_s_rules():
    """The IPC model normalised any quaternion: a zero one gave value 0 with a NaN gradient,
    and one of norm 2 was taken as a rotation. It now refuses both as ContactModel does."""
    model = IpcContactModel([icosphere(0), icosphere(0)], dhat=0.1, names=["ball", "crate"])
    poses = identity_poses([[0, 0, 0], [1.05, 0, 0]])
    assert np.isfinite(model.evaluate(poses).grad).all()
    for quaternion, norm in (([0, 0, 0, 0], "0"), ([0, 0, 0, 2], "2")):
        bad = poses.copy()
        bad[1, 3:] = quaternion
        for call in (model.evaluate, model.vertex_terms):
            with pytest.raises(ValueError, match=rf"body 1 \(crate\) has quaternion norm {norm};"):
                call(bad)
    with pytest.raises(ValueError, match="expected 2 rows"):
        model.evaluate(poses[:1])


@pytest.mark.parametrize("mode", ["ipc", "brute", "bsh"])
def test_a_scene_of_static_bodies_alone_steps(mode):
    """Nothing moves, so the Hessians have no rows: the IPC model's projection onto no
    columns raised (axis 1 index 5 exceeds matrix dimension 0), and brute force's empty
    lists could not be sliced for friction."""
    import warp as wp

    import warpcontact as wc

    builder = wc.ModelBuilder(friction=0.5, contact_mode=mode)
    builder.add_box((2.0, 2.0, 0.2), static=True, pose=(0, 0, -0.1, 0, 0, 0, 1), name="ground")
    builder.add_box((0.2, 0.2, 0.2), static=True, pose=(0, 0, 0.1005, 0, 0, 0, 1), name="block")
    model = builder.finalize()
    contact = model.contact
    assert contact.evaluate(model.state().body_q.numpy()).hessian.shape == (0, 0)
    assert contact.friction_terms(contact.friction_frame(1e-6, model.friction, 1e-4))[2].shape == (0, 0)
    states = [model.state(requires_grad=True) for _ in range(2)]
    tape = wp.Tape()
    with tape:
        wc.ImplicitSolver(model).step(states[0], states[1], None, 0.02)
    np.testing.assert_array_equal(states[1].body_q.numpy(), states[0].body_q.numpy())
    tape.backward(grads={states[1].body_q: wp.array([[1.0, 0, 0, 0, 0, 0, 0]] * 2, dtype=wp.transformd)})
    np.testing.assert_array_equal(states[0].body_q.grad.numpy()[:, 0], [1.0, 1.0])


def test_the_ipc_model_checks_its_bodies_as_the_other_contact_models_do():
    """Found by a probe: a face index past the vertices crashed the process inside ipctk's
    mesh (a segfault), a NaN vertex gave a potential of 0, fractional face indices were cut,
    a short static list gave an IndexError and a short names list blamed the poses."""
    vertices, faces = icosphere(0)
    for meshes, options, match in (
        ([(vertices[:3], np.array([[0, 1, 5]]))], {}, r"mesh 'body0': face 0 has vertex indices \[0, 1, 5\] outside \[0, 3\)"),
        ([(np.where(np.arange(len(vertices))[:, None] == 2, np.nan, vertices), faces)], {}, r"mesh 'body0': vertex 2 is not finite"),
        ([(vertices, faces + 0.5)], {}, r"mesh 'body0': face 0 has non-integer vertex indices"),
        ([(vertices, faces)] * 2, dict(static=[True]), r"static: expected 2 flags"),
        ([(vertices, faces)] * 2, dict(names=["ball"]), r"names: 1 names for 2 bodies"),
        ([], {}, r"meshes: need at least one body"),
    ):
        with pytest.raises(ValueError, match=match):
            IpcContactModel(meshes, **options)


def test_ctrl_c_while_ipctk_initialises_is_an_interrupt_not_a_missing_toolkit(monkeypatch):
    """Found by a probe: Ctrl-C inside ipctk's initialisation surfaces as an ImportError, which
    was reported as "needs the IPC Toolkit" (exit 2), and the interrupt was lost."""
    import builtins
    import sys

    real_import = builtins.__import__

    def interrupted(name, *args, **kwargs):
        if name == "ipctk":
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as interrupt:
                raise ImportError("initialization failed") from interrupt
        return real_import(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "ipctk", raising=False)
    monkeypatch.setattr(builtins, "__import__", interrupted)
    with pytest.raises(KeyboardInterrupt):
        IpcContactModel([icosphere(0)] * 2)
    monkeypatch.setattr(builtins, "__import__", real_import)
    monkeypatch.setitem(sys.modules, "ipctk", None)  # not installed: still the clear error
    with pytest.raises(ValueError, match=r"the ipc baseline needs the IPC Toolkit"):
        IpcContactModel([icosphere(0)] * 2)


def test_ipc_bodies_pressed_closer_than_rounding_of_a_step_are_pushed_apart():
    """One distance for every pair (the global least) kept the solver's check of pressed pairs
    off for ipc: a box started 1e-12 m from another, pushed by 5e10 N, "converged" at its first
    step and never moved (1e-11 m: "no convergence"). Close pairs now get their own distances."""
    import warpcontact as wc

    for gap in (1e-11, 1e-12):
        b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0), contact_stiffness=1e5, contact_mode="ipc")
        b.add_box((0.3, 0.3, 0.3), density=100.0, name="left", pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
        b.add_box((0.3, 0.3, 0.3), density=100.0, name="right", pose=(0.3 + gap, 0.02, 0.0, 0.0, 0.0, 0.0, 1.0))
        b.add_box((0.3, 0.3, 0.3), density=100.0, name="far", pose=(5.0, 0.02, 0.0, 0.0, 0.0, 0.0, 1.0))
        model = b.finalize()
        separation = model.contact.evaluate(model.initial_q).pair_separation
        pairs = [tuple(p) for p in model.contact.body_pairs]
        assert separation[pairs.index((0, 1))] == pytest.approx(gap, rel=1e-3) and separation[pairs.index((0, 2))] == model.contact.dhat
        solver, states = wc.ImplicitSolver(model), [model.state() for _ in range(3)]
        for t in range(2):
            solver.step(states[t], states[t + 1], None, 0.02)
        assert states[-1].body_q.numpy()[1, 0] - 0.3 > 1e-3  # pushed apart, as bsh does


def test_the_solver_interface_checks_as_the_contact_model_s_does():
    """Found by a probe: before any evaluate, friction_frame found 0 pairs and
    advancement_limit returned 0 (every body's mesh at the origin); friction_terms at a NaN
    pose gave a NaN value, at a row short an IndexError; a static body's step row was taken."""
    import warp as wp

    model = IpcContactModel([icosphere(1), icosphere(1)], dhat=0.1, static=[True, False], names=["ground", "ball"])
    friction = wp.array([0.5], dtype=wp.float64, device="cpu")
    with pytest.raises(RuntimeError, match="friction_frame: uses the collisions and vertices of the last evaluate"):
        model.friction_frame(1.0, friction, 1e-4)
    with pytest.raises(RuntimeError, match="advancement_limit: uses"):
        model.advancement_limit(np.array([[0, 0, 0, 0, 0, 0], [0, 0, -1.0, 0, 0, 0]]))
    with pytest.raises(RuntimeError, match="advancement_frame: uses"):
        model.advancement_frame()
    poses = identity_poses([[0, 0, 0], [1.05, 0, 0]])
    model.evaluate(poses)
    lagged = model.friction_frame(1.0, friction, 1e-4)
    assert lagged.pairs > 0
    nan = poses.copy()
    nan[1, 0] = np.nan
    with pytest.raises(ValueError, match="poses: non-finite value nan"):
        model.friction_terms(lagged, poses=nan)
    with pytest.raises(ValueError, match="poses: expected 2 rows"):
        model.friction_terms(lagged, poses=poses[1:])
    assert model.friction_terms(lagged, poses=poses)[0] == model.friction_terms(lagged)[0]
    with pytest.raises(ValueError, match="static body 'ground' \\(row 0\\) has a non-zero row"):
        model.advancement_limit(np.array([[0.1, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0.0]]))
    assert model.advancement_limit(np.array([[0, 0, 0, 0, 0, 0], [-0.1, 0, 0, 0, 0, 0.0]])) < 1.0


def _pedestal_scene(*, arm: bool, mount: bool = False):
    """A floor, a pedestal standing on it (static, touching to the bit), a box at rest and,
    with ``arm``, a bar hinged to the pedestal's top, or with ``mount`` as well, to a static
    mount of its own 1.5 m up."""
    import warpcontact as wc

    builder = wc.ModelBuilder(gravity=(0, 0, -9.81), contact_stiffness=1e5, contact_mode="ipc")
    builder.add_box((6, 6, 0.2), static=True, name="floor", pose=(0, 0, -0.1, 0, 0, 0, 1))
    pedestal = builder.add_box((0.3, 0.3, 0.8), static=True, name="pedestal", pose=(2, 2, 0.4, 0, 0, 0, 1))
    builder.add_box((0.3, 0.3, 0.3), density=200.0, name="box", pose=(0.0137, 0.0071, 0.151, 0, 0, 0, 1))
    if arm:
        parent = builder.add_box((0.2, 0.2, 0.1), static=True, name="mount", pose=(-2, -2, 1.5, 0, 0, 0, 1)) if mount else pedestal
        x = -2 if mount else 2
        bar = builder.add_box((0.05, 0.05, 0.5), density=500.0, name="bar", pose=(x, x, 1.1 if not mount else 1.15, 0, 0, 0, 1))
        builder.add_joint("revolute", child=bar, parent=parent, anchor=(x, x, 0.85 if not mount else 1.42), axis=(0, 1, 0))
    return builder.finalize()


def test_static_bodies_that_touch_have_no_ipc_terms_between_them():
    """A pedestal standing on the floor made the ipc potential infinite at every pose, and
    every step failed blaming inertia, gravity and PD terms (a probe, stop 65): static bodies
    have no contact terms between them, as in ContactModel."""
    import warpcontact as wc

    model = _pedestal_scene(arm=False)
    assert np.isfinite(model.contact.evaluate(model.initial_q).value)
    states = [model.state() for _ in range(2)]
    wc.ImplicitSolver(model).step(states[0], states[1], None, 0.01)
    # Where a static body shares its (jointed) group with a dynamic body, the static bodies
    # cannot share one patch of ipctk's filter without switching off that body's contact with
    # the others: the touching pair is named as the step's start.
    model = _pedestal_scene(arm=True)
    evaluation = model.contact.evaluate(model.initial_q)
    assert np.isposinf(evaluation.value) and evaluation.contact_pairs == [("floor", "pedestal")]
    with pytest.raises(ValueError, match="state_in: bodies intersect or touch at the start of the step: floor and pedestal"):
        wc.ImplicitSolver(model).step(model.state(), model.state(), None, 0.01)
    # Only the groups of static bodies alone share a patch: a static mount jointed to a bar
    # elsewhere kept the floor and the pedestal apart as well (a review, stop 65).
    model = _pedestal_scene(arm=True, mount=True)
    assert np.isfinite(model.contact.evaluate(model.initial_q).value)
    wc.ImplicitSolver(model).step(model.state(), model.state(), None, 0.01)
