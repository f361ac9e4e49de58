"""USD import / export: hand-written UsdPhysics scenes, round trips, trajectories, errors."""

import dataclasses
import contextlib
import re
import warnings

import numpy as np
import pytest
import trimesh
import warp as wp
from pxr import Gf, Sdf, Ts, Usd, UsdGeom, UsdPhysics, UsdShade

import warpcontact as wc
from warpcontact import io
from warpcontact.rotation import quat_to_matrix as quat_matrix


def write_physics_scene(path, *, meters=1.0, mass=None, joint=None, face_counts=None, points=None, drop_height=0.6):
    """A scene written with UsdPhysics schemas only: a cube body above a static mesh ground."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, meters)
    scene = UsdPhysics.Scene.Define(stage, "/World/physicsScene")
    scene.CreateGravityDirectionAttr(Gf.Vec3f(0, 0, -1))
    scene.CreateGravityMagnitudeAttr(9.81 / meters)
    ground = UsdGeom.Mesh.Define(stage, "/World/ground")
    n = 4
    xs = np.linspace(-2, 2, n + 1) / meters
    pts = [(float(x), float(y), 0.0) for x in xs for y in xs]
    quads = [(i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1) for i in range(n) for j in range(n)]
    ground.CreatePointsAttr(points if points is not None else pts)
    counts = face_counts if face_counts is not None else [4] * len(quads)
    ground.CreateFaceVertexCountsAttr(counts)
    ground.CreateFaceVertexIndicesAttr([int(i) for q, c in zip(quads, counts) for i in q[:c]])
    UsdPhysics.CollisionAPI.Apply(ground.GetPrim())
    box = UsdGeom.Xform.Define(stage, "/World/box")
    box.AddTranslateOp().Set(Gf.Vec3d(0.1 / meters, 0.0, drop_height / meters))
    UsdPhysics.RigidBodyAPI.Apply(box.GetPrim())
    if mass is not None:
        UsdPhysics.MassAPI.Apply(box.GetPrim()).CreateMassAttr(mass)
    cube = UsdGeom.Cube.Define(stage, "/World/box/shape")
    cube.CreateSizeAttr(0.5 / meters)
    UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
    if joint:
        getattr(UsdPhysics, joint).Define(stage, "/World/joint").CreateBody0Rel().SetTargets(["/World/box"])
    stage.GetRootLayer().Save()
    return path


def _append_ground_quad(stage, face, corners):
    """Lists ``write_physics_scene``'s ground quad ``face`` again as a 17th face, its corner
    indices passed through ``corners``."""
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ground"))
    indices = list(mesh.GetFaceVertexIndicesAttr().Get())
    mesh.GetFaceVertexCountsAttr().Set(list(mesh.GetFaceVertexCountsAttr().Get()) + [4])
    mesh.GetFaceVertexIndicesAttr().Set(indices + [int(i) for i in corners(np.array(indices[4 * face : 4 * face + 4]))])


def _load_refused(stage, path, match):
    """Save ``stage`` (opened from ``path``) and check that loading it is refused with ``match``."""
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=match):
        io.load_scene(path)


def simulate(scene, frames):
    model = scene.build_model()
    solver = wc.ImplicitSolver(model)
    dt = scene.settings.time_step
    states = [model.state(requires_grad=False)]
    lin, ang = scene.initial_velocities()
    wc.set_body_velocity(states[0], wp.array(lin, dtype=wp.vec3d), wp.array(ang, dtype=wp.vec3d), dt)
    for _ in range(frames):
        nxt = model.state(requires_grad=False)
        solver.step(states[-1], nxt, None, dt)
        states.append(nxt)
    q = np.array([s.body_q.numpy() for s in states])
    for frame in q:
        assert model.contact.evaluate(frame).ok
    return model, q


def test_physics_only_scene_loads_with_defaults_and_simulates(tmp_path):
    scene = io.load_scene(write_physics_scene(tmp_path / "plain.usda"))
    assert [b.name for b in scene.bodies] == ["ground", "box"]  # stage order
    ground, box = scene.bodies
    assert not box.static and ground.static
    assert len(box.faces) == 12 and len(ground.faces) == 32  # quads fan-triangulated
    np.testing.assert_allclose(scene.gravity, [0, 0, -9.81])
    assert scene.settings == io.SimulationSettings()  # documented defaults
    model, q = simulate(scene, 10)
    # Default density 1000 kg/m^3 for a 0.5 m cube.
    assert model.body_mass.numpy()[1] == pytest.approx(125.0)
    assert q[-1, 1, 2] < q[0, 1, 2]  # falls under gravity


def test_stage_units_are_converted_to_metres(tmp_path):
    scene = io.load_scene(write_physics_scene(tmp_path / "cm.usda", meters=0.01))
    box = scene.body("box")
    np.testing.assert_allclose(np.ptp(box.vertices, axis=0), [0.5, 0.5, 0.5])
    np.testing.assert_allclose(box.pose[:3], [0.1, 0.0, 0.6])
    np.testing.assert_allclose(scene.gravity, [0, 0, -9.81])


def test_round_trip_preserves_bodies_masses_meshes_and_poses(tmp_path):
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda", mass=3.0))
    box = scene.body("box")
    box.inertia = np.array([[0.2, 0.01, 0.0], [0.01, 0.15, 0.0], [0.0, 0.0, 0.1]])
    box.linear_velocity = np.array([1.0, 0.0, 0.5])
    box.angular_velocity = np.array([0.0, 2.0, 0.0])
    box.target_position = np.array([1.0, 2.0, 0.25])
    box.target_tolerance = 0.1
    box.kp_linear = np.array([10.0, 10.0, 0.0])
    box.control_dofs = ("x", "y")
    box.group = 1
    scene.settings = io.SimulationSettings(time_step=0.02, frames=30, contact_stiffness=3e-8, eps=0.7, centred_weight="pairs", leaf_precision="float32", friction=0.4)
    scene.task = io.TaskSpec(
        name="gather",
        control="pd_targets",
        horizon=30,
        receding_horizon=8,
        learning_rate=0.01,
        iterations=5,
        receding_stride=4,
        quick_horizon=12,
        quick_receding_horizon=0,
        quick_learning_rate=0.05,
        quick_iterations=3,
        quick_receding_stride=2,
    )
    io.save_scene(scene, tmp_path / "b.usda")
    again = io.load_scene(tmp_path / "b.usda")
    assert [b.name for b in again.bodies] == [b.name for b in scene.bodies]
    for b0, b1 in zip(scene.bodies, again.bodies):
        assert b0.static == b1.static
        np.testing.assert_allclose(b1.vertices, b0.vertices, atol=1e-6)  # float32 points
        np.testing.assert_array_equal(b1.faces, b0.faces)
        np.testing.assert_allclose(b1.pose, b0.pose, atol=1e-12)
    b1 = again.body("box")
    assert b1.mass == 3.0
    np.testing.assert_allclose(b1.inertia, box.inertia, atol=1e-7)
    np.testing.assert_allclose(b1.linear_velocity, box.linear_velocity, atol=1e-7)
    np.testing.assert_allclose(b1.angular_velocity, box.angular_velocity, atol=1e-6)
    np.testing.assert_allclose(b1.target_position, box.target_position)
    assert b1.target_tolerance == 0.1 and b1.control_dofs == ("x", "y") and b1.group == 1
    np.testing.assert_allclose(b1.kp_linear, box.kp_linear)
    assert again.settings == scene.settings and again.task == scene.task
    m0, m1 = scene.build_model(), again.build_model()
    assert m1.contact.centred_weight == "pairs" and m1.contact.leaf_precision == "float32"
    np.testing.assert_allclose(m1.body_mass.numpy(), m0.body_mass.numpy())
    np.testing.assert_allclose(m1.initial_q, m0.initial_q, atol=1e-12)


def test_an_authored_centre_of_mass_and_inertia_count_with_a_mass_from_density(tmp_path):
    """UsdPhysics computes only what is not authored: without a mass, the authored centre of
    mass and inertia were both dropped, and the exported trajectory started 0.2 m away from
    the stage's pose (the export used the authored centre, the model the mesh's)."""
    path = write_physics_scene(tmp_path / "com.usda")
    stage = Usd.Stage.Open(str(path))
    mass_api = UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath("/World/box"))
    mass_api.CreateCenterOfMassAttr(Gf.Vec3f(0.2, 0.0, 0.0))
    mass_api.CreateDiagonalInertiaAttr(Gf.Vec3f(5.0, 5.0, 5.0))
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    model, q = simulate(scene, 1)
    assert model.body_mass.numpy()[1] == pytest.approx(125.0)  # 1,000 kg/m^3 of a 0.5 m cube
    np.testing.assert_allclose(model.body_center_of_mass[1], [0.2, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(np.diag(model.body_unit_second_moment.numpy()[1]), 2.5 / 125.0, rtol=1e-6)  # S = tr(J)/2 - J
    np.testing.assert_allclose(io.model_to_scene_poses(scene, model, q)[0, 1], scene.body("box").pose, atol=1e-12)
    with pytest.raises(ValueError, match=r"body_q: expected \(\.\.\., 2, 7\) poses of a model of the scene's 2 bodies, got shape \(1, 3, 7\)"):
        io.model_to_scene_poses(scene, model, np.zeros((1, 3, 7)))  # an IndexError before
    # A quaternion at another norm (the step keeps a static body's as given) turns the centre
    # of mass's offset as its unit quaternion does (a probe: a plate 2 m off its frame at 4 m).
    turned = q.copy()
    turned[..., 3:] = [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]
    scaled = turned.copy()
    scaled[..., 3:] *= 1.7
    np.testing.assert_allclose(io.model_to_scene_poses(scene, model, scaled)[..., :3], io.model_to_scene_poses(scene, model, turned)[..., :3], rtol=0, atol=1e-12)
    turned[..., 3:] = 0.0
    with pytest.raises(ValueError, match="body_q: every quaternion must be finite and non-zero"):
        io.model_to_scene_poses(scene, model, turned)


def test_a_usd_write_that_fails_is_an_os_error_naming_the_file(tmp_path):
    """A full disk or a file size limit was a traceback of an empty pxr error (a run's
    handler for a failed write, with its --resume hint, never saw it)."""
    import resource

    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    poses = np.repeat(np.array([b.pose for b in scene.bodies])[None], 50, axis=0)
    out = tmp_path / "out"
    out.mkdir()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2048, hard))  # Python ignores SIGXFSZ: writes fail with EFBIG
    try:
        with pytest.raises(OSError, match=r"out/traj.usda: USD could not write the file \(.*File too large; [\d,]+ bytes free on its disk\)"):
            io.export_trajectory(scene, poses, out / "traj.usda")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert not list(out.iterdir())  # no partial file, no temporary


def test_trajectory_export_authors_its_first_frame_as_the_default_and_keeps_the_up_axis(tmp_path):
    # Only time samples were written: read without a time, every moving body sat at the
    # origin; and a Y-up scene's trajectory was labelled Z-up (lying on its side in usdview).
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    model, q = simulate(scene, 3)
    poses = io.model_to_scene_poses(scene, model, q)
    scene.up_axis = "Y"
    io.export_trajectory(scene, poses, tmp_path / "traj.usda")
    stage = Usd.Stage.Open(str(tmp_path / "traj.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    translate = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).GetOrderedXformOps()[0]
    np.testing.assert_allclose(translate.Get(Usd.TimeCode.Default()), poses[0, 1, :3])
    np.testing.assert_allclose(translate.Get(3), poses[3, 1, :3])
    # Loaded as a scene it was "no dynamic rigid bodies (apply PhysicsRigidBodyAPI ...)"
    # (a probe): it holds no physics, and names the scene it came from.
    with pytest.raises(ValueError, match=r"traj.usda: a trajectory written by warpcontact for viewing .*; load the scene it was simulated from \(.*a.usda\)"):
        io.load_scene(tmp_path / "traj.usda")
    # Named absolute (a review: a scene loaded by a relative path was named relative to the
    # folder it was loaded from).
    with contextlib.chdir(tmp_path):
        relative = io.load_scene("a.usda")
        io.export_trajectory(relative, poses, tmp_path / "rel.usda")
    with pytest.raises(ValueError, match=re.escape(f"load the scene it was simulated from ({tmp_path.resolve() / 'a.usda'})")):
        io.load_scene(tmp_path / "rel.usda")
    io.save_scene(scene, tmp_path / "saved.usda")
    assert io.load_scene(tmp_path / "saved.usda").up_axis == "Y"


def test_non_unit_quaternions_are_refused_by_save_and_normalised_by_export(tmp_path):
    """Found by a probe: USD's orient op draws a quaternion as given. A body posed at
    (0, 0, 1, 1), 90 degrees about z at norm 1.41 (which the builder refuses), was saved and
    loaded as the identity, and a static body's pose written at that norm was exported so."""
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    turned = scene.body("box")
    turned.pose = np.array([*turned.pose[:3], 0.0, 0.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"saved.usda: body 'box': its pose quaternion has norm 1.41421356, expected 1"):
        io.save_scene(scene, tmp_path / "saved.usda")
    assert not (tmp_path / "saved.usda").exists()
    poses = np.repeat(np.stack([b.pose for b in scene.bodies])[None], 2, axis=0)
    io.export_trajectory(scene, poses, tmp_path / "traj.usda")
    stage = Usd.Stage.Open(str(tmp_path / "traj.usda"))
    drawn = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).GetOrderedXformOps()[1].Get(1)
    np.testing.assert_allclose([*drawn.GetImaginary(), drawn.GetReal()], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_concave_polygons_are_ear_clipped_and_self_intersecting_ones_refused(tmp_path):
    # A fan over an L-shaped face covered its notch: a box over the notch came to rest on it.
    stage = _hanging_box_stage(tmp_path / "l.usda")
    ground = UsdGeom.Mesh.Define(stage, "/World/ground")
    ground.CreatePointsAttr([(0, 0, 0), (2, 0, 0), (2, 1, 0), (1, 1, 0), (1, 2, 0), (0, 2, 0)])
    ground.CreateFaceVertexCountsAttr([6])
    ground.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 5])
    UsdPhysics.CollisionAPI.Apply(ground.GetPrim())
    stage.GetRootLayer().Save()
    body = io.load_scene(tmp_path / "l.usda").body("ground")
    tri = body.vertices[body.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (cross[:, 2] > 0).all()  # the face's winding kept
    assert 0.5 * cross[:, 2].sum() == pytest.approx(3.0)  # the L's area, not the fan's 3.5
    ground.GetFaceVertexCountsAttr().Set([7])
    ground.GetFaceVertexIndicesAttr().Set([0, 1, 2, 3, 3, 4, 5])  # a corner listed twice: still simple
    stage.GetRootLayer().Save()
    body = io.load_scene(tmp_path / "l.usda").body("ground")
    tri = body.vertices[body.faces]
    assert 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2].sum() == pytest.approx(3.0)
    bow = [(0, 0, 0), (2, 0, 0), (2, 2, 0), (1, -1, 0), (0, 2, 0)]  # its edges cross
    ground.GetPointsAttr().Set(bow)
    ground.GetFaceVertexCountsAttr().Set([5])
    ground.GetFaceVertexIndicesAttr().Set([0, 1, 2, 3, 4])
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match="prim /World/ground: face 0 \\(5 vertices\\) is a self-intersecting polygon"):
        io.load_scene(tmp_path / "l.usda")


@pytest.mark.parametrize(
    "corners",
    [
        [(0, 0, 0), (1, 0, 0), (2, 0, 0), (2, 2, 0), (0, 2, 0)],  # a corner in the middle of an edge
        [(0, 0, 0), (1, 0, 0), (2, 0, 0), (1, 1, 0), (0, 2, 0), (0, 1, 0)],  # a triangle with its edges' midpoints
        [(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0), (3, 1, 0)],  # two straight corners in a row
        [(0, 0, 0), (2, 0, 0), (2, 1, 0), (1, 1, 0), (0.5, 1, 0), (0, 1, 0)],  # the same on the far edge
        [(0, 0, 0), (3, 0, 0), (3, 1, 0), (2, 1, 0), (1, 2, 0), (1, 1, 0), (0, 1, 0)],  # concave
    ],
)
def test_polygons_with_straight_corners_are_split_without_zero_area_triangles(corners):
    """A fan from corner 0 over a corner in the middle of an edge (as CAD exports write a
    T-junction) made a zero-area triangle, which the contact model counts as one more copy
    of that edge, and the neighbouring faces' edges no longer matched for the mass."""
    corners = np.asarray(corners, dtype=np.float64)
    triangles = np.asarray(io._polygon_triangles(corners))
    tri = corners[triangles]
    twice_area = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]
    assert len(triangles) == len(corners) - 2 and (twice_area > 1e-9).all()
    x, y = corners[:, 0], corners[:, 1]
    assert 0.5 * twice_area.sum() == pytest.approx(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def test_straight_corners_far_from_the_origin_are_judged_against_rounding():
    """Star-shaped polygons with edge midpoints, 1 mm wide, turned, 370 m from the origin:
    rounding bends their straight corners by ~1e-11 of the polygon, above the 1e-12 that
    counted as straight, and 147 of 1,000 got zero-area triangles."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        n = rng.integers(4, 12)
        angles, radii = np.sort(rng.uniform(0.0, 2.0 * np.pi, n)), rng.uniform(0.3, 1.0, n)
        star = np.stack([radii * np.cos(angles), radii * np.sin(angles), np.zeros(n)], axis=1)
        with_midpoints = np.concatenate([[star[k], 0.5 * (star[k] + star[(k + 1) % n])] for k in range(n)])
        turn, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        triangles = io._polygon_triangles(with_midpoints @ turn.T * 1e-3 + [100.0, 200.0, 300.0])
        if triangles is None:
            continue  # a star whose closing edge crosses the others
        tri = with_midpoints[np.asarray(triangles)]
        twice_area = np.abs(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2])
        assert twice_area.min() > 1e-9 * twice_area.sum()


def test_a_cube_of_pentagons_loads_like_the_cube_of_quads(tmp_path):
    """Its bottom and front faces share a vertex in the middle of their common edge: it was
    refused for its mass from density (the fans' zero-area triangles wound the edge the same
    way twice)."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "pentagons.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    box = UsdGeom.Mesh.Define(stage, "/World/box")
    box.CreatePointsAttr([(-0.25, -0.25, -0.25), (0.25, -0.25, -0.25), (0.25, 0.25, -0.25), (-0.25, 0.25, -0.25), (-0.25, -0.25, 0.25), (0.25, -0.25, 0.25), (0.25, 0.25, 0.25), (-0.25, 0.25, 0.25), (0.0, -0.25, -0.25)])
    box.CreateFaceVertexCountsAttr([5, 4, 5, 4, 4, 4])
    box.CreateFaceVertexIndicesAttr([0, 3, 2, 1, 8, 4, 5, 6, 7, 0, 8, 1, 5, 4, 1, 2, 6, 5, 2, 3, 7, 6, 3, 0, 4, 7])
    UsdPhysics.RigidBodyAPI.Apply(box.GetPrim())
    UsdPhysics.CollisionAPI.Apply(box.GetPrim())
    UsdPhysics.MassAPI.Apply(box.GetPrim()).CreateDensityAttr(1000.0)
    stage.GetRootLayer().Save()
    scene = io.load_scene(tmp_path / "pentagons.usda")
    body = scene.body("box")
    tri = body.vertices[body.faces]
    assert len(body.faces) == 14 and (np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 1e-9).all()
    assert scene.build_model().body_mass.numpy()[0] == pytest.approx(125.0)


def test_quads_fanned_at_once_give_the_face_by_face_triangles():
    """Triangles and strictly convex quads are split in one step (a 90,000-quad ground took
    25 s face by face); the others (concave, with a straight corner, a corner named twice)
    still go through the face-by-face path, and the triangles keep the faces' order."""
    rng = np.random.default_rng(3)
    points = rng.normal(size=(400, 3))
    points[:, 2] *= 0.01  # nearly planar polygons of every shape
    square = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.0, 0.0]])
    points = np.vstack([points, square])
    s = len(points) - 5
    polygons = [rng.choice(400, size=n, replace=False) for n in rng.choice([3, 4, 4, 4, 5], size=300)]
    polygons += [np.array(p) for p in ([s, s + 1, s + 2, s + 3], [s, s + 4, s + 1, s + 2], [s, s + 1, s + 1, s + 2])]
    polygons = [p for p in polygons if io._polygon_triangles(points[p]) is not None]  # simple ones
    expected = np.concatenate([p[np.asarray(io._polygon_triangles(points[p]))] for p in polygons])
    counts = np.array([len(p) for p in polygons])
    assert (counts == 4).sum() > 100  # enough quads for both paths
    got, owners = io._polygon_mesh_faces(points, counts, np.concatenate(polygons), np.ones(len(counts), dtype=bool), "test")
    np.testing.assert_array_equal(got, expected)
    # Each triangle's authored face, which error messages name.
    np.testing.assert_array_equal(owners, np.repeat(np.arange(len(counts)), [len(io._polygon_triangles(points[p])) for p in polygons]))
    # A quad listed in holeIndices adds nothing.
    with_hole, _ = io._polygon_mesh_faces(points, np.append(counts, 4), np.concatenate(polygons + [np.arange(s, s + 4)]), np.append(np.ones(len(counts), dtype=bool), False), "test")
    np.testing.assert_array_equal(with_hole, expected)


@pytest.mark.parametrize("kind", ["Sphere", "Capsule", "Cylinder"])
def test_round_colliders_scaled_unevenly_take_the_shape_usd_draws(tmp_path, kind):
    """UsdPhysics gives a round shape one radius, its largest scale's: a Sphere of radius
    0.5 scaled (1, 1, 4) came out a sphere of radius 2 (16x the ellipsoid's mass), and a
    Capsule's caps stayed round when scaled along its axis."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "scaled.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    body = UsdGeom.Xform.Define(stage, "/World/ball")
    body.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 3.0))
    UsdPhysics.RigidBodyAPI.Apply(body.GetPrim())
    shape = getattr(UsdGeom, kind).Define(stage, "/World/ball/shape")
    shape.CreateRadiusAttr(0.5)
    if kind != "Sphere":
        shape.CreateHeightAttr(1.0)
        shape.CreateAxisAttr("Z")
    shape.AddScaleOp().Set(Gf.Vec3f(1.0, 3.0, 4.0))
    UsdPhysics.CollisionAPI.Apply(shape.GetPrim())
    stage.GetRootLayer().Save()
    unscaled = np.array([1.0, 1.0, 2.0 if kind == "Capsule" else 1.0])
    extent = np.ptp(io.load_scene(tmp_path / "scaled.usda").body("ball").vertices, axis=0)
    np.testing.assert_allclose(extent, unscaled * [1.0, 3.0, 4.0], rtol=2e-2)
    # Scaled uniformly, the description path reads it as before.
    shape.GetPrim().GetAttribute("xformOp:scale").Set(Gf.Vec3f(2.0, 2.0, 2.0))
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(np.ptp(io.load_scene(tmp_path / "scaled.usda").body("ball").vertices, axis=0), 2.0 * unscaled, rtol=2e-2)


@pytest.mark.parametrize(
    "kind, values, message",
    [
        ("Cube", {"size": -0.5}, "size must be a positive finite number, got -0.5"),
        ("Cube", {"size": 0.0}, "size must be a positive finite number, got 0"),
        ("Sphere", {"radius": float("inf")}, "radius must be a positive finite number, got inf"),
        ("Capsule", {"radius": 0.2, "height": -0.5}, "height must be a finite number >= 0, got -0.5"),
        ("Cylinder", {"radius": -0.2, "height": 0.5}, "radius must be a positive finite number, got -0.2"),
        ("Cone", {"radius": 0.2, "height": float("nan")}, "height must be a positive finite number, got nan"),
    ],
)
@pytest.mark.parametrize("body_scale", [1.0, 2.0])
def test_primitive_dimensions_that_make_no_solid_are_refused(tmp_path, kind, values, message, body_scale):
    """A Cube of size -0.5 loaded as a 0.5 m cube on an unscaled body and inside out on a
    scaled one; a Sphere of radius inf gave NaN vertices, naming no attribute."""
    stage = _hanging_box_stage(tmp_path / "bad.usda")
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).AddScaleOp().Set(Gf.Vec3f(1.0, 1.0, body_scale))
    stage.RemovePrim("/World/box/shape")
    shape = getattr(UsdGeom, kind).Define(stage, "/World/box/shape")
    for name, value in values.items():
        shape.GetPrim().GetAttribute(name).Set(value)
    UsdPhysics.CollisionAPI.Apply(shape.GetPrim())
    _load_refused(stage, tmp_path / "bad.usda", rf"prim /World/box/shape: {message}")


def test_a_referenced_layer_in_other_units_is_named(tmp_path):
    """USD does not convert units across a reference: a 50 cm asset in a metre stage was read
    as 50 m with nothing said but the builder's stiffness warning."""
    asset = Usd.Stage.CreateNew(str(tmp_path / "asset.usda"))
    UsdGeom.SetStageMetersPerUnit(asset, 0.01)
    UsdGeom.SetStageUpAxis(asset, UsdGeom.Tokens.z)
    cube = UsdGeom.Cube.Define(asset, "/box")
    cube.CreateSizeAttr(50.0)
    asset.SetDefaultPrim(cube.GetPrim())
    asset.GetRootLayer().Save()
    stage = _hanging_box_stage(tmp_path / "root.usda")
    crate = stage.DefinePrim("/World/crate")
    crate.GetReferences().AddReference("./asset.usda")
    UsdPhysics.CollisionAPI.Apply(crate)
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match=r"layer .*asset.usda authors metersPerUnit = 0.01, the stage 1.0; USD does not convert"):
        io.load_scene(tmp_path / "root.usda")
    UsdGeom.SetStageMetersPerUnit(asset, 1.0)
    asset.GetRootLayer().Save()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        io.load_scene(tmp_path / "root.usda")


_METRE_STAGE = """#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Z"
)
"""


_TYPED_STAGE = _METRE_STAGE + """
def Xform "World"
{
    def PhysicsScene "physicsScene"
    {
        vector3f physics:gravityDirection = (0, 0, -1)
        GRAVITY_TYPE physics:gravityMagnitude = 2
    }
    def Xform "box" (prepend apiSchemas = ["PhysicsRigidBodyAPI"])
    {
        double3 xformOp:translate = (0, 0, 1)
        uniform token[] xformOpOrder = ["xformOp:translate"]
        def Cube "shape" (prepend apiSchemas = ["PhysicsCollisionAPI"])
        {
            SIZE_TYPE size = 0.5
        }
    }
}
"""


@pytest.mark.parametrize(
    "size_type, gravity_type, match",
    [
        ("float", "float", r"prim /World/box/shape: size is written as float but its schema declares double; USD would ignore the value"),
        ("double", "double", r"prim /World/physicsScene: physics:gravityMagnitude is written as double but its schema declares float"),
    ],
    ids=["cube-size", "gravity"],
)
def test_values_of_another_type_than_their_schema_are_refused(tmp_path, size_type, gravity_type, match):
    """Found by a probe: USD's readers ignore a value written with another type than its schema
    declares and use the default, silently: a cube's ``float size = 0.5`` loaded as a 2 m cube,
    ``double physics:gravityMagnitude = 2`` as 9.81, an ant knee's double limits and drive
    gain were dropped. Role names do not count (the shipped scenes' points load)."""
    (tmp_path / "scene.usda").write_text(_TYPED_STAGE.replace("SIZE_TYPE", size_type).replace("GRAVITY_TYPE", gravity_type))
    with pytest.raises(ValueError, match=match):
        io.load_scene(tmp_path / "scene.usda")
    (tmp_path / "fixed.usda").write_text(_TYPED_STAGE.replace("SIZE_TYPE", "double").replace("GRAVITY_TYPE", "float"))
    scene = io.load_scene(tmp_path / "fixed.usda")
    np.testing.assert_allclose(scene.gravity, [0.0, 0.0, -2.0])
    np.testing.assert_allclose(np.ptp(scene.body("box").vertices, axis=0), 0.5)


@pytest.mark.parametrize(
    "op, name, match",
    [
        ("float xformOp:scale = 2", "xformOp:scale", r"prim /World/box: xformOp:scale is written as float, but a transform op of type scale takes double3 or float3 or half3"),
        ("double xformOp:rotateXYZ = 30", "xformOp:rotateXYZ", r"prim /World/box: xformOp:rotateXYZ is written as double, but a transform op of type rotateXYZ"),
        ("float4 xformOp:orient = (0.7071068, 0, 0, 0.7071068)", "xformOp:orient", r"prim /World/box: xformOp:orient is written as float4, but a transform op of type orient takes quatd"),
        ("double3 xformOp:spin = (0, 0, 1)", "xformOp:spin", r"prim /World/box: xformOpOrder names 'xformOp:spin', which is not a transform op USD knows"),
    ],
    ids=["scalar-scale", "scalar-rotate", "float4-orient", "unknown-op"],
)
def test_transform_ops_of_another_type_than_their_kind_are_refused(tmp_path, op, name, match):
    """Found by a probe: a scale written as a scalar (``float xformOp:scale = 2``) made
    UsdPhysics' parser raise a raw pxr.Tf.ErrorException naming neither the file nor the prim
    (a traceback from the CLI), and an orient written as float4 composed as the identity, so
    the box loaded unturned, silently."""
    text = _TYPED_STAGE.replace("SIZE_TYPE", "double").replace("GRAVITY_TYPE", "float")
    text = text.replace('double3 xformOp:translate = (0, 0, 1)\n        uniform token[] xformOpOrder = ["xformOp:translate"]', f'double3 xformOp:translate = (0, 0, 1)\n        {op}\n        uniform token[] xformOpOrder = ["xformOp:translate", "{name}"]')
    assert op in text
    (tmp_path / "scene.usda").write_text(text)
    with pytest.raises(ValueError, match=re.escape(str(tmp_path / "scene.usda")) + ": " + match):
        io.load_scene(tmp_path / "scene.usda")
    (tmp_path / "fixed.usda").write_text(text.replace(op, "quatf xformOp:orient = (0.7071068, 0, 0, 0.7071068)").replace(name, "xformOp:orient"))
    np.testing.assert_allclose(io.load_scene(tmp_path / "fixed.usda").body("box").pose[3:], [0, 0, 0.7071068, 0.7071068], atol=1e-6)


@pytest.mark.parametrize("physics_scene", [True, False], ids=["scene", "no-scene"])
def test_an_up_axis_other_than_y_or_z_is_refused(tmp_path, physics_scene):
    """Found by a probe: upAxis "X" loaded with gravity along -X beside a PhysicsScene and
    along -Y without one, and its trajectory was labelled Z-up."""
    text = _TYPED_STAGE.replace("SIZE_TYPE", "double").replace("GRAVITY_TYPE", "float").replace('upAxis = "Z"', 'upAxis = "X"')
    if not physics_scene:
        text = text.replace('def PhysicsScene "physicsScene"', 'def Xform "notAScene"').replace("vector3f physics:gravityDirection = (0, 0, -1)", "").replace("float physics:gravityMagnitude = 2", "")
    (tmp_path / "x_up.usda").write_text(text)
    with pytest.raises(ValueError, match=r"x_up.usda: upAxis must be \"Y\" or \"Z\", got 'X'"):
        io.load_scene(tmp_path / "x_up.usda")


def test_checks_reach_inside_instances_and_spline_animation(tmp_path):
    # Checks that walked stage.Traverse() skipped instance proxies: a warpcontact: typo inside
    # an instanceable asset loaded (its gain 0); a spline-animated transform without a default
    # loaded at the identity (USD has it at 90 degrees at time 0).
    (tmp_path / "asset.usda").write_text(_METRE_STAGE + """
def Xform "Asset"
{
    def Xform "a" (prepend apiSchemas = ["PhysicsRigidBodyAPI"])
    {
        double3 warpcontact:pd:kpLinaer = (1, 1, 1)
        def Cube "geom" (prepend apiSchemas = ["PhysicsCollisionAPI"]) {
            double size = 0.5
        }
    }
}
""")
    (tmp_path / "scene.usda").write_text(_METRE_STAGE + """
def Xform "World"
{
    def Xform "A" (instanceable = true
        prepend references = @./asset.usda@</Asset>) {}
}
""")
    with pytest.raises(ValueError, match=r"prim /World/A/a: unknown attribute warpcontact:pd:kpLinaer here"):
        io.load_scene(tmp_path / "scene.usda")
    (tmp_path / "spline.usda").write_text(_METRE_STAGE + """
def Xform "World"
{
    def Xform "B" (prepend apiSchemas = ["PhysicsRigidBodyAPI"])
    {
        float xformOp:rotateZ.spline = {
            0: 90; post held,
            10: 180; post held,
        }
        uniform token[] xformOpOrder = ["xformOp:rotateZ"]
        def Cube "g" (prepend apiSchemas = ["PhysicsCollisionAPI"]) {
            double size = 1
        }
    }
}
""")
    with pytest.raises(ValueError, match=r"prim /World/B: /World/B.xformOp:rotateZ is animated \(time samples or a spline\) but has no default"):
        io.load_scene(tmp_path / "spline.usda")


def test_physics_materials_inherited_or_per_face_and_refused_physics(tmp_path):
    body = """
    def Xform "B" (prepend apiSchemas = ["PhysicsRigidBodyAPI", "MaterialBindingAPI"])
    {
        rel material:binding:physics = </World/Rubber>
        double3 xformOp:translate = (0, 0, 2)
        uniform token[] xformOpOrder = ["xformOp:translate"]
        def Cube "geom" (prepend apiSchemas = ["PhysicsCollisionAPI"]) {
            double size = 1
        }
    }
    def Material "Rubber" (prepend apiSchemas = ["PhysicsMaterialAPI"])
    {
        float physics:dynamicFriction = 0.8
        float physics:density = 3000
    }
"""
    # A binding on the body is its collider's (UsdShade's inheritance): it was ignored.
    (tmp_path / "inherited.usda").write_text(_METRE_STAGE + 'def Xform "World"\n{' + body + "}\n")
    scene = io.load_scene(tmp_path / "inherited.usda")
    assert scene.settings.friction == pytest.approx(0.8) and scene.body("B").density == pytest.approx(3000.0)
    # Per-face materials of one collider that disagree were read as the first one's.
    (tmp_path / "faces.usda").write_text(_METRE_STAGE + """
def Xform "World"
{
    def Xform "B" (prepend apiSchemas = ["PhysicsRigidBodyAPI"])
    {
        double3 xformOp:translate = (0, 0, 2)
        uniform token[] xformOpOrder = ["xformOp:translate"]
        def Mesh "m" (prepend apiSchemas = ["PhysicsCollisionAPI"])
        {
            point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
            int[] faceVertexCounts = [3, 3, 3, 3]
            int[] faceVertexIndices = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3]
            def GeomSubset "ice" (prepend apiSchemas = ["MaterialBindingAPI"])
            {
                uniform token elementType = "face"
                uniform token familyName = "physics"
                int[] indices = [0]
                rel material:binding:physics = </World/Ice>
            }
            def GeomSubset "rest" (prepend apiSchemas = ["MaterialBindingAPI"])
            {
                uniform token elementType = "face"
                uniform token familyName = "physics"
                int[] indices = [1, 2, 3]
                rel material:binding:physics = </World/Rubber>
            }
        }
    }
    def Material "Ice" (prepend apiSchemas = ["PhysicsMaterialAPI"]) {
            float physics:density = 900
        }
    def Material "Rubber" (prepend apiSchemas = ["PhysicsMaterialAPI"]) {
            float physics:density = 1200
        }
}
""")
    with pytest.raises(ValueError, match=r"prim /World/B/m: its physics materials author different density \(/World/Ice: 900, /World/Rubber: 1200\)"):
        io.load_scene(tmp_path / "faces.usda")
    # A sleeping body (it would hang until touched) and instanced bodies (dropped) are refused.
    asleep = body.replace('rel material:binding:physics = </World/Rubber>', "bool physics:startsAsleep = true")
    (tmp_path / "asleep.usda").write_text(_METRE_STAGE + 'def Xform "World"\n{' + asleep + "}\n")
    with pytest.raises(ValueError, match="prim /World/B: physics:startsAsleep is not supported"):
        io.load_scene(tmp_path / "asleep.usda")
    (tmp_path / "instancer.usda").write_text(_METRE_STAGE + """
def Xform "World"
{
    def PointInstancer "Boxes"
    {
        point3f[] positions = [(0, 0, 1), (2, 0, 1)]
        int[] protoIndices = [0, 0]
        rel prototypes = </World/Boxes/Protos/Box>
        def Scope "Protos"
        {
            def Xform "Box" (prepend apiSchemas = ["PhysicsRigidBodyAPI"])
            {
                def Cube "g" (prepend apiSchemas = ["PhysicsCollisionAPI"]) {
            double size = 0.5
        }
            }
        }
    }
}
""")
    with pytest.raises(ValueError, match="prim /World/Boxes: a PointInstancer of rigid bodies or colliders"):
        io.load_scene(tmp_path / "instancer.usda")
    # Prototypes under an ``over`` or ``class`` container, or inside an instanceable reference,
    # are drawn as well, but the default traversal skipped them: their bodies were dropped
    # silently (a probe, stop 59).
    instancer = (tmp_path / "instancer.usda").read_text()
    for specifier in ("over", "class"):
        (tmp_path / f"{specifier}.usda").write_text(instancer.replace('def Scope "Protos"', f'{specifier} Scope "Protos"'))
        with pytest.raises(ValueError, match=r"prim /World/Boxes: a PointInstancer of rigid bodies or colliders \(/World/Boxes/Protos/Box\)"):
            io.load_scene(tmp_path / f"{specifier}.usda")
    (tmp_path / "crate.usda").write_text(_METRE_STAGE + _CRATE)
    # An instanceable reference's local children are ignored: the prototype holds the crate only.
    referenced = instancer.replace('def Xform "Box" (prepend apiSchemas = ["PhysicsRigidBodyAPI"])', 'def Xform "Box" (instanceable = true\n references = @crate.usda@</Crate>)')
    (tmp_path / "referenced.usda").write_text(referenced)
    with pytest.raises(ValueError, match=r"prim /World/Boxes: a PointInstancer of rigid bodies or colliders \(/World/Boxes/Protos/Box/Body\)"):
        io.load_scene(tmp_path / "referenced.usda")


_CRATE = """
def Xform "Crate"
{
    def Xform "Body" (prepend apiSchemas = ["PhysicsRigidBodyAPI"])
    {
        def Cube "g" (prepend apiSchemas = ["PhysicsCollisionAPI"])
        {
            double size = 0.5
        }
    }
}
"""

_LAYOUT_ASSET = """
def Xform "World"
{
    def Cube "ground" (prepend apiSchemas = ["PhysicsCollisionAPI"])
    {
        double size = 1
        double3 xformOp:translate = (0, 0, -0.5)
        double3 xformOp:scale = (10, 10, 1)
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:scale"]
    }
    def Cube "box" (prepend apiSchemas = ["PhysicsRigidBodyAPI", "PhysicsCollisionAPI"])
    {
        double size = 0.2
        double3 xformOp:translate = (0, 0, 0.1)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
}
"""


def test_time_samples_in_a_stronger_layer_than_the_default_are_refused(tmp_path):
    """A layout layer placing an asset's body by one time sample: USD shows the sample at every
    time code, while the load read the weaker layer's default, which no viewer shows (the box
    loaded at the asset's origin, silently; a probe, stop 59). Samples beside a default in the
    same layer keep their meaning: the default is the initial state."""
    (tmp_path / "asset.usda").write_text(_METRE_STAGE + _LAYOUT_ASSET)
    layout = '#usda 1.0\n(\n    metersPerUnit = 1\n    upAxis = "Z"\n    subLayers = [@./asset.usda@]\n)\n'
    layout += 'over "World"\n{\n    over "box"\n    {\n        double3 xformOp:translate.timeSamples = {\n            1: (3, 0, 0.1),\n        }\n    }\n}\n'
    (tmp_path / "layout.usda").write_text(layout)
    with pytest.raises(ValueError, match=r"prim /World/box: /World/box.xformOp:translate has time samples in .*layout.usda, which override at every time code its default in the weaker .*asset.usda"):
        io.load_scene(tmp_path / "layout.usda")
    same = _LAYOUT_ASSET.replace("double3 xformOp:translate = (0, 0, 0.1)", "double3 xformOp:translate = (0, 0, 0.1)\n        double3 xformOp:translate.timeSamples = {1: (3, 0, 0.1)}")
    (tmp_path / "same.usda").write_text(_METRE_STAGE + same)
    assert np.array_equal(io.load_scene(tmp_path / "same.usda").body("box").pose, [0, 0, 0.1, 0, 0, 0, 1])


def test_a_static_body_in_a_contact_group_keeps_it_through_save(tmp_path):
    # A static body was saved as a bare collider, which dropped its warpcontact:group.
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    ground = next(b for b in scene.bodies if b.static)
    ground.group = 3
    io.save_scene(scene, tmp_path / "saved.usda")
    again = io.load_scene(tmp_path / "saved.usda")
    kept = next(b for b in again.bodies if b.name == ground.name)
    assert kept.static and kept.group == 3
    np.testing.assert_allclose(kept.vertices, ground.vertices, atol=1e-6)
    np.testing.assert_allclose(kept.pose, ground.pose, atol=1e-12)


def test_a_body_named_targets_keeps_its_trajectory_and_its_marker(tmp_path):
    """"targets" was the writer's own prim: a body so named was refused only when a whole task
    run had finished, and its --resume failed the same way. The markers move aside instead."""
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    box = scene.body("box")
    box.name, box.target_position = "targets", np.array([1.0, 0.0, 0.25])
    model, q = simulate(scene, 2)
    io.export_trajectory(scene, io.model_to_scene_poses(scene, model, q), tmp_path / "traj.usda")
    stage = Usd.Stage.Open(str(tmp_path / "traj.usda"))
    assert stage.GetPrimAtPath("/World/targets/mesh").IsA(UsdGeom.Mesh)
    assert stage.GetPrimAtPath("/World/targets_1/targets").IsA(UsdGeom.Sphere)


def test_flat_transforms_and_repeated_polygons_refused_only_where_they_change_the_shape(tmp_path):
    """The refusals of flattening transforms and repeated polygons (a probe, stop 57) keep
    what loaded before (a review): a ground mesh in z = 0 under a scale of (2, 2, 0), an
    infinite Plane under (1, 1, 0), a convexHull collider whose mesh repeats a polygon (its
    hull is taken of the points). A copy whose corner is named twice in a row (read as the
    quad) is still a copy."""
    path = write_physics_scene(tmp_path / "a.usda")
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/ground")).AddScaleOp().Set(Gf.Vec3f(2, 2, 0))
    stage.GetRootLayer().Save()
    ground = io.load_scene(path).body("ground")
    np.testing.assert_allclose(np.ptp(ground.vertices, axis=0), [8.0, 8.0, 0.0])

    stage = Usd.Stage.Open(str(write_physics_scene(tmp_path / "b.usda")))
    plane = UsdGeom.Plane.Define(stage, "/World/floor")
    UsdPhysics.CollisionAPI.Apply(plane.GetPrim())
    plane.AddTranslateOp().Set(Gf.Vec3d(0, 0, -1))
    plane.AddScaleOp().Set(Gf.Vec3f(1, 1, 0))
    stage.GetRootLayer().Save()
    assert "floor" in [b.name for b in io.load_scene(tmp_path / "b.usda").bodies]

    stage = Usd.Stage.Open(str(write_physics_scene(tmp_path / "c.usda")))
    lump = UsdGeom.Mesh.Define(stage, "/World/lump")  # a cube whose top is listed again, reversed
    lump.CreatePointsAttr([(x, y, z) for z in (0.0, 1.0) for y in (3.0, 4.0) for x in (3.0, 4.0)])
    cube_faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [1, 3, 7, 5], [3, 2, 6, 7], [2, 0, 4, 6]]
    lump.CreateFaceVertexCountsAttr([4] * 7)
    lump.CreateFaceVertexIndicesAttr([i for face in cube_faces + [cube_faces[1][::-1]] for i in face])
    UsdPhysics.CollisionAPI.Apply(lump.GetPrim())
    UsdPhysics.MeshCollisionAPI.Apply(lump.GetPrim()).CreateApproximationAttr("convexHull")
    stage.GetRootLayer().Save()
    assert len(io.load_scene(tmp_path / "c.usda").body("lump").faces) == 12
    UsdPhysics.MeshCollisionAPI(lump.GetPrim()).GetApproximationAttr().Set("none")
    _load_refused(stage, tmp_path / "c.usda", r"prim /World/lump: faces 1 and 6 have the same 4 corners")

    stage = Usd.Stage.Open(str(write_physics_scene(tmp_path / "d.usda")))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ground"))
    indices = list(mesh.GetFaceVertexIndicesAttr().Get())
    mesh.GetFaceVertexCountsAttr().Set(list(mesh.GetFaceVertexCountsAttr().Get()) + [5])
    mesh.GetFaceVertexIndicesAttr().Set(indices + indices[4:8][::-1] + [indices[4]])
    _load_refused(stage, tmp_path / "d.usda", r"prim /World/ground: faces 1 and 16 have the same 4 corners")


def test_a_plane_is_sized_by_the_faces_of_the_other_bodies_not_their_unused_points(tmp_path):
    """A point no face used (1e6 m out) made the square standing in for a Plane 1e8 m across,
    which moved how a box rested on it (a probe, stop 57)."""
    sizes = []
    for stray in (False, True):
        stage = Usd.Stage.Open(str(write_physics_scene(tmp_path / f"p{stray}.usda")))
        plane = UsdGeom.Plane.Define(stage, "/World/floor")
        UsdPhysics.CollisionAPI.Apply(plane.GetPrim())
        plane.AddTranslateOp().Set(Gf.Vec3d(0, 0, -1))
        if stray:
            mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ground"))
            mesh.GetPointsAttr().Set(list(mesh.GetPointsAttr().Get()) + [Gf.Vec3f(1e6, 0, 0)])
        stage.GetRootLayer().Save()
        sizes.append(np.ptp(io.load_scene(tmp_path / f"p{stray}.usda").body("floor").vertices, axis=0))
    np.testing.assert_array_equal(sizes[1], sizes[0])
    assert sizes[0].max() < 1e4  # 1e8 with the stray point counted


def test_trajectory_export_keeps_a_static_body_moved_between_steps(tmp_path):
    """A static body the caller moves between steps (a kinematic paddle) was written at its
    first pose only: drawn still beside the box it pushed. One that stays put is written once."""
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    model, q = simulate(scene, 4)
    poses = io.model_to_scene_poses(scene, model, q)
    assert scene.bodies[0].static and scene.bodies[0].name == "ground"
    io.export_trajectory(scene, poses, tmp_path / "still.usda")
    stage = Usd.Stage.Open(str(tmp_path / "still.usda"))  # held: its prims live as long as it
    assert UsdGeom.Xformable(stage.GetPrimAtPath("/World/ground")).GetOrderedXformOps()[0].GetTimeSamples() == []
    poses[:, 0, 0] += 1e-3 * np.arange(len(poses))
    io.export_trajectory(scene, poses, tmp_path / "moved.usda")
    stage = Usd.Stage.Open(str(tmp_path / "moved.usda"))
    moved = UsdGeom.Xformable(stage.GetPrimAtPath("/World/ground")).GetOrderedXformOps()[0]
    np.testing.assert_allclose([moved.Get(frame)[0] for frame in range(len(poses))], poses[:, 0, 0], rtol=0, atol=1e-12)


def test_trajectory_export_opens_with_time_samples(tmp_path):
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    scene.body("box").target_position = np.array([1.0, 0.0, 0.25])
    model, q = simulate(scene, 5)
    poses = io.model_to_scene_poses(scene, model, q)
    np.testing.assert_allclose(poses[0, 1], scene.body("box").pose, atol=1e-12)
    out = tmp_path / "traj.usda"
    io.export_trajectory(scene, poses, out)
    stage = Usd.Stage.Open(str(out))
    assert stage.GetTimeCodesPerSecond() == 25.0 and stage.GetFramesPerSecond() == 25.0
    assert stage.GetEndTimeCode() == 5
    xf = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box"))
    translate = xf.GetOrderedXformOps()[0]
    assert len(translate.GetTimeSamples()) == 6
    np.testing.assert_allclose(translate.Get(5), poses[5, 1, :3])
    assert stage.GetPrimAtPath("/World/box/mesh").IsA(UsdGeom.Mesh)
    assert stage.GetPrimAtPath("/World/targets/box").IsA(UsdGeom.Sphere)
    with pytest.raises(FileExistsError, match="traj.usda"):
        io.export_trajectory(scene, poses, out)
    io.export_trajectory(scene, poses[:2], out, overwrite=True)
    Sdf.Layer.FindOrOpen(str(out)).Reload()  # USD caches the layer opened above
    assert Usd.Stage.Open(str(out)).GetEndTimeCode() == 1
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp")] == []
    with pytest.raises(ValueError, match="does not exist"):
        io.export_trajectory(scene, poses, tmp_path / "missing" / "x.usda")
    with pytest.raises(ValueError, match="poses"):
        io.export_trajectory(scene, poses[..., :6], tmp_path / "y.usda")
    with pytest.raises(ValueError, match="with at least one frame"):  # an IndexError before
        io.export_trajectory(scene, poses[:0], tmp_path / "z.usda")
    # Each of these used to write a file USD viewers cannot use, or fail inside pxr.
    unrotated = poses.copy()
    unrotated[3, 1, 3:] = 0.0
    with pytest.raises(ValueError, match="poses: body 'box' has a zero rotation quaternion at frame 3"):
        io.export_trajectory(scene, unrotated, tmp_path / "y.usda")
    for fps in (0.0, float("nan"), -25.0):
        with pytest.raises(ValueError, match="fps: must be a positive finite number"):
            io.export_trajectory(scene, poses, tmp_path / "y.usda", fps=fps)
    for name in ("y.txt", "y"):
        with pytest.raises(ValueError, match=rf"{name}: a USD file name must end in .usda, .usd, .usdc"):
            io.export_trajectory(scene, poses, tmp_path / name)
        with pytest.raises(ValueError, match=rf"{name}: a USD file name must end in"):
            io.save_scene(scene, tmp_path / name)
    (tmp_path / "folder.usda").mkdir()
    with pytest.raises(ValueError, match="folder.usda: is a folder, not a file name"):
        io.export_trajectory(scene, poses, tmp_path / "folder.usda", overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.usda", "folder.usda", "traj.usda"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(mass=-2.0), r"/World/box: mass must be positive"),
        # It used to say "body1 (none) is not a rigid body with a collider (every link needs a mesh)".
        (dict(joint="RevoluteJoint"), r"/World/joint: physics:body1 is not set; a joint here moves the rigid body in body1"),
        (dict(joint="FixedJoint"), r"/World/joint: the fixed joint's frames on /World/box and on the world disagree by 0.608 m"),
        (dict(joint="DistanceJoint"), r"/World/joint: DistanceJoint is not supported"),
        (dict(face_counts=[2] * 16), r"/World/ground: .*face 0 has 2 vertices"),
        (dict(drop_height=0.2), r"intersect in the initial pose: /World/ground and /World/box"),
    ],
)
def test_bad_scenes_name_the_prim_and_problem(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        io.load_scene(write_physics_scene(tmp_path / "bad.usda", **kwargs)).build_model()


@pytest.mark.parametrize(
    "attribute, value, match",
    [
        ("centredWeight", "count", r"w\.usda: prim .*warpcontact:centredWeight must be one of \('paper', 'pairs'\), got 'count'"),
        ("leafPrecision", "half", r"w\.usda: prim .*warpcontact:leafPrecision must be one of \('float64', 'float32'\), got 'half'"),
        # Named no attribute and left out 'ipc', which loads.
        ("contactMode", "exact", r"w\.usda: prim .*warpcontact:contactMode must be one of \('bsh', 'brute', 'sdrs', 'ipc'\), got 'exact'"),
    ],
)
def test_unknown_setting_token_names_the_file_prim_and_attribute(tmp_path, attribute, value, match):
    from pxr import Sdf, Usd

    path = write_physics_scene(tmp_path / "w.usda")
    stage = Usd.Stage.Open(str(path))
    scene_prim = next(p for p in stage.Traverse() if p.GetTypeName() == "PhysicsScene")
    scene_prim.CreateAttribute("warpcontact:" + attribute, Sdf.ValueTypeNames.Token).Set(value)
    stage.Save()
    with pytest.raises(ValueError, match=match):
        io.load_scene(path)


def test_non_finite_points_missing_files_and_empty_stages(tmp_path):
    pts = [(float(x), float(y), 0.0) for x in np.linspace(-2, 2, 5) for y in np.linspace(-2, 2, 5)]
    pts[3] = (float("nan"), 0.0, 0.0)
    with pytest.raises(ValueError, match=r"/World/ground: point 3 is not finite"):
        io.load_scene(write_physics_scene(tmp_path / "nan.usda", points=pts))
    with pytest.raises(ValueError, match="file not found"):
        io.load_scene(tmp_path / "nope.usda")
    stage = Usd.Stage.CreateNew(str(tmp_path / "empty.usda"))
    UsdGeom.Xform.Define(stage, "/World")
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match="metersPerUnit is not authored"), pytest.raises(ValueError, match="no dynamic rigid bodies"):
        io.load_scene(tmp_path / "empty.usda")


def test_load_scene_reads_the_file_on_disk_while_a_stage_of_it_is_open(tmp_path):
    """USD keeps one copy of each open file a process and Stage.Open hands it back unread: a
    file saved or fixed while a viewer's stage held it, or while a failed load's traceback
    did (a notebook keeps the last one), loaded as it was before (a probe, stop 63). Unsaved
    in-process edits are loaded with a warning."""
    path = write_physics_scene(tmp_path / "held.usda")
    good = path.read_text()
    path.write_text(good.replace("double size = 0.5", "double size = -1"))
    with pytest.raises(ValueError, match="size must be a positive finite number") as kept:
        io.load_scene(path)
    path.write_text(good)
    fixed = io.load_scene(path)
    np.testing.assert_allclose(np.ptp(fixed.bodies[-1].vertices, axis=0), 0.5)
    assert kept.value.__traceback__ is not None  # the failed load's frame, and its stage, still alive
    held = Usd.Stage.Open(str(path))
    held.GetPrimAtPath("/World/box/shape").GetAttribute("size").Set(0.4)
    with pytest.warns(UserWarning, match="unsaved changes in this process"):
        edited = io.load_scene(path)
    np.testing.assert_allclose(np.ptp(edited.bodies[-1].vertices, axis=0), 0.4)
    held.Reload()  # the edit dropped: the viewer's stage holds the file as saved
    scene = io.load_scene(path)
    scene.settings.time_step = 0.03
    io.save_scene(scene, path, overwrite=True)
    assert io.load_scene(path).settings.time_step == 0.03


def test_a_scene_without_metersperunit_is_warned_about_and_a_tolerance_without_a_target_refused(tmp_path):
    # USD's fallback unit is the centimetre: a hand-written scene in metres that left it out
    # became 100 times smaller, silently.
    path = write_physics_scene(tmp_path / "a.usda")
    stage = Usd.Stage.Open(str(path))
    stage.ClearMetadata("metersPerUnit")
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match="a.usda: metersPerUnit is not authored, so USD's fallback of 0.01"):
        io.load_scene(path)
    # A tolerance without a position was ignored: the body was no target, with no message.
    path = write_physics_scene(tmp_path / "b.usda")
    stage = Usd.Stage.Open(str(path))
    stage.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:target:tolerance", Sdf.ValueTypeNames.Double).Set(0.1)
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match="prim /World/box: warpcontact:target:tolerance is authored without a warpcontact:target:position"):
        io.load_scene(path)


def _author(path, edit):
    stage = Usd.Stage.Open(str(path))
    edit(stage)
    stage.Save()
    return path


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda st: UsdPhysics.RigidBodyAPI(st.GetPrimAtPath("/World/box")).CreateVelocityAttr(Gf.Vec3f(float("nan"), 0, 0)), r"prim /World/box: physics:velocity must be finite, got \[nan, 0.0, 0.0\]"),
        # A probe: a misspelt position met the tolerance's error, and a cm stage's -20 read "got -0.2".
        (lambda st: [st.GetPrimAtPath("/World/box").CreateAttribute(name, Sdf.ValueTypeNames.Double3 if "pos" in name else Sdf.ValueTypeNames.Double).Set(value) for name, value in (("warpcontact:target:positon", Gf.Vec3d(1, 0, 0)), ("warpcontact:target:tolerance", 0.1))], r"prim /World/box: warpcontact:target:tolerance is authored without a warpcontact:target:position, which makes a body a target \(found warpcontact:target:positon: misspelt\?\)"),
        (lambda st: [UsdGeom.SetStageMetersPerUnit(st, 0.01)] + [st.GetPrimAtPath("/World/box").CreateAttribute(name, kind).Set(value) for name, kind, value in (("warpcontact:target:position", Sdf.ValueTypeNames.Double3, Gf.Vec3d(250, 0, 0)), ("warpcontact:target:tolerance", Sdf.ValueTypeNames.Double, -20.0))], r"prim /World/box: warpcontact:target:tolerance must be finite, >= 0 and at most 1e\+150 m, got -0.2 \(authored: position \[250.0, 0.0, 0.0\], tolerance -20.0, at metersPerUnit 0.01\)"),
        # A zero was replaced by 1 silently; a negative or NaN one surfaced as some other value's error.
        (lambda st: UsdGeom.SetStageMetersPerUnit(st, 0.0), r"metersPerUnit must be positive and finite, got 0.0"),
        (lambda st: UsdGeom.SetStageMetersPerUnit(st, float("nan")), r"metersPerUnit must be positive and finite, got nan"),
        # A probe: a ZeroDivisionError and an OverflowError converting densities.
        (lambda st: UsdGeom.SetStageMetersPerUnit(st, 1e-110), r"metersPerUnit must be from 1e-30 to 1e\+30, got 1e-110"),
        (lambda st: UsdGeom.SetStageMetersPerUnit(st, 1e105), r"metersPerUnit must be from 1e-30 to 1e\+30, got 1e\+105"),
        (lambda st: UsdPhysics.SetStageKilogramsPerUnit(st, 1e-200), r"kilogramsPerUnit must be from 1e-30 to 1e\+30, got 1e-200"),
        (lambda st: UsdPhysics.MassAPI.Apply(st.GetPrimAtPath("/World/box")).CreateCenterOfMassAttr(Gf.Vec3f(0, float("inf"), 0)), r"prim /World/box: centerOfMass must be finite"),
        (lambda st: UsdPhysics.MassAPI.Apply(st.GetPrimAtPath("/World/box")).CreateDiagonalInertiaAttr(Gf.Vec3f(float("nan"), 1, 1)), r"prim /World/box: diagonalInertia must be positive"),
        (lambda st: st.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:target:position", Sdf.ValueTypeNames.Double3).Set(Gf.Vec3d(float("nan"), 0, 0)), r"prim /World/box: warpcontact:target:position must be 3 finite numbers"),
        (lambda st: [st.GetPrimAtPath("/World/box").CreateAttribute(name, kind).Set(value) for name, kind, value in (("warpcontact:target:position", Sdf.ValueTypeNames.Double3, Gf.Vec3d(1, 0, 0)), ("warpcontact:target:tolerance", Sdf.ValueTypeNames.Double, -0.1))], r"prim /World/box: warpcontact:target:tolerance must be finite, >= 0 and at most 1e\+150 m, got -0.1"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:friction", Sdf.ValueTypeNames.Double).Set(float("inf")), r"prim /World/physicsScene: warpcontact:friction must be >= 0 and finite, got inf"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:contactStiffness", Sdf.ValueTypeNames.Double).Set(-1.0), r"prim /World/physicsScene: warpcontact:contactStiffness must be positive and finite, got -1.0"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:timeStep", Sdf.ValueTypeNames.String).Set("fast"), r"prim /World/physicsScene: warpcontact:timeStep must be a number, got 'fast'"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:task:horizon", Sdf.ValueTypeNames.String).Set("long"), r"prim /World/physicsScene: warpcontact:task:horizon must be a whole number, got 'long'"),
        (lambda st: st.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:pd:kpLinear", Sdf.ValueTypeNames.DoubleArray).Set([1.0, 2.0]), r"prim /World/box: warpcontact:pd:kpLinear must be 1 or 3 numbers"),
        (lambda st: st.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:control:dofs", Sdf.ValueTypeNames.String).Set("x"), r"prim /World/box: warpcontact:control:dofs must be a list of strings, got 'x'"),
        # Values of another type were converted: a bool timeStep of 1 ran frames of 1 s, the
        # text "0.1" ran 0.1 s, bool arrays became positions, text arrays numbers.
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:timeStep", Sdf.ValueTypeNames.Bool).Set(True), r"prim /World/physicsScene: warpcontact:timeStep must be a number, got True"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:timeStep", Sdf.ValueTypeNames.String).Set("0.1"), r"prim /World/physicsScene: warpcontact:timeStep must be a number, got '0.1'"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:task:name", Sdf.ValueTypeNames.Int).Set(3), r"prim /World/physicsScene: warpcontact:task:name must be text, got 3"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:task:sampleLow", Sdf.ValueTypeNames.StringArray).Set(["0"]), r"prim /World/physicsScene: warpcontact:task:sampleLow must be a list of numbers"),
        (lambda st: st.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:target:position", Sdf.ValueTypeNames.BoolArray).Set([True, False, True]), r"prim /World/box: warpcontact:target:position must be a list of numbers"),
        (lambda st: st.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:pd:kpLinear", Sdf.ValueTypeNames.Bool).Set(True), r"prim /World/box: warpcontact:pd:kpLinear must be 1 or 3 numbers, got True"),
        (lambda st: st.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:control:dofs", Sdf.ValueTypeNames.IntArray).Set([1, 2]), r"prim /World/box: warpcontact:control:dofs must be a list of strings"),
        # A non-finite transform ended in numpy's "SVD did not converge", naming nothing.
        (lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/box")).GetOrderedXformOps()[0].Set(Gf.Vec3d(0, 0, float("nan"))), r"prim /World/box: /World/box.xformOp:translate must be finite, got \(0, 0, nan\)"),
        (lambda st: UsdGeom.Xform.Define(st, "/World").AddScaleOp().Set(Gf.Vec3f(float("inf"), 1, 1)), r"prim /World/\w+: /World.xformOp:scale must be finite, got \(inf, 1, 1\)"),
        # An orient of real part NaN composed to the identity, a finite matrix.
        (lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/box")).AddOrientOp().Set(Gf.Quatf(float("nan"), 0, 0, 0)), r"prim /World/box: /World/box.xformOp:orient must be finite, got \(nan, 0, 0, 0\)"),
        # A round collider's or a Plane's axis other than X, Y or Z was read as X.
        (lambda st: [st.RemovePrim("/World/box/shape"), UsdPhysics.CollisionAPI.Apply(UsdGeom.Capsule.Define(st, "/World/box/shape").GetPrim()), UsdGeom.Capsule(st.GetPrimAtPath("/World/box/shape")).CreateAxisAttr("w")], r"prim /World/box/shape: axis must be one of the tokens X, Y, Z \(upper case\), got 'w'"),
        (lambda st: [st.RemovePrim("/World/ground"), UsdPhysics.CollisionAPI.Apply(UsdGeom.Plane.Define(st, "/World/ground").GetPrim()), UsdGeom.Plane(st.GetPrimAtPath("/World/ground")).CreateAxisAttr("Up")], r"prim /World/ground: axis must be one of the tokens X, Y, Z \(upper case\), got 'Up'"),
        # USD draws an orient off unit norm as given: (0, 0, 0, 0) as the identity, (0.5, 0, 0,
        # 0.5) as 120 degrees about z (normalised: 90); both loaded without a word.
        (lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/box")).AddOrientOp().Set(Gf.Quatf(0, 0, 0, 0)), r"prim /World/box: /World/box.xformOp:orient must be a unit quaternion, got \(0, 0, 0, 0\) \(norm 0\)"),
        (lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/ground")).AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(0.5, 0, 0, 0.5)), r"prim /World/ground: /World/ground.xformOp:orient must be a unit quaternion, got \(0.5, 0, 0, 0.5\) \(norm 0.707106781\)"),
        # A probe: a zero scale was blamed on the mesh ("faces 0 and 3 are the same triangle")
        # or, on a Cube, on an open mesh; scales fine alone flatten once composed.
        (lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/box")).AddScaleOp().Set(Gf.Vec3f(1, 1, 0)), r"prim /World/box/shape: its world transform flattens it \(/World/box.xformOp:scale is \(1, 1, 0\)\); a scale must be non-zero on every axis"),
        (lambda st: [UsdGeom.Xformable(st.GetPrimAtPath(path)).AddScaleOp().Set(Gf.Vec3f(1, 1e-7, 1)) for path in ("/World/box", "/World/box/shape")], r"prim /World/box/shape: its world transform flattens it \(its transform ops, none flat alone, compose to a singular matrix\)"),
        (lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/box")).AddTransformOp().Set(Gf.Matrix4d(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1)), r"prim /World/box/shape: its world transform flattens it \(/World/box.xformOp:transform is"),
        # A probe: a value block on a UsdPhysics attribute (USD's "use the fallback") was read
        # as leftover memory by UsdPhysics' parser: gravity along a random direction each run.
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("physics:gravityMagnitude", Sdf.ValueTypeNames.Float).Block(), r"prim /World/physicsScene: physics:gravityMagnitude is blocked \(authored as None\), which UsdPhysics' parser does not reliably read as its fallback; author the value instead \(the fallback is -inf\)"),
        (lambda st: UsdPhysics.RigidBodyAPI(st.GetPrimAtPath("/World/box")).CreateAngularVelocityAttr().Block(), r"prim /World/box: physics:angularVelocity is blocked \(authored as None\)"),
        # A probe: a negative face count that kept the counts' sum right was an IndexError.
        (lambda st: UsdGeom.Mesh(st.GetPrimAtPath("/World/ground")).GetFaceVertexCountsAttr().Set([4] * 14 + [8, 4, -4]), r"prim /World/ground: face 16 has -4 vertices; cannot be triangulated"),
        # A probe: a hole index beyond the faces was ignored and its face stayed solid.
        (lambda st: UsdGeom.Mesh(st.GetPrimAtPath("/World/ground")).CreateHoleIndicesAttr([16]), r"prim /World/ground: holeIndices has 16, not a face index \(the mesh has faces 0 to 15\)"),
        # A probe: a quad listed again from another corner, or reversed (two-sided), split
        # along the other diagonal and escaped the repeated-triangle check: the ground pushed
        # twice as hard.
        (lambda st: _append_ground_quad(st, 1, lambda quad: quad[::-1]), r"prim /World/ground: faces 1 and 16 have the same 4 corners \(a polygon listed twice, or a two-sided copy\)"),
        (lambda st: _append_ground_quad(st, 0, lambda quad: np.roll(quad, 1)), r"prim /World/ground: faces 0 and 16 have the same 4 corners"),
        # A projective matrix op had its last column dropped: the body sat metres off.
        (
            lambda st: UsdGeom.Xformable(st.GetPrimAtPath("/World/box")).AddTransformOp().Set(Gf.Matrix4d(1, 0, 0, 0.1, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1)),
            r"prim /World/box: /World/box.xformOp:transform is not an affine transform \(its last column must be 0, 0, 0, 1\)",
        ),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:timestep", Sdf.ValueTypeNames.Double).Set(0.01), r"prim /World/physicsScene: unknown attribute warpcontact:timestep here \(did you mean warpcontact:timeStep\?\)"),
        (lambda st: st.GetPrimAtPath("/World/physicsScene").CreateAttribute("warpcontact:task:learningrate", Sdf.ValueTypeNames.Double).Set(0.1), r"prim /World/physicsScene: unknown attribute warpcontact:task:learningrate here \(did you mean warpcontact:task:learningRate\?\)"),
        (lambda st: st.GetPrimAtPath("/World/ground").CreateAttribute("warpcontact:target:position", Sdf.ValueTypeNames.Double3).Set(Gf.Vec3d(1, 0, 0)), r"prim /World/ground: unknown attribute warpcontact:target:position here \(it belongs on a rigid-body prim\)"),
        (lambda st: st.GetPrimAtPath("/World/box").CreateAttribute("warpcontact:frames", Sdf.ValueTypeNames.Int).Set(3), r"prim /World/box: unknown attribute warpcontact:frames here \(it belongs on the PhysicsScene prim\)"),
        (lambda st: st.GetPrimAtPath("/World/box/shape").CreateAttribute("warpcontact:spin", Sdf.ValueTypeNames.Int).Set(3), r"prim /World/box/shape: unknown attribute warpcontact:spin here \(the attributes read are listed in docs/scene_format\.md\)"),
    ],
)
def test_bad_values_name_the_file_prim_and_attribute(tmp_path, edit, match):
    path = _author(write_physics_scene(tmp_path / "v.usda"), edit)
    with pytest.raises(ValueError, match=r"v\.usda: " + match):
        io.load_scene(path)


@pytest.mark.parametrize(
    ("precision", "quaternion", "expected"),
    [
        # 90 degrees about z as quath is of norm 0.99979.
        (UsdGeom.XformOp.PrecisionHalf, Gf.Quath(0.5**0.5, 0, 0, 0.5**0.5), [0.0, 0.0, 0.5**0.5, 0.5**0.5]),
        # Written to 4 or 5 decimals (norms 0.99999037, 1.000025): refused at a tolerance of 1e-6 (a review).
        (UsdGeom.XformOp.PrecisionFloat, Gf.Quatf(0.7071, 0, 0, 0.7071), [0.0, 0.0, 0.5**0.5, 0.5**0.5]),
        (UsdGeom.XformOp.PrecisionDouble, Gf.Quatd(0.9239, 0, 0, 0.3827), [0.0, 0.0, 0.3826834, 0.9238795]),
    ],
)
def test_an_orient_rounded_off_unit_norm_loads_as_its_rotation(tmp_path, precision, quaternion, expected):
    """Orients off unit norm are refused (USD draws them as neither rotation), beyond the
    rounding of a half-precision quaternion or of one written to 4 decimals."""
    path = write_physics_scene(tmp_path / "rounded.usda")
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).AddOrientOp(precision).Set(quaternion)
    stage.GetRootLayer().Save()
    pose = io.load_scene(path).body("box").pose
    np.testing.assert_allclose(np.abs(pose[3:]), expected, atol=1e-4)


def test_unreadable_files_are_clear_errors(tmp_path):
    (tmp_path / "broken.usda").write_text("#usda 1.0\n( not a layer }}}\n")
    with pytest.raises(ValueError, match=r"broken\.usda: not a readable USD stage \(.*broken\.usda:2"):
        io.load_scene(tmp_path / "broken.usda")
    # USD's error quotes the bytes, and reading it raised UnicodeDecodeError naming nothing.
    (tmp_path / "latin1.usda").write_bytes(b'#usda 1.0\ndef Xform "W" {\n    custom string note = "caf\xe9"\n}\n')
    with pytest.raises(ValueError, match=r"latin1\.usda: not a readable USD stage \(it holds bytes that are not UTF-8"):
        io.load_scene(tmp_path / "latin1.usda")
    (tmp_path / "binary.usda").write_bytes(b"\x00\x01 not text")
    with pytest.raises(ValueError, match=r"binary\.usda: not a readable USD stage"):
        io.load_scene(tmp_path / "binary.usda")
    with pytest.raises(ValueError, match=r": not a file"):
        io.load_scene(tmp_path)


def _hanging_box_stage(path):
    """A metre stage with a 0.2 m box body at z = 1 m, for a joint to hang it from."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.Scene.Define(stage, "/World/physicsScene")
    box = UsdGeom.Xform.Define(stage, "/World/box")
    box.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 1.0))
    UsdPhysics.RigidBodyAPI.Apply(box.GetPrim())
    cube = UsdGeom.Cube.Define(stage, "/World/box/shape")
    cube.CreateSizeAttr(0.2)
    UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
    return stage


def _hang_and_save(stage, joint):
    """Hang _hanging_box_stage's box from ``joint``, anchored 0.5 m above it, and save."""
    joint.CreateBody1Rel().SetTargets(["/World/box"])
    joint.CreateLocalPos0Attr(Gf.Vec3f(0.0, 0.0, 1.5))
    joint.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.5))
    stage.GetRootLayer().Save()


def write_hinged_box(path, *, limits=(-30.0, 60.0), stiffness=2.0, cone=None, cone1=None, d6_ball=False, ball_drives=None):
    """A box hanging from a world revolute joint about y (UsdPhysics only: degrees, per-degree
    gains), or from a spherical joint with a ``cone`` limit, or from a D6 joint with three free
    rotations (``d6_ball``); ``ball_drives`` {"rotX": (stiffness, damping), ...} drive the
    latter two."""
    stage = _hanging_box_stage(path)
    if d6_ball:
        joint = UsdPhysics.Joint.Define(stage, "/World/hinge")
        for axis in ("transX", "transY", "transZ"):
            locked = UsdPhysics.LimitAPI.Apply(joint.GetPrim(), axis)
            locked.CreateLowAttr(1.0)
            locked.CreateHighAttr(-1.0)
    elif cone is None:
        joint = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
        joint.CreateAxisAttr("Y")
        joint.CreateLowerLimitAttr(limits[0])
        joint.CreateUpperLimitAttr(limits[1])
        drive = UsdPhysics.DriveAPI.Apply(joint.GetPrim(), "angular")
        drive.CreateStiffnessAttr(stiffness)
        drive.CreateDampingAttr(0.1)
    else:
        joint = UsdPhysics.SphericalJoint.Define(stage, "/World/hinge")
        joint.CreateAxisAttr("Z")
        joint.CreateConeAngle0LimitAttr(cone)
        joint.CreateConeAngle1LimitAttr(cone if cone1 is None else cone1)
    for token, (drive_stiffness, damping) in (ball_drives or {}).items():
        drive = UsdPhysics.DriveAPI.Apply(joint.GetPrim(), token)
        drive.CreateStiffnessAttr(drive_stiffness)
        drive.CreateDampingAttr(damping)
    _hang_and_save(stage, joint)
    return path


@pytest.mark.filterwarnings("ignore:contact_stiffness .* holds these bodies")  # the test bodies float; not what is tested
def test_revolute_joint_imports_limits_and_drive_in_si_units(tmp_path):
    scene = io.load_scene(write_hinged_box(tmp_path / "hinge.usda"))
    model = scene.build_model()
    art = model.articulation
    assert art.coordinate_names == ["hinge:0"] and art.num_dofs == 1
    np.testing.assert_allclose([art.lower[0], art.upper[0]], np.radians([-30.0, 60.0]))
    assert art.kp[0] == pytest.approx(2.0 * 180.0 / np.pi)  # per degree -> per radian
    assert art.kd[0] == pytest.approx(0.1 * 180.0 / np.pi)
    assert art.initial_coordinates[0] == pytest.approx(0.0, abs=1e-9)
    # it swings about the hinge 0.5 m above the box, which stays attached
    solver = wc.ImplicitSolver(model)
    state = model.state(requires_grad=False)
    state.joint_q.assign([0.3])
    state.joint_q_prev.assign([0.3])
    moved = art.retract(model.initial_q, np.array([0.3]))
    state.body_q.assign(moved)
    state.body_q_prev.assign(moved)
    nxt = model.state(requires_grad=False)
    solver.step(state, nxt, model.control(requires_grad=False), 0.01)
    assert nxt.joint_q.numpy()[0] < 0.3
    assert art.anchor_gaps(nxt.body_q.numpy()).max() < 1e-12


@pytest.mark.filterwarnings("ignore:contact_stiffness .* holds these bodies")  # the test bodies float; not what is tested
def test_spherical_joint_cone_limit_loads_in_radians_and_round_trips(tmp_path):
    scene = io.load_scene(write_hinged_box(tmp_path / "cone.usda", cone=45.0))
    (joint,) = scene.joints
    assert joint.kind == "ball" and joint.cone_limit == pytest.approx(np.pi / 4)
    np.testing.assert_allclose(joint.axes, [[0.0, 0.0, 1.0]])
    cone = scene.build_model().articulation.cones[0]
    assert cone["limit"] == pytest.approx(np.pi / 4)
    io.save_scene(scene, tmp_path / "again.usda")
    again = io.load_scene(tmp_path / "again.usda").build_model().articulation.cones[0]
    assert again["limit"] == pytest.approx(np.pi / 4, rel=1e-6)
    with pytest.raises(ValueError, match=r"/World/hinge: elliptical cone limits"):
        io.load_scene(write_hinged_box(tmp_path / "ellipse.usda", cone=45.0, cone1=30.0))


@pytest.mark.filterwarnings("ignore:contact_stiffness .* holds these bodies")  # the test bodies float; not what is tested
def test_ball_joint_drives_load_per_radian_and_round_trip(tmp_path):
    equal = {token: (2.0, 0.1) for token in ("rotX", "rotY", "rotZ")}
    per_radian = np.array([2.0, 0.1]) * 180.0 / np.pi
    for name, options in (("spherical", dict(cone=45.0)), ("d6", dict(d6_ball=True))):
        scene = io.load_scene(write_hinged_box(tmp_path / f"{name}.usda", ball_drives=equal, **options))
        (joint,) = scene.joints
        assert joint.kind == "ball"
        art = scene.build_model().articulation
        np.testing.assert_allclose([art.ball_kp[0], art.ball_kd[0]], per_radian, rtol=1e-6)  # float attributes
        io.save_scene(scene, tmp_path / f"{name}_again.usda")
        again = io.load_scene(tmp_path / f"{name}_again.usda").build_model().articulation
        np.testing.assert_allclose([again.ball_kp[0], again.ball_kd[0]], per_radian, rtol=1e-6)
    stage = Usd.Stage.Open(str(tmp_path / "spherical_again.usda"))
    saved = stage.GetPrimAtPath("/World/joints/hinge")
    assert saved.IsA(UsdPhysics.SphericalJoint) and all(saved.HasAPI(UsdPhysics.DriveAPI, t) for t in ("rotX", "rotY", "rotZ"))
    unequal = {**equal, "rotY": (3.0, 0.1)}
    with pytest.raises(ValueError, match=r"/World/hinge: a ball joint's drives need equal stiffness and damping on rotX, rotY and rotZ.*RotY stiffness 3 damping 0.1"):
        io.load_scene(write_hinged_box(tmp_path / "unequal.usda", cone=45.0, ball_drives=unequal))
    missing = {"rotX": (2.0, 0.1), "rotY": (2.0, 0.1)}
    with pytest.raises(ValueError, match=r"/World/hinge: a ball joint's drives need equal.*RotZ missing"):
        io.load_scene(write_hinged_box(tmp_path / "missing.usda", d6_ball=True, ball_drives=missing))


def test_articulated_scene_round_trip_preserves_joints(tmp_path):
    from warpcontact import scenes

    built = scenes.build_scene("ant_push")
    io.save_scene(built, tmp_path / "ant.usda")
    loaded = io.load_scene(tmp_path / "ant.usda")
    assert sorted((j.name, j.kind, j.parent, j.child) for j in loaded.joints) == sorted((j.name, j.kind, j.parent, j.child) for j in built.joints)
    a, b = built.build_model().articulation, loaded.build_model().articulation
    assert a.num_dofs == b.num_dofs == 16 + 6
    order = [b.coordinate_names.index(name) for name in a.coordinate_names]
    b.kp, b.kd, b.lower, b.upper, b.initial_coordinates = (arr[order] for arr in (b.kp, b.kd, b.lower, b.upper, b.initial_coordinates))
    np.testing.assert_allclose(b.kp, a.kp, rtol=1e-6)
    np.testing.assert_allclose(b.kd, a.kd, rtol=1e-6)
    np.testing.assert_allclose(b.lower, a.lower, rtol=1e-6)
    np.testing.assert_allclose(b.upper, a.upper, rtol=1e-6)
    np.testing.assert_allclose(b.initial_coordinates, a.initial_coordinates, atol=1e-6)


def _cube_corners_in_world(stage, path, meters):
    matrix = UsdGeom.Xformable(stage.GetPrimAtPath(path)).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    half = 0.5 * UsdGeom.Cube(stage.GetPrimAtPath(path)).GetSizeAttr().Get()
    corners = [Gf.Vec3d(x, y, z) for x in (-half, half) for y in (-half, half) for z in (-half, half)]
    return np.array([list(matrix.Transform(c)) for c in corners]) * meters


@pytest.mark.parametrize(
    "body_ops, shape_ops",
    [
        ([("Scale", (1.0, 1.0, 3.0))], [("RotateX", 45.0)]),  # a shear: came out 0.5 m off at the corners
        ([("RotateZ", 30.0), ("Scale", (1.0, 2.0, 3.0))], [("Translate", (0.5, 0.2, 0.3))]),  # body turned 32.5 degrees, not 30
        ([("RotateX", 30.0), ("Scale", (2.0, 2.0, 2.0))], [("Translate", (0.1, 0.2, 0.3))]),  # turned 34.2 degrees, not 30
        ([("Scale", (2.0, 2.0, 2.0))], [("RotateX", 45.0), ("Scale", (1.0, 1.0, 3.0))]),  # supported before: unchanged
    ],
)
def test_scaled_and_sheared_colliders_load_where_usd_puts_them(tmp_path, body_ops, shape_ops):
    meters = 0.01
    path = write_physics_scene(tmp_path / "scaled.usda", meters=meters, drop_height=2.0)
    stage = Usd.Stage.Open(str(path))
    for prim_path, ops in (("/World/box", body_ops), ("/World/box/shape", shape_ops)):
        xform = UsdGeom.Xformable(stage.GetPrimAtPath(prim_path))
        for op, value in ops:
            getattr(xform, f"Add{op}Op")().Set(Gf.Vec3d(*value) if op == "Translate" else Gf.Vec3f(*value) if op == "Scale" else value)
    stage.GetRootLayer().Save()
    expected = _cube_corners_in_world(stage, "/World/box/shape", meters)
    box = io.load_scene(path).body("box")
    posed = box.vertices @ quat_matrix(box.pose[3:]).T + box.pose[:3]
    assert len(posed) == 8
    for corner in expected:
        # UsdPhysics hands the case it describes exactly float32 dimensions and offsets.
        assert np.linalg.norm(posed - corner, axis=1).min() < 1e-7
    model = io.load_scene(path).build_model()
    volume = abs(np.linalg.det(expected[[4, 2, 1]] - expected[0]))  # edges from one corner
    assert model.body_mass.numpy()[1] == pytest.approx(1000.0 * volume, rel=1e-6)


def test_a_sheared_static_collider_loads_where_usd_puts_it(tmp_path):
    path = write_physics_scene(tmp_path / "sheared.usda")
    stage = Usd.Stage.Open(str(path))
    wall = UsdGeom.Xform.Define(stage, "/World/leaning")
    wall.AddTranslateOp().Set(Gf.Vec3d(2.0, 0.0, 0.5))
    wall.AddScaleOp().Set(Gf.Vec3f(1.0, 1.0, 4.0))
    cube = UsdGeom.Cube.Define(stage, "/World/leaning/slab")
    cube.AddRotateYOp().Set(30.0)
    cube.CreateSizeAttr(0.2)
    UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
    stage.GetRootLayer().Save()
    expected = _cube_corners_in_world(stage, "/World/leaning/slab", 1.0)
    slab = io.load_scene(path).body("slab")
    assert slab.static
    posed = slab.vertices @ quat_matrix(slab.pose[3:]).T + slab.pose[:3]
    for corner in expected:
        assert np.linalg.norm(posed - corner, axis=1).min() < 1e-9


def test_a_transform_with_time_samples_only_is_refused_and_a_default_is_read(tmp_path):
    """With samples only, the default time has no value and the body used to load at the origin."""
    path = write_physics_scene(tmp_path / "sampled.usda")
    stage = Usd.Stage.Open(str(path))
    translate = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).GetOrderedXformOps()[0]
    translate.GetAttr().Clear()
    translate.Set(Gf.Vec3d(0.5, 0.0, 1.0), 1.0)
    translate.Set(Gf.Vec3d(0.9, 0.0, 1.0), 10.0)
    _load_refused(stage, path, r"prim /World/box: /World/box.xformOp:translate is animated \(time samples or a spline\) but has no default value")
    translate.Set(Gf.Vec3d(0.2, 0.0, 0.8))
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(io.load_scene(path).body("box").pose[:3], [0.2, 0.0, 0.8])


def test_a_joint_on_a_scaled_turned_body_keeps_its_anchor(tmp_path):
    """The body's frame was Gf's rotation of its scaled matrix (34.2 degrees for 30), which
    moved the joint's anchor on the body 0.23 m away from the world's."""
    path = write_physics_scene(tmp_path / "hinged.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    body = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box"))
    body.AddRotateXOp().Set(30.0)
    body.AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))
    anchor = np.array(body.ComputeLocalToWorldTransform(Usd.TimeCode.Default()).Transform(Gf.Vec3d(0.0, 0.0, 0.5)))
    hinge = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
    hinge.CreateBody1Rel().SetTargets(["/World/box"])
    hinge.CreateAxisAttr("X")
    hinge.CreateLocalPos0Attr(Gf.Vec3f(*anchor))
    hinge.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.5))
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    box, joint = scene.body("box"), scene.joints[0]
    on_body = quat_matrix(box.pose[3:]) @ joint.child_frame[:3] + box.pose[:3]
    np.testing.assert_allclose(on_body, anchor, atol=1e-6)  # float32 joint positions


def test_a_scaled_body_s_center_of_mass_is_read_in_its_scaled_local_space(tmp_path):
    path = write_physics_scene(tmp_path / "com.usda", mass=2.0, drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    body = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box"))
    body.AddRotateXOp().Set(30.0)
    body.AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))
    UsdPhysics.MassAPI(stage.GetPrimAtPath("/World/box")).CreateCenterOfMassAttr(Gf.Vec3f(0.0, 0.0, 0.1))
    world = np.array(body.ComputeLocalToWorldTransform(Usd.TimeCode.Default()).Transform(Gf.Vec3d(0.0, 0.0, 0.1)))
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    np.testing.assert_allclose(box.center_of_mass, [0.0, 0.0, 0.2], atol=1e-7)  # was (0, 0, 0.1): half-way to the centre
    np.testing.assert_allclose(quat_matrix(box.pose[3:]) @ box.center_of_mass + box.pose[:3], world, atol=1e-7)


def test_velocities_are_read_in_the_parent_s_space(tmp_path):
    """UsdPhysics authors velocities in the space of the body's xform (its parent's); under a
    parent turned 90 degrees about z, (1, 0, 0) m/s used to be taken as world x."""
    path = write_physics_scene(tmp_path / "moving.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Xform.Define(stage, "/World").AddRotateZOp().Set(90.0)
    rigid = UsdPhysics.RigidBodyAPI(stage.GetPrimAtPath("/World/box"))
    rigid.CreateVelocityAttr(Gf.Vec3f(1.0, 0.0, 0.0))
    rigid.CreateAngularVelocityAttr(Gf.Vec3f(0.0, 90.0, 0.0))
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    np.testing.assert_allclose(box.linear_velocity, [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(box.angular_velocity, [-np.pi / 2, 0.0, 0.0], atol=1e-7)
    # A Scope between them has no transform of its own: the turned root still places the
    # body (its velocities were read in world axes).
    UsdGeom.Scope.Define(stage, "/World/group")
    Sdf.CopySpec(stage.GetRootLayer(), "/World/box", stage.GetRootLayer(), "/World/group/box")
    stage.RemovePrim("/World/box")
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    np.testing.assert_allclose(box.linear_velocity, [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(box.angular_velocity, [-np.pi / 2, 0.0, 0.0], atol=1e-7)


def _cube_collider(stage, path, size, position):
    """A Cube collider prim of ``size`` at ``position`` in its parent's frame."""
    cube = UsdGeom.Cube.Define(stage, path)
    cube.CreateSizeAttr(size)
    cube.AddTranslateOp().Set(Gf.Vec3d(*position))
    UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
    return cube.GetPrim()


def test_mass_properties_on_a_collider_are_used_or_refused(tmp_path):
    """A collider's MassAPI used to be ignored: density 5,000 kg/m^3 gave the default 1,000."""
    path = write_physics_scene(tmp_path / "dense.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    shape_mass = UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath("/World/box/shape"))
    shape_mass.CreateDensityAttr(5000.0)
    stage.GetRootLayer().Save()
    assert io.load_scene(path).build_model().body_mass.numpy()[1] == pytest.approx(5000.0 * 0.5**3)
    shape_mass.CreateCenterOfMassAttr(Gf.Vec3f(0.0, 0.0, 0.1))
    _load_refused(stage, path, r"prim /World/box/shape: physics:density, physics:centerOfMass on a collider of rigid body /World/box is not supported")
    shape_mass.GetCenterOfMassAttr().Clear()
    _cube_collider(stage, "/World/box/second", 0.1, (0.0, 0.0, 0.4))
    _load_refused(stage, path, r"prim /World/box/shape: physics:density on a collider of rigid body /World/box is not supported")


def _bind_physics_material(stage, prim_path, material_path, **values):
    material = UsdShade.Material.Define(stage, material_path)
    api = UsdPhysics.MaterialAPI.Apply(material.GetPrim())
    for name, value in values.items():
        getattr(api, f"Create{name[0].upper()}{name[1:]}Attr")(value)
    UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath(prim_path)).Bind(material, UsdShade.Tokens.weakerThanDescendants, "physics")


def test_physics_materials_give_density_and_friction_or_are_refused(tmp_path):
    """Bound physics materials used to be ignored: density 5,000 kg/m^3 gave the default
    1,000, and dynamicFriction 0.9 simulated without friction."""
    path = write_physics_scene(tmp_path / "materials.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    _bind_physics_material(stage, "/World/box/shape", "/World/steel", density=5000.0, dynamicFriction=0.5)
    _bind_physics_material(stage, "/World/ground", "/World/floor", dynamicFriction=0.5)
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    assert scene.settings.friction == pytest.approx(0.5)
    assert scene.build_model().body_mass.numpy()[1] == pytest.approx(5000.0 * 0.5**3)
    UsdPhysics.MaterialAPI(stage.GetPrimAtPath("/World/floor")).GetDynamicFrictionAttr().Set(0.9)
    _load_refused(stage, path, r"different dynamicFriction \(/World/ground: 0.9.*/World/box/shape: 0.5|different dynamicFriction \(/World/box/shape: 0.5.*/World/ground: 0.9")
    scene_prim = stage.GetPrimAtPath("/World/physicsScene")
    scene_prim.CreateAttribute("warpcontact:friction", Sdf.ValueTypeNames.Double).Set(0.3)
    stage.GetRootLayer().Save()
    assert io.load_scene(path).settings.friction == pytest.approx(0.3)  # the scene's own coefficient wins


def test_the_physics_scene_material_is_the_default_and_a_partial_binding_warns(tmp_path):
    """Found by a probe: a material bound to the PhysicsScene (PhysX's default material) was
    ignored (friction 0, the default density), and a material bound to the ground alone set
    the friction of every contact without a word."""
    path = write_physics_scene(tmp_path / "default_material.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    _bind_physics_material(stage, "/World/physicsScene", "/World/rubber", density=3000.0, dynamicFriction=0.8)
    stage.GetRootLayer().Save()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = io.load_scene(path)
    assert scene.settings.friction == pytest.approx(0.8)
    assert scene.build_model().body_mass.numpy()[1] == pytest.approx(3000.0 * 0.5**3)
    _bind_physics_material(stage, "/World/ground", "/World/floor", dynamicFriction=0.8)
    stage.GetRootLayer().Save()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert io.load_scene(path).settings.friction == pytest.approx(0.8)  # the box takes the scene's material: every collider has one
    stage.GetPrimAtPath("/World/physicsScene").GetRelationship("material:binding:physics").ClearTargets(True)
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match=r"prim /World/box/shape binds no physics material giving dynamicFriction, but others do: the scene's one coefficient, 0.8, holds for their contacts too"):
        assert io.load_scene(path).settings.friction == pytest.approx(0.8)


def test_colliders_of_one_body_with_different_material_densities_are_refused(tmp_path):
    path = write_physics_scene(tmp_path / "mixed.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    _cube_collider(stage, "/World/box/cap", 0.1, (0.0, 0.0, 0.4))
    _bind_physics_material(stage, "/World/box/shape", "/World/steel", density=5000.0)
    _bind_physics_material(stage, "/World/box/cap", "/World/cork", density=200.0)
    _load_refused(stage, path, r"prim /World/box: its colliders' physics materials give different densities")


@pytest.mark.parametrize("name", ["density", "dynamicFriction"])
def test_a_physics_material_value_authored_only_in_time_samples_is_refused(tmp_path, name):
    """It read as its fallback 0, "not specified": a sampled 3,000 kg/m^3 gave the default
    density's mass, a sampled friction none."""
    path = write_physics_scene(tmp_path / "sampled.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    _bind_physics_material(stage, "/World/box/shape", "/World/steel")
    attr = getattr(UsdPhysics.MaterialAPI(stage.GetPrimAtPath("/World/steel")), f"Create{name[0].upper()}{name[1:]}Attr")()
    attr.Set(0.7 if name == "dynamicFriction" else 3000.0, 0.0)
    _load_refused(stage, path, rf"prim /World/box/shape: /World/steel.physics:{name} is animated \(time samples or a spline\) but has no default value")


def test_collision_filters_are_refused_naming_the_prim(tmp_path):
    """They were ignored: the filtered bodies still pushed each other."""
    path = write_physics_scene(tmp_path / "filtered.usda")
    stage = Usd.Stage.Open(str(path))
    UsdPhysics.FilteredPairsAPI.Apply(stage.GetPrimAtPath("/World/box")).CreateFilteredPairsRel().SetTargets(["/World/ground"])
    _load_refused(stage, path, r"prim /World/box: physics:filteredPairs is not supported")
    UsdPhysics.FilteredPairsAPI(stage.GetPrimAtPath("/World/box")).GetFilteredPairsRel().ClearTargets(True)
    group = UsdPhysics.CollisionGroup.Define(stage, "/World/group")
    group.CreateFilteredGroupsRel().SetTargets(["/World/group"])
    _load_refused(stage, path, r"prim /World/group: collision-group filtering is not supported")
    group.GetFilteredGroupsRel().ClearTargets(True)
    stage.GetRootLayer().Save()
    io.load_scene(path)  # a group that filters nothing loads


def test_a_static_body_with_a_target_or_gains_is_refused_on_load_as_on_save(tmp_path):
    """A kinematic body with a target, or a disabled one with PD gains, loaded without a word
    and its scene could not be saved ("static body ... has a target")."""
    path = write_physics_scene(tmp_path / "kinematic.usda")
    stage = Usd.Stage.Open(str(path))
    box = stage.GetPrimAtPath("/World/box")
    box.CreateAttribute("warpcontact:target:position", Sdf.ValueTypeNames.Double3Array).Set([(1.0, 0.0, 0.3)])
    UsdPhysics.RigidBodyAPI(box).CreateKinematicEnabledAttr(True)
    _load_refused(stage, path, r"prim /World/box: a static body here \(kinematic, disabled or welded to the world\) has a target, which only a dynamic body takes")
    box.RemoveProperty("warpcontact:target:position")
    box.CreateAttribute("warpcontact:pd:kpLinear", Sdf.ValueTypeNames.Double).Set(100.0)
    _load_refused(stage, path, r"prim /World/box: a static body here .* has PD gains")


def test_task_metadata_without_a_name_is_saved_as_authored(tmp_path):
    """save_scene wrote the task only where it had a name: its horizon and control were lost."""
    scene = io.load_scene(write_physics_scene(tmp_path / "partial.usda"))
    scene.task = io.TaskSpec(control="pd_targets", horizon=9)
    io.save_scene(scene, tmp_path / "saved.usda")
    assert io.load_scene(tmp_path / "saved.usda").task == scene.task


def test_an_animated_kinematic_body_or_static_collider_is_refused(tmp_path):
    """It loaded as a static body held at its default pose, its animation ignored."""
    path = write_physics_scene(tmp_path / "platform.usda")
    stage = Usd.Stage.Open(str(path))
    box = stage.GetPrimAtPath("/World/box")
    UsdPhysics.RigidBodyAPI(box).CreateKinematicEnabledAttr(True)
    UsdPhysics.RigidBodyAPI.Apply(_cube_collider(stage, "/World/crate", 0.2, (1.5, 0.0, 0.5)))
    stage.GetRootLayer().Save()
    assert io.load_scene(path).body("box").static  # not animated: a static body, as documented
    UsdGeom.Xformable(box).GetOrderedXformOps()[0].Set(Gf.Vec3d(0.5, 0.0, 0.6), 10.0)
    _load_refused(stage, path, r"prim /World/box: a kinematic body moved by time-sampled transforms is not supported")
    UsdGeom.Xformable(box).GetOrderedXformOps()[0].GetAttr().Clear()
    UsdGeom.Xformable(box).GetOrderedXformOps()[0].Set(Gf.Vec3d(0.1, 0.0, 0.6))
    stage.GetRootLayer().Save()
    io.load_scene(path)
    ground = UsdGeom.Xformable(stage.GetPrimAtPath("/World/ground"))
    ground.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 0.0))
    for time in (0.0, 1.0, 2.0):  # samples that repeat the default, as exporters baking every frame write: no motion
        ground.GetOrderedXformOps()[0].Set(Gf.Vec3d(0.0, 0.0, 0.0), time)
        stage.GetRootLayer().Save()
        io.load_scene(path)  # three samples were refused (a probe)
    ground.GetOrderedXformOps()[0].Set(Gf.Vec3d(3.0, 0.0, 0.0), 50.0)
    _load_refused(stage, path, r"prim /World/ground: a static collider moved by time-sampled transforms is not supported")
    ground.GetOrderedXformOps()[0].GetAttr().Clear()
    ground.GetOrderedXformOps()[0].Set(Gf.Vec3d(0.0, 0.0, 0.0))
    slide = ground.AddTranslateXOp(opSuffix="slide")
    slide.Set(0.0)
    spline = Ts.Spline()
    for time, value in ((0.0, 0.0), (10.0, 3.0)):
        knot = Ts.Knot()
        knot.SetTime(time)
        knot.SetValue(value)
        spline.SetKnot(knot)
    slide.GetAttr().SetSpline(spline)  # a spline has no time samples, and a default here
    _load_refused(stage, path, r"prim /World/ground: a static collider moved by time-sampled transforms is not supported")


def test_an_animated_collider_shape_or_place_on_its_body_is_refused(tmp_path):
    """Found by a probe: a collider's animated size, points or transform on its body loaded
    at the default value without a word, while an animated static collider was refused. A
    dynamic body's own animated transform (a recorded trajectory) still loads at its default."""
    path = write_physics_scene(tmp_path / "animated.usda")
    stage = Usd.Stage.Open(str(path))
    body = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box"))
    body.GetOrderedXformOps()[0].Set(Gf.Vec3d(2.0, 0.0, 3.0), 10.0)
    stage.GetRootLayer().Save()
    io.load_scene(path)
    shape = UsdGeom.Cube(stage.GetPrimAtPath("/World/box/shape"))
    shape.GetSizeAttr().Set(0.8, 10.0)
    _load_refused(stage, path, r"prim /World/box/shape: size is animated, but a collider's shape and its place on its body are read once, at the default time")
    shape.GetSizeAttr().ClearAtTime(10.0)
    UsdGeom.Xformable(shape).AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 0.0))
    UsdGeom.Xformable(shape).GetOrderedXformOps()[0].Set(Gf.Vec3d(0.3, 0.0, 0.0), 10.0)
    _load_refused(stage, path, r"prim /World/box/shape: xformOp:translate is animated, but a collider's shape")
    ground = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ground"))
    UsdGeom.Xformable(shape).GetOrderedXformOps()[0].GetAttr().Clear()
    ground.GetPointsAttr().Set(ground.GetPointsAttr().Get() * 2.0, 10.0)
    _load_refused(stage, path, r"prim /World/ground: points is animated")


def test_an_animated_body_attribute_is_refused(tmp_path):
    """Found by a probe: a body's time-sampled task target, PD gain or mass (with a default)
    loaded at the default without a word, while the same on a PhysicsScene or a joint was
    refused."""
    for name, type_name, default, sample in (
        ("warpcontact:target:position", Sdf.ValueTypeNames.Double3, Gf.Vec3d(2.5, 0.0, 0.25), Gf.Vec3d(0.0, 2.5, 0.25)),
        ("warpcontact:pd:kpAngular", Sdf.ValueTypeNames.Double, 10.0, 20.0),
        ("physics:mass", Sdf.ValueTypeNames.Float, 2.0, 3.0),
    ):
        path = write_physics_scene(tmp_path / f"{name.replace(':', '_')}.usda")
        stage = Usd.Stage.Open(str(path))
        if name == "physics:mass":  # read only under MassAPI (without it: refused since stop 58)
            UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath("/World/box"))
        attr = stage.GetPrimAtPath("/World/box").CreateAttribute(name, type_name, custom=name.startswith("warpcontact"))
        attr.Set(default)
        for time in (0.0, 50.0):  # samples repeating the default are no animation
            attr.Set(default, time)
        stage.GetRootLayer().Save()
        io.load_scene(path)
        attr.Set(sample, 100.0)
        _load_refused(stage, path, rf"prim /World/box: {name} is animated, but a RigidBody's values are read once, at the default time")


def _mesh_box_collider(stage, path, *, left_handed=False, extra_hole=False):
    """A closed 0.5 m Mesh box collider: counter-clockwise (outward) triangles, or clockwise
    ones authored as leftHanded; ``extra_hole`` adds a 1 m flap face listed in holeIndices."""
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    faces = np.asarray(box.faces)[:, ::-1] if left_handed else np.asarray(box.faces)
    points = [Gf.Vec3f(*map(float, p)) for p in box.vertices]
    indices = [int(i) for i in faces.ravel()]
    counts = [3] * len(faces)
    if extra_hole:
        points += [Gf.Vec3f(1.0, 0.0, 0.0), Gf.Vec3f(1.0, 1.0, 0.0), Gf.Vec3f(0.0, 1.0, 0.0)]
        indices += [8, 9, 10]
        counts.append(3)
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(indices)
    if left_handed:
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    if extra_hole:
        mesh.CreateHoleIndicesAttr([len(faces)])
    UsdPhysics.CollisionAPI.Apply(mesh.GetPrim())
    return mesh


@pytest.mark.parametrize(
    "body_scale, shape_scale, left_handed",
    [
        ((-1.0, 1.0, 1.0), None, False),  # refused: "needs a closed, outward-oriented mesh"
        ((-1.0, 2.0, 1.0), None, False),
        (None, (1.0, -2.0, 1.0), False),
        ((-1.0, 1.0, 1.0), (1.0, -1.0, 1.0), False),  # mirrored twice: not mirrored
        (None, None, True),  # leftHanded winding: refused the same way
        ((1.0, 1.0, -1.0), None, True),
    ],
)
def test_mirrored_and_left_handed_meshes_load_outward_with_their_mass(tmp_path, body_scale, shape_scale, left_handed):
    path = write_physics_scene(tmp_path / "mirror.usda", drop_height=2.0)
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/World/box/shape")
    mesh = _mesh_box_collider(stage, "/World/box/shape", left_handed=left_handed)
    body = UsdGeom.Xformable(stage.GetPrimAtPath("/World/box"))
    body.AddRotateZOp().Set(30.0)
    if body_scale:
        body.AddScaleOp().Set(Gf.Vec3f(*body_scale))
    if shape_scale:
        mesh.AddScaleOp().Set(Gf.Vec3f(*shape_scale))
    stage.GetRootLayer().Save()
    matrix = mesh.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    expected = np.array([list(matrix.Transform(Gf.Vec3d(*p))) for p in mesh.GetPointsAttr().Get()])
    box = io.load_scene(path).body("box")
    np.testing.assert_allclose(box.vertices @ quat_matrix(box.pose[3:]).T + box.pose[:3], expected, atol=1e-12)
    volume = 0.125 * abs(np.linalg.det(_linear(matrix)))
    assert io.load_scene(path).build_model().body_mass.numpy()[1] == pytest.approx(1000.0 * volume, rel=1e-9)


def _linear(matrix):
    return np.array([[matrix[i][j] for j in range(3)] for i in range(3)])


def test_hole_faces_are_not_collided(tmp_path):
    path = write_physics_scene(tmp_path / "holes.usda", drop_height=2.0)
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/World/box/shape")
    _mesh_box_collider(stage, "/World/box/shape", extra_hole=True)
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    assert len(box.faces) == 12 and box.faces.max() < 8  # the flap was collided before
    assert io.load_scene(path).build_model().body_mass.numpy()[1] == pytest.approx(125.0)


def test_a_joint_on_a_mirrored_body_is_refused(tmp_path):
    """Its anchor came out 0.6 m from where USD puts it under a scale of (-1, 1, 1)."""
    path = write_physics_scene(tmp_path / "hinged.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).AddScaleOp().Set(Gf.Vec3f(-1.0, 1.0, 1.0))
    hinge = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
    hinge.CreateBody1Rel().SetTargets(["/World/box"])
    hinge.CreateLocalPos0Attr(Gf.Vec3f(0.4, 0.2, 3.5))
    hinge.CreateLocalPos1Attr(Gf.Vec3f(0.3, 0.2, 0.5))
    _load_refused(stage, path, r"prim /World/hinge: body1 /World/box is mirrored \(a negative scale in its transform\)")


def test_a_mirrored_body_s_authored_inertia_is_reflected_with_its_geometry(tmp_path):
    """Found by a probe: under a scale of (-1, 1, 1) the collider and centerOfMass came
    through the mirror, and the authored inertia (principal axes turned 34 degrees about
    (1, 1, 1)) was only turned: its principal axes 31-56 degrees off, a free spin at 3 rad/s
    66 degrees off after 20 frames."""
    axis, half = np.ones(3) / np.sqrt(3.0), 0.3

    def world_inertia(scale):
        path = write_physics_scene(tmp_path / f"inertia{scale[0]:+.0f}.usda", drop_height=2.0)
        stage = Usd.Stage.Open(str(path))
        UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).AddScaleOp().Set(Gf.Vec3f(*scale))
        mass = UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath("/World/box"))
        mass.CreateMassAttr(1.0)
        mass.CreateCenterOfMassAttr(Gf.Vec3f(0.1, 0.05, 0.0))
        mass.CreateDiagonalInertiaAttr(Gf.Vec3f(0.15, 0.2, 0.3))
        mass.CreatePrincipalAxesAttr(Gf.Quatf(float(np.cos(half)), Gf.Vec3f(*(np.sin(half) * axis).tolist())))
        stage.GetRootLayer().Save()
        box = io.load_scene(path).body("box")
        turn = quat_matrix(box.pose[3:])
        return turn @ box.inertia @ turn.T, turn @ box.center_of_mass  # in world axes

    plain, plain_offset = world_inertia((1.0, 1.0, 1.0))
    mirrored, mirrored_offset = world_inertia((-1.0, 1.0, 1.0))
    mirror = np.diag([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(mirrored_offset, mirror @ plain_offset, atol=1e-7)
    np.testing.assert_allclose(mirrored, mirror @ plain @ mirror, atol=1e-7)


def test_velocities_under_a_mirroring_parent(tmp_path):
    """An angular velocity is a pseudovector: a parent mirrored in x turns a spin about z
    around (it was carried over unchanged)."""
    path = write_physics_scene(tmp_path / "spin.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Xform.Define(stage, "/World").AddScaleOp().Set(Gf.Vec3f(-1.0, 1.0, 1.0))
    rigid = UsdPhysics.RigidBodyAPI(stage.GetPrimAtPath("/World/box"))
    rigid.CreateVelocityAttr(Gf.Vec3f(1.0, 0.0, 0.0))
    rigid.CreateAngularVelocityAttr(Gf.Vec3f(0.0, 0.0, 90.0))
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    np.testing.assert_allclose(box.linear_velocity, [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(box.angular_velocity, [0.0, 0.0, -np.pi / 2], atol=1e-7)


def _l_shaped_mesh(stage, path):
    """A closed L-shaped prism (concave): two 0.5 m cubes side by side and one on top of the first."""
    l_shape = trimesh.util.concatenate([trimesh.creation.box(extents=(0.5, 0.5, 0.5), transform=trimesh.transformations.translation_matrix(offset)) for offset in ((0, 0, 0), (0.5, 0, 0), (0, 0, 0.5))])
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(*map(float, p)) for p in l_shape.vertices])
    mesh.CreateFaceVertexCountsAttr([3] * len(l_shape.faces))
    mesh.CreateFaceVertexIndicesAttr([int(i) for i in l_shape.faces.ravel()])
    UsdPhysics.CollisionAPI.Apply(mesh.GetPrim())
    return mesh


def test_a_convex_hull_approximation_collides_the_hull_of_the_mesh(tmp_path):
    """It was ignored: the concave mesh itself collided."""
    path = write_physics_scene(tmp_path / "hull.usda", drop_height=2.0)
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/World/box/shape")
    mesh = _l_shaped_mesh(stage, "/World/box/shape")
    UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath("/World/box")).CreateMassAttr(3.0)
    UsdPhysics.MeshCollisionAPI.Apply(mesh.GetPrim()).CreateApproximationAttr("convexHull")
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).AddScaleOp().Set(Gf.Vec3f(1.0, 2.0, 1.0))  # the hull of the scaled points
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    hull = trimesh.Trimesh(box.vertices, box.faces, process=False)
    assert hull.is_watertight and hull.is_convex and hull.volume > 0
    # The L's 3 cubes (0.125 m^3 each, doubled in y) and the wedge its hull adds: 0.25 x 0.5 x 0.5 x 2 / 2.
    assert hull.volume == pytest.approx(2 * 3 * 0.125 + 2 * 0.5 * 0.5 * 0.5 * 0.5, rel=1e-9)
    mesh.GetPointsAttr().Set([Gf.Vec3f(float(x), float(y), 0.0) for x, y, _ in mesh.GetPointsAttr().Get()])  # flattened
    _load_refused(stage, path, r"prim /World/box/shape: physics:approximation 'convexHull': points: they span no volume \(all in one plane\); author 'none'")


@pytest.mark.parametrize("approximation", ["boundingSphere", "boundingCube"])
def test_bounding_shape_approximations_are_refused(tmp_path, approximation):
    path = write_physics_scene(tmp_path / "approx.usda")
    stage = Usd.Stage.Open(str(path))
    api = UsdPhysics.MeshCollisionAPI.Apply(stage.GetPrimAtPath("/World/ground"))
    api.CreateApproximationAttr("convexDecomposition")  # stands in for the triangles: loads as they are
    stage.GetRootLayer().Save()
    assert len(io.load_scene(path).body("ground").faces) == 32
    api.GetApproximationAttr().Set(approximation)
    _load_refused(stage, path, rf"prim /World/ground: physics:approximation '{approximation}' is not supported \(its fit is the engine's choice\)")


def test_a_stage_that_does_not_compose_is_refused(tmp_path):
    """A missing reference or sublayer loaded with a USD warning and without its bodies."""
    path = write_physics_scene(tmp_path / "refs.usda")
    stage = Usd.Stage.Open(str(path))
    crate = UsdGeom.Xform.Define(stage, "/World/crate")
    crate.GetPrim().GetReferences().AddReference("./missing_crate.usda")
    _load_refused(stage, path, r"refs\.usda: the stage does not compose: Could not open asset @.*missing_crate\.usda@ for reference")
    crate.GetPrim().GetReferences().ClearReferences()
    stage.GetRootLayer().subLayerPaths.append("./missing_layer.usda")
    _load_refused(stage, path, r"the stage does not compose: Could not load sublayer @.*missing_layer\.usda@")
    stage.GetRootLayer().subLayerPaths.clear()
    stage.GetRootLayer().Save()
    io.load_scene(path)  # composes again


def test_gravity_that_is_not_finite_and_several_physics_scenes_are_refused(tmp_path):
    """An infinite or NaN gravity magnitude was replaced by 9.81 m/s^2 silently, and of two
    PhysicsScenes the first was taken."""
    path = write_physics_scene(tmp_path / "g.usda")
    stage = Usd.Stage.Open(str(path))
    physics = UsdPhysics.Scene(stage.GetPrimAtPath("/World/physicsScene"))
    physics.GetGravityMagnitudeAttr().Set(-1.0)  # negative: Earth's gravity, as UsdPhysics says
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(io.load_scene(path).gravity, [0.0, 0.0, -9.81])
    for magnitude in (float("inf"), float("nan")):
        physics.GetGravityMagnitudeAttr().Set(magnitude)
        _load_refused(stage, path, rf"prim /World/physicsScene: gravity must be finite, got direction \[0.0, 0.0, -1.0\], magnitude {magnitude}")
    physics.GetGravityMagnitudeAttr().Set(3.71)
    UsdPhysics.Scene.Define(stage, "/World/moon").CreateGravityMagnitudeAttr(1.62)
    _load_refused(stage, path, r"several PhysicsScene prims \(/World/physicsScene, /World/moon\)")


@pytest.mark.filterwarnings("ignore:contact_stiffness .* holds these bodies")
def test_mass_and_drive_units_follow_the_stage_s_meters_and_kilograms(tmp_path):
    """A stage in centimetres and grams: masses and inertias were read as kilograms and
    kg m^2 scaled by lengths only, and drive gains divided by metersPerUnit (a prismatic
    drive of 300 g/s^2 became 30,000 N/m instead of 0.3)."""
    path = write_physics_scene(tmp_path / "cgs.usda", meters=0.01, drop_height=2.0)
    stage = Usd.Stage.Open(str(path))
    UsdPhysics.SetStageKilogramsPerUnit(stage, 0.001)
    mass = UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath("/World/box"))
    mass.CreateMassAttr(500.0)  # g
    mass.CreateDiagonalInertiaAttr(Gf.Vec3f(2.0e4, 3.0e4, 4.0e4))  # g cm^2
    slider = UsdPhysics.PrismaticJoint.Define(stage, "/World/slider")
    slider.CreateAxisAttr("X")
    slider.CreateBody1Rel().SetTargets(["/World/box"])
    slider.CreateLocalPos0Attr(Gf.Vec3f(10.0, 0.0, 200.0))  # cm, at the box's centre
    slider.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
    drive = UsdPhysics.DriveAPI.Apply(slider.GetPrim(), "linear")
    drive.CreateStiffnessAttr(300.0)  # g / s^2
    drive.CreateDampingAttr(40.0)  # g / s
    drive.CreateTargetPositionAttr(5.0)  # cm
    stage.GetRootLayer().Save()
    model = io.load_scene(path).build_model()
    assert model.body_mass.numpy()[1] == pytest.approx(0.5)
    inertia = model.body_mass.numpy()[1] * np.trace(model.body_unit_second_moment.numpy()[1]) * np.ones(3) - model.body_mass.numpy()[1] * np.diag(model.body_unit_second_moment.numpy()[1])
    np.testing.assert_allclose(inertia, np.array([2.0e4, 3.0e4, 4.0e4]) * 1e-3 * 1e-4, rtol=1e-6)
    art = model.articulation
    np.testing.assert_allclose([art.kp[0], art.kd[0], art.default_targets[0]], [0.3, 0.04, 0.05], rtol=1e-6)
    UsdPhysics.MassAPI(stage.GetPrimAtPath("/World/box")).GetMassAttr().Clear()
    UsdPhysics.MassAPI(stage.GetPrimAtPath("/World/box")).GetDiagonalInertiaAttr().Clear()
    UsdPhysics.MassAPI(stage.GetPrimAtPath("/World/box")).CreateDensityAttr(2.0)  # g / cm^3
    stage.RemovePrim("/World/slider")
    hinge = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
    hinge.CreateAxisAttr("Y")
    hinge.CreateBody1Rel().SetTargets(["/World/box"])
    hinge.CreateLocalPos0Attr(Gf.Vec3f(10.0, 0.0, 200.0))
    hinge.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
    turn = UsdPhysics.DriveAPI.Apply(hinge.GetPrim(), "angular")
    turn.CreateStiffnessAttr(5.0e6)  # g cm^2 / degree / s^2
    turn.CreateDampingAttr(1.0e5)  # g cm^2 / degree / s
    stage.GetRootLayer().Save()
    model = io.load_scene(path).build_model()
    assert model.body_mass.numpy()[1] == pytest.approx(2000.0 * 0.5**3)  # kg / m^3 times the 0.5 m cube
    per_radian = 1e-3 * 1e-4 * 180.0 / np.pi
    np.testing.assert_allclose([model.articulation.kp[0], model.articulation.kd[0]], [5.0e6 * per_radian, 1.0e5 * per_radian], rtol=1e-6)


@pytest.mark.parametrize(
    "author, match",
    [
        (lambda joint: joint.CreateCollisionEnabledAttr(True), r"physics:collisionEnabled is not supported: a joint's two bodies never collide here"),
        (lambda joint: joint.CreateBreakForceAttr(50.0), r"breakable joints are not supported \(physics:breakForce 50, physics:breakTorque inf\)"),
    ],
)
def test_joint_collision_and_breaking_are_refused(tmp_path, author, match):
    """Both were ignored: the joint's bodies never collided, and the joint never broke."""
    path = write_physics_scene(tmp_path / "links.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    UsdPhysics.RigidBodyAPI.Apply(_cube_collider(stage, "/World/link", 0.2, (1.0, 0.0, 3.0)))
    joint = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
    joint.CreateBody0Rel().SetTargets(["/World/box"])
    joint.CreateBody1Rel().SetTargets(["/World/link"])
    joint.CreateLocalPos0Attr(Gf.Vec3f(0.5, 0.0, 0.0))
    joint.CreateLocalPos1Attr(Gf.Vec3f(-0.4, 0.0, 0.0))
    stage.GetRootLayer().Save()
    assert len(io.load_scene(path).joints) == 1
    author(joint)
    _load_refused(stage, path, r"prim /World/hinge: " + match)


def _hinge_drive(stage):
    return UsdPhysics.DriveAPI(stage.GetPrimAtPath("/World/hinge"), "angular")


@pytest.mark.filterwarnings("ignore:contact_stiffness .* holds these bodies")
def test_a_drive_s_target_position_is_the_default_joint_target_and_round_trips(tmp_path):
    """A revolute drive targeting 30 degrees held its joint at the initial 0 instead (target
    positions were not read): the hanging box now swings up towards 30 degrees, less the
    sag of its weight (~23 degrees at 2 N m/degree)."""
    path = write_hinged_box(tmp_path / "aim.usda")
    stage = Usd.Stage.Open(str(path))
    _hinge_drive(stage).CreateTargetPositionAttr(30.0)
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    model = scene.build_model()
    control = model.control(requires_grad=False)
    np.testing.assert_allclose(control.joint_target.numpy(), np.radians([30.0]), rtol=1e-6)
    np.testing.assert_allclose(model.state().joint_q.numpy(), [0.0], atol=1e-9)  # the state starts where it is
    solver, state = wc.ImplicitSolver(model), model.state(requires_grad=False)
    angles = []
    for _ in range(200):
        nxt = model.state(requires_grad=False)
        solver.step(state, nxt, control, 0.01)
        state = nxt
        angles.append(state.joint_q.numpy()[0])
    assert 0.3 < np.mean(angles[-50:]) < 0.5
    io.save_scene(scene, tmp_path / "again.usda")
    again = io.load_scene(tmp_path / "again.usda").build_model()
    np.testing.assert_allclose(again.control(requires_grad=False).joint_target.numpy(), np.radians([30.0]), rtol=1e-6)


@pytest.mark.parametrize(
    "author, match",
    [
        (lambda drive: drive.CreateTargetVelocityAttr(10.0), r"drive:angular:physics:targetVelocity 10 is not supported"),
        (lambda drive: drive.CreateTypeAttr("acceleration"), r"drive:angular:physics:type 'acceleration' is not supported"),
        (lambda drive: drive.CreateMaxForceAttr(5.0), r"drive:angular:physics:maxForce 5 is not supported"),
    ],
)
def test_drive_features_a_pd_drive_cannot_follow_are_refused(tmp_path, author, match):
    """Each was ignored: the drive damped towards rest, used force gains, and was unlimited."""
    path = write_hinged_box(tmp_path / "drive.usda")
    stage = Usd.Stage.Open(str(path))
    author(_hinge_drive(stage))
    _load_refused(stage, path, r"prim /World/hinge: " + match)


def test_a_ball_joint_drive_target_is_refused(tmp_path):
    drives = {token: (2.0, 0.1) for token in ("rotX", "rotY", "rotZ")}
    path = write_hinged_box(tmp_path / "ball.usda", cone=45.0, ball_drives=drives)
    stage = Usd.Stage.Open(str(path))
    UsdPhysics.DriveAPI(stage.GetPrimAtPath("/World/hinge"), "rotY").CreateTargetPositionAttr(20.0)
    _load_refused(stage, path, r"prim /World/hinge: drive:rotY:physics:targetPosition 20 is not supported on a ball joint")


def test_bodies_closer_than_the_plane_search_resolves_are_refused_with_a_hint(tmp_path):
    """A 0.5 m box 1e-14 m above a 4 m table: its leaf plane searches do not converge. It used
    to fail at the first step as 'objective is not finite at the start pose (unsolved leaf
    pairs: ...)'. Until the searches ran in each pair's own frame, that was so from 1e-9 m
    (its side faces against the table, whose plane Hessian had a condition number of ~4e15
    in world axes); now 1e-13 m is solved."""
    from warpcontact import scenes

    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    for gap, refused in ((1e-9, False), (1e-13, False), (1e-14, True)):
        body = io.BodySpec("box", "/World/box", np.asarray(box.vertices), np.asarray(box.faces), np.array([0.0, 0.0, 0.25 + gap, 0.0, 0.0, 0.0, 1.0]))
        scene = io.Scene(bodies=[scenes.ground_rectangle(4.0, 4.0), body])
        if not refused:
            scene.build_model()
            continue
        with pytest.raises(ValueError, match=r"in the initial pose, /World/ground and /World/box: their leaf plane searches did not converge, most likely because they are closer than float64 resolves"):
            scene.build_model()
        b = wc.ModelBuilder()
        b.add_body((scene.bodies[0].vertices, scene.bodies[0].faces), static=True, name="ground")
        b.add_body((body.vertices, body.faces), density=1000.0, name="box", pose=body.pose)
        model = b.finalize()
        with pytest.raises(wc.SolverError, match=r"objective is not finite at the start pose: ground and box: their leaf plane searches did not converge"):
            wc.ImplicitSolver(model).step(model.state(requires_grad=False), model.state(requires_grad=False), None, 0.04)


def test_unmodelled_damping_and_restitution_are_named_in_a_warning(tmp_path):
    """Isaac assets author PhysX damping, and materials restitution: both change how bodies
    move, and neither is modelled (they were ignored silently)."""
    path = write_physics_scene(tmp_path / "damped.usda")
    stage = Usd.Stage.Open(str(path))
    box = stage.GetPrimAtPath("/World/box")
    box.CreateAttribute("physxRigidBody:angularDamping", Sdf.ValueTypeNames.Float).Set(0.05)
    box.CreateAttribute("physxRigidBody:linearDamping", Sdf.ValueTypeNames.Float).Set(0.0)  # zero: nothing ignored
    stage.GetRootLayer().Save()
    _bind_physics_material(stage, "/World/box/shape", "/World/rubber", restitution=0.8)
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match=r"damped\.usda: not modelled, so ignored: /World/box physxRigidBody:angularDamping 0.05, /World/rubber physics:restitution 0.8$"):
        io.load_scene(path)
    # Gravity switched off and locked axes were not named: the box fell, free.
    box.CreateAttribute("physxRigidBody:disableGravity", Sdf.ValueTypeNames.Bool).Set(True)
    box.CreateAttribute("physxRigidBody:lockedRotAxis", Sdf.ValueTypeNames.Int).Set(7)
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match=r"angularDamping 0.05, /World/box physxRigidBody:disableGravity 1, /World/box physxRigidBody:lockedRotAxis 7, /World/rubber"):
        io.load_scene(path)


def test_physics_attributes_of_no_usd_physics_schema_are_named_in_a_warning(tmp_path):
    """A misspelt physics:densty, or another tool's physics:linearDamping, loaded without a
    word (a probe, stop 62); the warpcontact: namespace refuses such names."""
    path = write_physics_scene(tmp_path / "typo.usda")
    stage = Usd.Stage.Open(str(path))
    box = stage.GetPrimAtPath("/World/box")
    box.CreateAttribute("physics:densty", Sdf.ValueTypeNames.Float).Set(300.0)
    box.CreateAttribute("physics:linearDamping", Sdf.ValueTypeNames.Float).Set(0.1)
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match=r"typo\.usda: no UsdPhysics schema has these attributes or schemas, so they are ignored: /World/box physics:densty \(did you mean physics:density\?\), /World/box physics:linearDamping"):
        io.load_scene(path)


@pytest.mark.parametrize("attribute, value", [("pd:kpLinear", (400.0, 400.0, -400.0)), ("pd:kdLinear", (60.0, float("nan"), 60.0)), ("pd:kdAngular", -1.0)])
def test_a_negative_or_nan_pd_gain_is_named_by_its_attribute(tmp_path, attribute, value):
    """The builder's check named its own argument and a numpy repr ("kp_linear must be 1 or 3
    numbers ..., got array([ 400., 400., -400.])"; a probe, stop 64)."""
    path = write_physics_scene(tmp_path / "gain.usda")
    stage = Usd.Stage.Open(str(path))
    box = stage.GetPrimAtPath("/World/box")
    kind = Sdf.ValueTypeNames.Double3 if isinstance(value, tuple) else Sdf.ValueTypeNames.Double
    box.CreateAttribute("warpcontact:" + attribute, kind, custom=True).Set(Gf.Vec3d(*value) if isinstance(value, tuple) else value)
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=rf"gain\.usda: prim /World/box: warpcontact:{attribute} must be finite and >= 0 \(a PD gain\), got [-\[]"):
        io.load_scene(path)


def test_a_mesh_error_names_the_authored_faces_and_points(tmp_path):
    """A box of six quads with the third flipped was "faces 5 and 10 both run from vertex 0 to
    vertex 4": triangles of the triangulation, counted over all of a body's colliders; the
    file has quads 2 and 5 (a probe, stop 64). A primitive's triangles are named as such."""
    path = write_physics_scene(tmp_path / "flipped.usda")
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/World/box/shape")
    collider = UsdGeom.Mesh.Define(stage, "/World/box/collider")
    collider.CreatePointsAttr([(-0.25, -0.25, -0.25), (0.25, -0.25, -0.25), (0.25, 0.25, -0.25), (-0.25, 0.25, -0.25), (-0.25, -0.25, 0.25), (0.25, -0.25, 0.25), (0.25, 0.25, 0.25), (-0.25, 0.25, 0.25)])
    quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    quads[2] = quads[2][::-1]
    collider.CreateFaceVertexCountsAttr([4] * 6)
    collider.CreateFaceVertexIndicesAttr([i for quad in quads for i in quad])
    UsdPhysics.CollisionAPI.Apply(collider.GetPrim())
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    with pytest.raises(ValueError, match=r"prim /World/box: body 'box': mass from density needs a closed, consistently outward-oriented mesh \(face 2 of /World/box/collider and face 5 of /World/box/collider both run from point 0 of /World/box/collider to point 4 of /World/box/collider: one of them is wound the other way round"):
        scene.build_model(device="cpu")
    # A second, primitive collider after the mesh: the names still point into the mesh.
    UsdPhysics.CollisionAPI.Apply(UsdGeom.Cube.Define(stage, "/World/box/knob").GetPrim())
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"face 2 of /World/box/collider and face 5 of /World/box/collider both run"):
        io.load_scene(path).build_model(device="cpu")
    part = io.ColliderPart("/World/box/knob", 12, 8)
    assert part.face_name(3) == "triangle 3 of /World/box/knob's triangulation" and part.vertex_name(1) == "vertex 1 of /World/box/knob's triangulation"
    # A mesh replaced in Python is named by its own numbers: the colliders it was read from
    # named a point the prim does not have, and a face past their end was an IndexError (a
    # review, stop 64). Where a body came from is no part of its equality.
    scene = io.load_scene(path)
    box = scene.body("box")
    assert box == dataclasses.replace(box, mesh_origin=None)
    box.faces = box.faces[:-1]
    with pytest.raises(ValueError, match=rf"the edge between vertex \d+ and vertex \d+ borders face {len(box.faces) - 1} alone"):
        scene.build_model(device="cpu")
    # A triangle listed twice (across the box, on none of its faces) is named by its authored faces too.
    collider.CreateFaceVertexCountsAttr([4] * 6 + [3, 3])
    collider.CreateFaceVertexIndicesAttr([i for quad in quads for i in quad] + [0, 2, 5, 5, 0, 2])
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"mesh 'box': face 6 of /World/box/collider and face 7 of /World/box/collider are the same triangle"):
        io.load_scene(path).build_model(device="cpu")


def test_a_scene_or_path_of_the_wrong_kind_is_named(tmp_path):
    """A probe (stop 64): None or a list as a path gave pathlib's TypeError, None as a scene an
    AttributeError, a static flag "no" read as true, and an up axis "X" was written as Z."""
    scene = io.load_scene(write_physics_scene(tmp_path / "box.usda"))
    for call in (lambda: io.load_scene(None), lambda: io.save_scene(scene, ["a.usda"]), lambda: io.export_trajectory(scene, np.zeros((1, 2, 7)), 3)):
        with pytest.raises(ValueError, match=r"path: expected a file path \(str or pathlib.Path\), got (NoneType|list|int)"):
            call()
    with pytest.raises(ValueError, match=r"scene: expected a warpcontact Scene \(io.load_scene, scenes.build_scene\), got NoneType"):
        io.save_scene(None, tmp_path / "none.usda")
    with pytest.raises(ValueError, match=r"x.usda: scene.up_axis must be 'Y' or 'Z' \(USD's up axes\), got 'X'"):
        io.save_scene(dataclasses.replace(scene, up_axis="X"), tmp_path / "x.usda")
    scene.body("box").static = "no"
    with pytest.raises(ValueError, match=r"flag.usda: body 'box': static: expected True/False"):
        io.save_scene(scene, tmp_path / "flag.usda")
    assert not any(tmp_path.glob("[nxf]*.usda"))


def test_misspelt_usd_physics_schemas_are_named_in_a_warning(tmp_path):
    """USD drops an API schema it does not know without a word: a crate listing
    PhysicsRigidbodyAPI loaded as a static obstacle, silently (a probe, stop 64). Names that
    look like UsdPhysics' are named; other tools' schemas (PhysX's) are not."""
    path = write_physics_scene(tmp_path / "schema.usda")
    stage = Usd.Stage.Open(str(path))
    crate = UsdGeom.Xform.Define(stage, "/World/crate")
    crate.AddTranslateOp().Set(Gf.Vec3d(1.2, 0.0, 0.6))
    listed = Sdf.TokenListOp()
    listed.prependedItems = ["PhysicsRigidbodyAPI", "physicsMassAPI", "PhysxRigidBodyAPI", "PhysicsDriveAPI"]
    crate.GetPrim().SetMetadata("apiSchemas", listed)
    UsdPhysics.CollisionAPI.Apply(UsdGeom.Cube.Define(stage, "/World/crate/shape").GetPrim())
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match=r"schema\.usda: no UsdPhysics schema has these attributes or schemas, so they are ignored: /World/crate apiSchemas PhysicsRigidbodyAPI \(did you mean PhysicsRigidBodyAPI\?\), /World/crate apiSchemas physicsMassAPI \(did you mean PhysicsMassAPI\?\), /World/crate apiSchemas PhysicsDriveAPI \(did you mean PhysicsDriveAPI:<instance>\?\)$"):
        scene = io.load_scene(path)
    assert scene.body("shape").static and not scene.body("box").static  # the crate's collider, static


@pytest.mark.parametrize("axis", ["Z", "Y", "X"])
def test_a_plane_collider_becomes_a_large_square_under_the_scene(tmp_path, axis):
    """Plane colliders (infinite in UsdPhysics) were refused, so a typical ground plane
    could not load."""
    path = write_physics_scene(tmp_path / "plane.usda")
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/World/ground")
    plane = UsdGeom.Plane.Define(stage, "/World/groundPlane")
    plane.CreateAxisAttr(axis)
    plane.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, -0.5))
    if axis != "Z":  # turn the plane so that its axis points up (+z)
        plane.AddRotateXYZOp().Set(Gf.Vec3f(-90.0, 0.0, 0.0) if axis == "Y" else Gf.Vec3f(0.0, -90.0, 0.0))
    UsdPhysics.CollisionAPI.Apply(plane.GetPrim())
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    ground = scene.body("groundPlane")
    assert ground.static and len(ground.faces) == 2
    corners = ground.vertices @ quat_matrix(ground.pose[3:]).T + ground.pose[:3]
    np.testing.assert_allclose(corners[:, 2], -0.5, atol=1e-12)
    box = scene.body("box")
    box_corners = box.vertices + box.pose[:3]
    side = io.PLANE_SIZE_FACTOR * np.linalg.norm(np.ptp(np.vstack([box_corners]), axis=0))
    np.testing.assert_allclose(np.ptp(corners[:, :2], axis=0), [side, side], rtol=1e-9)
    np.testing.assert_allclose(corners[:, :2].mean(axis=0), box.pose[:2], atol=1e-9)  # centred under the box
    model, q = simulate(scene, 30)
    assert q[-1, 0, 2] == pytest.approx(-0.25, abs=1e-3)  # the box rests on it


def test_two_plane_colliders_are_each_sized_by_the_other_bodies(tmp_path):
    """A floor and a wall: the second was sized by the first's 100-fold square as well."""
    path = write_physics_scene(tmp_path / "planes.usda")
    stage = Usd.Stage.Open(str(path))
    for name, ops in (("floor", []), ("wall", [("Translate", (3.0, 0.0, 0.0)), ("RotateY", -90.0)])):
        plane = UsdGeom.Plane.Define(stage, f"/World/{name}")
        for op, value in ops:
            getattr(plane, f"Add{op}Op")().Set(Gf.Vec3d(*value) if op == "Translate" else value)
        UsdPhysics.CollisionAPI.Apply(plane.GetPrim())
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    sides = [np.ptp(scene.body(name).vertices, axis=0).max() for name in ("floor", "wall")]
    assert sides[0] == pytest.approx(sides[1], rel=1e-9)


def test_a_plane_collider_on_a_rigid_body_is_refused(tmp_path):
    path = write_physics_scene(tmp_path / "plane_body.usda")
    stage = Usd.Stage.Open(str(path))
    plane = UsdGeom.Plane.Define(stage, "/World/box/flat")
    UsdPhysics.CollisionAPI.Apply(plane.GetPrim())
    _load_refused(stage, path, r"prim /World/box/flat: a Plane collider is infinite; it cannot belong to rigid body /World/box")


@pytest.mark.parametrize("scaled", [False, True])
def test_a_cone_collider_loads_where_usd_puts_it(tmp_path, scaled):
    """Cone colliders were refused. UsdGeom's cone is centred on its origin with its apex
    towards +axis; under a body scaled (1, 2, 1) its points take the exact path."""
    path = write_physics_scene(tmp_path / "cone.usda", drop_height=2.0)
    stage = Usd.Stage.Open(str(path))
    cone = UsdGeom.Cone.Define(stage, "/World/box/tip")
    cone.CreateRadiusAttr(0.2)
    cone.CreateHeightAttr(0.4)
    cone.CreateAxisAttr("X")
    cone.AddTranslateOp().Set(Gf.Vec3d(0.5, 0.0, 0.0))
    UsdPhysics.CollisionAPI.Apply(cone.GetPrim())
    if scaled:
        UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).AddScaleOp().Set(Gf.Vec3f(1.0, 2.0, 1.0))
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    world = box.vertices @ quat_matrix(box.pose[3:]).T + box.pose[:3]
    matrix = cone.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    apex = np.array(matrix.Transform(Gf.Vec3d(0.2, 0.0, 0.0)))
    rim = np.array(matrix.Transform(Gf.Vec3d(-0.2, 0.0, 0.2)))
    assert np.linalg.norm(world - apex, axis=1).min() < 1e-7
    assert np.linalg.norm(world - rim, axis=1).min() < 1e-7  # a rim point at angle 90 degrees


def test_tapered_capsule_and_cylinder_colliders_load(tmp_path):
    """Capsule_1 and Cylinder_1 (different top and bottom radii) failed with an AttributeError."""
    path = write_physics_scene(tmp_path / "tapered.usda", drop_height=2.0)
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/World/box/shape")
    frustum = UsdGeom.Cylinder_1.Define(stage, "/World/box/shape")
    frustum.CreateRadiusBottomAttr(0.15)
    frustum.CreateRadiusTopAttr(0.05)
    frustum.CreateHeightAttr(0.3)
    UsdPhysics.CollisionAPI.Apply(frustum.GetPrim())
    stage.GetRootLayer().Save()
    body = io.load_scene(path).body("box")
    area = [0.5 * io.ROUND_SEGMENTS * r * r * np.sin(2 * np.pi / io.ROUND_SEGMENTS) for r in (0.15, 0.05)]
    volume = 0.3 / 3 * (area[0] + area[1] + np.sqrt(area[0] * area[1]))  # a 32-gon frustum
    assert trimesh.Trimesh(body.vertices, body.faces).volume == pytest.approx(volume, rel=1e-6)  # float32 radii
    stage.RemovePrim("/World/box/shape")
    capsule = UsdGeom.Capsule_1.Define(stage, "/World/box/shape")
    capsule.CreateRadiusBottomAttr(0.2)
    capsule.CreateRadiusTopAttr(0.1)
    capsule.CreateHeightAttr(0.4)
    capsule.CreateAxisAttr("X")
    UsdPhysics.CollisionAPI.Apply(capsule.GetPrim())
    stage.GetRootLayer().Save()
    body = io.load_scene(path).body("box")
    posed = body.vertices + body.pose[:3] - [0.1, 0.0, 2.0]  # the body's origin
    np.testing.assert_allclose([posed[:, 0].min(), posed[:, 0].max()], [-0.4, 0.3], atol=1e-7)  # -0.2 - 0.2 and 0.2 + 0.1
    assert trimesh.Trimesh(body.vertices, body.faces).is_convex
    capsule.CreateRadiusTopAttr(0.0)
    capsule.CreateRadiusBottomAttr(0.0)
    _load_refused(stage, path, r"prim /World/box/shape: radii must be >= 0 \(one of them > 0\) and height >= 0, got radii 0, 0")


def test_mass_properties_authored_at_their_unspecified_values_are_not_specified(tmp_path):
    """UsdPhysics: mass, density and diagonalInertia mean something only if non-zero, and a
    centre of mass of -inf is none. Exported assets author these defaults; a mass of 0 was
    refused as "mass must be positive"."""
    path = write_physics_scene(tmp_path / "defaults.usda", mass=0.0)
    stage = Usd.Stage.Open(str(path))
    mass = UsdPhysics.MassAPI(stage.GetPrimAtPath("/World/box"))
    mass.CreateDensityAttr(0.0)
    mass.CreateCenterOfMassAttr(Gf.Vec3f(-np.inf, -np.inf, -np.inf))
    mass.CreateDiagonalInertiaAttr(Gf.Vec3f(0.0, 0.0, 0.0))
    mass.CreatePrincipalAxesAttr(Gf.Quatf(0.0, 0.0, 0.0, 0.0))
    _bind_physics_material(stage, "/World/box/shape", "/World/plain", density=0.0)
    stage.GetRootLayer().Save()
    box = io.load_scene(path).body("box")
    assert box.mass is None and box.density is None and box.center_of_mass is None and box.inertia is None
    assert io.load_scene(path).build_model().body_mass.numpy()[1] == pytest.approx(1000.0 * 0.5**3)  # the default density
    mass.GetDiagonalInertiaAttr().Set(Gf.Vec3f(1.0, 0.0, 1.0))  # partly zero: not a default
    _load_refused(stage, path, r"prim /World/box: diagonalInertia must be positive \(or 0 on every axis: not specified\)")
    # A rotation that is no unit quaternion also scaled the inertia: (0.1, 0.1, 0.1) loaded
    # as (0.05, 0.05, 0.1).
    mass.GetDiagonalInertiaAttr().Set(Gf.Vec3f(0.1, 0.1, 0.1))
    mass.GetPrincipalAxesAttr().Set(Gf.Quatf(0.5, 0.5, 0.0, 0.0))
    _load_refused(stage, path, r"prim /World/box: physics:principalAxes must be a unit quaternion \(or all 0: not specified\), got .* \(norm 0.707106")
    mass.GetPrincipalAxesAttr().Set(Gf.Quatf(0.5**0.5, 0.5**0.5, 0.0, 0.0))
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(io.load_scene(path).body("box").inertia, 0.1 * np.eye(3), rtol=1e-6, atol=1e-7)


def test_a_body_welded_to_the_world_by_a_fixed_joint_is_static(tmp_path):
    """An articulated robot's fixed base (a FixedJoint from the world) was refused as
    "FixedJoint is not supported"; a fixed joint between two rigid bodies still is."""
    path = write_physics_scene(tmp_path / "welded.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    weld = UsdPhysics.FixedJoint.Define(stage, "/World/root_joint")
    weld.CreateBody1Rel().SetTargets(["/World/box"])
    weld.CreateLocalPos0Attr(Gf.Vec3f(0.1, 0.0, 3.0))  # the box's place in the world
    UsdPhysics.RigidBodyAPI.Apply(_cube_collider(stage, "/World/link", 0.2, (0.6, 0.0, 3.0)))
    hinge = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
    hinge.CreateAxisAttr("Y")
    hinge.CreateBody0Rel().SetTargets(["/World/box"])
    hinge.CreateBody1Rel().SetTargets(["/World/link"])
    hinge.CreateLocalPos0Attr(Gf.Vec3f(0.3, 0.0, 0.0))
    hinge.CreateLocalPos1Attr(Gf.Vec3f(-0.2, 0.0, 0.0))
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    assert scene.body("box").static and not scene.body("link").static
    model, q = simulate(scene, 20)
    np.testing.assert_array_equal(q[-1, 1], q[0, 1])  # the base holds
    assert q[-1, 2, 2] < q[0, 2, 2] - 0.05  # the link swings down about the hinge
    weld.CreateBody0Rel().SetTargets(["/World/link"])
    _load_refused(stage, path, r"prim /World/root_joint: this fixed joint joins two rigid bodies \(merge them into one body\)")


def _two_hinged_links(path):
    """Two boxes, each hung from the world by a hinge prim named "hinge" under its own scope."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.Scene.Define(stage, "/World/physicsScene")
    for i, x in enumerate((0.0, 3.0)):
        link = UsdGeom.Xform.Define(stage, f"/World/r{i}/link")
        link.AddTranslateOp().Set(Gf.Vec3d(x, 0.0, 1.0))
        UsdPhysics.RigidBodyAPI.Apply(link.GetPrim())
        cube = UsdGeom.Cube.Define(stage, f"/World/r{i}/link/shape")
        cube.CreateSizeAttr(0.2)
        UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
        hinge = UsdPhysics.RevoluteJoint.Define(stage, f"/World/r{i}/hinge")
        hinge.CreateAxisAttr("Y")
        hinge.CreateBody1Rel().SetTargets([f"/World/r{i}/link"])
        hinge.CreateLocalPos0Attr(Gf.Vec3f(x, 0.0, 1.5))
        hinge.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.5))
    stage.GetRootLayer().Save()
    return stage


def test_prims_of_one_name_get_their_paths_names_and_save_back_whole(tmp_path):
    """Two joints named "hinge" (one per robot) kept that name: the model refused them, and
    save_scene wrote one over the other, leaving a link free."""
    path = tmp_path / "robots.usda"
    _two_hinged_links(path)
    scene = io.load_scene(path)
    assert [j.name for j in scene.joints] == ["World_r0_hinge", "World_r1_hinge"]
    assert [b.name for b in scene.bodies] == ["World_r0_link", "World_r1_link"]
    assert scene.build_model().articulation.coordinate_names == ["World_r0_hinge:0", "World_r1_hinge:0"]
    io.save_scene(scene, tmp_path / "saved.usda")
    assert [(j.name, j.child) for j in io.load_scene(tmp_path / "saved.usda").joints] == [(j.name, j.child) for j in scene.joints]
    # A path-derived name that another prim already has is refused, naming both.
    stage = Usd.Stage.Open(str(path))
    other = UsdGeom.Cube.Define(stage, "/World/World_r0_link")
    other.AddTranslateOp().Set(Gf.Vec3d(6.0, 0.0, 1.0))
    UsdPhysics.CollisionAPI.Apply(other.GetPrim())
    _load_refused(stage, path, "prims /World/r0/link, /World/World_r0_link would all be the body named 'World_r0_link'; rename one")


@pytest.mark.parametrize(
    ("name", "writer", "match"),
    [
        ("ball-1", "save", r"body 'ball-1': not a valid USD prim name"),
        ("2nd", "export", r"body '2nd': not a valid USD prim name"),
        ("physicsScene", "save", r"body 'physicsScene': the name of a prim the writer uses itself"),
        ("joints", "save", r"body 'joints': the name of a prim the writer uses itself"),
    ],
)
def test_writers_refuse_body_names_that_cannot_be_their_prims(tmp_path, name, writer, match):
    """These raised a raw pxr error, or wrote a body over the PhysicsScene (the file then
    failed to load) or a target marker under a body."""
    scene = io.load_scene(write_physics_scene(tmp_path / "a.usda"))
    scene.body("box").name = name
    with pytest.raises(ValueError, match=match):
        if writer == "save":
            io.save_scene(scene, tmp_path / "b.usda")
        else:
            io.export_trajectory(scene, np.array([[b.pose for b in scene.bodies]]), tmp_path / "b.usda")
    assert not (tmp_path / "b.usda").exists()


@pytest.mark.parametrize(
    ("prim", "attribute", "kind", "value"),
    [
        ("/World/box", "physics:mass", Sdf.ValueTypeNames.Float, 7.0),
        ("/World/box", "physics:velocity", Sdf.ValueTypeNames.Vector3f, Gf.Vec3f(1.0, 0.0, 0.0)),
        ("/World/box/shape", "size", Sdf.ValueTypeNames.Double, 0.5),
        ("/World/physicsScene", "physics:gravityMagnitude", Sdf.ValueTypeNames.Float, 5.0),
    ],
)
def test_a_value_authored_only_as_time_samples_is_refused(tmp_path, prim, attribute, kind, value):
    """The initial state is read at the default time: a sampled mass of 7 kg gave the
    default density's 125 kg, a sampled velocity none, a sampled Cube size the fallback 2 m."""
    path = write_physics_scene(tmp_path / "sampled.usda")
    stage = Usd.Stage.Open(str(path))
    if attribute == "physics:mass":  # read only under MassAPI (without it: refused since stop 58)
        UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath(prim))
    attr = stage.GetPrimAtPath(prim).GetAttribute(attribute) or stage.GetPrimAtPath(prim).CreateAttribute(attribute, kind)
    attr.Clear()
    attr.Set(value, 0.0)
    _load_refused(stage, path, f"prim {prim}: {prim}.{attribute} is animated \\(time samples or a spline\\) but has no default value")


def test_animated_attributes_a_load_does_not_read_are_left_alone(tmp_path):
    path = write_physics_scene(tmp_path / "visible.usda")
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/box/shape")).CreateVisibilityAttr().Set(UsdGeom.Tokens.invisible, 3.0)
    stage.GetRootLayer().Save()
    assert io.load_scene(path).body("box").faces.shape == (12, 3)


def test_a_disabled_rigid_body_loads_static_with_its_collider_and_reset_stacks_keep_world_velocities(tmp_path):
    """rigidBodyEnabled = false was refused ("rigid body has no collider": UsdPhysics gives
    its colliders no body); a body that resets the transform stack had its velocity turned
    by the parent whose transform it ignores."""
    path = write_physics_scene(tmp_path / "disabled.usda")
    stage = Usd.Stage.Open(str(path))
    parent = UsdGeom.Xform.Define(stage, "/World/turned")
    parent.AddTranslateOp().Set(Gf.Vec3d(5.0, 0.0, 0.0))
    parent.AddRotateZOp().Set(90.0)
    box = UsdGeom.Xform.Define(stage, "/World/turned/still")
    box.SetResetXformStack(True)
    box.AddTranslateOp().Set(Gf.Vec3d(2.0, 0.0, 1.0))
    body = UsdPhysics.RigidBodyAPI.Apply(box.GetPrim())
    body.CreateRigidBodyEnabledAttr(False)
    body.CreateVelocityAttr(Gf.Vec3f(1.0, 0.0, 0.0))
    cube = UsdGeom.Cube.Define(stage, "/World/turned/still/shape")
    cube.CreateSizeAttr(0.4)
    UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
    UsdPhysics.RigidBodyAPI(stage.GetPrimAtPath("/World/box")).CreateVelocityAttr(Gf.Vec3f(1.0, 0.0, 0.0))
    moving = UsdGeom.Xform.Define(stage, "/World/turned/moving")
    moving.SetResetXformStack(True)
    moving.AddTranslateOp().Set(Gf.Vec3d(-2.0, 0.0, 1.0))
    UsdPhysics.RigidBodyAPI.Apply(moving.GetPrim()).CreateVelocityAttr(Gf.Vec3f(1.0, 0.0, 0.0))
    cube = UsdGeom.Cube.Define(stage, "/World/turned/moving/shape")
    cube.CreateSizeAttr(0.4)
    UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
    stage.GetRootLayer().Save()
    # A static body's velocity never moved it, and a save dropped it (a probe, stop 63).
    with pytest.warns(UserWarning, match=r"prim /World/turned/still: a static body here .* does not move: its authored physics:velocity \[1.0, 0.0, 0.0\] m/s"):
        scene = io.load_scene(path)
    still = scene.body("still")
    assert still.static and len(still.faces) == 12
    np.testing.assert_allclose(still.pose[:3], [2.0, 0.0, 1.0], atol=1e-12)
    world = quat_matrix(still.pose[3:]) @ still.vertices.T
    np.testing.assert_allclose(np.ptp(world, axis=1), [0.4, 0.4, 0.4], atol=1e-6)
    np.testing.assert_array_equal(still.linear_velocity, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(scene.body("moving").linear_velocity, [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(scene.body("box").linear_velocity, [1.0, 0.0, 0.0])
    # Python-built, the same is an error: it would be lost on a save.
    still.linear_velocity = np.array([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"static body 'still' has a velocity, which only a dynamic body takes"):
        io.save_scene(scene, tmp_path / "saved.usda")



def _hinge_stage(path, *, joint="RevoluteJoint", lower=None, upper=None, target=None, locked=("transX", "transY", "transZ", "rotX", "rotZ")):
    """A box hanging from a world hinge about y (for ``joint="D6"``, a D6 with the ``locked``
    axes locked)."""
    stage = _hanging_box_stage(path)
    if joint == "D6":
        hinge = UsdPhysics.Joint.Define(stage, "/World/hinge")
        for axis in locked:
            lock = UsdPhysics.LimitAPI.Apply(hinge.GetPrim(), axis)
            lock.CreateLowAttr(1.0)
            lock.CreateHighAttr(-1.0)
        if lower is not None:
            limit = UsdPhysics.LimitAPI.Apply(hinge.GetPrim(), "rotY")
            limit.CreateLowAttr(lower)
            limit.CreateHighAttr(upper)
        token = "rotY"
    else:
        hinge = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
        hinge.CreateAxisAttr("Y")
        if lower is not None:
            hinge.CreateLowerLimitAttr(lower)
            hinge.CreateUpperLimitAttr(upper)
        token = "angular"
    if target is not None:
        drive = UsdPhysics.DriveAPI.Apply(hinge.GetPrim(), token)
        drive.CreateStiffnessAttr(1.0)
        drive.CreateTargetPositionAttr(target)
    _hang_and_save(stage, hinge)
    return stage


def test_a_joint_starting_outside_its_limits_is_named_by_its_prim(tmp_path):
    """A probe at stop 61: the message named the coordinate ('hinge:0') but not the prim."""
    path = tmp_path / "outside.usda"
    _hinge_stage(path, lower=10.0, upper=20.0)
    with pytest.raises(ValueError, match=r"outside.usda: prim /World/hinge: joint coordinate 'hinge:0': initial value 0 is not strictly inside its limits \[0.174533, 0.349066\]"):
        io.load_scene(path).build_model()


@pytest.mark.parametrize("joint", ["RevoluteJoint", "D6"])
def test_joint_limits_open_on_one_side_and_a_zero_drive_target_load(tmp_path, joint):
    """UsdPhysics leaves a limit side open with -inf: such a limit was dropped whole (the
    hinge swung to 74 degrees past a 10 degree stop), and a targetPosition of 0 was read as
    none (the drive held the joint where it started)."""
    path = tmp_path / "hinge.usda"
    _hinge_stage(path, joint=joint, lower=-np.inf, upper=10.0, target=0.0)
    scene = io.load_scene(path)
    np.testing.assert_allclose(scene.joints[0].limits, [(-np.inf, np.radians(10.0))])
    np.testing.assert_array_equal(scene.joints[0].targets, [0.0])
    io.save_scene(scene, tmp_path / "saved.usda")
    again = io.load_scene(tmp_path / "saved.usda").joints[0]
    np.testing.assert_allclose(again.limits, scene.joints[0].limits, rtol=1e-6)
    np.testing.assert_array_equal(again.targets, [0.0])


@pytest.mark.parametrize(
    ("author", "match"),
    [
        (lambda st: st.GetPrimAtPath("/World/hinge").GetAttribute("physics:lowerLimit").Set(float("nan")), r"prim /World/hinge: limit must be numbers \(-inf or inf for an open side\), got \(nan, 10.0\)"),
        (lambda st: UsdPhysics.DriveAPI(st.GetPrimAtPath("/World/hinge"), "angular").GetTargetPositionAttr().Set(float("nan")), "drive:angular:physics:targetPosition must be finite, got nan"),
        (lambda st: st.GetPrimAtPath("/World/hinge").GetRelationship("physics:body0").SetTargets(["/World/no_such_body"]), "physics:body0 targets /World/no_such_body, which does not exist"),
        (lambda st: st.GetPrimAtPath("/World/hinge").GetRelationship("physics:body1").AddTarget("/World/box/shape"), "physics:body1 targets 2 prims"),
        # Read as the identity (a zero quaternion) or normalised, with no word.
        (lambda st: st.GetPrimAtPath("/World/hinge").CreateAttribute("physics:localRot0", Sdf.ValueTypeNames.Quatf).Set(Gf.Quatf(0.0, 0.0, 0.0, 0.0)), r"prim /World/hinge: physics:localRot0 must be a unit quaternion, got \(0, 0, 0, 0\) \(norm 0\)"),
        (lambda st: st.GetPrimAtPath("/World/hinge").CreateAttribute("physics:localRot1", Sdf.ValueTypeNames.Quatf).Set(Gf.Quatf(2.0, 0.0, 0.0, 0.0)), r"prim /World/hinge: physics:localRot1 must be a unit quaternion"),
        # UsdPhysics allows X, Y and Z; the parser read any other token ("W", a lowercase "y") as X.
        (lambda st: st.GetPrimAtPath("/World/hinge").GetAttribute("physics:axis").Set("W"), r"prim /World/hinge: physics:axis must be one of the tokens X, Y, Z \(upper case\), got 'W'"),
        (lambda st: st.GetPrimAtPath("/World/hinge").GetAttribute("physics:axis").Set("y"), r"prim /World/hinge: physics:axis must be one of the tokens X, Y, Z \(upper case\), got 'y'"),
        # A body1 that is no body read as "physics:body1 is not set".
        (lambda st: [UsdGeom.Xform.Define(st, "/World/plain"), st.GetPrimAtPath("/World/hinge").GetRelationship("physics:body1").SetTargets(["/World/plain"])], r"prim /World/hinge: body1 /World/plain is not a rigid body with a collider"),
    ],
)
def test_joint_values_the_parser_drops_are_refused(tmp_path, author, match):
    """A NaN limit or target, and a body0 naming a prim that does not exist, loaded as no
    limit, the initial value, and the world."""
    path = tmp_path / "hinge.usda"
    stage = _hinge_stage(path, lower=-30.0, upper=10.0, target=5.0)
    author(stage)
    _load_refused(stage, path, match)


def test_d6_values_that_were_ignored_are_refused(tmp_path):
    # A drive on an axis its limit locks loaded with no gain, and nothing moved (a probe, stop 61).
    path = tmp_path / "locked_drive.usda"
    stage = _hinge_stage(path, joint="D6")
    drive = UsdPhysics.DriveAPI.Apply(stage.GetPrimAtPath("/World/hinge"), "rotZ")
    drive.CreateStiffnessAttr(10.0)
    drive.CreateTargetPositionAttr(30.0)
    _load_refused(stage, path, r"prim /World/hinge: drive:rotZ drives an axis its limit locks \(low > high\), which it cannot move; remove the drive or free the axis")
    path = tmp_path / "d6.usda"
    stage = _hinge_stage(path, joint="D6")
    hinge = stage.GetPrimAtPath("/World/hinge")
    distance = UsdPhysics.LimitAPI.Apply(hinge, "distance")
    distance.CreateLowAttr(0.0)
    distance.CreateHighAttr(0.05)
    _load_refused(stage, path, r"PhysicsLimitAPI:distance is not read on a D6Joint \(it reads PhysicsLimitAPI:transX, .*\); rename or remove it")
    # Free translations and rotations make a base joint; three free rotations are one group,
    # which takes no drives: they were dropped.
    path = tmp_path / "base.usda"
    stage = _hinge_stage(path, joint="D6", target=10.0, locked=())
    stage.GetPrimAtPath("/World/hinge").GetAttribute("physics:localPos0").Set(Gf.Vec3f(0.0, 0.0, 1.0))
    stage.GetPrimAtPath("/World/hinge").GetAttribute("physics:localPos1").Set(Gf.Vec3f(0.0, 0.0, 0.0))
    _load_refused(stage, path, r"a D6 joint with free translations and three free rotations takes no drives or limits on its rotations \(RotY\)")
    # Locked translations with a free rotation turn the body about its centre of mass here:
    # an anchor elsewhere (a pendulum on a sliding pivot) loaded and turned about the centre.
    path = tmp_path / "pivot.usda"
    stage = _hinge_stage(path, joint="D6", locked=("transY", "transZ", "rotX", "rotZ"))
    io.load_scene(path)
    with pytest.raises(ValueError, match="prim /World/hinge: a D6 joint from the world with locked translations and free rotations .* its anchor is 0.5 m from it"):
        io.load_scene(path).build_model()
    # With free translations too, UsdPhysics' coordinates (and their drives and limits) are
    # the anchor's, a base's the centre's: drives to 0 held the centre where the anchor belongs.
    path = tmp_path / "sliding_pivot.usda"
    stage = _hinge_stage(path, joint="D6", locked=("rotX", "rotZ"))
    with pytest.raises(ValueError, match=r"prim /World/hinge: a D6 joint from the world with free translations \(the anchor's\) and free rotations .* its anchor is 0.5 m from it"):
        io.load_scene(path).build_model()


def _slider_stage(path, *, limits=(0.5, 1.5), target=1.2):
    """_hanging_box_stage's box (z = 1 m) on a D6 joint from the world whose frames sit at
    the world's origin and the box's: transZ free (limits, drive target in its UsdPhysics
    coordinate, the frames' offset: 1 m at the start), every other axis locked."""
    stage = _hanging_box_stage(path)
    stage.GetPrimAtPath("/World/physicsScene").CreateAttribute("physics:gravityMagnitude", Sdf.ValueTypeNames.Float).Set(0.0)
    joint = UsdPhysics.Joint.Define(stage, "/World/slider")
    joint.CreateBody1Rel().SetTargets(["/World/box"])
    joint.CreateLocalPos0Attr(Gf.Vec3f(0.0, 0.0, 0.0))
    joint.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
    for axis in ("transX", "transY", "rotX", "rotY", "rotZ"):
        locked = UsdPhysics.LimitAPI.Apply(joint.GetPrim(), axis)
        locked.CreateLowAttr(1.0)
        locked.CreateHighAttr(-1.0)
    limit = UsdPhysics.LimitAPI.Apply(joint.GetPrim(), "transZ")
    limit.CreateLowAttr(limits[0])
    limit.CreateHighAttr(limits[1])
    drive = UsdPhysics.DriveAPI.Apply(joint.GetPrim(), "transZ")
    drive.CreateStiffnessAttr(100.0)
    drive.CreateDampingAttr(20.0)
    drive.CreateTargetPositionAttr(target)
    stage.GetRootLayer().Save()
    return stage


@pytest.mark.filterwarnings("ignore:contact_stiffness .* holds these bodies")
def test_a_d6_base_joint_reads_its_limits_and_targets_from_where_its_frames_start(tmp_path):
    # UsdPhysics' transZ starts at the frames' 1 m offset, a base coordinate at 0: limits
    # (0.5, 1.5) refused the stage, and with (-1, 2) the drive to 1.2 settled the box at 2.2.
    path = tmp_path / "slider.usda"
    stage = _slider_stage(path)
    model = io.load_scene(path).build_model()
    art = model.articulation
    np.testing.assert_allclose([art.lower[0], art.upper[0], art.default_targets[0]], [-0.5, 0.5, 0.2], atol=1e-6)
    solver = wc.ImplicitSolver(model)
    state = model.state(requires_grad=False)
    for _ in range(150):
        nxt = model.state(requires_grad=False)
        solver.step(state, nxt, model.control(requires_grad=False), 0.02)
        state = nxt
    assert state.body_q.numpy()[0, 2] == pytest.approx(1.2, abs=0.01)  # still ringing down (2.2 before)
    # A locked axis the start violates held the body where it was, not where the joint puts it.
    stage.GetPrimAtPath("/World/slider").GetAttribute("physics:localPos0").Set(Gf.Vec3f(0.0, 0.3, 0.0))
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"prim /World/slider: its locked transY axis starts -0.3 m apart"):
        io.load_scene(path).build_model()


def test_a_cone_limited_in_one_direction_is_refused(tmp_path):
    # UsdPhysics: a negative cone angle leaves that direction free; the parser reports no limit,
    # and the other direction's 30 degrees were dropped.
    with pytest.raises(ValueError, match=r"a cone limited in one direction only \(coneAngle0Limit -1, coneAngle1Limit 30 degrees\)"):
        io.load_scene(write_hinged_box(tmp_path / "cone.usda", cone=-1.0, cone1=30.0))


def test_a_limit_that_locks_a_joint_or_a_zero_cone_is_refused_with_a_way_out(tmp_path):
    """Equal limits, as authors lock an axis, were "limits must be ... lower < upper", naming
    no way out, and a zero cone "cone_limit must be in (0, pi) rad", the builder's argument (a
    probe, stop 64)."""
    for joint in ("RevoluteJoint", "D6"):
        path = tmp_path / f"locked_{joint}.usda"
        _hinge_stage(path, joint=joint, lower=5.0, upper=5.0)
        with pytest.raises(ValueError, match=r"prim /World/hinge: (limit|the Rot. limit) has lower == upper \(5\), which locks the coordinate: .*lock a D6 axis with low > high, or join the bodies with a fixed joint"):
            io.load_scene(path)
    with pytest.raises(ValueError, match=r"physics:coneAngle0Limit / coneAngle1Limit of 0 degrees leave no swing; a cone limit must be in \(0, 180\) degrees"):
        io.load_scene(write_hinged_box(tmp_path / "cone.usda", cone=0.0, cone1=0.0))


def test_a_joint_far_from_the_origin_loads_despite_float32_anchors(tmp_path):
    """localPos is float32: a consistent joint at x = 13.7 m was refused, its anchors 1.9e-7 m
    apart against a tolerance of 1e-6 of the 0.1 m box."""
    path = tmp_path / "far.usda"
    stage = _hinge_stage(path)
    stage.GetPrimAtPath("/World/box").GetAttribute("xformOp:translate").Set(Gf.Vec3d(13.7, 0.0, 1.0))
    stage.GetPrimAtPath("/World/hinge").GetAttribute("physics:localPos0").Set(Gf.Vec3f(13.7, 0.0, 1.5))
    stage.GetRootLayer().Save()
    assert io.load_scene(path).build_model().articulation.coordinate_names == ["hinge:0"]


def test_overwrite_must_be_a_flag(tmp_path):
    """overwrite="False" was truth-tested, and replaced the file."""
    from warpcontact.scenes import build_scene

    path = tmp_path / "kept.usda"
    path.write_text("keep")
    with pytest.raises(ValueError, match="overwrite: expected True/False"):
        io.save_scene(build_scene("push"), path, overwrite="False")
    assert path.read_text() == "keep"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda s: setattr(s.bodies[1], "linear_velocity", np.array([1e39, 0.0, 0.0])), r"prim /World/cue: physics:velocity must be finite"),
        (lambda s: s.bodies[1].__dict__.update(target_position=np.zeros(3), target_tolerance=-1.0), r"prim /World/cue: warpcontact:target:tolerance must be finite, >= 0"),
        (lambda s: setattr(s.bodies[1], "inertia", -np.eye(3)), r"prim /World/cue: diagonalInertia must be positive \(or 0 on every axis: not specified\), got \[-1. -1. -1.\]"),
    ],
)
def test_save_scene_never_writes_a_file_load_scene_refuses(tmp_path, change, message):
    """Found by a probe: each of these was written, with overwrite over a good file, and the
    file was then refused at load (a float32 mass or velocity overflowing to inf)."""
    from warpcontact.scenes import build_scene

    scene = build_scene("billiards_512")
    path = tmp_path / "scene.usda"
    io.save_scene(scene, path)
    good = path.read_bytes()
    change(scene)
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: not written, as load_scene would refuse it \(values the schemas type as float are written as float32\): {message}"):
        io.save_scene(scene, path, overwrite=True)
    assert path.read_bytes() == good and [p.name for p in tmp_path.iterdir()] == ["scene.usda"]


@pytest.mark.parametrize(
    ("field", "value", "label", "read_back"),
    [
        ("mass", 1e-46, "physics:mass", "0"),  # read back as "not given": the default density's mass, silently (a probe, stop 65)
        ("mass", 1e40, "physics:mass", "inf"),
        ("density", 1e-40, "physics:density", r"9.99995e-41"),  # a subnormal, its digits lost
        ("inertia", np.diag([1e-45, 1.0, 1.0]), "physics:diagonalInertia", r"1.4013e-45"),
    ],
)
def test_save_scene_refuses_mass_properties_float32_cannot_hold(tmp_path, field, value, label, read_back):
    from warpcontact.scenes import build_scene

    scene = build_scene("billiards_512")
    cue = scene.body("cue")
    setattr(cue, field, value)
    if field == "density":
        cue.mass = None
    path = tmp_path / "scene.usda"
    shown = f"{float(np.min(np.diag(value)) if field == 'inertia' else value):g}"
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: body 'cue': {label} {re.escape(shown)} is outside the float32 range \[1.17549e-38, 3.40282e\+38\] in which UsdPhysics stores it \(written, it would read back as {read_back}\)"):
        io.save_scene(scene, path)
    assert not path.exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda s: setattr(s.settings, "time_step", -1.0), r"scene settings: warpcontact:timeStep must be a positive finite number of seconds, got -1.0"),
        # Found by a probe: 1e200 s crashed the step (dt^2 overflowed), 1e-320 s lost the frames.
        (lambda s: setattr(s.settings, "time_step", 1e200), r"warpcontact:timeStep must lie in \[1e-150, 1e\+150\] s \(its square and inverse must be representable\), got 1e\+200"),
        (lambda s: setattr(s.settings, "time_step", 1e-320), r"warpcontact:timeStep must lie in \[1e-150, 1e\+150\] s"),
        (lambda s: setattr(s.settings, "contact_mode", "xyz"), r"scene settings: warpcontact:contactMode must be one of"),
        (lambda s: setattr(s.settings, "friction", float("nan")), r"scene settings: warpcontact:friction must be >= 0 and finite, got nan"),
        (lambda s: s.bodies[1].vertices.__setitem__((0, 0), np.nan), r"body 'cue': its mesh vertices are not all finite"),
        (lambda s: setattr(s, "bodies", [b for b in s.bodies if b.static]), r"the scene has no dynamic bodies, which load_scene requires"),
        (lambda s: setattr(s.bodies[0], "target_position", np.zeros(3)), r"static body 'ground' has a target, which only a dynamic body takes"),
        (lambda s: setattr(s.settings, "frames", True), r"warpcontact:frames: expected a number, got True"),
        (lambda s: setattr(s.settings, "frames", 2.5), r"warpcontact:frames: expected a whole number, got 2.5"),
        # Found by a probe: simulate held every frame of 1e11 until it was killed.
        (lambda s: setattr(s.settings, "frames", 10**9), r"scene settings: warpcontact:frames must be a whole number from 1 to 1,000,000, got 1000000000"),
        (lambda s: setattr(s.settings, "frames", 0), r"scene settings: warpcontact:frames must be a whole number from 1 to 1,000,000, got 0"),
        (lambda s: setattr(s.task, "horizon", 2**62), r"warpcontact:task:horizon: expected a whole number a 32-bit int holds, got 4611686018427387904"),
    ],
)
def test_save_scene_refuses_what_load_scene_would(tmp_path, change, message):
    """Such scenes were written without a word, and loading them failed later."""
    from warpcontact.scenes import build_scene

    scene = build_scene("billiards_512")
    scene.bodies[1].vertices = np.array(scene.bodies[1].vertices, dtype=np.float64)
    change(scene)
    path = tmp_path / "bad.usda"
    with pytest.raises(ValueError, match=message):
        io.save_scene(scene, path)
    assert not path.exists()


def test_a_universal_joint_with_axes_not_of_unit_length_saves_them_as_the_model_reads_them(tmp_path):
    """The model normalises a joint's axes; the saved frames were turned by the first axis as
    given, and (0, 0, 2), (0, 3, 0) reloaded with its first axis 37 degrees off, silently."""
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.5))
    vertices, faces = np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.int64)
    upper = io.BodySpec("upper", "/World/upper", vertices, faces, np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]), density=500.0)
    lower = io.BodySpec("lower", "/World/lower", vertices, faces, np.array([0.0, 0.0, 0.48, 0.0, 0.0, 0.0, 1.0]), density=500.0)
    joints = [
        io.JointSpec("top", "/World/joints/top", "ball", None, "upper", np.array([0.0, 0.0, 1.26, 0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.26, 0.0, 0.0, 0.0, 1.0])),
        io.JointSpec(
            "cardan", "/World/joints/cardan", "universal", "upper", "lower", np.array([0.0, 0.0, -0.26, 0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.26, 0.0, 0.0, 0.0, 1.0]),
            axes=np.array([[0.0, 0.0, 2.0], [0.0, 3.0, 0.0]]), kp=np.array([2.0, 3.0]), kd=np.array([0.2, 0.3]), targets=np.array([0.2, -0.1]),
        ),
    ]
    scene = io.Scene(bodies=[upper, lower], joints=joints)
    io.save_scene(scene, tmp_path / "cardan.usda")
    models = [scene.build_model(), io.load_scene(tmp_path / "cardan.usda").build_model()]
    poses = []
    for model in models:
        state, control = model.state(requires_grad=False), model.control(requires_grad=False)
        solver = wc.ImplicitSolver(model)
        for _ in range(10):
            nxt = model.state(requires_grad=False)
            solver.step(state, nxt, control, 0.01)
            state = nxt
        poses.append(state.body_q.numpy())
    np.testing.assert_allclose(poses[1], poses[0], atol=1e-6)  # the save rounds to float32


def test_saving_keeps_joint_frames_whose_axis_is_x(tmp_path):
    """A single axis along X was turned -90 degrees about X at every save, so a file never
    settled and a ball joint's rotations (its targets' frame) changed: a child frame turned
    30 degrees about z read (0, 0.259, 0, 0.966) after one save, (0, 0, -0.259, 0.966) after
    two."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    vertices, faces = np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.int64)
    a = io.BodySpec("a", "/World/a", vertices, faces, np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]), density=500.0)
    b = io.BodySpec("b", "/World/b", vertices, faces, np.array([0.0, 0.0, 1.5, 0.0, 0.0, 0.0, 1.0]), density=500.0)
    turned = np.array([0.0, 0.0, np.sin(np.pi / 12), np.cos(np.pi / 12)])
    joint = io.JointSpec(
        "ball", "/World/joints/ball", "ball", "a", "b", np.array([0.0, 0.0, 0.25, 0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, -0.25, *turned]),
        axes=np.array([[1.0, 0.0, 0.0]]), cone_limit=1.0, kp=np.array([5.0]), kd=np.array([0.5]),
    )
    scene = io.Scene(bodies=[a, b], joints=[joint])
    first, second, third = tmp_path / "first.usda", tmp_path / "second.usda", tmp_path / "third.usda"
    io.save_scene(scene, first)
    io.save_scene(io.load_scene(first), second)
    io.save_scene(io.load_scene(second), third)
    assert second.read_text() == third.read_text()  # the first save rounds to float32 once
    for loaded in (io.load_scene(first), io.load_scene(second), io.load_scene(third)):
        np.testing.assert_allclose(loaded.build_model().articulation.initial_ball_rotations, [turned], atol=1e-7)


def test_joints_load_in_the_order_they_were_authored(tmp_path):
    """Joints were read grouped by type: a prismatic joint authored before a revolute one came
    back after it, permuting the joint coordinates (and anything indexed by them)."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    vertices, faces = np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.int64)
    slider = io.BodySpec("slider", "/World/slider", vertices, faces, np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]), density=500.0)
    hinge = io.BodySpec("hinge", "/World/hinge", vertices, faces, np.array([2.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]), density=500.0)
    world = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    joints = [
        io.JointSpec("slide", "/World/joints/slide", "prismatic", None, "slider", world + [0, 0, 1.0, 0, 0, 0, 0], world, axes=np.array([[0.0, 0.0, 1.0]])),
        io.JointSpec("swing", "/World/joints/swing", "revolute", None, "hinge", world + [2.0, 0, 1.5, 0, 0, 0, 0], world + [0, 0, 0.5, 0, 0, 0, 0], axes=np.array([[0.0, 1.0, 0.0]])),
    ]
    path = tmp_path / "order.usda"
    io.save_scene(io.Scene(bodies=[slider, hinge], joints=joints), path)
    loaded = io.load_scene(path)
    assert [j.name for j in loaded.joints] == ["slide", "swing"]
    assert loaded.build_model().articulation.coordinate_names == ["slide:0", "swing:0"]


def test_a_static_collider_keeps_its_double_precision_pose(tmp_path):
    """A collider without a rigid body took its pose from UsdPhysics' float32 localPos /
    localRot: a ground at x = 1000.123456789 came back 1.7e-5 m off (a dynamic body, 6e-17)."""
    box = trimesh.creation.box(extents=(4.0, 4.0, 0.1))
    vertices, faces = np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.int64)
    turn = np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])
    ground = io.BodySpec("ground", "/World/ground", vertices, faces, np.array([1000.123456789, -0.05, 0.1, *turn]), static=True)
    crate = io.BodySpec("crate", "/World/crate", vertices * 0.05, faces, np.array([1000.123456789, 0.05, 3.1, *turn]), density=500.0)
    path = tmp_path / "far.usda"
    io.save_scene(io.Scene(bodies=[ground, crate]), path)
    for saved, loaded in zip((ground, crate), io.load_scene(path).bodies):
        np.testing.assert_allclose(loaded.pose, saved.pose, rtol=0, atol=1e-12)


@pytest.mark.parametrize(("shape", "blocked", "scale"), [("Cube", "size", None), ("Sphere", "radius", None), ("Capsule_1", "radiusTop", "(1, 1, 2)")])
def test_a_blocked_primitive_dimension_is_named(tmp_path, shape, blocked, scale):
    """A value block (`double size = None`) reads as None: float(None) was a TypeError traceback."""
    path = tmp_path / "blocked.usda"
    scaled = f"double3 xformOp:scale = {scale}\n        uniform token[] xformOpOrder = [\"xformOp:scale\"]" if scale else ""
    path.write_text(f"""#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Z"
)
def Xform "body" ( prepend apiSchemas = ["PhysicsRigidBodyAPI"] ) {{
    def {shape} "shape" ( prepend apiSchemas = ["PhysicsCollisionAPI"] ) {{
        double {blocked} = None
        {scaled}
    }}
}}
""")
    with pytest.raises(ValueError, match=rf"blocked.usda: prim /body/shape: {blocked} is blocked \(authored as None\)"):
        io.load_scene(path)


def test_a_sheared_plane_loads_as_usd_draws_it(tmp_path):
    """A Plane turned 45 degrees inside a parent scaled (1, 1, 3) loaded at 45 degrees (its
    frame's nearest rotation); USD draws it at 71.6: a point 5 m along it lay 5 m off."""
    path = tmp_path / "sheared_plane.usda"
    path.write_text("""#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Z"
)
def Xform "parent" {
    double3 xformOp:scale = (1, 1, 3)
    uniform token[] xformOpOrder = ["xformOp:scale"]
    def Plane "ground" ( prepend apiSchemas = ["PhysicsCollisionAPI"] ) {
        uniform token axis = "Z"
        float xformOp:rotateY = 45
        uniform token[] xformOpOrder = ["xformOp:rotateY"]
    }
}
def Xform "body" ( prepend apiSchemas = ["PhysicsRigidBodyAPI"] ) {
    double3 xformOp:translate = (0, 0, 5)
    uniform token[] xformOpOrder = ["xformOp:translate"]
    def Cube "shape" ( prepend apiSchemas = ["PhysicsCollisionAPI"] ) {
        double size = 1
    }
}
""")
    ground = io.load_scene(path).body("ground")
    corners = ground.vertices @ quat_matrix(ground.pose[3:]).T + ground.pose[:3]
    stage = Usd.Stage.Open(str(path))
    matrix = np.array(UsdGeom.Xformable(stage.GetPrimAtPath("/parent/ground")).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    # USD draws the plane through its origin (row 3) along its x and y axes (rows 0 and 1).
    normal = np.cross(matrix[0, :3], matrix[1, :3])
    np.testing.assert_allclose((corners - matrix[3, :3]) @ (normal / np.linalg.norm(normal)), 0.0, atol=1e-9 * np.abs(corners).max())


def test_a_collider_keeps_its_double_precision_place_on_its_body(tmp_path):
    """A rigid body's collider was placed by UsdPhysics' float32 localPos: a cube at x =
    1000.123456789 on its body at the origin moved 1.7e-5 m and overlapped a ground authored
    1e-5 m from it (build_model refused the scene)."""
    x = 1000.123456789
    path = tmp_path / "offset.usda"
    path.write_text(f"""#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Z"
)
def PhysicsScene "physicsScene" {{}}
def Xform "body" ( prepend apiSchemas = ["PhysicsRigidBodyAPI"] ) {{
    def Cube "shape" ( prepend apiSchemas = ["PhysicsCollisionAPI"] ) {{
        double size = 1
        double3 xformOp:translate = ({x!r}, 0, 0.5)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
}}
def Cube "ground" ( prepend apiSchemas = ["PhysicsCollisionAPI"] ) {{
    double size = 1
    double3 xformOp:translate = ({x + 1 + 1e-5!r}, 0, 0.5)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}}
""")
    scene = io.load_scene(path)
    body = scene.body("body")
    np.testing.assert_allclose(body.vertices[:, 0].min() + body.pose[0], x - 0.5, rtol=0, atol=1e-12)
    scene.build_model()


def test_save_scene_takes_numpy_settings_and_broadcast_joint_values(tmp_path):
    """np.float32 / np.int64 settings raised a raw pxr type-mismatch error, and a universal
    joint's single limit pair or gain (which the builder broadcasts) an IndexError."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    vertices, faces = np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.int64)
    arm = io.BodySpec("arm", "/World/arm", vertices, faces, np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]), density=500.0)
    world = np.array([0.0, 0.0, 1.2, 0.0, 0.0, 0.0, 1.0])
    joint = io.JointSpec(
        "cardan", "/World/joints/cardan", "universal", None, "arm", world, np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0]),
        axes=np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), limits=(-0.3, 0.3), kp=np.array([2.0]), kd=np.array([0.1]),
    )  # a flat limit pair, as the builder also takes it
    scene = io.Scene(bodies=[arm], joints=[joint], settings=io.SimulationSettings(time_step=np.float32(0.04), frames=np.int64(50)))
    path = tmp_path / "numpy.usda"
    io.save_scene(scene, path)
    loaded = io.load_scene(path)
    assert loaded.settings.frames == 50 and loaded.settings.time_step == pytest.approx(0.04, rel=1e-7)
    art = loaded.build_model().articulation
    np.testing.assert_allclose(art.lower, [-0.3, -0.3], rtol=1e-6)
    np.testing.assert_allclose(art.kp, [2.0, 2.0], rtol=1e-6)
    # A revolute joint's flat limit pair too (a TypeError).
    hinge = io.JointSpec("hinge", "/World/joints/hinge", "revolute", None, "arm", world, np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0]), axes=np.array([[1.0, 0.0, 0.0]]), limits=(-0.3, 0.3))
    io.save_scene(io.Scene(bodies=[arm], joints=[hinge]), tmp_path / "hinge.usda")
    np.testing.assert_allclose(io.load_scene(tmp_path / "hinge.usda").build_model().articulation.lower, [-0.3], rtol=1e-6)


@pytest.mark.parametrize(
    ("joint", "attribute"),
    [
        ("RevoluteJoint", "drive:angular:physics:stiffness"),
        ("RevoluteJoint", "drive:angular:physics:targetPosition"),
        ("D6", "limit:transX:physics:low"),
    ],
)
def test_a_joint_drive_or_limit_animated_is_refused(tmp_path, joint, attribute):
    """Multiple-apply schema attributes were not among those a load checks: a drive gain in
    time samples alone loaded as 0, a locked D6 axis's limit as free, and a drive target
    animated over the frames was held at its default; all without a word."""
    path = tmp_path / "hinge.usda"
    stage = _hinge_stage(path, joint=joint, target=5.0)
    attr = stage.GetPrimAtPath("/World/hinge").GetAttribute(attribute)
    value = attr.Get()
    attr.Clear()
    attr.Set(value, 0.0)
    _load_refused(stage, path, f"prim /World/hinge: /World/hinge.{attribute} is animated \\(time samples or a spline\\) but has no default value")
    attr.Set(value)
    attr.Set(value + 10.0, 20.0)
    _load_refused(stage, path, f"prim /World/hinge: {attribute} is animated, but a {'D6Joint' if joint == 'D6' else joint}'s values are read once")
    attr.Clear()
    attr.Set(value)
    attr.Set(value, 0.0)  # one sample equal to the default, as exporters write a constant
    # A recording's joint state is not read: animated, with or without a default, it loads
    # (a review: the first version of the rule refused it).
    state = stage.GetPrimAtPath("/World/hinge").CreateAttribute("state:angular:physics:position", Sdf.ValueTypeNames.Float)
    state.Set(0.0, 0.0)
    state.Set(30.0, 20.0)
    stage.GetRootLayer().Save()
    assert len(io.load_scene(path).joints) == 1


@pytest.mark.parametrize(
    ("joint", "schema", "instance", "match"),
    [
        ("RevoluteJoint", "DriveAPI", "angualr", r"PhysicsDriveAPI:angualr is not read on a RevoluteJoint \(it reads PhysicsDriveAPI:angular\)"),
        ("RevoluteJoint", "DriveAPI", "rotY", r"PhysicsDriveAPI:rotY is not read on a RevoluteJoint \(it reads PhysicsDriveAPI:angular\)"),
        ("RevoluteJoint", "LimitAPI", "rotY", r"PhysicsLimitAPI:rotY is not read on a RevoluteJoint \(it reads none\)"),
        ("D6", "LimitAPI", "rotx", r"PhysicsLimitAPI:rotx is not read on a D6Joint \(it reads PhysicsLimitAPI:transX, .*rotZ\)"),
        ("D6", "DriveAPI", "angular", r"PhysicsDriveAPI:angular is not read on a D6Joint \(it reads PhysicsDriveAPI:transX, .*rotZ\)"),
    ],
)
def test_a_drive_or_limit_a_joint_does_not_read_is_refused(tmp_path, joint, schema, instance, match):
    """Found by a probe: a misspelt or wrong-kind drive or limit instance was dropped without a
    word (the ant's knee loaded unactuated, a hip's limited axis free), as were drive and
    limit attributes authored without their instance applied."""
    path = tmp_path / "hinge.usda"
    stage = _hinge_stage(path, joint=joint, target=5.0)
    prim = stage.GetPrimAtPath("/World/hinge")
    extra = getattr(UsdPhysics, schema).Apply(prim, instance)
    extra.CreateStiffnessAttr(2.0) if schema == "DriveAPI" else extra.CreateLowAttr(-1.0)
    _load_refused(stage, path, f"prim /World/hinge: {match}; rename or remove it")
    prim.RemoveAPI(getattr(UsdPhysics, schema), instance)
    _load_refused(stage, path, f"prim /World/hinge: {'drive' if schema == 'DriveAPI' else 'limit'}:{instance}:physics:{'stiffness' if schema == 'DriveAPI' else 'low'} is authored without Physics{schema}:{instance} applied")
    prim.RemoveProperty(f"{'drive' if schema == 'DriveAPI' else 'limit'}:{instance}:physics:{'stiffness' if schema == 'DriveAPI' else 'low'}")
    stage.GetRootLayer().Save()
    assert len(io.load_scene(path).joints) == 1


def test_a_disabled_body_inside_an_enabled_one_gives_it_its_colliders(tmp_path):
    """UsdPhysics gives the colliders under a disabled body to the nearest enabled body above
    it; the disabled one, left with none, was refused as "rigid body has no collider"."""
    path = write_physics_scene(tmp_path / "nested.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    inner = UsdGeom.Xform.Define(stage, "/World/box/inner")
    inner.AddTranslateOp().Set(Gf.Vec3d(0.6, 0.0, 0.0))
    UsdPhysics.RigidBodyAPI.Apply(inner.GetPrim()).CreateRigidBodyEnabledAttr(False)
    _cube_collider(stage, "/World/box/inner/shape", 0.2, (0.0, 0.0, 0.0))
    stage.GetRootLayer().Save()
    scene = io.load_scene(path)
    assert [b.name for b in scene.bodies] == ["ground", "box"]
    assert len(scene.body("box").faces) == 24  # its own cube and the inner one
    np.testing.assert_allclose(scene.body("box").vertices[:, 0].max() - scene.body("box").vertices[:, 0].min(), 0.25 + 0.7, atol=1e-9)
    hinge = UsdPhysics.RevoluteJoint.Define(stage, "/World/hinge")
    hinge.CreateAxisAttr("Y")
    hinge.CreateBody1Rel().SetTargets(["/World/box/inner"])
    stage.GetRootLayer().Save()
    assert io.load_scene(path).joints[0].child == "box"  # UsdPhysics' resolution, as for the colliders


def test_every_world_weld_of_a_body_is_checked(tmp_path):
    """Only the last of two fixed joints welding one body was checked: a contradicting weld
    authored first loaded, holding the body where the other put it."""
    path = write_physics_scene(tmp_path / "welded.usda", drop_height=3.0)
    stage = Usd.Stage.Open(str(path))
    for name, x in (("wrong", 5.1), ("right", 0.1)):
        weld = UsdPhysics.FixedJoint.Define(stage, f"/World/{name}")
        weld.CreateBody1Rel().SetTargets(["/World/box"])
        weld.CreateLocalPos0Attr(Gf.Vec3f(x, 0.0, 3.0))
    _load_refused(stage, path, "prim /World/wrong: the fixed joint's frames on /World/box and on the world disagree by 5 m")


def _hinged_arm(**joint_options):
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.6))
    arm = io.BodySpec("arm", "/World/arm", np.asarray(box.vertices), np.asarray(box.faces), np.array([0, 0, 1.0, 0, 0, 0, 1.0]), density=500.0)
    options = {"axes": np.array([[0, 1.0, 0]])} | joint_options
    hinge = io.JointSpec("h", "/World/joints/h", "revolute", options.pop("parent", None), options.pop("child", "arm"), np.array([0, 0, 1.3, 0, 0, 0, 1.0]), np.array([0, 0, 0.3, 0, 0, 0, 1.0]), **options)
    return io.Scene(bodies=[arm], joints=[hinge])


def test_scene_joint_gains_reach_the_model_as_given(tmp_path):
    """A damper without a stiffness lost its kd in build_model (a save and load restored it),
    and a scalar kp raised TypeError (a probe, stop 58)."""
    damper = _hinged_arm(kd=np.array([5.0]))
    assert damper.build_model().articulation.kd.tolist() == [5.0]
    io.save_scene(damper, tmp_path / "kd.usda")
    assert io.load_scene(tmp_path / "kd.usda").build_model().articulation.kd == pytest.approx([5.0], rel=1e-7)
    scalar = _hinged_arm(kp=5.0, kd=1.0).build_model().articulation
    assert scalar.kp.tolist() == [5.0] and scalar.kd.tolist() == [1.0]


def test_scene_joint_naming_a_missing_body_is_an_error_naming_the_prim():
    # It raised a bare KeyError 'Arm'.
    for options, role, name in (({"child": "Arm"}, "child", "Arm"), ({"parent": "world"}, "parent", "world")):
        with pytest.raises(ValueError, match=rf"prim /World/joints/h: joint 'h' names {role} body '{name}', which is not a body of the scene \(bodies: arm\)"):
            _hinged_arm(**options).build_model()


def test_scene_base_joint_takes_one_limit_pair_for_every_coordinate(tmp_path):
    # One pair (nested or flat) crashed build_model (zip, unpacking) while save_scene took it.
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    cube = io.BodySpec("cube", "/World/cube", np.asarray(box.vertices), np.asarray(box.faces), np.array([0, 0, 1.0, 0, 0, 0, 1.0]), density=500.0)
    identity = np.array([0, 0, 0, 0, 0, 0, 1.0])
    for limits in ([(-1.0, 1.5)], (-1.0, 1.5)):
        scene = io.Scene(bodies=[cube], gravity=np.zeros(3), joints=[io.JointSpec("b", "/World/joints/b", "base", None, "cube", identity, identity, dofs=("x", "z"), limits=limits)])
        art = scene.build_model().articulation
        io.save_scene(scene, tmp_path / "base.usda", overwrite=True)
        loaded = io.load_scene(tmp_path / "base.usda").build_model().articulation
        assert art.lower.tolist() == loaded.lower.tolist() == [-1.0, -2.0] and art.upper.tolist() == loaded.upper.tolist() == [1.5, 0.5]
    bad = io.Scene(bodies=[cube], gravity=np.zeros(3), joints=[io.JointSpec("b", "/World/joints/b", "base", None, "cube", identity, identity, dofs=("x", "z"), limits=[(1.0, -1.0)])])
    with pytest.raises(ValueError, match=r"prim /World/joints/b: joint 'b': limits must be 2 \(lower, upper\) pairs"):
        bad.build_model()


def test_save_scene_writes_a_scalar_linear_gain_for_every_axis(tmp_path):
    # add_body reads a scalar kp_linear as all three axes; save_scene raised TypeError on it.
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    rod = io.BodySpec("rod", "/World/rod", np.asarray(ball.vertices), np.asarray(ball.faces), np.array([0, 0, 0, 0, 0, 0, 1.0]), density=100.0, kp_linear=400.0, kd_linear=60.0)
    scene = io.Scene(bodies=[rod], gravity=np.zeros(3))
    io.save_scene(scene, tmp_path / "kp.usda")
    loaded = io.load_scene(tmp_path / "kp.usda").build_model()
    assert loaded.body_kp_linear.numpy().tolist() == scene.build_model().body_kp_linear.numpy().tolist() == [[400.0] * 3]
    assert loaded.body_kd_linear.numpy().tolist() == [[60.0] * 3]


def _box_stage(path, *, parent_rotation=None):
    """A stage with a ground cube and a rigid body /World/box (or /World/rig/box under a
    rotated Xform) with a 0.5 m Cube collider; returns (stage, box prim)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, "Z")
    UsdPhysics.Scene.Define(stage, "/World/physicsScene")
    ground = UsdGeom.Cube.Define(stage, "/World/ground")
    ground.CreateSizeAttr(1.0)
    ground.AddTranslateOp().Set(Gf.Vec3d(0, 0, -0.5))
    ground.AddScaleOp().Set(Gf.Vec3f(10, 10, 1))
    UsdPhysics.CollisionAPI.Apply(ground.GetPrim())
    if parent_rotation is None:
        box = UsdGeom.Xform.Define(stage, "/World/box")
        box.AddTranslateOp().Set(Gf.Vec3d(0, 0, 0.3))
    else:
        rig = UsdGeom.Xform.Define(stage, "/World/rig")
        rig.AddRotateXYZOp().Set(Gf.Vec3f(*parent_rotation))
        world = Gf.Matrix4d(1.0).SetTranslateOnly(Gf.Vec3d(0, 0, 0.3))
        box = UsdGeom.Xform.Define(stage, "/World/rig/box")
        box.AddTransformOp().Set(world * rig.ComputeLocalToWorldTransform(Usd.TimeCode.Default()).GetInverse())
    UsdPhysics.RigidBodyAPI.Apply(box.GetPrim())
    collider = UsdGeom.Cube.Define(stage, str(box.GetPrim().GetPath()) + "/geo/collider")
    collider.CreateSizeAttr(0.5)
    UsdPhysics.CollisionAPI.Apply(collider.GetPrim())
    return stage, box.GetPrim()


def test_mass_and_velocity_attributes_that_usd_physics_would_not_read_are_refused(tmp_path):
    """Mass attributes without MassAPI applied, MassAPI on a grouping Xform, and a velocity on a
    prim that is no body were ignored: the box weighed the default density's 125 kg for an
    authored 7 kg, silently (a probe, stop 58)."""
    stage, box = _box_stage(tmp_path / "noapi.usda")
    box.CreateAttribute("physics:mass", Sdf.ValueTypeNames.Float).Set(7.0)
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"prim /World/box: physics:mass authored without PhysicsMassAPI applied"):
        io.load_scene(tmp_path / "noapi.usda")
    stage, box = _box_stage(tmp_path / "group.usda")
    UsdPhysics.MassAPI.Apply(stage.GetPrimAtPath("/World/box/geo")).CreateMassAttr(7.0)
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"prim /World/box/geo: PhysicsMassAPI on a prim that is neither a rigid body nor a collider is not read"):
        io.load_scene(tmp_path / "group.usda")
    stage, box = _box_stage(tmp_path / "velocity.usda")
    stage.GetPrimAtPath("/World/ground").CreateAttribute("physics:velocity", Sdf.ValueTypeNames.Vector3f).Set(Gf.Vec3f(3, 0, 0))
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"prim /World/ground: physics:velocity authored on a prim without PhysicsRigidBodyAPI"):
        io.load_scene(tmp_path / "velocity.usda")
    stage, box = _box_stage(tmp_path / "applied.usda")
    UsdPhysics.MassAPI.Apply(box).CreateMassAttr(7.0)
    stage.GetRootLayer().Save()
    assert io.load_scene(tmp_path / "applied.usda").build_model().body_mass.numpy()[1] == pytest.approx(7.0)


def test_a_matrix_op_within_rounding_of_affine_loads_where_usd_draws_it(tmp_path):
    # world * parent^-1 (a reparented prim keeping its world pose) leaves 1 - 2e-16 in the last
    # column: the stage was refused as "not an affine transform".
    stage, box = _box_stage(tmp_path / "rig.usda", parent_rotation=(30, 40, 50))
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(io.load_scene(tmp_path / "rig.usda").body("box").pose, [0, 0, 0.3, 0, 0, 0, 1], atol=1e-12)
