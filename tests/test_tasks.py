"""Task optimisation: losses, control parameterisations, gradients, optimiser, CLI."""

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import interrupt_call
import trimesh
import warp as wp
from pxr import Usd

import warpcontact as wc
from warpcontact import cli, io
from warpcontact.cli import main
from warpcontact.kernels import task as task_kernels
from warpcontact.kernels.state import quat_from_rotation_vector
from warpcontact.tasks import GENERIC_QUICK_HORIZON, TaskProblem, TaskSettings, adam


def ball(radius=0.5):
    m = trimesh.creation.icosphere(subdivisions=1, radius=radius)
    return np.asarray(m.vertices), np.asarray(m.faces)


def space_billiards(gap=0.5):
    """A cue ball (initial x, y, vx, vy optimised) and a target ball, no gravity, no ground."""
    V, F = ball()
    cue = io.BodySpec("cue", "/World/cue", V, F, np.array([0, 0, 0, 0, 0, 0, 1.0]), density=100.0, control_dofs=("x", "y", "vx", "vy"))
    target = io.BodySpec("target", "/World/target", V, F, np.array([1.0 + gap, 0.3, 0, 0, 0, 0, 1.0]), density=100.0)
    target.target_position = np.array([3.0, 0.8, 0.0])
    target.target_tolerance = 0.1
    return io.Scene(
        bodies=[cue, target],
        gravity=np.zeros(3),
        settings=io.SimulationSettings(time_step=0.04, frames=15, contact_stiffness=1e-4),
        task=io.TaskSpec(name="space_billiards", control="initial_state", horizon=15, iterations=8, learning_rate=0.3),
    )


def test_target_loss_is_a_relu_of_squared_distance():
    q = wp.array([[0.0, 0, 0, 0, 0, 0, 1], [2.0, 0, 0, 0, 0, 0, 1]], dtype=wp.transformd)
    loss = wp.zeros(1, dtype=wp.float64)
    wp.launch(
        task_kernels.target_loss_kernel,
        dim=2,
        inputs=[wp.array([0, 1], dtype=wp.int32), wp.array([[0.05, 0, 0], [0.0, 0, 0]], dtype=wp.vec3d), wp.array([0.1, 0.5], dtype=wp.float64), q],
        outputs=[loss],
    )
    assert loss.numpy()[0] == pytest.approx(4.0 - 0.25)  # first target inside its tolerance: 0


def test_pd_targets_apply_translation_and_yaw_offsets():
    base = wp.transformd(wp.vec3d(1.0, 2.0, 0.3), wp.quatd(0.0, 0.0, 0.0, 1.0))
    values = wp.array([[0.5, -0.2, 0.0, np.pi / 2]], dtype=wp.float64)
    codes = wp.array([task_kernels.DOF_CODES[d] for d in ("x", "y", "z", "rz")], dtype=wp.int32)  # a Z-up stage's yaw
    out = wp.zeros(3, dtype=wp.transformd)
    wp.launch(task_kernels.pd_target_kernel, dim=1, inputs=[2, base, codes, values, 0], outputs=[out])
    pose = out.numpy()[2]
    np.testing.assert_allclose(pose[:3], [1.5, 1.8, 0.3])
    np.testing.assert_allclose(pose[3:], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)], atol=1e-12)


def test_adam_uses_paper_betas_and_is_scale_free():
    x = np.array([0.0])
    step = adam((0.3, 0.5), 0.1)
    step(x, np.array([1e-12]))  # a tiny gradient still moves by the learning rate
    assert x[0] == pytest.approx(-0.1)


def test_initial_state_gradient_matches_finite_differences():
    problem = TaskProblem(space_billiards())
    values = np.array([[0.0, 0.1, 2.0, 0.2]])
    q0 = problem.model.initial_q
    loss, grad, _ = problem.rollout(values, (q0, q0), 15)
    assert loss > 0 and np.all(grad != 0)
    for k in range(4):
        e = np.zeros_like(values)
        e[0, k] = 1e-6
        fd = (problem.rollout(values + e, (q0, q0), 15, gradient=False)[0] - problem.rollout(values - e, (q0, q0), 15, gradient=False)[0]) / 2e-6
        assert grad[0, k] == pytest.approx(fd, rel=1e-5)


@pytest.mark.filterwarnings("ignore:contact_stiffness .* holds these bodies")  # the test bodies float; not what is tested
def test_pd_target_gradient_matches_finite_differences():
    scene = io.load_scene(Path(__file__).resolve().parents[1] / "scenes" / "push.usda")
    # A stiffer potential makes the rod's long-range effect (~1e-9 at mu = 1e-6) large
    # enough for finite differences of a loss of ~6 to resolve.
    scene.settings.contact_stiffness = 1e-3
    problem = TaskProblem(scene, settings=TaskSettings(horizon=6, receding_horizon=0, iterations=1, learning_rate=0.01))
    # Friction holds the box, so the loss moves by ~1e-5 per metre of rod target; at the
    # default tolerance (1e-10 of the body size) the steps' residual errors move it by as
    # much as a finite difference resolves, on a flat ground by 7e-4 of the gradient.
    problem.solver.tolerance = 1e-13
    values = np.zeros((6, len(problem.dof_names)))
    values[:, 0] = -0.4  # move the rod toward the box
    q0 = problem.model.initial_q
    loss, grad, _ = problem.rollout(values, (q0, q0), 6)
    assert np.abs(grad).max() > 0  # long-range influence: non-zero although nothing touches
    # Each entry to its own size: the rotation targets' gradients (rx, ry, rz, at zero
    # rotation, through quat_from_rotation_vector's series branch) are 1e-3 of the largest,
    # and a tolerance relative to that one let a 20% error in them pass.
    for r, c in ((0, 0), (2, 1), (1, 3), (3, 4), (5, 5)):
        e = np.zeros_like(values)
        e[r, c] = 1e-3
        fd = (problem.rollout(values + e, (q0, q0), 6, gradient=False)[0] - problem.rollout(values - e, (q0, q0), 6, gradient=False)[0]) / 2e-3
        assert abs(grad[r, c] - fd) <= 1e-3 * abs(fd) + 1e-6 * np.abs(grad).max(), (r, c, grad[r, c], fd)


@wp.kernel
def _rotation_vector_exponential_kernel(w: wp.array(dtype=wp.vec3d), q_out: wp.array(dtype=wp.quatd)):
    i = wp.tid()
    q_out[i] = quat_from_rotation_vector(w[i])


def test_rotation_vector_exponential_adjoint_matches_finite_differences():
    """exp of a rotation vector, as the task and state kernels differentiate it: at zero
    (the series branch that zero spins and unrotated targets take), just past the switch
    between its branches and at a finite angle. d q / d w is I/2 on the vector part at zero."""
    points = np.array([[0.0, 0.0, 0.0], [3e-9, -2e-9, 1e-9], [2e-8, 1e-8, -3e-8], [0.3, -0.5, 0.8]])

    def exponential(w):
        q = wp.zeros(len(w), dtype=wp.quatd)
        wp.launch(_rotation_vector_exponential_kernel, dim=len(w), inputs=[wp.array(w, dtype=wp.vec3d)], outputs=[q])
        return q.numpy()

    w = wp.array(points, dtype=wp.vec3d, requires_grad=True)
    q = wp.zeros(len(points), dtype=wp.quatd, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(_rotation_vector_exponential_kernel, dim=len(points), inputs=[w], outputs=[q])
    h = 1e-6
    for row in range(4):
        seed = np.zeros((len(points), 4))
        seed[:, row] = 1.0
        tape.backward(grads={q: wp.array(seed, dtype=wp.quatd)})
        jacobian_row = w.grad.numpy().copy()
        tape.zero()
        for col in range(3):
            e = np.zeros(3)
            e[col] = h
            fd = (exponential(points + e)[:, row] - exponential(points - e)[:, row]) / (2 * h)
            np.testing.assert_allclose(jacobian_row[:, col], fd, atol=1e-8, err_msg=f"d q[{row}] / d w[{col}]")
    assert jacobian_row[0] == pytest.approx([0.0, 0.0, 0.0])


def test_gradient_descent_finds_the_shot_from_rest():
    """The cue ball starts at rest, not touching the target ball: only the long-range
    potential links them, yet 10 Adam steps on its initial velocity find the shot
    (measured: loss 2.43 -> 0.003)."""
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("vx", "vy")
    settings = TaskSettings(horizon=15, receding_horizon=0, iterations=10, learning_rate=1.0)
    result = TaskProblem(scene, settings=settings).optimize()
    assert len(result.loss_history) == 10
    assert result.final_loss < 0.05 * result.initial_loss
    assert result.trajectory.shape == (16, 2, 7)


def test_descent_stops_at_success():
    """A zero loss puts every target within its tolerance: Adam's momentum alone would only
    carry the solution off it, so the descent ends there."""
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("vx", "vy")
    scene.bodies[1].target_tolerance = 1.2  # reachable within a few steps
    settings = TaskSettings(horizon=15, receding_horizon=0, iterations=10, learning_rate=1.0)
    result = TaskProblem(scene, settings=settings).optimize()
    assert result.success and result.final_loss == 0.0
    assert result.loss_history[-1] == 0.0 and min(result.loss_history[:-1]) > 0.0
    assert result.iterations == len(result.loss_history) < 10


@pytest.mark.parametrize("model", ["ours", "gb"])
def test_a_window_at_success_costs_one_rollout_and_no_backward_pass(monkeypatch, model):
    """Found by a probe: a descent whose first rollout already met every target still ran a
    backward pass (ours) or drew a whole bundle (gb: 8 more rollouts, each with its backward
    pass) for a gradient it never used; receding windows after success paid it each."""
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("vx", "vy")
    scene.bodies[1].target_tolerance = 10.0  # met at the start
    backward = []
    real = wp.Tape.backward
    monkeypatch.setattr(wp.Tape, "backward", lambda tape, *args, **kwargs: backward.append(1) or real(tape, *args, **kwargs))
    rollouts = []
    real_rollout = TaskProblem.rollout
    monkeypatch.setattr(TaskProblem, "rollout", lambda problem, *args, **kwargs: rollouts.append(1) or real_rollout(problem, *args, **kwargs))
    settings = TaskSettings(horizon=6, receding_horizon=0, iterations=5, learning_rate=1.0)
    result = TaskProblem(scene, settings=settings, model=model).optimize()
    assert result.success and result.loss_history == [0.0]
    assert backward == [] and len(rollouts) == 1
    if model == "ours":  # the benches read the backward's time of every rollout they ask it of (a review)
        problem = TaskProblem(scene, settings=settings)
        q0 = problem.model.initial_q
        timings = {}
        loss, grad, _ = problem.rollout(problem.initial_values(1), (q0, q0), 6, timings=timings)
        assert loss == 0.0 and not grad.any() and timings == {"backward_seconds": 0.0}


def test_infeasible_updates_are_undone():
    """Position offsets can push the cue ball into the target ball; such steps are rejected."""
    result = TaskProblem(space_billiards()).optimize()
    assert result.final_loss < result.initial_loss
    assert np.isfinite(result.loss_history).all()


def test_infeasible_updates_are_halved_back_without_slowing_later_steps():
    """A wall at x = 3 that the loss first pulls towards, then away from: updates into it are
    halved back towards the last feasible x, the learning rate is kept (the steps away from
    the wall are full ones), and no rollout is repeated. Pressed against the wall for good,
    the descent stops; an infeasible start is an error."""
    from warpcontact.tasks import TaskSettings, _descend

    def wall_problem(turn):
        feasible = []

        def rollout(values, gradient=True):
            x = float(values[0, 0])
            if x > 3.0:
                raise ValueError("state_in: bodies intersect at the start")
            feasible.append(x)
            goal = 5.0 if len(feasible) <= turn else -5.0
            return (x - goal) ** 2, np.array([[2.0 * (x - goal)]]), None

        return rollout, feasible

    settings = TaskSettings(horizon=1, receding_horizon=0, iterations=40, learning_rate=0.5)
    rollout, feasible = wall_problem(turn=9)
    history = []
    best = _descend(rollout, np.zeros((1, 1)), settings, history)
    assert len(history) == len(feasible) == 40 and len(set(feasible)) == 40
    assert 2.9 < max(feasible) <= 3.0 and best[0] == min(history)
    steps = np.diff(feasible)
    assert np.all(steps[7:9] < 0.02)  # halved back at the wall
    assert np.all(steps[10:20] < -0.45)  # then full steps away from it (lr 0.5, not halved)

    rollout, feasible = wall_problem(turn=10**6)
    history = []
    _descend(rollout, np.zeros((1, 1)), settings, history)
    assert len(history) == len(feasible) < 40 and max(feasible) > 3.0 - 1e-5  # stopped at the wall
    with pytest.raises(ValueError, match="intersect"):
        _descend(rollout, np.full((1, 1), 4.0), settings, [])


def test_the_descent_asks_for_no_gradient_at_its_last_iterate():
    """The last iterate is only evaluated: its gradient (a backward pass; for gb a whole
    bundle of rollouts) was computed and dropped. Halved-back updates ask as the iterate
    they replace would."""
    from warpcontact.tasks import TaskSettings, _descend

    asked = []

    def rollout(values, gradient=True):
        asked.append(gradient)
        x = float(values[0, 0])
        if x > 1.2:
            raise ValueError("state_in: bodies intersect at the start")
        return (x - 5.0) ** 2, np.array([[2.0 * (x - 5.0)]]) if gradient else None, None

    history = []
    _descend(rollout, np.zeros((1, 1)), TaskSettings(horizon=1, receding_horizon=0, iterations=4, learning_rate=0.5), history)
    assert len(history) == 4
    assert asked == [True, True, True, False, False, False]  # the last update is halved back twice
    asked.clear()
    _descend(rollout, np.zeros((1, 1)), TaskSettings(horizon=1, receding_horizon=0, iterations=1, learning_rate=0.5), [])
    assert asked == [False]


def test_task_problem_rejects_scenes_without_task_metadata():
    scene = space_billiards()
    scene.task = io.TaskSpec()
    with pytest.raises(ValueError, match="no task metadata"):
        TaskProblem(scene)
    scene = space_billiards()
    scene.bodies[1].target_position = None
    with pytest.raises(ValueError, match="no target bodies"):
        TaskProblem(scene)


def test_a_joint_sine_task_refuses_control_dofs_it_would_not_read():
    """Found by a probe: control dofs on a body of Ant-Push loaded and ran, and were never
    read (validate_task even named that body the controlled one)."""
    from warpcontact.scenes import build_scene
    from warpcontact.tasks import validate_task

    scene = build_scene("ant_push")
    assert validate_task(scene)[0] is None
    scene.body("box").control_dofs = ("x",)
    with pytest.raises(ValueError, match=r"prim /World/box: warpcontact:control:dofs is not read by a joint_sine task"):
        validate_task(scene)


def test_quick_uses_the_scene_preset_or_caps_the_paper_settings():
    scene = space_billiards()
    scene.task.horizon, scene.task.receding_horizon, scene.task.iterations = 200, 48, 50
    paper = TaskSettings.from_task(scene)
    assert (paper.horizon, paper.receding_horizon, paper.iterations, paper.learning_rate, paper.receding_stride) == (200, 48, 50, 0.3, 1)
    capped = TaskSettings.from_task(scene, quick=True)
    assert (capped.horizon, capped.receding_horizon, capped.iterations, capped.learning_rate) == (24, 8, 8, 0.3)
    scene.task.quick_horizon, scene.task.quick_receding_horizon, scene.task.quick_iterations, scene.task.quick_learning_rate = 64, 16, 60, 0.05
    scene.task.quick_receding_stride = 4
    preset = TaskSettings.from_task(scene, quick=True, iterations=7)
    assert (preset.horizon, preset.receding_horizon, preset.iterations, preset.learning_rate, preset.receding_stride) == (64, 16, 7, 0.05, 4)
    assert (paper.window, capped.window, preset.window) == (48, 8, 16)
    strided = TaskSettings.from_task(scene, receding_stride=6)
    assert (strided.receding_stride, strided.window, strided.iterations) == (6, 48, 50)
    with pytest.raises(ValueError, match=r"--stride must be a whole number >= 1 and at most the window \(48\), got 49"):
        TaskSettings.from_task(scene, receding_stride=49)
    scene.task.receding_horizon = 0
    with pytest.raises(ValueError, match="--stride applies to receding-window tasks; this one optimises a single window of 200 frames"):
        TaskSettings.from_task(scene, receding_stride=2)
    scene.task.receding_horizon = 48
    assert TaskSettings(horizon=10, receding_horizon=0, iterations=1, learning_rate=0.1).window == 10
    assert TaskSettings(horizon=10, receding_horizon=12, iterations=1, learning_rate=0.1).window == 10
    scene.task.horizon = 0  # the scene's frame count
    assert TaskSettings.from_task(scene).horizon == scene.settings.frames


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("iterations", 0, "warpcontact:task:iterations must be a whole number from 1 to 10,000,000, got 0"),
        ("horizon", 10**9, "warpcontact:task:horizon must be a whole number from 1 to 1,000,000, got 1000000000"),
        ("learning_rate", -0.1, "warpcontact:task:learningRate must be positive and finite, got -0.1"),
        ("learning_rate", float("nan"), "warpcontact:task:learningRate must be positive and finite"),
        ("receding_horizon", -2, "warpcontact:task:recedingHorizon must be a whole number >= 0, got -2"),
        # A single window (this task's) executes no stride: any whole number >= 1 does (one
        # past the window was refused here, the same on a longer horizon passed; stop 64).
        ("receding_stride", 0, r"warpcontact:task:recedingStride must be a whole number >= 1, got 0"),
        ("quick_learning_rate", 0.0, "warpcontact:task:quick:learningRate must be positive and finite, got 0.0"),
    ],
)
def test_out_of_range_task_settings_are_clear_errors(tmp_path, field, value, message):
    scene = space_billiards()
    scene.task.quick_horizon, scene.task.quick_iterations, scene.task.quick_learning_rate = 5, 2, 0.1
    setattr(scene.task, field, value)
    path = tmp_path / "bad.usda"
    io.save_scene(scene, path)
    # The task's own settings also under --quick, whose preset replaces them: a scene with a
    # negative learning rate ran --quick and failed only its real run (a probe, stop 62).
    for quick in (True,) if field.startswith("quick") else (False, True):
        with pytest.raises(ValueError, match=f"bad.usda: {message}"):
            TaskSettings.from_task(io.load_scene(path), quick=quick)


def test_a_horizon_taken_from_the_scenes_frames_names_them():
    """Without warpcontact:task:horizon the scene's frames are the horizon; past the cap the
    error named warpcontact:task:horizon, which the scene never authored."""
    scene = space_billiards()
    scene.task.horizon, scene.settings.frames = 0, 2_000_000
    with pytest.raises(ValueError, match=r"warpcontact:frames \(the horizon: no warpcontact:task:horizon\) must be a whole number from 1 to 1,000,000, got 2000000"):
        TaskSettings.from_task(scene)


def test_a_rollout_from_a_non_finite_start_names_it():
    # It was blamed on zero velocities: "velocities give a non-finite previous pose".
    problem = TaskProblem(space_billiards(), settings=TaskSettings(horizon=2, receding_horizon=0, iterations=1, learning_rate=0.1))
    q, q_prev = (np.array(a) for a in problem.start)
    q[0, 0] = np.nan
    name = problem.model.body_names[0]
    with pytest.raises(ValueError, match=rf"start q: body '{name}' \(index 0\) has pose \[nan, "):
        problem.rollout(problem.initial_values(1), (q, q_prev), 2)


def test_non_finite_decision_variables_a_moved_controlled_body_and_string_dofs_are_named():
    """Found by a probe: an initial state's x = NaN (or rz = 1e300) was blamed on the scene's
    finite velocities; a start that moved the controlled body was replaced by the scene's pose
    without a word; control dofs given as one string ran letter by letter ("xy" as x and y,
    "yaw" as unknown y, a, w)."""
    problem = TaskProblem(space_billiards(), settings=TaskSettings(horizon=2, receding_horizon=0, iterations=1, learning_rate=0.1))
    values = problem.initial_values(1)
    values[0, 2] = np.nan
    with pytest.raises(ValueError, match=r"values: row 0, dof 'vx' is nan; decision variables must be finite"):
        problem.rollout(values, problem.start, 2)
    q, q_prev = (np.array(a) for a in problem.start)
    q[0, 0] = -0.3
    with pytest.raises(ValueError, match=r"start: an initial_state control places body 'cue' itself .*; start's pose for it must be the scene's, \[\S+, \S+, \S+, 0.0, 0.0, 0.0, 1.0\]"):  # its centre of mass
        problem.rollout(problem.initial_values(1), (q, q_prev), 2)
    scene = space_billiards()
    scene.bodies[0].control_dofs = "xy"
    with pytest.raises(ValueError, match=r"prim /World/cue: warpcontact:control:dofs: expected a sequence of dof names, got the string 'xy'"):
        TaskProblem(scene)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("target_position", np.array([np.nan, 0.0, 0.0]), r"prim /World/target: warpcontact:target:position must be 3 finite numbers of at most 1e\+150 m in magnitude, got \[nan, 0.0, 0.0\]"),
        ("target_position", np.array([1.0, 0.0]), r"warpcontact:target:position must be 3 finite numbers .*, got \[1.0, 0.0\]"),
        # Beyond 1e150 m the loss's squared distance overflowed to inf.
        ("target_position", np.array([1e160, 0.0, 0.0]), r"warpcontact:target:position must be 3 finite numbers of at most 1e\+150 m in magnitude, got \[1e\+160, 0.0, 0.0\]"),
        ("target_tolerance", -1.0, r"prim /World/target: warpcontact:target:tolerance must be finite, >= 0 and at most 1e\+150 m, got -1.0"),
        # Its square overflowed in the receding loss: a traceback after the whole run (a probe, stop 63).
        ("target_tolerance", 1e155, r"warpcontact:target:tolerance must be finite, >= 0 and at most 1e\+150 m, got 1e\+155"),
        ("target_tolerance", float("inf"), r"warpcontact:target:tolerance must be finite, >= 0 and at most 1e\+150 m, got inf"),
    ],
)
def test_a_scene_built_in_python_is_refused_a_goal_that_is_not_finite(field, value, message):
    """load_scene refuses these in USD; a Scene built in Python used to run with them, a NaN
    target giving a NaN loss at every iteration and a negative tolerance a wrong one."""
    scene = space_billiards()
    target = next(b for b in scene.bodies if b.target_position is not None)
    target.path = "/World/target"
    setattr(target, field, value)
    with pytest.raises(ValueError, match=message):
        TaskProblem(scene)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        (dict(horizon=0), "settings.horizon must be a whole number from 1 to 1,000,000, got 0"),
        (dict(horizon=8.5), "settings.horizon must be a whole number from 1 to 1,000,000, got 8.5"),
        # Allocated up front: 1e9 frames ended in numpy's MemoryError, naming nothing.
        (dict(horizon=10**9, receding_horizon=2, receding_stride=2), "settings.horizon must be a whole number from 1 to 1,000,000, got 1000000000"),
        (dict(iterations=0), "settings.iterations must be a whole number from 1 to 10,000,000, got 0"),
        (dict(learning_rate=float("nan")), "settings.learning_rate must be positive and finite, got nan"),
        (dict(receding_horizon=-4), "settings.receding_horizon must be a whole number >= 0, got -4"),
        (dict(receding_stride=3), r"settings.receding_stride must be a whole number >= 1 and at most the window \(2\), got 3"),
        (dict(receding_stride=0, receding_horizon=0), r"settings.receding_stride must be a whole number >= 1, got 0"),
        (dict(betas=(1.5, 0.5)), r"settings.betas must be two numbers in \[0, 1\), got \(1.5, 0.5\)"),
        (dict(initial_samples=-1), "settings.initial_samples must be a whole number >= 0, got -1"),
    ],
)
def test_settings_built_directly_are_checked_like_a_scenes(changes, message):
    """The Python API's own TaskSettings meet the rules of the scene metadata they stand in
    for: they used to run silently (a horizon of 0, a negative or NaN learning rate, a
    stride past the window) or fail deep inside (0 iterations: a TypeError)."""
    settings = dataclasses.replace(_CHECKPOINTED_RUNS["receding"][1], **changes)
    with pytest.raises(ValueError, match=message):
        TaskProblem(_pd_space_billiards(), settings=settings)


def test_a_task_problem_of_the_wrong_kind_of_scene_or_settings_is_named():
    """None as a scene, and a dict as settings, failed with an AttributeError (a probe, stop 64)."""
    with pytest.raises(ValueError, match=r"scene: expected a warpcontact Scene \(io.load_scene, scenes.build_scene\), got NoneType"):
        TaskProblem(None)
    with pytest.raises(ValueError, match=r"settings: expected a TaskSettings \(or None for the scene's own\), got dict"):
        TaskProblem(space_billiards(), settings={"horizon": 2})
    problem = TaskProblem(space_billiards())
    with pytest.raises(ValueError, match=r"start: expected \(q, q_prev\), two \(nbodies, 7\) pose arrays \(TaskProblem.start\), got NoneType"):
        problem.rollout(problem.initial_values(1), None, 2)
    for rows in (-1, "2"):
        with pytest.raises(ValueError, match=r"rows: must be a whole number >= 0, got"):
            problem.initial_values(rows)


def test_flags_of_the_task_api_are_flags():
    """quick="yes" and gradient="no" were truth-tested (a probe, stop 64)."""
    with pytest.raises(ValueError, match="quick: expected True/False"):
        TaskSettings.from_task(space_billiards(), quick="yes")
    problem = TaskProblem(space_billiards())
    with pytest.raises(ValueError, match="gradient: expected True/False"):
        problem.rollout(problem.initial_values(1), problem.start, 2, gradient="no")


def test_a_single_window_takes_any_stride():
    """A stride past the window of a task optimised as one window was refused, though the same
    stride passed on a longer horizon and a single window executes none (a probe, stop 64)."""
    settings = dataclasses.replace(_CHECKPOINTED_RUNS["receding"][1], horizon=6, receding_horizon=0, receding_stride=8)
    assert not settings.receding
    settings.check()
    settings.receding_horizon = 8  # a window at least the horizon: one window too
    settings.check()
    settings.receding_horizon = 4
    with pytest.raises(ValueError, match=r"settings.receding_stride must be a whole number >= 1 and at most the window \(4\), got 8"):
        settings.check()


@pytest.mark.parametrize("stride", [1, 2])
def test_receding_windows_execute_their_first_frames_and_hold_the_last_planned_action(stride):
    """Each window executes its first ``stride`` frames, then the window shifts; the rows that
    enter a window start as copies of the last planned row (zero would send the PD target
    back to the start pose at the end of every window)."""
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("x", "y")
    scene.bodies[0].kp_linear = np.full(3, 100.0)
    scene.task.control = "pd_targets"
    problem = TaskProblem(scene, settings=TaskSettings(horizon=5, receding_horizon=2, iterations=2, learning_rate=0.05, receding_stride=stride))
    windows = []
    rollout = problem.rollout

    def recording(values, start, frames, **kwargs):
        if frames == 5:  # the trivial plan's rollout, for the initial loss
            return rollout(values, start, frames, **kwargs)
        if not windows or len(windows[-1]) == 2:  # two iterations a window
            windows.append([])
        loss, grad, trajectory = rollout(values, start, frames, **kwargs)
        windows[-1].append((np.array(values), start[0].copy(), trajectory))
        return loss, grad, trajectory

    reported = []
    problem.rollout = recording
    result = problem.optimize(progress=lambda done, total, loss: reported.append(loss))
    assert len(windows) == -(-5 // stride) and np.abs(result.values).max() > 0
    assert result.trajectory.shape[0] == 6
    # A window ends at the horizon: the last one at frame 4 (stride 1) plans one frame, not
    # two past the task's end (a probe, stop 59).
    starts = range(0, 5, stride)
    assert [len(attempts[0][0]) for attempts in windows] == [min(2, 5 - t) for t in starts]
    for (first_guess, _, _), _ in windows[1:]:
        if len(first_guess) == 2:
            np.testing.assert_array_equal(first_guess[1], first_guess[0])
    assert any(np.abs(first_guess).max() > 0 for (first_guess, _, _), _ in windows[1:])
    # Progress reports each window's kept plan, and the last one's is the task's final loss.
    assert reported[-1] == result.final_loss
    # Each window starts where the previous one's executed frames ended.
    frame = 0
    for w, attempts in enumerate(windows):
        start = attempts[0][1]
        np.testing.assert_array_equal(start, result.trajectory[frame])
        frame = min(frame + stride, 5)


def test_cli_run_says_when_it_cannot_plot(tmp_path, monkeypatch, capsys):
    import warpcontact.bench

    monkeypatch.setattr(warpcontact.bench, "optional_pyplot", lambda: None)
    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    assert main(["run", str(scene_path), "--iters", "1", "--out", str(tmp_path / "out")]) == 0
    assert "not convergence.png (matplotlib is not installed" in capsys.readouterr().out
    assert not (tmp_path / "out" / "convergence.png").exists() and (tmp_path / "out" / "metrics.json").exists()
    # An earlier run's plot stayed beside the new metrics.
    (tmp_path / "out" / "convergence.png").write_bytes(b"an earlier plot")
    assert main(["run", str(scene_path), "--iters", "1", "--out", str(tmp_path / "out"), "--overwrite"]) == 0
    assert not (tmp_path / "out" / "convergence.png").exists()


def test_cli_run_writes_metrics_plot_and_trajectory(tmp_path):
    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    assert main(["run", str(scene_path), "--iters", "3", "--out", str(tmp_path / "out")]) == 0
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    for key in ("task", "model", "device", "loss_history", "initial_loss", "final_loss", "success", "seconds", "iterations"):
        assert key in metrics
    assert metrics["model"] == "ours" and len(metrics["loss_history"]) == 3
    assert (tmp_path / "out" / "convergence.png").stat().st_size > 1000
    assert Usd.Stage.Open(str(tmp_path / "out" / "trajectory.usda")).GetEndTimeCode() == 15


def test_cli_run_keeps_an_earlier_runs_results_unless_told(tmp_path, capsys):
    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    argv = ["run", str(scene_path), "--iters", "1", "--out", str(tmp_path / "out")]
    assert main(argv) == 0
    before = (tmp_path / "out" / "metrics.json").read_text()
    assert main(argv + ["--iters", "2"]) == 2
    assert "metrics.json holds an earlier run's results (use --overwrite)" in capsys.readouterr().err
    assert (tmp_path / "out" / "metrics.json").read_text() == before
    assert main(argv + ["--iters", "2", "--overwrite"]) == 0
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["iterations"] == 2


def test_cli_run_accepts_baselines_and_seed(tmp_path):
    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    assert main(["run", str(scene_path), "--model", "gb", "--seed", "5", "--quick", "--iters", "1", "--out", str(tmp_path / "out")]) == 0
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["model"] == "gb" and metrics["seed"] == 5
    # The schedule resolved: None stands for 10 and 1 times the learning rate.
    assert metrics["bundle"] == {"samples": 4, "initial_sigma": None, "final_sigma": None, "seed": 5, "sigma_schedule": [10 * metrics["learning_rate"]] * 2}
    # One iteration draws no bundle: the counts were missing, not 0 (a probe, stop 58); and the
    # contact mode run is recorded (gb: sdrs; "ours" runs the scene's own).
    assert metrics["bundle_samples"] == metrics["bundle_samples_dropped"] == 0 and metrics["contact_mode"] == "sdrs"
    assert main(["run", str(scene_path), "--iters", "1", "--out", str(tmp_path / "ours")]) == 0
    assert json.loads((tmp_path / "ours" / "metrics.json").read_text())["contact_mode"] == "bsh"


def test_ipc_stiffness_is_checked_by_name_for_every_model():
    # 1e200 was named as contact_stiffness, and -1 passed for the models that do not use it.
    for model, value in (("ipc", 1e200), ("sdrs", -1.0), ("ours", float("nan"))):
        with pytest.raises(ValueError, match=r"^ipc_stiffness: must"):
            TaskProblem(space_billiards(), model=model, ipc_stiffness=value)


def test_cli_compare_writes_json_and_plot(tmp_path, capsys):
    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    out = tmp_path / "cmp"
    assert main(["compare", str(scene_path), "--models", "ours,sdrs,gb", "--iters", "2", "--quick", "--seed", "3", "--out", str(out)]) == 0
    data = json.loads((out / "compare.json").read_text())
    assert list(data["models"]) == ["ours", "sdrs", "gb"] and data["complete"] is True
    assert data["task"] == "space_billiards" and data["seed"] == 3 and data["iterations_per_window"] == 2
    for result in data["models"].values():
        for key in ("loss_history", "initial_loss", "final_loss", "success", "seconds"):
            assert key in result
        assert len(result["loss_history"]) == 2
    assert data["models"]["gb"]["bundle"]["seed"] == 3
    # Each model's contact settings (a probe, stop 62: no output recorded dhat, and gb's
    # sigmas read null): the scene's mu, SDRS's dhat, gb's sigma schedule (10 lr down to lr
    # over a window's updates).
    models = data["models"]
    assert models["ours"]["contact_stiffness"] == models["sdrs"]["contact_stiffness"] == space_billiards().settings.contact_stiffness
    assert "dhat_m" not in models["ours"] and models["sdrs"]["dhat_m"] == models["gb"]["dhat_m"] == 1e-2
    # --iters 2: one Adam update, at the schedule's first sigma, 10 lr.
    assert models["gb"]["bundle"]["sigma_schedule"] == pytest.approx([10 * data["learning_rate"]] * 2, rel=1e-12)
    assert (out / "compare.png").stat().st_size > 1000
    assert "wrote" in capsys.readouterr().out


def test_cli_compare_runs_baselines_with_friction_and_reports_models_that_cannot_run(tmp_path, capsys, monkeypatch):
    scene = space_billiards()
    scene.settings.friction = 0.5
    scene_path = tmp_path / "friction.usda"
    io.save_scene(scene, scene_path)
    argv = ["compare", str(scene_path), "--models", "ours,sdrs", "--iters", "1", "--out", str(tmp_path / "cmp")]
    assert main(argv) == 0
    data = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert not data["frictionless"] and all("loss_history" in r for r in data["models"].values())
    real = cli._task_problem

    def sdrs_cannot_run(scene, settings, model, args):
        if model == "sdrs":
            raise ValueError("sdrs cannot run this scene")
        return real(scene, settings, model, args)

    monkeypatch.setattr(cli, "_task_problem", sdrs_cannot_run)
    before = (tmp_path / "cmp" / "compare.json").read_text()
    assert main(argv + ["--frictionless"]) == 2  # the first comparison's results stay
    assert "compare.json holds an earlier run's results (use --overwrite)" in capsys.readouterr().err
    assert (tmp_path / "cmp" / "compare.json").read_text() == before
    assert main(argv + ["--frictionless", "--overwrite"]) == 0
    data = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert data["frictionless"] and "loss_history" in data["models"]["ours"]
    assert "cannot run" in data["models"]["sdrs"]["error"]
    assert "sdrs: skipped" in capsys.readouterr().err
    # Where no model runs, no plot says "loss 0 at every iteration" beside compare.json.
    (tmp_path / "c2").mkdir()
    (tmp_path / "c2" / "compare.png").write_bytes(b"an earlier plot")
    assert main(["compare", str(scene_path), "--models", "sdrs", "--iters", "1", "--out", str(tmp_path / "c2"), "--overwrite"]) == 1
    captured = capsys.readouterr()
    assert "no model could run" in captured.err and "not compare.png (no model ran)" in captured.out
    assert not (tmp_path / "c2" / "compare.png").exists() and "error" in json.loads((tmp_path / "c2" / "compare.json").read_text())["models"]["sdrs"]


def test_cli_compare_interrupted_keeps_and_plots_the_finished_models(tmp_path, capsys, monkeypatch):
    # Ctrl-C during compare ended in a traceback with no plot and no message.
    from warpcontact.tasks import TaskProblem

    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    interrupt_call(monkeypatch, TaskProblem, "optimize", 2)
    out = tmp_path / "cmp"
    assert main(["compare", str(scene_path), "--models", "ours,sdrs,gb", "--iters", "1", "--out", str(out)]) == 130
    stopped = json.loads((out / "compare.json").read_text())
    # It read as a finished comparison of ours alone (the benches' JSON say "complete").
    assert list(stopped["models"]) == ["ours"] and stopped["complete"] is False
    assert (out / "compare.png").is_file()
    assert "interrupted during sdrs: the models before it are in" in capsys.readouterr().err
    # Stopped during the first model, an earlier comparison's compare.json was announced as
    # this one's, beside a new plot of "loss 0 at every iteration".
    earlier = {name: (out / name).read_bytes() for name in ("compare.json", "compare.png")}
    interrupt_call(monkeypatch, TaskProblem, "optimize", 1)
    assert main(["compare", str(scene_path), "--models", "sdrs,ours", "--iters", "1", "--out", str(out), "--overwrite"]) == 130
    captured = capsys.readouterr()
    assert "interrupted during sdrs before any model finished: nothing written (compare.json, compare.png in" in captured.err
    assert "wrote" not in captured.out
    assert {name: (out / name).read_bytes() for name in earlier} == earlier
    # Stopped while its plot was drawn, the earlier run's compare.png stayed beside the new
    # compare.json, and only "interrupted" was said.
    interrupt_call(monkeypatch, cli, "_plot_convergence", 1)
    assert main(["compare", str(scene_path), "--models", "sdrs", "--iters", "1", "--out", str(out), "--overwrite"]) == 130
    assert list(json.loads((out / "compare.json").read_text())["models"]) == ["sdrs"]
    assert not (out / "compare.png").exists()
    assert "interrupted while drawing compare.png:" in capsys.readouterr().err
    # Killed (SIGTERM) after its first model, a comparison left its compare.json beside an
    # earlier run's compare.png (a probe, stop 64): the earlier plot goes with the first write.
    assert main(["compare", str(scene_path), "--models", "sdrs", "--iters", "1", "--out", str(out), "--overwrite"]) == 0
    assert (out / "compare.png").is_file()

    class Killed(BaseException):
        pass

    calls, optimize = [], TaskProblem.optimize

    def killed_at_the_second_model(self, **options):
        calls.append(1)
        if len(calls) == 2:
            raise Killed
        return optimize(self, **options)

    monkeypatch.setattr(TaskProblem, "optimize", killed_at_the_second_model)
    with pytest.raises(Killed):
        main(["compare", str(scene_path), "--models", "ours,sdrs", "--iters", "1", "--out", str(out), "--overwrite"])
    assert list(json.loads((out / "compare.json").read_text())["models"]) == ["ours"]
    assert not (out / "compare.png").exists()


def test_quick_preset_values_without_a_quick_horizon_are_an_error():
    # The generic caps ran instead, at the task's learning rate, without a word.
    scene = space_billiards()
    scene.task.quick_receding_horizon, scene.task.quick_learning_rate = 32, 0.05
    with pytest.raises(ValueError, match=r"warpcontact:task:quick:recedingHorizon, warpcontact:task:quick:learningRate are authored but warpcontact:task:quick:horizon is 0 \(none\)"):
        TaskSettings.from_task(scene, quick=True)
    assert TaskSettings.from_task(scene).horizon == scene.task.horizon  # without --quick the preset is not read
    scene.task.quick_receding_horizon, scene.task.quick_learning_rate = 0, 0.0
    assert TaskSettings.from_task(scene, quick=True).horizon <= GENERIC_QUICK_HORIZON  # no preset: the caps


def test_an_authored_quick_value_out_of_range_is_not_called_a_partial_preset():
    scene = space_billiards()
    scene.task.quick_horizon, scene.task.quick_receding_horizon, scene.task.quick_iterations, scene.task.quick_learning_rate = 6, 4, 2, 0.1
    scene.task.quick_receding_stride = 5
    with pytest.raises(ValueError, match=r"quick:recedingStride must be .* got 5$"):
        TaskSettings.from_task(scene, quick=True)


def test_an_articulated_task_whose_window_covers_its_horizon_runs_as_one_window():
    # Refused as receding control, while --quick (whose caps reset the window) ran it.
    from warpcontact.scenes import build_scene

    problem = TaskProblem(build_scene("ant_push"), settings=TaskSettings(horizon=3, receding_horizon=10, iterations=1, learning_rate=3e-2))
    assert problem.settings.window == 3 and not problem.settings.receding
    with pytest.raises(ValueError, match="receding-horizon control of articulated scenes is not supported"):
        TaskProblem(build_scene("ant_push"), settings=TaskSettings(horizon=4, receding_horizon=2, iterations=1, learning_rate=3e-2))


def test_a_partial_quick_preset_says_what_a_preset_is(tmp_path):
    # The error named quick:iterations, which the scene never authored.
    scene = space_billiards()
    scene.task.quick_horizon = 3
    with pytest.raises(ValueError, match=r"warpcontact:task:quick:iterations must be .* \(a --quick preset is warpcontact:task:quick:horizon, recedingHorizon"):
        TaskSettings.from_task(scene, quick=True)
    # A bad command-line value is not the preset's fault.
    scene.task.quick_receding_horizon, scene.task.quick_iterations, scene.task.quick_learning_rate = 2, 1, 0.1
    with pytest.raises(ValueError, match=r"--stride must be .*got 1000$"):
        TaskSettings.from_task(scene, quick=True, receding_stride=1000)


def test_iterations_are_capped_with_a_clear_error(capsys):
    """gb's sigma schedule holds one number per iteration: --iters 1e12 died in a 7.3 TiB
    MemoryError traceback."""
    with pytest.raises(ValueError, match=r"iterations \(--iters\) must be a whole number from 1 to 10,000,000, got 1000000000000"):
        TaskSettings.from_task(space_billiards(), iterations=10**12)
    # The command line's bound is the same (it was 2,147,483,647 there; a probe, stop 65).
    from warpcontact.cli import main

    with pytest.raises(SystemExit):
        main(["run", "push", "--iters", "20000000"])
    assert "--iters: must be a whole number from 1 to 10,000,000, got 20000000" in capsys.readouterr().err


def test_cli_compare_skips_ipc_without_ipctk_and_keeps_the_other_models(tmp_path, capsys, monkeypatch):
    import sys

    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    monkeypatch.setitem(sys.modules, "ipctk", None)  # import ipctk now fails, as where it is not installed
    assert main(["compare", str(scene_path), "--models", "ours,ipc", "--iters", "1", "--out", str(tmp_path / "cmp")]) == 0
    data = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert "loss_history" in data["models"]["ours"]
    assert "the ipc baseline needs the IPC Toolkit: pip install 'warpcontact[ipc]'" in data["models"]["ipc"]["error"]
    assert "ipc: skipped" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["run", "compare"])
def test_cli_task_errors_are_clear(tmp_path, capsys, command):
    assert main([command, "no_such_task", "--out", str(tmp_path)]) == 2
    assert "not a USD file (.usda, .usd, .usdc, .usdz)" in capsys.readouterr().err
    plain = tmp_path / "plain.usda"
    scene = space_billiards()
    scene.task = io.TaskSpec()
    io.save_scene(scene, plain)
    assert main([command, str(plain), "--out", str(tmp_path / "o")]) == 2
    assert "no task metadata" in capsys.readouterr().err
    assert main([command, str(plain), "--device", "cuda:7", "--out", str(tmp_path / "o")]) == 2
    assert "device: 'cuda:7' is not available" in capsys.readouterr().err
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    assert main([command, str(plain), "--out", str(a_file)]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert main([command, str(plain), "--out", str(a_file / "sub")]) == 2
    assert "cannot create the output folder" in capsys.readouterr().err
    locked = tmp_path / "locked"
    locked.mkdir()
    os.chmod(locked, 0o500)
    try:
        if not os.access(locked, os.W_OK):  # root can write anywhere
            assert main([command, str(plain), "--out", str(locked)]) == 2
            assert "not writable" in capsys.readouterr().err
    finally:
        os.chmod(locked, 0o700)


def test_a_folder_the_file_system_refuses_is_named_not_its_lock_file(tmp_path, monkeypatch):
    """Found by a probe: as root, os.access passes /sys/kernel, and the lock file's
    PermissionError was the message ("[Errno 13] Permission denied: '.../.warpcontact-lock'")."""
    from warpcontact import _files

    real_open = os.open

    def refusing_open(path, *args, **kwargs):
        if str(path).endswith(_files.LOCK_NAME):
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(_files.os, "open", refusing_open)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(tmp_path))}: output folder is not writable \(Permission denied\)$"):
        _files.hold_folder(tmp_path)


def test_cli_stride_reaches_the_settings_and_is_checked_against_the_window(tmp_path, capsys):
    assert main(["run", "push", "--stride", "49", "--out", str(tmp_path)]) == 2
    assert "--stride must be a whole number >= 1 and at most the window (48), got 49" in capsys.readouterr().err
    scene = _pd_space_billiards()
    scene.task.horizon, scene.task.receding_horizon = 4, 2
    scene_path = tmp_path / "receding.usda"
    io.save_scene(scene, scene_path)
    assert main(["run", str(scene_path), "--stride", "2", "--iters", "1", "--out", str(tmp_path / "out")]) == 0
    assert "window 2 executed 2 frame(s) at a time" in capsys.readouterr().out
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["receding_stride"] == 2 and metrics["window"] == 2 and len(metrics["loss_history"]) == 2
    # An authored receding horizon not shorter than the horizon leaves one window: the
    # metrics said "receding horizon 10, stride 2" for a one-window run (a probe).
    scene.task.receding_horizon = 10
    io.save_scene(scene, scene_path, overwrite=True)
    assert main(["run", str(scene_path), "--iters", "1", "--out", str(tmp_path / "one")]) == 0
    metrics = json.loads((tmp_path / "one" / "metrics.json").read_text())
    assert (metrics["receding_horizon"], metrics["window"], metrics["receding_stride"]) == (10, 4, None)
    with pytest.raises(SystemExit):
        main(["run", str(scene_path), "--stride", "0", "--out", str(tmp_path / "bad")])


@pytest.mark.parametrize("argv", [["run", "push", "--model", "mujoco"], ["compare", "push", "--models", "ours,mujoco"], ["compare", "push", "--models", ","]])
def test_cli_unknown_models_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert "ours" in capsys.readouterr().err  # names the choices


def test_cli_list_names_the_tasks(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ("billiards", "push", "sort", "gather", "gather_bunny"):
        assert name in out


def test_ant_push_sine_controls_get_long_range_gradients_and_lower_the_loss():
    from warpcontact.scenes import build_scene

    problem = TaskProblem(build_scene("ant_push"), settings=TaskSettings(horizon=12, receding_horizon=0, iterations=2, learning_rate=3e-2))
    assert len(problem.dof_names) == 12  # hips (swing, lift) and knees of four legs
    values = problem.initial_values(1)
    assert values.shape == (12, 12) and not values[:, 0::3].any()
    q0 = problem.model.initial_q
    loss, grad, _ = problem.rollout(values, (q0, q0), 12)
    # The box is 1 m from the ant's feet: only the long-range potential links them.
    assert loss > 0 and np.abs(grad[:, 0::3]).max() > 0
    result = problem.optimize()
    assert result.final_loss < result.initial_loss
    # Another start would keep the initial joint coordinates under moved poses.
    moved = q0.copy()
    moved[:, 0] += 0.1
    with pytest.raises(ValueError, match="start: an articulated scene's rollouts start from its initial poses at rest"):
        problem.rollout(values, (moved, moved), 2)


@pytest.mark.parametrize("name", ["push", "sort"])
def test_shipped_rod_tasks_lower_the_loss_from_the_trivial_guess(name):
    """Two Adam steps on an 8-frame window: the rod is far from every object (only the
    long-range potential links them), yet the second iterate's loss is strictly lower.
    (Gather's rod starts 2.4 m from its nearest cube: there its preset's first steps change
    the loss by ~1e-11 either way, the size of what the implicit solves' tolerance leaves
    in it; its loss falls only once the rod nears the cubes, docs/tasks.md.)"""
    from warpcontact.scenes import build_scene

    scene = build_scene(name)
    settings = TaskSettings.from_task(scene, quick=True)
    settings.horizon, settings.receding_horizon, settings.iterations = 8, 0, 2
    result = TaskProblem(scene, settings=settings).optimize()
    assert result.loss_history[1] < result.loss_history[0]
    assert result.final_loss < result.initial_loss


def test_gather_rod_behind_a_cube_lowers_the_loss_through_the_long_range_potential():
    """Gather with its shipped settings (pair-weighted centred terms, the preset's steps of
    0.05), the rod 0.3 m behind the nearest cube as seen from the goal: nothing touches, yet
    each Adam step lowers the loss (measured ~1e-9 a step, far above the ~1e-12 that the
    implicit solves' tolerance leaves in it)."""
    from warpcontact.scenes import build_scene

    scene = build_scene("gather")
    assert scene.settings.centred_weight == "pairs"
    rod, cube = scene.body("rod"), scene.body("cube7")
    away_from_goal = cube.pose[:2] / np.linalg.norm(cube.pose[:2])
    rod.pose[:2] = cube.pose[:2] + away_from_goal * (0.15 + 0.05 + 0.3)  # cube half-width, rod half-width, gap
    settings = TaskSettings.from_task(scene, quick=True)
    settings.horizon, settings.receding_horizon, settings.iterations = 8, 0, 3
    history = TaskProblem(scene, settings=settings).optimize().loss_history
    assert history[0] > 0
    assert np.all(np.diff(history) < -1e-10)


def sampled_space_billiards():
    """space_billiards with a sample box for the cue's (x, y, vx, vy): some draws strike."""
    scene = space_billiards()
    scene.task.sample_low, scene.task.sample_high = (-0.3, -0.3, 0.0, -1.0), (0.3, 0.6, 8.0, 2.0)
    return scene


def test_initial_samples_start_the_descent_at_the_best_draw():
    """The paper's random-sampling initialisation: the descent starts from the lowest-loss
    draw of the scene's box, and every draw (seeded) is recorded with its loss."""
    settings = TaskSettings(horizon=15, receding_horizon=0, iterations=2, learning_rate=0.3, initial_samples=5, sample_seed=1)
    scene = sampled_space_billiards()
    drawn = []
    result = TaskProblem(scene, settings=settings).optimize(sample_progress=lambda *reported: drawn.append(reported))
    samples = result.extra["initial_samples"]
    assert len(samples) == 5
    # Each draw is reported as it finishes: eight Billiards draws took minutes in silence (a probe, stop 63).
    assert drawn == [(k + 1, 5, sample["loss"]) for k, sample in enumerate(samples)]
    losses = [s["loss"] for s in samples]
    low, high = np.array(scene.task.sample_low), np.array(scene.task.sample_high)
    for s in samples:
        assert np.all(low <= s["values"]) and np.all(np.array(s["values"]) <= high)
    best = int(np.argmin(losses))
    assert result.loss_history[0] == pytest.approx(losses[best], rel=1e-12)
    trivial = TaskProblem(space_billiards(), settings=TaskSettings(15, 0, 1, 0.3)).optimize()
    assert min(losses) < trivial.initial_loss  # some draw strikes the target
    again = TaskProblem(sampled_space_billiards(), settings=settings).optimize()
    assert again.extra["initial_samples"] == samples  # the seed fixes the draws


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda s: setattr(s.task, "sample_low", ()), "warpcontact:task:sampleHigh is authored without warpcontact:task:sampleLow"),
        (lambda s: setattr(s.task, "sample_high", (1.0, 1.0, 1.0)), "sampleHigh has 3 values for the 4 control DOFs"),
        (lambda s: setattr(s.task, "sample_low", (0.0, 0.0, np.nan, 0.0)), "sampleLow must be finite"),
        # numpy's draw overflowed (a traceback), or every draw was "not feasible" (a probe, stop 63).
        (lambda s: setattr(s.task, "sample_low", (-1e308, 0.0, 0.0, 0.0)), r"sampleLow must be finite and within \+-1e\+150, got \[-1e\+308"),
        (lambda s: setattr(s.task, "sample_high", (1e200, 1.0, 1.0, 1.0)), r"sampleHigh must be finite and within \+-1e\+150"),
        (lambda s: setattr(s.task, "sample_low", (0.5, -0.3, 0.0, -1.0)), "exceeds warpcontact:task:sampleHigh"),
        (lambda s: (setattr(s.task, "control", "pd_targets"), setattr(s.bodies[0], "control_dofs", ("x", "y")), setattr(s.bodies[0], "kp_linear", np.full(3, 100.0))), "this task's control is 'pd_targets'"),
    ],
)
def test_initial_samples_need_a_valid_box(change, message):
    scene = sampled_space_billiards()
    change(scene)
    with pytest.raises(ValueError, match=message):
        TaskProblem(scene, settings=TaskSettings(15, 0, 1, 0.3, initial_samples=2))


def test_initial_samples_all_infeasible_is_a_clear_error():
    scene = sampled_space_billiards()
    scene.task.sample_low, scene.task.sample_high = (1.0, 0.3, 0.0, 0.0), (1.0, 0.3, 0.0, 0.0)  # the cue inside the target
    problem = TaskProblem(scene, settings=TaskSettings(15, 0, 1, 0.3, initial_samples=2))
    with pytest.raises(ValueError, match="none of the 2 initial samples is feasible"):
        problem.optimize()


def test_cli_init_samples_round_trip_the_box_and_record_the_draws(tmp_path, capsys):
    scene_path = tmp_path / "space.usda"
    io.save_scene(sampled_space_billiards(), scene_path)
    assert io.load_scene(scene_path).task.sample_high == (0.3, 0.6, 8.0, 2.0)
    out = tmp_path / "out"
    assert main(["run", str(scene_path), "--init-samples", "3", "--seed", "2", "--iters", "1", "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["init_samples"] == 3 and len(metrics["initial_samples"]) == 3
    assert "initial samples: 3/3 drawn" in capsys.readouterr().out
    assert metrics["initial_loss"] == min(s["loss"] for s in metrics["initial_samples"])
    plain = tmp_path / "plain.usda"
    io.save_scene(space_billiards(), plain)
    assert main(["run", str(plain), "--init-samples", "3", "--out", str(tmp_path / "out2")]) == 2
    assert "need warpcontact:task:sampleLow" in capsys.readouterr().err


def test_cli_compare_init_samples_start_every_model_from_one_draw(tmp_path, capsys):
    """Each model chose the best draw by its own loss, so a compare's models started from
    different draws (ours from a strike, sdrs from a miss; a probe, stop 62). The draws are
    now scored once, by ours, and every model starts from the same values."""
    scene_path = tmp_path / "space.usda"
    io.save_scene(sampled_space_billiards(), scene_path)
    out = tmp_path / "cmp"
    assert main(["compare", str(scene_path), "--models", "sdrs,ours", "--init-samples", "3", "--seed", "2", "--iters", "1", "--out", str(out)]) == 0
    payload = json.loads((out / "compare.json").read_text())
    chosen = payload["initial_samples"]
    assert chosen["scored_by"] == "ours" and len(chosen["samples"]) == 3
    feasible = [x for x in chosen["samples"] if x["loss"] is not None]
    best = min(feasible, key=lambda x: x["loss"])
    assert chosen["start"] == best["values"]
    assert payload["models"]["ours"]["initial_loss"] == best["loss"]
    settings = TaskSettings(15, 0, 1, 0.3, initial_values=tuple(best["values"]))
    for model in ("ours", "sdrs"):
        alone = TaskProblem(io.load_scene(scene_path), settings=dataclasses.replace(settings, horizon=payload["horizon"]), model=model).optimize()
        assert payload["models"][model]["initial_loss"] == pytest.approx(alone.initial_loss, rel=1e-12)
    assert "the best of 3 draws by ours's loss" in capsys.readouterr().out


@pytest.mark.parametrize(
    "values, samples, message",
    [
        ((0.1, 0.2, 1.0), 0, r"settings.initial_values must hold one value per control DOF \(x, y, vx, vy\)"),
        ((0.1, 0.2, np.nan, 0.0), 0, "settings.initial_values must be None or a tuple of finite numbers"),
        ((0.1, 0.2, 1.0, 0.0), 2, "settings.initial_values must be None or a tuple of finite numbers, and None with initial_samples"),
    ],
)
def test_initial_values_are_checked(values, samples, message):
    with pytest.raises(ValueError, match=message):
        TaskProblem(sampled_space_billiards(), settings=TaskSettings(15, 0, 1, 0.3, initial_samples=samples, initial_values=values)).optimize()


def test_initial_values_start_the_descent_there():
    settings = TaskSettings(15, 0, 1, 0.3, initial_values=(0.1, 0.2, 6.0, 1.0))
    problem = TaskProblem(space_billiards(), settings=settings)
    start = np.array([settings.initial_values])
    assert problem.optimize().initial_loss == pytest.approx(problem.rollout(start, problem.start, 15, gradient=False)[0], rel=1e-12)


def _simulated(scene, frames: int, *, held: bool) -> np.ndarray:
    """The final poses of ``scene`` stepped frame by frame from its authored velocities, with
    the model's control (PD targets at the scene's poses, as `simulate` steps) when ``held``,
    else without one."""
    model = scene.build_model()
    solver = wc.ImplicitSolver(model)
    state = model.state(requires_grad=False)
    linear, angular = scene.initial_velocities()
    wc.set_body_velocity(state, wp.array(linear, dtype=wp.vec3d), wp.array(angular, dtype=wp.vec3d), scene.settings.time_step)
    for _ in range(frames):
        following = model.state(requires_grad=False)
        solver.step(state, following, model.control(requires_grad=False) if held else None, scene.settings.time_step)
        state = following
    return state.body_q.numpy()


def test_an_initial_state_rollout_holds_pd_bodies_at_their_targets_as_simulate_does():
    """Found by a probe: an initial_state rollout stepped without a control, so a PD-driven
    body's spring followed the body (only its damping acted) and the run optimised other
    physics than `simulate` showed (a held ball at x 0.7353 against 0.6876 after 4 frames)."""
    scene = space_billiards()
    held = scene.bodies[1]
    held.kp_linear, held.kd_linear = np.full(3, 400.0), np.full(3, 20.0)
    held.linear_velocity = np.array([2.0, 0.0, 0.0])
    problem = TaskProblem(scene)
    _, _, trajectory = problem.rollout(problem.initial_values(1), problem.start, 4, gradient=False)
    np.testing.assert_array_equal(trajectory[-1], _simulated(scene, 4, held=True))
    following = _simulated(scene, 4, held=False)  # the springs following their bodies, as the rollout stepped before
    assert following[1, 0] - trajectory[-1][1, 0] > 0.01


def test_an_initial_state_control_on_a_jointed_body_is_refused():
    """Found by a probe: its velocities moved nothing (the joints' coordinates did not follow)
    and its offsets failed every rollout with an internal 'joint anchors apart' message."""
    from warpcontact.scenes import build_scene
    from warpcontact.tasks import validate_task

    scene = build_scene("ant_push")
    leg = next(b for b in scene.bodies if any(b.name == j.child and j.parent is not None for j in scene.joints))
    joint = next(j for j in scene.joints if leg.name in (j.child, j.parent))
    scene.task.control = "initial_state"
    leg.control_dofs = ("vx", "vy")
    with pytest.raises(ValueError, match=rf"prim {re.escape(leg.path)}: warpcontact:control:dofs: an initial_state control sets a free body's start pose and velocity, but joint {re.escape(joint.path)} links {leg.name!r}"):
        validate_task(scene)


def test_a_push_that_slides_and_turns_the_box_has_the_gradient_of_central_differences():
    """Task gradients in contact with friction (a probe found none tested): the shipped Push
    scene with the rod started just behind the box, off its centre line, driven 0.6 m on, so
    the box slides 0.49 m and turns 27 degrees in 12 frames; the taped gradient along random
    directions against central differences of two step sizes."""
    from warpcontact.scenes import shipped_scene

    problem = TaskProblem(io.load_scene(shipped_scene("push")))
    problem.solver.tolerance = 1e-13
    q = problem.start[0].copy()
    q[2, :3] = (-0.33, 0.1, 0.33)
    start, frames = (q, q.copy()), 12
    values = problem.initial_values(frames)
    values[:, 0], values[:, 1] = 0.6, 1.1
    _, grad, trajectory = problem.rollout(values, start, frames)
    assert trajectory[-1, 1, 0] > 0.4 and abs(trajectory[-1, 1, 5]) > 0.2  # slid and turned
    rng = np.random.default_rng(3)
    for _ in range(2):
        direction = rng.standard_normal(values.shape)
        analytic = float(np.sum(grad * direction))
        for h in (1e-5, 1e-6):
            ahead = problem.rollout(values + h * direction, start, frames, gradient=False)[0]
            behind = problem.rollout(values - h * direction, start, frames, gradient=False)[0]
            assert (ahead - behind) / (2 * h) == pytest.approx(analytic, rel=1e-5)


def test_a_sample_box_is_checked_whether_or_not_a_run_draws_from_it():
    """A probe at stop 61: a box on a pd_targets task, or an inverted or short one, ran
    without a word unless --init-samples asked for it."""
    from warpcontact.tasks import validate_task

    scene = space_billiards()
    scene.task.sample_low, scene.task.sample_high = (-1.0, -1.0, 0.0, 0.0), (1.0, 1.0, 2.0, 2.0)
    validate_task(scene)
    scene.task.sample_high = (1.0, 1.0, -2.0, 2.0)
    with pytest.raises(ValueError, match=r"warpcontact:task:sampleLow \[-1.0, -1.0, 0.0, 0.0\] exceeds warpcontact:task:sampleHigh"):
        validate_task(scene)
    scene.task.sample_high = ()
    with pytest.raises(ValueError, match=r"warpcontact:task:sampleLow is authored without warpcontact:task:sampleHigh; a random-sampling box needs both"):
        validate_task(scene)
    pushed = _pd_space_billiards()
    pushed.task.sample_low, pushed.task.sample_high = (-1.0, -1.0), (1.0, 1.0)
    with pytest.raises(ValueError, match=r"sampleLow and sampleHigh bound random initial-state controls; this task's control is 'pd_targets', which never reads them: remove them"):
        validate_task(pushed)


def _pd_space_billiards():
    """space_billiards with the cue driven by PD targets in x, y (a receding-horizon task)."""
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("x", "y")
    scene.bodies[0].kp_linear = np.full(3, 100.0)
    scene.task.control = "pd_targets"
    return scene


@pytest.mark.parametrize(
    "dofs, control, match",
    [
        (("x", "x"), "pd_targets", r"\['x'\] control the same coordinate more than once"),
        (("yaw", "rz"), "pd_targets", r"\['rz', 'yaw'\] control the same coordinate more than once"),
        (("x", "vx"), "pd_targets", r"\['vx'\] are initial velocities, which pd_targets control does not use"),
        (("x", "yaw"), "pd_targets", r"the PD targets of \['yaw'\] move nothing without a positive PD stiffness there .*got \{'yaw': 0.0\}"),
        (("x", "spin"), "initial_state", r"unknown control dofs \['spin'\]"),
    ],
)
def test_control_dofs_that_move_nothing_are_refused(dofs, control, match):
    """Every decision variable must move the controlled body; otherwise its gradient is zero
    and the run would silently optimise nothing."""
    scene = _pd_space_billiards()  # kp_linear 100, kp_angular 0
    scene.bodies[0].control_dofs = dofs
    scene.task.control = control
    with pytest.raises(ValueError, match=r"prim /World/cue: warpcontact:control:dofs: " + match):
        TaskProblem(scene)
    scene.bodies[0].control_dofs = ("x", "y", "vx") if control == "initial_state" else ("x", "y")
    TaskProblem(scene)  # the same body with dofs that move it


@pytest.mark.parametrize("index, label", [(1, "target"), (0, "controlled")])
def test_a_static_target_or_controlled_body_is_refused(index, label):
    """A kinematic target box ran the whole optimisation at one loss."""
    scene = _pd_space_billiards()
    scene.bodies[index].static = True
    with pytest.raises(ValueError, match=rf"prim {scene.bodies[index].path}: a {label} body must be dynamic, but it is static"):
        TaskProblem(scene)


def test_yaw_turns_about_the_stage_up_axis():
    """Found by a probe: yaw turned about world z on a Y-up stage too, a horizontal axis there."""
    from warpcontact.scenes import build_scene
    from warpcontact.rotation import quat_mul, quat_rotate

    turn = np.array([-np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])  # z -> y
    for up, code in (("Z", task_kernels.DOF_CODES["rz"]), ("Y", task_kernels.DOF_CODES["ry"])):
        scene = build_scene("push")
        if up == "Y":
            scene.up_axis, scene.gravity = "Y", quat_rotate(turn, scene.gravity)
            for body in scene.bodies:
                body.pose = np.array([*quat_rotate(turn, body.pose[:3]), *quat_mul(turn, body.pose[3:])])
        scene.body("rod").control_dofs = ("x", "yaw")
        assert TaskProblem(scene)._dof_codes.numpy().tolist() == [0, code]
        scene.body("rod").control_dofs = ("yaw", "ry" if up == "Y" else "rz")
        with pytest.raises(ValueError, match=r"control the same coordinate more than once"):
            TaskProblem(scene)


def test_rollout_refuses_values_of_the_wrong_shape():
    """Fewer rows than frames were read out of bounds by the control kernel: the process
    aborted ("corrupted double-linked list")."""
    problem = TaskProblem(_pd_space_billiards(), settings=TaskSettings(horizon=3, receding_horizon=0, iterations=1, learning_rate=0.05))
    q0 = problem.model.initial_q
    assert problem.rollout(np.zeros((3, 2)), (q0, q0), 3)[1].shape == (3, 2)
    for values in (np.zeros((2, 2)), np.zeros((3, 3)), np.zeros(2)):
        with pytest.raises(ValueError, match=r"values: pd_targets control over 3 frames needs at least 3 rows of 2 values \(x, y\), got shape"):
            problem.rollout(values, (q0, q0), 3)
    with pytest.raises(ValueError, match=r"frames: must be a whole number >= 0, got -1"):
        problem.rollout(np.zeros((3, 2)), (q0, q0), -1)
    with pytest.raises(ValueError, match=r"start q: expected \(2, 7\) poses .*got shape \(1, 7\)"):
        problem.rollout(np.zeros((3, 2)), (q0[:1], q0[:1]), 3)  # the missing pose was left as it was
    # Found by a probe: text was read as numbers, and 1e200 was blamed on control.body_target.
    with pytest.raises(ValueError, match=r"values: must be real numbers \(integers or floats\), got <U1 values"):
        problem.rollout(np.full((3, 2), "1"), (q0, q0), 3)
    values = np.zeros((3, 2))
    values[2, 1] = -1e200
    with pytest.raises(ValueError, match=r"values: row 2, dof 'y' is -1e\+200, beyond the \+-1e\+150"):
        problem.rollout(values, (q0, q0), 3)


def test_settings_changed_after_the_problem_was_built_are_checked_again():
    """Found by a probe: the problem's settings are its own attribute and may be changed,
    but optimize never checked them again: 0 iterations ended in an IndexError, a negative
    learning rate ran uphill, and a receding horizon on an initial_state task ran one window."""
    problem = TaskProblem(space_billiards(), settings=TaskSettings(horizon=2, receding_horizon=0, iterations=1, learning_rate=0.1))
    for field, value, message in (
        ("iterations", 0, r"settings.iterations must be a whole number from 1 to"),
        ("learning_rate", -5.0, r"settings.learning_rate must be positive and finite, got -5.0"),
        ("receding_horizon", 1, r"receding-horizon control applies to pd_targets tasks, and this task's control is initial_state"),
    ):
        original = getattr(problem.settings, field)
        setattr(problem.settings, field, value)
        with pytest.raises(ValueError, match=message):
            problem.optimize()
        setattr(problem.settings, field, original)
    assert problem.optimize().iterations == 1


def test_a_negative_pd_stiffness_is_reported_as_such():
    """It was reported as moving nothing "without a positive PD stiffness" (a probe, stop 64)."""
    scene = _pd_space_billiards()
    scene.bodies[0].kp_linear = np.array([-400.0, 100.0, 100.0])
    with pytest.raises(ValueError, match=r"warpcontact:control:dofs: a PD stiffness must be finite and >= 0 \(warpcontact:pd:kpLinear / kpAngular\), got \{'x': -400.0\}"):
        TaskProblem(scene)


def test_a_task_control_and_its_controlled_bodies_are_named_by_attribute():
    """A misspelt or missing control was "task control '' is not one of (...)", naming no
    attribute, and two controlled bodies were counted, not named (a probe, stop 64)."""
    scene = _pd_space_billiards()
    scene.task.control = "pd_target"
    with pytest.raises(ValueError, match=r"warpcontact:task:control \(on the PhysicsScene prim\) is 'pd_target'; it must be one of initial_state, pd_targets, joint_sine"):
        TaskProblem(scene)
    scene.task.control = ""
    with pytest.raises(ValueError, match=r"warpcontact:task:control \(on the PhysicsScene prim\) is not authored; it must be one of"):
        TaskProblem(scene)
    scene = _pd_space_billiards()
    scene.bodies[1].control_dofs = ("x",)
    with pytest.raises(ValueError, match=r"a pd_targets task controls exactly one body, the one with warpcontact:control:dofs; found 2: /World/cue, /World/target"):
        TaskProblem(scene)
    for body in scene.bodies:
        body.control_dofs = ()
    with pytest.raises(ValueError, match=r"controls exactly one body, the one with warpcontact:control:dofs; found none"):
        TaskProblem(scene)


_CHECKPOINTED_RUNS = {
    # Receding windows (the resumed window continues mid-descent, later ones start afresh).
    "receding": (_pd_space_billiards, TaskSettings(horizon=5, receding_horizon=2, iterations=3, learning_rate=0.05, receding_stride=1), "ours"),
    # One window, gradient bundles: the random generator and the sigma schedule carry over.
    "bundles": (space_billiards, TaskSettings(horizon=15, receding_horizon=0, iterations=4, learning_rate=0.3), "gb"),
}


def _interrupt(problem, calls, checkpoint):
    """Run ``problem.optimize(checkpoint=checkpoint)`` until its ``calls``-th rollout raises
    KeyboardInterrupt, as Ctrl-C there would."""
    rollout, count = problem.rollout, [0]

    def interrupting(*args, **kwargs):
        count[0] += 1
        if count[0] >= calls:
            raise KeyboardInterrupt
        return rollout(*args, **kwargs)

    problem.rollout = interrupting
    with pytest.raises(KeyboardInterrupt):
        problem.optimize(checkpoint=checkpoint)


# Rollouts before the interruption: mid-window and at window starts (a receding run's
# trivial-plan rollout, for its initial loss, comes after the windows); gb rolls out 3 times an iteration
# (the loss, then 2 samples) but once at the last, which is only evaluated, and its first
# checkpoint follows its first 3. The receding run's 4th and 10th calls resume from a
# window's last iterate, whose checkpoint holds no gradient.
@pytest.mark.parametrize(("run", "calls"), [("receding", 3), ("receding", 4), ("receding", 6), ("receding", 10), ("bundles", 4), ("bundles", 8), ("bundles", 10)])
def test_an_interrupted_optimisation_resumes_bit_for_bit(tmp_path, run, calls):
    from warpcontact.bundle import BundleSettings

    make_scene, settings, model = _CHECKPOINTED_RUNS[run]
    bundle = BundleSettings(samples=2, seed=3) if model == "gb" else None

    def problem():
        return TaskProblem(make_scene(), settings=settings, model=model, bundle=bundle)

    full = problem().optimize()
    checkpoint = tmp_path / "checkpoint.npz"
    interrupted = problem()
    _interrupt(interrupted, calls, checkpoint)
    assert checkpoint.exists()
    resumed = problem().optimize(checkpoint=checkpoint, resume=True)
    assert resumed.loss_history == full.loss_history and resumed.final_loss == full.final_loss
    np.testing.assert_array_equal(resumed.values, full.values)
    np.testing.assert_array_equal(resumed.trajectory, full.trajectory)
    assert resumed.extra == full.extra and not checkpoint.exists()


def test_a_checkpoint_is_never_overwritten_or_resumed_into_another_problem(tmp_path):
    make_scene, settings, model = _CHECKPOINTED_RUNS["receding"]
    checkpoint = tmp_path / "checkpoint.npz"
    interrupted = TaskProblem(make_scene(), settings=settings)
    _interrupt(interrupted, 4, checkpoint)
    saved = checkpoint.read_bytes()
    with pytest.raises(ValueError, match=r"checkpoint.npz: holds an unfinished run \(task space_billiards, model ours, frame 0 of 5, 2 Adam iterations"):
        TaskProblem(make_scene(), settings=settings).optimize(checkpoint=checkpoint)
    other = TaskSettings(horizon=5, receding_horizon=2, iterations=3, learning_rate=0.1, receding_stride=1)
    with pytest.raises(ValueError, match=r"checkpoint of another problem \(settings: .*'learning_rate': 0.05.* saved, .*'learning_rate': 0.1"):
        TaskProblem(make_scene(), settings=other).optimize(checkpoint=checkpoint, resume=True)
    with pytest.raises(ValueError, match="checkpoint of another problem .*model: 'ours' saved, 'sdrs' now"):
        TaskProblem(make_scene(), settings=settings, model="sdrs").optimize(checkpoint=checkpoint, resume=True)
    # A yaw turns about the stage's up axis: the same bodies on a Y-up stage are another problem (a probe).
    with pytest.raises(ValueError, match="checkpoint of another problem .*up_axis: None saved, 'Y' now"):
        TaskProblem(dataclasses.replace(make_scene(), up_axis="Y"), settings=settings).optimize(checkpoint=checkpoint, resume=True)
    assert checkpoint.read_bytes() == saved
    with pytest.raises(ValueError, match="missing.npz: no checkpoint to resume"):
        TaskProblem(make_scene(), settings=settings).optimize(checkpoint=tmp_path / "missing.npz", resume=True)
    with pytest.raises(ValueError, match="resume: needs the checkpoint"):
        TaskProblem(make_scene(), settings=settings).optimize(resume=True)
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="broken.npz: not a readable checkpoint"):
        TaskProblem(make_scene(), settings=settings).optimize(checkpoint=broken, resume=True)


def test_cli_run_keeps_its_progress_when_interrupted_and_resumes_it(tmp_path, capsys, monkeypatch):
    from warpcontact import tasks

    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    argv = ["run", str(scene_path), "--iters", "4"]
    assert main([*argv, "--out", str(tmp_path / "full")]) == 0
    full = json.loads((tmp_path / "full" / "metrics.json").read_text())
    out = tmp_path / "out"
    interrupt_call(monkeypatch, tasks.TaskProblem, "rollout", 3)
    capsys.readouterr()
    assert main([*argv, "--out", str(out)]) == 130
    assert "interrupted: progress kept in" in capsys.readouterr().err and (out / cli.CHECKPOINT_NAME).exists()
    assert not (out / "metrics.json").exists()
    assert main([*argv, "--out", str(out)]) == 2
    assert "holds an unfinished run (task space_billiards, model ours, 1 Adam iteration, " in capsys.readouterr().err
    # A checkpoint of other settings is refused before the header says it resumes.
    assert main(["run", str(scene_path), "--iters", "5", "--out", str(out), "--resume"]) == 2
    refused = capsys.readouterr()
    assert "checkpoint of another problem" in refused.err and "resumed from" not in refused.out
    assert main([*argv, "--out", str(out), "--resume"]) == 0
    assert "resumed from" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["loss_history"] == full["loss_history"] and not (out / cli.CHECKPOINT_NAME).exists()
    assert main([*argv, "--out", str(out), "--resume"]) == 2
    assert "no checkpoint to resume" in capsys.readouterr().err
    # A file of the user's by that name: kept, and the way out named (a probe).
    (out / cli.CHECKPOINT_NAME).write_bytes(b"my own data")
    assert main([*argv, "--out", str(out), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.npz: not a readable checkpoint (" in err and err.rstrip().endswith("): remove or rename it, or choose another --out")
    assert (out / cli.CHECKPOINT_NAME).read_bytes() == b"my own data"


def test_a_failed_results_write_leaves_the_earlier_results_whole(tmp_path, capsys, monkeypatch):
    """metrics.json, convergence.png and trajectory.usda were replaced one by one: a failed
    trajectory write left a new metrics.json beside the earlier run's trajectory. They are
    replaced as one set now; the run stays resumable and its resume writes them."""
    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    out = tmp_path / "out"
    assert main(["run", str(scene_path), "--iters", "2", "--out", str(out)]) == 0
    earlier = {name: (out / name).read_bytes() for name in ("metrics.json", "trajectory.usda")}

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(io, "export_trajectory", full_disk)
    capsys.readouterr()
    assert main(["run", str(scene_path), "--iters", "3", "--out", str(out), "--overwrite"]) == 1
    assert "writing the results failed" in capsys.readouterr().err
    assert {name: (out / name).read_bytes() for name in earlier} == earlier
    assert sorted(p.name for p in out.iterdir()) == sorted([cli.CHECKPOINT_NAME, "convergence.png", *earlier])
    monkeypatch.undo()
    assert main(["run", str(scene_path), "--iters", "3", "--out", str(out), "--overwrite", "--resume"]) == 0
    assert json.loads((out / "metrics.json").read_text())["iterations"] == 3
    assert not (out / cli.CHECKPOINT_NAME).exists()


def test_a_resumed_run_keeps_results_another_command_wrote_since_its_checkpoint(tmp_path, capsys, monkeypatch):
    """--resume skipped the check for earlier results: a simulate's trajectory written into
    the folder of an interrupted run was replaced by the resumed run's, without a word.
    Since stop 63 simulate refuses that folder; a trajectory put there otherwise is still
    kept."""
    from warpcontact import tasks

    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    out = tmp_path / "out"
    argv = ["run", str(scene_path), "--iters", "3", "--out", str(out)]
    interrupt_call(monkeypatch, tasks.TaskProblem, "rollout", 2)
    assert main(argv) == 130
    monkeypatch.undo()
    capsys.readouterr()
    assert main(["simulate", str(scene_path), "--frames", "2", "--out", str(out)]) == 2
    assert "an unfinished run's progress" in capsys.readouterr().err
    (out / "trajectory.usda").write_text("another trajectory")
    assert main([*argv, "--resume"]) == 2
    assert "trajectory.usda holds an earlier run's results (use --overwrite)" in capsys.readouterr().err
    assert (out / "trajectory.usda").read_text() == "another trajectory"
    # Replacing it would leave the simulate's summary.json beside the run's trajectory.
    (out / "summary.json").write_text("{}")
    assert main([*argv, "--resume", "--overwrite"]) == 2
    assert "belongs with summary.json" in capsys.readouterr().err
    (out / "summary.json").unlink()
    assert main([*argv, "--resume", "--overwrite"]) == 0


def test_a_descent_without_a_feasible_update_says_so(tmp_path, capsys):
    """An Adam update whose every halving failed to simulate ended the descent without a word
    (a learning rate of 1e300: 1 of 4 iterations, exit 0, no reason given)."""
    scene = space_billiards()
    scene.task.learning_rate = 1e300
    scene_path = tmp_path / "space.usda"
    io.save_scene(scene, scene_path)
    out = tmp_path / "out"
    assert main(["run", str(scene_path), "--iters", "4", "--out", str(out)]) == 0
    assert "note: 1 descent(s) stopped before their iterations were done (the first: iteration 1, no feasible Adam update" in capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 1 and metrics["stalled"][0]["iteration"] == 1


def test_cli_run_reports_a_failed_simulation_without_a_traceback(tmp_path, capsys, monkeypatch):
    from warpcontact import tasks
    from warpcontact.solver import SolverError

    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)

    def failing(self, *args, **kwargs):
        raise SolverError("implicit step: no convergence after 500 Newton iterations")

    monkeypatch.setattr(tasks.TaskProblem, "rollout", failing)
    assert main(["run", str(scene_path), "--iters", "2", "--out", str(tmp_path / "out")]) == 1
    assert "error: the simulation failed: implicit step: no convergence" in capsys.readouterr().err


def _failing_from_window(problem, window):
    """Make the rollouts of ``problem``'s receding windows from the ``window``-th (1-based) on
    fail as a step that does not converge does."""
    from warpcontact.solver import SolverError

    objective, windows = problem._objective, []

    def failing(start, frames, rng, tally=None):
        windows.append(start)
        if len(windows) < window:
            return objective(start, frames, rng, tally)

        def fail(values, gradient=True):
            raise SolverError("implicit step: no convergence after 500 Newton iterations")

        return fail

    problem._objective = failing


def test_a_receding_run_that_cannot_go_on_keeps_the_frames_it_executed(tmp_path):
    """A window whose carried-over plan cannot be simulated ends the run with the frames
    executed before it (hours of a long run are not lost with a traceback), says where and
    why, and claims no success; a trivial guess that cannot be simulated is still an error."""
    from warpcontact.solver import SolverError

    make_scene, settings, _ = _CHECKPOINTED_RUNS["receding"]
    full = TaskProblem(make_scene(), settings=settings).optimize()
    problem = TaskProblem(make_scene(), settings=settings)
    _failing_from_window(problem, 3)
    checkpoint = tmp_path / "checkpoint.npz"
    stopped = problem.optimize(checkpoint=checkpoint)
    assert stopped.extra["stopped"] == {"frame": 2, "error": "implicit step: no convergence after 500 Newton iterations"}
    np.testing.assert_array_equal(stopped.trajectory, full.trajectory[:3])
    assert stopped.loss_history == full.loss_history[: len(stopped.loss_history)] and len(stopped.loss_history) == 2 * settings.iterations
    assert stopped.final_loss == problem._loss_at(full.trajectory[2]) and not stopped.success and not checkpoint.exists()
    # The initial loss is the trivial plan's at the same frame (it was the horizon's, frame 5).
    q0 = problem.model.initial_q
    assert stopped.initial_loss == problem.rollout(np.zeros((2, 2)), (q0, q0), 2, gradient=False)[0] != full.initial_loss
    first = TaskProblem(make_scene(), settings=settings)
    _failing_from_window(first, 1)
    with pytest.raises(SolverError, match="no convergence"):
        first.optimize()


def _trivial_plan_failing(problem, frames):
    """Make ``problem``'s rollouts of the trivial (all-zero) plan over ``frames`` frames fail."""
    from warpcontact.solver import SolverError

    rollout = problem.rollout

    def failing(values, start, count, **kwargs):
        if count == frames and not np.any(values):
            raise SolverError("bodies 'bullet' and 'wall' pass through each other")
        return rollout(values, start, count, **kwargs)

    problem.rollout = failing


def test_a_stopped_run_keeps_its_frames_when_the_trivial_plan_fails_later():
    """The trivial plan's rollout over the whole horizon (for the initial loss) ran before any
    window: a failure past the frame where the windows stop ended the run with nothing kept.
    Where the trivial plan cannot reach the final loss's frame, the initial loss is None and
    the result says why."""
    make_scene, settings, _ = _CHECKPOINTED_RUNS["receding"]
    problem = TaskProblem(make_scene(), settings=settings)
    _failing_from_window(problem, 3)
    _trivial_plan_failing(problem, settings.horizon)
    stopped = problem.optimize()
    assert stopped.extra["stopped"]["frame"] == 2 and len(stopped.trajectory) == 3 and stopped.initial_loss is not None
    finished = TaskProblem(make_scene(), settings=settings)
    _trivial_plan_failing(finished, settings.horizon)
    result = finished.optimize()
    assert result.initial_loss is None and len(result.trajectory) == settings.horizon + 1
    assert result.extra["initial_loss_error"] == "the trivial plan cannot be simulated to frame 5: bodies 'bullet' and 'wall' pass through each other"


def _receding_scene_file(tmp_path, monkeypatch, windows: tuple, patch) -> Path:
    """A receding space-billiards scene (horizon, window, stride = ``windows``) saved for the
    CLI, every TaskProblem of which ``patch(problem)`` alters once built."""
    from warpcontact import tasks

    scene = _pd_space_billiards()
    scene.task.horizon, scene.task.receding_horizon, scene.task.receding_stride = windows
    scene_path = tmp_path / "receding.usda"
    io.save_scene(scene, scene_path)
    init = tasks.TaskProblem.__init__

    def patched(self, *args, **kwargs):
        init(self, *args, **kwargs)
        patch(self)

    monkeypatch.setattr(tasks.TaskProblem, "__init__", patched)
    return scene_path


def test_cli_reports_an_initial_loss_the_trivial_plan_cannot_reach(tmp_path, capsys, monkeypatch):
    scene_path = _receding_scene_file(tmp_path, monkeypatch, (4, 2, 2), lambda problem: _trivial_plan_failing(problem, 4))
    assert main(["run", str(scene_path), "--iters", "2", "--out", str(tmp_path / "out")]) == 0
    assert "loss n/a -> " in capsys.readouterr().out
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["initial_loss"] is None and metrics["initial_loss_error"].startswith("the trivial plan cannot be simulated to frame 4")
    assert main(["compare", str(scene_path), "--models", "ours", "--iters", "2", "--out", str(tmp_path / "compare")]) == 0
    assert re.search(r"\n\s*ours\s+n/a\s", capsys.readouterr().out)


def test_cli_run_writes_what_a_stopped_receding_run_executed(tmp_path, capsys, monkeypatch):
    scene_path = _receding_scene_file(tmp_path, monkeypatch, (5, 2, 1), lambda problem: _failing_from_window(problem, 3))
    out = tmp_path / "out"
    assert main(["run", str(scene_path), "--iters", "2", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "error: the run stopped at frame 2 of 5: the simulation failed: implicit step: no convergence" in err and "Traceback" not in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["stopped"]["frame"] == 2 and metrics["success"] is False and len(metrics["loss_history"]) == 4
    stage = Usd.Stage.Open(str(out / "trajectory.usda"))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 2)
    assert not (out / cli.CHECKPOINT_NAME).exists()
    # compare reports the stopped model's row and keeps it in compare.json.
    assert main(["compare", str(scene_path), "--models", "ours", "--iters", "2", "--out", str(tmp_path / "compare")]) == 0
    assert "stopped at frame 2 (see compare.json)" in capsys.readouterr().out
    assert json.loads((tmp_path / "compare" / "compare.json").read_text())["models"]["ours"]["stopped"]["frame"] == 2


def test_a_checkpoint_knows_its_scene_by_content_not_by_path(tmp_path):
    make_scene, settings, _ = _CHECKPOINTED_RUNS["receding"]
    scene = make_scene()
    io.save_scene(scene, tmp_path / "a.usda")
    io.save_scene(scene, tmp_path / "b.usda")
    moved = make_scene()
    moved.bodies[1].pose = moved.bodies[1].pose + np.array([0.0, 0.01, 0, 0, 0, 0, 0])
    io.save_scene(moved, tmp_path / "moved.usda")
    checkpoint = tmp_path / "checkpoint.npz"
    interrupted = TaskProblem(io.load_scene(tmp_path / "a.usda"), settings=settings)
    _interrupt(interrupted, 4, checkpoint)
    with pytest.raises(ValueError, match="checkpoint of another problem .bodies:"):
        TaskProblem(io.load_scene(tmp_path / "moved.usda"), settings=settings).optimize(checkpoint=checkpoint, resume=True)
    assert TaskProblem(io.load_scene(tmp_path / "b.usda"), settings=settings).optimize(checkpoint=checkpoint, resume=True).loss_history


def test_a_receding_run_s_initial_loss_is_the_trivial_plan_s_at_the_horizon():
    """Where final_loss is measured: the first window's loss, at its own last frame, also
    counted what the bodies do unpushed, and was reported as the initial loss."""
    make_scene, settings, _ = _CHECKPOINTED_RUNS["receding"]
    problem = TaskProblem(make_scene(), settings=settings)
    result = problem.optimize()
    q0 = problem.model.initial_q
    trivial = problem.rollout(np.zeros((settings.horizon, 2)), (q0, q0), settings.horizon, gradient=False)[0]
    assert result.initial_loss == trivial and abs(result.loss_history[0] - trivial) > 1e-3
    # Without a gradient the plan stays trivial, and the executed frames are its rollout's.
    sdrs = TaskProblem(make_scene(), settings=settings, model="sdrs").optimize()
    assert sdrs.final_loss == sdrs.initial_loss


def _rewritten(path, **changes):
    """Rewrite checkpoint ``path`` with its meta (``meta=``, a JSON-able value) or arrays replaced."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    meta = changes.pop("meta", None)
    if meta is not None:
        arrays["meta"] = np.array(json.dumps(meta))
    arrays.update(changes)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("truncated", r"not a readable checkpoint \(File is not a zip file\)"),
        ("empty", r"not a readable checkpoint \(not an .npz archive\)"),
        # numpy's message advised loading the file as a pickle, unsafely (a probe, stop 65).
        ("text", r"not a readable checkpoint \(not an .npz archive\)"),
        ("single array", r"not a readable checkpoint \(a single array, not an .npz archive\)"),
        ("meta a list", r"not a readable checkpoint \(its meta is not a JSON object\)"),
        ("meta without a fingerprint", r"not a complete checkpoint \(missing fingerprint\)"),
        ("encryption flag", r"not a readable checkpoint \(strong encryption"),
        ("values reshaped", r"checkpoint array 'values' has shape \(7, 5\), expected \(2, 2\) for this problem"),
        ("fingerprint a list", r"not a readable checkpoint \(its fingerprint is \[\], expected a JSON object of the task, model and settings\)"),
        # A probe: the description of a checkpoint found without --resume was a KeyError
        # traceback, and a stall that was text a TypeError once the results were written.
        ("fingerprint empty", r"not a readable checkpoint \(its fingerprint is \{\}, expected a JSON object of the task, model and settings\)"),
        ("stalled text", r"not a readable checkpoint \(its extra is \{'stalled': 'x'\}, expected .*, its stalled a list of objects with iteration and error\)"),
        ("iteration 3.5", r"not a readable checkpoint \(its iteration is 3.5, expected a whole number >= 0\)"),
        ("iteration -5", r"not a readable checkpoint \(its iteration is -5, expected a whole number >= 0\)"),
        ("iteration 10**6", r"checkpoint iteration 1000000 is past this problem's 3"),
        ("adam_t text", r"not a readable checkpoint \(its adam_t is 'x', expected a whole number >= 0\)"),
        ("seconds text", r"not a readable checkpoint \(its seconds is 'x', expected a finite number >= 0\)"),
        ("values NaN", r"not a readable checkpoint \(its array 'values' is not all finite numbers\)"),
        ("history 2-D", r"not a readable checkpoint \(its loss history has shape \(2, 2\)"),
        ("moment reshaped", r"checkpoint array 'adam_m' has shape \(3,\), expected \(2, 2\) for this problem"),
        ("rng text", r"not a readable checkpoint \(its rng is 'x', expected null or a PCG64 generator state\)"),
        ("bundle_calls -3", r"not a readable checkpoint \(its bundle_calls is -3, expected a whole number >= 0\)"),
        # Found by a probe: metrics.json then said success, and 7 iterations of a 3-iteration run.
        ("extra with results", r"not a readable checkpoint \(its extra is \{'success': True, 'final_loss': 0.0\}, expected a JSON object of at most bundle, "),
        ("history too long", r"not a readable checkpoint \(its loss history holds 50 losses at iteration \d of the window at frame \d\)"),
    ],
)
def test_a_damaged_checkpoint_is_refused_naming_the_file(tmp_path, damage, message):
    """Each of these used to end in a traceback (BadZipFile, EOFError, TypeError,
    AttributeError, KeyError, a broadcast error naming no file)."""
    make_scene, settings, _ = _CHECKPOINTED_RUNS["receding"]
    checkpoint = tmp_path / "checkpoint.npz"
    interrupted = TaskProblem(make_scene(), settings=settings)
    _interrupt(interrupted, 4, checkpoint)
    if damage == "truncated":
        checkpoint.write_bytes(checkpoint.read_bytes()[:500])
    elif damage == "empty":
        checkpoint.write_bytes(b"")
    elif damage == "text":
        checkpoint.write_text("hello")
    elif damage == "encryption flag":
        # One flipped bit: the first central-directory entry's "strong encryption" flag.
        data = bytearray(checkpoint.read_bytes())
        data[data.find(b"PK\x01\x02") + 8] |= 0x40
        checkpoint.write_bytes(bytes(data))
    elif damage == "single array":
        with open(checkpoint, "wb") as f:
            np.save(f, np.zeros(3))
    else:
        with np.load(checkpoint) as data:
            meta = json.loads(str(data["meta"]))
        if damage == "meta a list":
            _rewritten(checkpoint, meta=[meta])
        elif damage == "meta without a fingerprint":
            del meta["fingerprint"]
            _rewritten(checkpoint, meta=meta)
        elif damage == "values reshaped":
            _rewritten(checkpoint, values=np.zeros((7, 5)))
        elif damage == "values NaN":
            _rewritten(checkpoint, values=np.full((2, 2), np.nan))
        elif damage == "history 2-D":
            _rewritten(checkpoint, history=np.zeros((2, 2)))
        elif damage == "moment reshaped":
            _rewritten(checkpoint, adam_m=np.zeros(3))
        elif damage == "history too long":
            _rewritten(checkpoint, history=np.ones(50))
        elif damage == "extra with results":
            meta["extra"] = {"success": True, "final_loss": 0.0}
            _rewritten(checkpoint, meta=meta)
        else:
            key, value = {"fingerprint a list": ("fingerprint", []), "fingerprint empty": ("fingerprint", {}), "stalled text": ("extra", {"stalled": "x"}), "iteration 3.5": ("iteration", 3.5), "iteration -5": ("iteration", -5),
                          "iteration 10**6": ("iteration", 10**6), "adam_t text": ("adam_t", "x"), "seconds text": ("seconds", "x"),
                          "rng text": ("rng", "x"), "bundle_calls -3": ("bundle_calls", -3)}[damage]
            meta[key] = value
            _rewritten(checkpoint, meta=meta)
    with pytest.raises(ValueError, match=f"checkpoint.npz: {message}"):
        TaskProblem(make_scene(), settings=settings).optimize(checkpoint=checkpoint, resume=True)
    if damage not in ("values reshaped", "moment reshaped", "iteration 10**6", "history too long"):  # a readable, complete file is described before it is resumed
        with pytest.raises(ValueError, match=f"checkpoint.npz: {message}"):
            TaskProblem(make_scene(), settings=settings).optimize(checkpoint=checkpoint)


@pytest.mark.parametrize("rng", [None, {"bit_generator": "PCG64"}], ids=["null", "partial"])
def test_a_gb_checkpoint_without_its_generator_state_is_refused(tmp_path, rng):
    """Found by a probe: a gb checkpoint whose generator state was altered ended in a
    traceback (TypeError: state must be a dict, or a KeyError) on --resume."""
    from warpcontact.bundle import BundleSettings

    make_scene, settings, model = _CHECKPOINTED_RUNS["bundles"]
    checkpoint = tmp_path / "checkpoint.npz"
    _interrupt(TaskProblem(make_scene(), settings=settings, model=model, bundle=BundleSettings(samples=2, seed=3)), 4, checkpoint)
    with np.load(checkpoint) as data:
        meta = json.loads(str(data["meta"]))
    assert isinstance(meta["rng"], dict)
    meta["rng"] = rng
    _rewritten(checkpoint, meta=meta)
    message = r"its rng is None, and the gb bundle needs its generator's state" if rng is None else r"its rng is \{'bit_generator': 'PCG64'\}, expected null or a PCG64"
    with pytest.raises(ValueError, match=rf"checkpoint.npz: not a readable checkpoint \({message}"):
        TaskProblem(make_scene(), settings=settings, model=model, bundle=BundleSettings(samples=2, seed=3)).optimize(checkpoint=checkpoint, resume=True)


def test_a_checkpoint_of_another_sampling_box_is_refused(tmp_path):
    """The box initial samples are drawn from is part of the problem: a resume under another
    box carried the old box's draws into it."""
    settings = TaskSettings(horizon=15, receding_horizon=0, iterations=3, learning_rate=0.3, initial_samples=3, sample_seed=1)
    checkpoint = tmp_path / "checkpoint.npz"
    _interrupt(TaskProblem(sampled_space_billiards(), settings=settings), 5, checkpoint)
    other = sampled_space_billiards()
    other.task.sample_high = (0.3, 0.6, 1.0, 0.5)
    with pytest.raises(ValueError, match=r"checkpoint of another problem \(sample_box: .*8\.0.* saved, .*1\.0.* now"):
        TaskProblem(other, settings=settings).optimize(checkpoint=checkpoint, resume=True)
    assert TaskProblem(sampled_space_billiards(), settings=settings).optimize(checkpoint=checkpoint, resume=True).loss_history


def test_numpy_integer_settings_checkpoint_and_resume_as_python_integers(tmp_path):
    """np.int64 settings pass TaskSettings.check; the first checkpoint save failed on them
    (not JSON serialisable), and their fingerprint was the string '1'."""
    make_scene, settings, _ = _CHECKPOINTED_RUNS["receding"]
    numpy_settings = dataclasses.replace(settings, horizon=np.int64(5), receding_horizon=np.int64(2), receding_stride=np.int64(1))
    checkpoint = tmp_path / "checkpoint.npz"
    interrupted = TaskProblem(make_scene(), settings=numpy_settings)
    _interrupt(interrupted, 6, checkpoint)
    resumed = TaskProblem(make_scene(), settings=settings).optimize(checkpoint=checkpoint, resume=True)
    assert resumed.loss_history == TaskProblem(make_scene(), settings=settings).optimize().loss_history


def test_cli_run_keeps_a_finished_run_until_its_results_are_written(tmp_path, capsys, monkeypatch):
    """The optimisation used to remove its checkpoint before the results were written: Ctrl-C
    while writing them, or a results name taken by a folder, lost the finished run."""
    scene_path = tmp_path / "space.usda"
    io.save_scene(space_billiards(), scene_path)
    argv = ["run", str(scene_path), "--iters", "3"]
    assert main([*argv, "--out", str(tmp_path / "full")]) == 0
    out = tmp_path / "out"
    export = io.export_trajectory

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(io, "export_trajectory", interrupted)
    capsys.readouterr()
    assert main([*argv, "--out", str(out)]) == 130
    assert "interrupted while writing the results: the run is kept in" in capsys.readouterr().err
    assert (out / cli.CHECKPOINT_NAME).exists()
    monkeypatch.setattr(io, "export_trajectory", export)
    assert main([*argv, "--out", str(out), "--resume"]) == 0
    assert not (out / cli.CHECKPOINT_NAME).exists()
    full, resumed = (json.loads((folder / "metrics.json").read_text()) for folder in (tmp_path / "full", out))
    assert resumed["loss_history"] == full["loss_history"] and resumed["final_loss"] == full["final_loss"]
    # A results or checkpoint name taken by a folder is refused before any work.
    for name in ("trajectory.usda", cli.CHECKPOINT_NAME):
        taken = tmp_path / f"taken_{name}"
        (taken / name).mkdir(parents=True)
        assert main([*argv, "--out", str(taken)]) == 2
        assert f"{name}: exists and is not a file" in capsys.readouterr().err
        assert sorted(p.name for p in taken.iterdir()) == [name]


def test_receding_settings_of_a_task_that_cannot_recede_are_refused():
    """An initial-state task with recedingHorizon below its horizon optimised one window of
    the whole horizon, while its header and metrics.json reported windows and a stride."""
    scene = space_billiards()
    scene.task.receding_horizon = 5
    with pytest.raises(ValueError, match="receding-horizon control applies to pd_targets tasks, and this task's control is initial_state"):
        TaskProblem(scene)


def test_generic_quick_caps_keep_the_stride_inside_the_window():
    scene = _pd_space_billiards()
    scene.task.horizon, scene.task.receding_horizon, scene.task.receding_stride = 40, 20, 10
    capped = TaskSettings.from_task(scene, quick=True)
    assert (capped.horizon, capped.window, capped.receding_stride) == (24, 8, 8)


@pytest.mark.parametrize(("make_scene", "horizon", "window"), [(space_billiards, 15, 20), (_pd_space_billiards, 30, 40)])
def test_generic_quick_caps_keep_a_one_window_task_one_window(make_scene, horizon, window):
    """A window authored longer than the horizon is one window; the caps made it a receding
    window of 8 frames (refused for an initial-state task, silently receding for PD targets)."""
    scene = make_scene()
    scene.task.horizon, scene.task.receding_horizon = horizon, window
    capped = TaskSettings.from_task(scene, quick=True)
    assert capped.window == capped.horizon == min(horizon, 24)
    TaskProblem(scene, settings=capped)


@pytest.mark.parametrize(
    ("attribute", "type_name", "value", "message"),
    [
        ("task:horizon", "double", 5.7, "warpcontact:task:horizon must be a whole number, got 5.7"),
        ("task:iterations", "bool", True, "warpcontact:task:iterations must be a whole number, got True"),
        ("task:sampleLow", "string", "low", "warpcontact:task:sampleLow must be a list of numbers, got 'low'"),
        ("target:tolerance", "string", "abc", "prim /World/target: warpcontact:target:tolerance must be a number, got 'abc'"),
        ("target:position", "string", "here", "prim /World/target: warpcontact:target:position must be a list of numbers, got 'here'"),
    ],
)
def test_task_metadata_of_the_wrong_type_is_refused_naming_the_attribute(tmp_path, attribute, type_name, value, message):
    """A fractional horizon was truncated (5.7 ran 5 frames); a string tolerance or position
    failed with a bare 'could not convert string to float'."""
    from pxr import Sdf

    path = tmp_path / "scene.usda"
    io.save_scene(space_billiards(), path)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/World/target" if attribute.startswith("target") else "/World/physicsScene")
    prim.RemoveProperty("warpcontact:" + attribute)
    prim.CreateAttribute("warpcontact:" + attribute, Sdf.ValueTypeNames.Find(type_name)).Set(value)
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=message):
        io.load_scene(path)


def test_settings_and_models_accept_numpy_betas_and_refuse_a_string_stiffness():
    settings = dataclasses.replace(_CHECKPOINTED_RUNS["receding"][1], betas=np.array([0.3, 0.5]))
    TaskProblem(_pd_space_billiards(), settings=settings)
    with pytest.raises(ValueError, match="ipc_stiffness: must be a number, not str, got '1e5'"):
        TaskProblem(_pd_space_billiards(), model="ipc", ipc_stiffness="1e5")


def test_task_rollouts_start_with_the_scene_s_authored_velocities():
    """`simulate` applied a body's authored velocity and `run` started it at rest: the same
    scene moved its target ball 0.061 m in 3 frames under one and 0.011 m in 6 under the
    other. Rollouts now start as `simulate` does; the controlled body's velocity controls are
    offsets from its own."""
    scene = space_billiards()
    scene.bodies[1].linear_velocity = np.array([0.5, 0.0, 0.0])
    scene.bodies[1].angular_velocity = np.array([0.0, 0.0, 2.0])
    scene.bodies[0].linear_velocity = np.array([0.0, 0.2, 0.0])
    problem = TaskProblem(scene, settings=TaskSettings(horizon=6, receding_horizon=0, iterations=1, learning_rate=0.1))
    _, _, trajectory = problem.rollout(np.zeros((1, 4)), problem.start, 6)
    np.testing.assert_array_equal(trajectory[-1], _simulated(scene, 6, held=False))
    assert trajectory[-1, 1, 0] - trajectory[0, 1, 0] > 0.1
    # Articulated scenes keep starting at rest: their joint coordinates would not follow.
    from warpcontact.scenes import build_scene

    ant = build_scene("ant_push")
    next(b for b in ant.bodies if not b.static).linear_velocity = np.array([0.1, 0.0, 0.0])
    with pytest.raises(ValueError, match="task rollouts of articulated scenes start at rest"):
        TaskProblem(ant)


def test_a_checkpoint_that_cannot_be_saved_is_named(tmp_path, monkeypatch):
    """A full disk printed "[Errno 28] No space left on device", naming neither the file nor
    what was kept."""
    from warpcontact import tasks

    def full_disk(path, write):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tasks, "replace_file", full_disk)
    with pytest.raises(OSError, match=r"checkpoint.npz: saving the checkpoint failed \(No space left on device\); no earlier one was written"):
        tasks.TaskCheckpoint(tmp_path / "checkpoint.npz").save({}, {})


def test_joint_sine_values_are_named_by_coordinate_and_wave_parameter():
    """A joint_sine rollout's bad value was named by the dof of its column (the rows are the
    coordinates), and past the last coordinate's column raised IndexError (a probe, stop 58)."""
    from warpcontact.scenes import build_scene

    problem = TaskProblem(build_scene("ant_push"))
    values = problem.initial_values(1)
    values[3, 0] = np.nan
    with pytest.raises(ValueError, match=rf"values: row 3 \(coordinate '{problem.dof_names[3]}'\), column 0 \(the amplitude of sine wave 0\) is nan"):
        problem.rollout(values, problem.start, 2)
    values = problem.initial_values(1)
    values[0, 11] = 1e200
    with pytest.raises(ValueError, match=rf"values: row 0 \(coordinate '{problem.dof_names[0]}'\), column 11 \(the phase of sine wave 3\) is 1e\+200, beyond"):
        problem.rollout(values, problem.start, 2)


def test_a_problem_keeps_the_goals_it_was_built_with():
    # A goal moved on the scene after construction reached only the executed trajectory's
    # host loss: a receding run reported success at loss 0 beside a history of 2.48.
    from warpcontact.scenes import build_scene

    scene = build_scene("push")
    problem = TaskProblem(scene, settings=TaskSettings(horizon=4, receding_horizon=2, iterations=1, learning_rate=0.1))
    target = next(i for i, b in enumerate(scene.bodies) if b.target_position is not None)
    scene.bodies[target].target_position = scene.bodies[target].pose[:3].copy()
    result = problem.optimize()
    assert result.final_loss == pytest.approx(problem.rollout(result.values, problem.start, 4, gradient=False)[0], rel=1e-12) and result.final_loss > 0


def test_optimize_and_the_bundle_refuse_values_of_another_kind():
    scene = space_billiards()
    with pytest.raises(ValueError, match="bundle: expected a BundleSettings, got dict"):
        TaskProblem(scene, model="gb", bundle={"samples": 2})
    problem = TaskProblem(scene, settings=TaskSettings(horizon=2, receding_horizon=0, iterations=1, learning_rate=0.1))
    with pytest.raises(ValueError, match="resume"):  # "no" resumed
        problem.optimize(checkpoint=None, resume="no")
