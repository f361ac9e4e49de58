"""Every shipped scene loads, steps 10 frames without penetration, and exports."""

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


@pytest.mark.parametrize("points, faces", [(18, 32), (42, 80), (82, 160), (196, 388)])
def test_fibonacci_balls_are_closed_convex_meshes(points, faces):
    v, f = scenes.fibonacci_ball(points)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert len(f) == faces and mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 0.5)


def test_unknown_scene_is_a_clear_error():
    with pytest.raises(ValueError, match="not one of"):
        scenes.build_scene("ant_walk")
