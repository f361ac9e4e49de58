"""Every shipped scene loads, steps 10 frames without penetration, and exports."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import trimesh

import warpcontact as wc
from warpcontact import io, scenes

SCENES = Path(__file__).resolve().parents[1] / "scenes"
FILES = sorted(SCENES.glob("*.usda")) if SCENES.is_dir() else []


def test_every_named_scene_is_shipped():
    if not SCENES.is_dir():
        pytest.skip("scenes/ not found next to tests/")
    assert {p.stem for p in FILES} == set(scenes.SCENE_NAMES)


def test_the_shipped_scenes_are_what_the_code_writes_and_are_never_overwritten_unasked(tmp_path, capsys):
    """`python -m warpcontact.scenes FOLDER` overwrote whatever NAME.usda files FOLDER held,
    and took --help for a folder name."""
    if not SCENES.is_dir():
        pytest.skip("scenes/ not found next to tests/")
    assert scenes.main([str(tmp_path)]) == 0
    for path in FILES:
        assert (tmp_path / path.name).read_bytes() == path.read_bytes(), path.name
    (tmp_path / "push.usda").write_text("mine")
    assert scenes.main([str(tmp_path)]) == 2
    assert "billiards.usda exists (10 of the 10 scene files do)" in capsys.readouterr().err
    assert (tmp_path / "push.usda").read_text() == "mine"
    assert scenes.main([str(tmp_path), "--overwrite"]) == 0
    assert (tmp_path / "push.usda").read_bytes() == (SCENES / "push.usda").read_bytes()
    with pytest.raises(SystemExit) as exit_info:
        scenes.main(["--help"])
    assert exit_info.value.code == 0 and not Path("--help").exists()


def test_writing_the_scenes_is_all_or_nothing_and_names_what_stops_it(tmp_path, capsys, monkeypatch):
    """A probe at stop 61: a name taken by a folder, a folder that cannot be made and an
    interrupt left a partial set of scenes (and tracebacks), and an empty folder name wrote
    into the current folder."""
    (tmp_path / "taken" / "push.usda").mkdir(parents=True)
    assert scenes.main([str(tmp_path / "taken"), "--overwrite"]) == 2
    assert "push.usda: is a folder, not a file name" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "taken").iterdir()) == ["push.usda"]
    assert scenes.main([""]) == 2
    assert "an empty name would write into the current folder" in capsys.readouterr().err
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    assert scenes.main([str(a_file / "sub")]) == 1
    assert "cannot write the scenes" in capsys.readouterr().err
    written = []

    def interrupted(scene, path, **kwargs):
        written.append(path)
        if len(written) == 3:
            raise KeyboardInterrupt
        return real(scene, path, **kwargs)

    real = scenes.save_scene
    monkeypatch.setattr(scenes, "save_scene", interrupted)
    assert scenes.main([str(tmp_path / "cut")]) == 130
    assert "interrupted; no scene file was changed" in capsys.readouterr().err
    assert list((tmp_path / "cut").iterdir()) == []


@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_scene_loads_steps_and_exports(path, tmp_path):
    scene = io.load_scene(path)
    assert scene.task.name and scene.task.horizon > 0
    assert any(b.target_position is not None for b in scene.bodies)
    model = scene.build_model()
    solver = wc.ImplicitSolver(model)
    dt = scene.settings.time_step
    states = [model.state(requires_grad=False)]
    for _ in range(10):
        nxt = model.state(requires_grad=False)
        solver.step(states[-1], nxt, model.control(requires_grad=False), dt)
        states.append(nxt)
    q = np.array([s.body_q.numpy() for s in states])
    for frame in q:
        assert model.contact.evaluate(frame).ok  # never touching or intersecting
    # Resting scenes stay put: nothing flies off in 10 frames.
    assert np.abs(q[-1, :, :3] - q[0, :, :3]).max() < 0.05
    out = tmp_path / "trajectory.usda"
    io.export_trajectory(scene, io.model_to_scene_poses(scene, model, q), out)
    assert out.stat().st_size > 1000


def test_shipped_scenes_match_the_generator():
    if not SCENES.is_dir():
        pytest.skip("scenes/ not found next to tests/")
    for name in ("push", "gather_bunny", "billiards_6208"):
        shipped = io.load_scene(SCENES / f"{name}.usda")
        built = scenes.build_scene(name)
        assert [b.name for b in shipped.bodies] == [b.name for b in built.bodies]
        for a, b in zip(shipped.bodies, built.bodies):
            np.testing.assert_array_equal(a.faces, b.faces)
            np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-6)


@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_every_goal_is_at_its_target_bodys_resting_height(path):
    """The loss is |x_com - x*|^2 beyond the tolerance (paper, "Benchmark Details"): a goal
    above the height where the body's centre of mass rests adds a term no push removes.
    Gather-Bunny's goals were the cubes' 0.15 m, 5 cm above every bunny's centre of mass."""
    scene = io.load_scene(path)
    model = scene.build_model()
    for body in scene.bodies:
        if body.target_position is not None:
            start = model.initial_q[model.body_names.index(body.name), 2]
            # Bodies start 1 mm above their support and settle onto it.
            assert abs(body.target_position[2] - start) < 2e-3, (body.name, body.target_position[2], start)


@pytest.mark.parametrize("points, faces", [(18, 32), (42, 80), (82, 160), (196, 388)])
def test_fibonacci_balls_are_closed_convex_meshes(points, faces):
    v, f = scenes.fibonacci_ball(points)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert len(f) == faces and mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 0.5)


@pytest.mark.parametrize("points", [18, 42, 82, 196])
def test_balls_rest_on_a_face_their_centre_of_mass_stands_over(points):
    points, f = scenes.fibonacci_ball(points)
    v, _ = scenes.rest_on_face(points, f)
    com = trimesh.Trimesh(v, f, process=False).center_mass
    bottom = f[np.all(np.abs(v[f][:, :, 2] - v[:, 2].min()) < 1e-12, axis=1)]
    assert len(bottom) == 1
    a, b, c = v[bottom[0]][:, :2]
    inside = []
    for p, q in ((a, b), (b, c), (c, a)):
        edge = q - p
        inside.append((edge[0] * (com[1] - p[1]) - edge[1] * (com[0] - p[0])) / np.linalg.norm(edge))
    inside = np.array(inside) * np.sign((b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0])
    # The face most nearly facing down, chosen before, was overhung by 1.1-1.9 cm.
    assert inside.min() > 0.03


def test_a_ball_at_rest_stays_at_rest():
    """A billiards ball on the table, untouched, for 25 frames (1 s): it must not tip over."""
    full = scenes.build_scene("billiards")
    scene = dataclasses.replace(full, bodies=[full.bodies[0], full.bodies[1]])
    model = scene.build_model()
    solver = wc.ImplicitSolver(model)
    state = model.state(requires_grad=False)
    start = state.body_q.numpy()[1].copy()
    for _ in range(25):
        nxt = model.state(requires_grad=False)
        solver.step(state, nxt, model.control(requires_grad=False), scene.settings.time_step)
        state = nxt
    end = state.body_q.numpy()[1]
    # On the face chosen before it tipped: 1.1 cm and 1.8 degrees (measured); now 1.5e-5 m
    # of creep on the flat table (3e-5 m on a grid of 0.5 m squares) and 1e-4 rad.
    assert np.linalg.norm(end[:2] - start[:2]) < 2e-4
    assert abs(abs(float(np.dot(end[3:], start[3:]))) - 1.0) < 1e-7


def test_billiards_goals_are_reached_by_the_reference_strike():
    """Billiards has a solution: the reference strike (the cue launched from its start at
    5.8 m/s) leaves both targets within their tolerance after the task's 100 frames, while
    at the start both are outside it (measured: 0.60 and 0.44 m from their goals)."""
    from warpcontact.tasks import TaskProblem, TaskSettings, sample_box

    scene = scenes.build_scene("billiards")
    problem = TaskProblem(scene, settings=TaskSettings(scene.task.horizon, 0, 1, 0.03))
    start = problem.model.initial_q.copy()
    for name in scenes.BILLIARDS_GOALS:
        body = next(b for b in scene.bodies if b.name == name)
        assert np.linalg.norm(body.pose[:2] - body.target_position[:2]) > body.target_tolerance + 0.2
    loss, _, trajectory = problem.rollout(np.array([scenes.BILLIARDS_REFERENCE_STRIKE]), (start, start), scene.task.horizon, gradient=False)
    assert loss == 0.0
    assert np.all(trajectory[:, 1:, 2] > 0.3)  # every ball stays on the table (body 0: the ground)
    low, high = sample_box(scene, 1)  # --init-samples' box holds the reference strike
    assert np.all(low <= scenes.BILLIARDS_REFERENCE_STRIKE) and np.all(np.array(scenes.BILLIARDS_REFERENCE_STRIKE) <= high)


def _sliding_cue(table_cell):
    """Billiards' cue alone on its table, launched at 1 m/s along x; its goal lies 1000 m
    behind it, so the loss gradient is 2 (x_stop - goal) d x_stop / d (x0, y0, vx, vy)."""
    from warpcontact.tasks import TaskProblem, TaskSettings

    full = scenes.billiards_scene(*scenes.fibonacci_ball(18), table_cell=table_cell)
    ground, cue = full.bodies[0], next(b for b in full.bodies if b.name == "cue")
    cue = dataclasses.replace(cue, target_position=cue.pose[:3] - np.array([1000.0, 0.0, 0.0]), target_tolerance=0.0)
    scene = dataclasses.replace(full, bodies=[ground, cue])
    problem = TaskProblem(scene, settings=TaskSettings(60, 0, 1, 0.03))
    start = problem.model.initial_q.copy()

    def stop(values, gradient=False):
        loss, grad, trajectory = problem.rollout(np.array([values]), (start, start), 60, gradient=gradient)
        x_stop = trajectory[-1, 1, 0]
        return x_stop, (None if grad is None else grad[0] / (2 * (x_stop - cue.target_position[0])))

    return stop


def test_a_sliding_ball_stops_where_its_start_says():
    """On Billiards' flat table the cue's stopping point follows its launch: d x_stop / d x0
    = 1 and d x_stop / d vx = v / (friction g) (uniform deceleration), in the task gradient
    and in finite differences. On a grid table of 0.5 m squares the ball feels the seams
    between coplanar triangles: the same launch gave d x_stop / d x0 = -2.30 and d x_stop /
    d vx = -1.75 (gradient and finite differences agreeing; the secant over 0.01 m/s was
    +1.6), which randomised the sign of Billiards' long-range gradient."""
    stop = _sliding_cue(None)
    launch = np.array([0.0, 0.0, 1.0, 0.0])
    x_stop, d_stop = stop(launch, gradient=True)
    assert x_stop - (-2.0) > 0.9  # it slid about v^2 / (2 friction g) = 1.02 m and stopped
    assert d_stop[0] == pytest.approx(1.0, abs=1e-3)
    assert d_stop[2] == pytest.approx(1.0 / (scenes.BILLIARDS_FRICTION * 9.81), rel=0.02)
    h = 1e-4
    for k in (0, 2):
        step = np.eye(4)[k] * h
        fd = (stop(launch + step)[0] - stop(launch - step)[0]) / (2 * h)
        assert fd == pytest.approx(d_stop[k], rel=1e-3)


def test_resting_needs_a_closed_outward_convex_mesh():
    v, f = scenes.fibonacci_ball(18)
    with pytest.raises(ValueError, match="outward-oriented"):
        scenes.rest_on_face(v, f[:, ::-1])  # inward-facing triangles
    with pytest.raises(ValueError, match="watertight: False"):
        scenes.rest_on_face(v, f[1:])
    dented = v.copy()
    dented[5] *= 0.5  # inside the hull of the other points
    with pytest.raises(ValueError, match="not convex"):
        scenes.rest_on_face(dented, f)


def test_a_zero_area_face_is_never_the_one_a_ball_rests_on():
    # A valid convex mesh with a zero-area face (a vertex inserted on an edge, and the
    # triangle that closes it) rested on that face's NaN margin: every vertex came back NaN.
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    vertices = np.asarray(box.vertices, dtype=np.float64)
    faces = [list(f) for f in box.faces]
    a, b, c = faces[0]
    m = len(vertices)
    vertices = np.vstack([vertices, 0.5 * (vertices[a] + vertices[b])])
    faces[0] = [a, m, c]
    faces += [[m, b, c], [a, b, m]]  # [a, b, m] has zero area
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.volume == pytest.approx(1.0)
    rested, height = scenes.rest_on_face(vertices, np.array(faces))
    assert np.isfinite(rested).all() and height == pytest.approx(0.5)


def test_unknown_scene_is_a_clear_error():
    with pytest.raises(ValueError, match="not one of"):
        scenes.build_scene("ant_walk")


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: scenes.fibonacci_ball(3), r"num_points: must be a whole number >= 4, got 3"),  # was an IndexError
        (lambda: scenes.fibonacci_ball(18, radius=0.0), r"radius: must be positive and finite, got 0.0"),  # was "point 4 is not in convex position"
        (lambda: scenes.decimate(*scenes.fibonacci_ball(42), 0.0), r"cell: must be positive and finite, got 0.0"),  # was an empty mesh
        (lambda: scenes.bunny_mesh(target_faces=270, height=-1.0), r"height: must be positive and finite \(m\), got -1.0"),  # was a mirrored bunny
        # A ground of no area, one facing down, NaN vertices, a TypeError, 6.9 EiB asked for:
        (lambda: scenes.ground_rectangle(0.0, 1.0), r"size_x: must be positive and finite \(m\), got 0.0"),
        (lambda: scenes.ground_rectangle(1.0, -2.0), r"size_y: must be positive and finite \(m\), got -2.0"),
        (lambda: scenes.ground_rectangle(1.0, 1.0, centre=(np.nan, 0.0)), r"centre: must be 2 finite numbers \(m\), got \(nan, 0.0\)"),
        (lambda: scenes.ground_rectangle("1", 1.0), r"size_x: must be positive and finite \(m\), got '1'"),
        (lambda: scenes.ground_rectangle(1.0, 1.0, cell=1e-9), r"cell: must be at least 0.001 m for this size \(at most 1,000,000 cells\), got 1e-09"),
        (lambda: scenes.rack_centres(0.0), r"spacing: must be positive and finite \(m\), got 0.0"),  # every ball on one point
        # An IndexError, trimesh's error, a TypeError:
        (lambda: scenes.billiards_scene(scenes.fibonacci_ball(18)[0], scenes.fibonacci_ball(18)[1] + 100), r"mesh 'ball': face 0 has vertex indices"),
        (lambda: scenes.benchmark_rack(None, None), r"mesh 'ball': vertices must be real numbers"),
        (lambda: scenes.build_scene(["push"]), r"scene: \['push'\] is not one of billiards"),
    ],
)
def test_mesh_helpers_name_a_bad_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_scenes_compare_equal_field_by_field_with_their_arrays():
    """``==`` on a Scene raised "the truth value of an array is ambiguous" (its numpy fields):
    a scene and its pickled copy now compare equal, and any changed array makes them differ."""
    import pickle

    scene = scenes.build_scene("push")
    copy = pickle.loads(pickle.dumps(scene))
    assert scene == copy and not scene != copy and scene == scenes.build_scene("push")
    copy.bodies[1].pose = copy.bodies[1].pose + 1e-9
    assert scene != copy and scene.bodies[0] == copy.bodies[0] and scene.bodies[1] != copy.bodies[1]
    assert scene != "push"
    with pytest.raises(TypeError):
        hash(scene)
