"""CLI commands run end to end on tiny cases and write well-formed output."""

import csv
import os
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import interrupt_call
from pxr import Usd

from warpcontact import io
from warpcontact.bench import accuracy_scene
from warpcontact import cli
from warpcontact.cli import main


def test_demo_writes_results(tmp_path, capsys):
    assert main(["demo", "--subdivisions", "0", "--gaps", "1", "0.01", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "demo.json").read_text())
    assert data["triangles_per_body"] == 20
    assert [r["gap"] for r in data["results"]] == [1.0, 0.01]
    assert data["results"][1]["potential"] > data["results"][0]["potential"] > 0
    assert "wrote" in capsys.readouterr().out


def test_bench_leaf_writes_results(tmp_path):
    assert main(["bench", "leaf", "--pairs", "200", "--repeats", "1", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "leaf.json").read_text())
    assert data["num_pairs"] == 200 and data["reference_precision"] == "float64"
    reference, float32 = data["rows"]
    assert (reference["precision"], float32["precision"]) == ("float64", "float32")
    for row in data["rows"]:
        assert row["fraction_ok"] == 1.0
        assert row["solves_per_second_value"] > 0 and row["solves_per_second_value_grad_hessian"] > 0
        assert 1 <= row["mean_newton_iterations"] <= row["max_newton_iterations"] <= 100
    # float32 searches are finished in float64 to the float64 tolerances; their planes are
    # not float64's to the last digit (the rows used to compare float32 with its own buffers
    # on a CPU, where .numpy() is a view: errors of 0).
    assert float32["value_error_max"] < 1e-13 and 0 < float32["gradient_error_max"] < 1e-9
    assert "value_error_max" not in reference
    assert (tmp_path / "leaf.csv").read_text().count("\n") == 3


def test_bench_contact_writes_results_and_plot(tmp_path, capsys):
    args = ["bench", "contact", "--eps", "0.5", "--gaps", "0.1", "--subdivisions", "0", "--repeats", "1", "--centred-weights", "paper", "pairs", "--out", str(tmp_path)]
    assert main(args) == 0
    assert "contact.csv, contact.png" in capsys.readouterr().out  # the plot was left out of the line
    data = json.loads((tmp_path / "contact.json").read_text())
    assert data["module_load_seconds"] >= 0 and data["repeats"] == 1
    rows = data["rows"]
    assert {(r["scene"], r["mode"], r["centred_weight"]) for r in rows} == {
        (s, m, w) for s in ("two_icospheres", "rack16") for m, w in (("brute", None), ("ipc", None), ("bsh", "paper"), ("bsh", "pairs"))
    }
    for scene in ("two_icospheres", "rack16"):  # pair-weighted centred terms estimate the brute-force sum
        ratio = {r["centred_weight"]: r["value_ratio"] for r in rows if r["scene"] == scene and r["mode"] == "bsh"}
        assert abs(ratio["pairs"] - 1) < 0.05 < abs(ratio["paper"] - 1)
    for r in rows:
        assert r["median_seconds"] > 0
        if r["mode"] == "ipc":  # ipctk side by side on the same geometry; no error vs brute force
            assert r["median_seconds_rigid"] > 0 and r["force_error_max"] is None
        elif r["mode"] == "brute":
            assert r["force_error_max"] == 0.0 and r["num_far"] == 0
        else:
            assert r["num_far"] + r["num_blend"] + r["num_leaf"] > 0
            assert 0 < r["force_cosine_min"] <= 1.0 + 1e-12
    assert (tmp_path / "contact.png").stat().st_size > 1000
    assert _csv_rows(tmp_path / "contact.csv") == len(rows)
    # Beyond 1e27 m brute force's leaf planes do not solve: rows were written from a reference
    # of value inf and zero forces, exit 0. A refused run also deleted the earlier plot alone.
    before = {name: (tmp_path / name).read_bytes() for name in ("contact.json", "contact.csv", "contact.png")}
    assert main([*args[:5], "1e-2", "1e28", *args[6:], "--overwrite"]) == 2
    assert "error: gaps: 1e+28 m is beyond the 1e+27 m up to which leaf planes are solved" in capsys.readouterr().err
    assert {name: (tmp_path / name).read_bytes() for name in before} == before


def test_bench_csv_cells_are_empty_where_the_json_has_null(tmp_path):
    """The CSV wrote nan and inf where the JSON wrote null."""
    from warpcontact import bench

    bench._write_csv(tmp_path / "rows.csv", [{"a": 1.5, "b": float("nan"), "c": np.float64("inf"), "d": (1.0, float("nan"))}])
    with (tmp_path / "rows.csv").open() as f:
        assert list(csv.DictReader(f)) == [{"a": "1.5", "b": "", "c": "", "d": "[1.0, null]"}]


def test_bench_leaf_names_pairs_it_cannot_allocate(tmp_path, monkeypatch):
    """--pairs 10000000, its largest, needs 29 GB: a RuntimeError traceback on smaller machines."""
    from warpcontact import bench

    def no_memory(*args, **kwargs):
        raise RuntimeError("Failed to allocate 25920000000 bytes on device 'cpu'")

    monkeypatch.setattr(bench, "leaf_solve_buffers", no_memory)
    with pytest.raises(ValueError, match=r"pairs: 10 pairs need 2.93e-05 GB of buffers on cpu \(2928 bytes a pair\), more than it could allocate"):
        bench.run_leaf_benchmark(num_pairs=10, repeats=1, device="cpu", out_dir=tmp_path)


def test_bench_strike_gaps_are_refused_where_positions_cannot_hold_them(capsys):
    """--gap 1e-30 placed the striker 1.1e-16 m into the struck ball while frame.json recorded
    1e-30; 1e200 was blamed on the striker's pose."""
    for gap, message in ((1e-30, r"gap: 1e-30 m rounds to \S+ m beside"), (1e200, r"gap: 1e\+200 m puts the striker beyond")):
        with pytest.raises(ValueError, match=message):
            accuracy_scene(points_per_ball=8, gap=gap)
    # A probe (stop 57): a speed whose step leaves the coordinates was blamed on state_in.body_q_prev.
    from warpcontact import bench

    with pytest.raises(ValueError, match=r"speed: 1e\+200 m/s moves the striker 4e\+198 m a step of 0.04 s, beyond the"):
        bench.strike_setup(bench.frame_scene("push"), gap=0.02, speed=1e200)
    assert main(["bench", "frame", "--scenes", "peer_billiards_abc", "--frames", "1", "--out", "unused"]) == 2
    assert "peer_billiards_abc: peer billiards come in" in capsys.readouterr().err


def test_a_broken_peer_ball_file_is_named(tmp_path):
    from warpcontact import bench

    (tmp_path / "broken.obj").write_text("# no vertices\n")
    with pytest.raises(ValueError, match=r"broken.obj: not a ball mesh \(0 vertices read\)"):
        bench._peer_ball(tmp_path / "broken.obj")


@pytest.mark.parametrize("subdivisions", [0, 1])
def test_bench_contact_pair_stands_at_the_surface_gap(subdivisions):
    """Its second ball was turned about z, which moved the surfaces 2.9 cm apart at 1 mm."""
    from warpcontact.bench import contact_benchmark_scenes
    from warpcontact.rotation import quat_rotate

    ipctk = pytest.importorskip("ipctk")
    for scene in contact_benchmark_scenes(subdivisions=subdivisions, gaps=[1e-3, 1e-1]):
        if scene["scene"] != "two_icospheres":
            continue
        (vertices, faces), pose = scene["meshes"][1], scene["poses"][1]
        points = np.concatenate([vertices, quat_rotate(pose[3:], vertices) + pose[:3]])
        triangles = np.concatenate([faces, faces + len(vertices)])
        mesh = ipctk.CollisionMesh(points, ipctk.edges(triangles), triangles)
        mesh.can_collide = ipctk.make_vertex_patches_filter(np.repeat([0, 1], len(vertices)).astype(np.int32))
        collisions = ipctk.NormalCollisions()
        collisions.build(mesh, points, 1.0)
        assert np.sqrt(collisions.compute_minimum_distance(mesh, points)) == pytest.approx(scene["gap"], rel=1e-9)


def test_bench_scaling_writes_results(tmp_path):
    assert main(["bench", "scaling", "--points", "8", "12", "--repeats", "1", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "scaling.json").read_text())
    rows = data["rows"]
    assert [(r["triangles"], r["mode"]) for r in rows] == [(192, "bsh"), (192, "brute"), (320, "bsh"), (320, "brute")]
    assert data["brute_max_triangles"] == 2560  # what explains missing brute rows (recorded nowhere before)
    # Compile time apart, as in the other benchmarks (left out until stop 64).
    assert data["module_load_seconds"] >= 0 and data["repeats"] == 1
    assert all(r["median_seconds"] > 0 for r in rows)
    assert (tmp_path / "scaling.png").stat().st_size > 1000


def _csv_rows(path):
    """Data lines of a CSV file, checking that every line has the header's columns."""
    with path.open(newline="") as f:
        lines = list(csv.reader(f))
    assert lines and all(len(line) == len(lines[0]) for line in lines)
    return len(lines) - 1


def _tiny_billiards(tmp_path) -> Path:
    """Cue and one 12-face ball on a cropped table, the cue 2 cm away at 1 m/s, as a .usda."""
    scene, _ = accuracy_scene(balls=1, points_per_ball=8)
    path = tmp_path / "tiny.usda"
    io.save_scene(scene, path)
    return path


def test_bench_frame_writes_results_and_plot(tmp_path):
    args = ["bench", "frame", "--scenes", str(_tiny_billiards(tmp_path)), "--frames", "2", "--warmup", "0", "--out", str(tmp_path)]
    assert main(args) == 0
    data = json.loads((tmp_path / "frame.json").read_text())
    assert data["module_load_seconds"] >= 0 and data["frames"] == 2
    assert "repeats" not in data  # it held the frame count (a probe, stop 64)
    assert data["host"].endswith(" logical cores")
    rows = data["rows"]
    assert [(r["scene"], r["model"]) for r in rows] == [("tiny", "bsh"), ("tiny", "brute"), ("tiny", "ipc")]
    for r in rows:
        assert r["error"] is None and r["frames"] == 2 and r["triangles"] == 24
        assert len(r["newton_iterations_per_frame"]) == 2 and r["newton_iterations"] >= 1
        assert r["forward_seconds"] > 0 and r["contact_seconds"] > 0 and r["backward_seconds"] > 0
        assert min(r["frame_seconds"], r["frame_seconds_mean"]) > 0
        assert len(r["forward_seconds_per_frame"]) == 2 and r["forward_seconds_mean"] == pytest.approx(np.mean(r["forward_seconds_per_frame"]))
        assert r["setup"] == "cue 0.02 m (bounding circles) from ball00 at 1 m/s"
        assert len(r["direction"]) == 3 and np.linalg.norm(r["direction"]) == pytest.approx(1.0)  # documented, never written (a probe, stop 61)
    assert rows[2]["contact_stiffness"] == 1e3 and rows[0]["contact_stiffness"] == rows[1]["contact_stiffness"] != 1e3
    assert rows[2]["friction"] == 0.0 and rows[0]["eps"] == 0.5 and rows[1]["eps"] is None
    # Which file and which centred terms a row measured (two push.usda files' rows were told
    # apart by nothing; a probe, stop 65).
    assert {r["source"] for r in rows} == {str((tmp_path / "tiny.usda").resolve())}
    assert [r["centred_weight"] for r in rows] == ["paper", None, None]
    assert _csv_rows(tmp_path / "frame.csv") == 3
    assert (tmp_path / "frame.png").stat().st_size > 1000


def test_a_bench_interrupted_between_its_json_and_csv_writes_both(tmp_path, monkeypatch, capsys):
    # Ctrl-C right after a row's JSON left the CSV a row short (a probe, stop 58).
    import os
    import signal

    from warpcontact import bench

    real, calls = bench.replace_json, []

    def interrupted_after(path, payload):
        real(path, payload)
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(bench, "replace_json", interrupted_after)
    # As a terminal's Ctrl-C finds it, whatever started the tests: a suite started in the
    # background by a script ignores SIGINT, and this test failed there (stop 63).
    started_with = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert main(["bench", "scaling", "--points", "4", "5", "8", "--repeats", "1", "--brute-max-triangles", "0", "--out", str(tmp_path)]) == 130
    finally:
        signal.signal(signal.SIGINT, started_with)
    rows = json.loads((tmp_path / "scaling.json").read_text())["rows"]
    assert len(rows) == 2 and _csv_rows(tmp_path / "scaling.csv") == 2


def test_bench_frame_first_frame_counts_what_a_frame_counts(tmp_path, monkeypatch):
    # first_frame_seconds added the timed contact evaluation that frame_seconds leaves out.
    from warpcontact import bench

    durations = iter([1.0, 10.0, 100.0] * 4)  # forward, contact evaluation, backward
    monkeypatch.setattr(bench, "_timed", lambda fn, dev: (fn(), next(durations)))
    assert main(["bench", "frame", "--scenes", str(_tiny_billiards(tmp_path)), "--models", "bsh", "--frames", "1", "--warmup", "1", "--out", str(tmp_path)]) == 0
    row = json.loads((tmp_path / "frame.json").read_text())["rows"][0]
    assert row["first_frame_seconds"] == row["frame_seconds"] == 101.0


def test_benches_without_the_ipc_toolkit_skip_its_rows_or_say_how_to(tmp_path, capsys, monkeypatch):
    """ipctk is an optional extra. Without it bench frame stopped at the first ipc row (the
    default run lost every scene after the first), and bench contact's error did not say how
    to run without it (a probe, stop 57)."""
    from warpcontact import ipc

    monkeypatch.setattr(ipc, "toolkit_problem", lambda: "the ipc baseline needs the IPC Toolkit: pip install 'warpcontact[ipc]' (test)")
    tiny = str(_tiny_billiards(tmp_path))
    assert main(["bench", "frame", "--scenes", tiny, tiny.replace("tiny", "tiny2"), "--models", "bsh", "ipc", "--frames", "1", "--warmup", "0", "--out", str(tmp_path / "f")]) == 2  # tiny2 missing
    (tmp_path / "tiny2.usda").write_bytes((tmp_path / "tiny.usda").read_bytes())
    assert main(["bench", "frame", "--scenes", tiny, str(tmp_path / "tiny2.usda"), "--models", "bsh", "ipc", "--frames", "1", "--warmup", "0", "--out", str(tmp_path / "f")]) == 0
    rows = json.loads((tmp_path / "f" / "frame.json").read_text())["rows"]
    assert [(r["scene"], r["model"]) for r in rows] == [("tiny", "bsh"), ("tiny", "ipc"), ("tiny2", "bsh"), ("tiny2", "ipc")]
    assert rows[0]["error"] is None and rows[2]["error"] is None
    assert rows[1]["error"] == rows[3]["error"] == "skipped: the ipc baseline needs the IPC Toolkit: pip install 'warpcontact[ipc]' (test)"
    assert rows[1]["contact_stiffness"] == 1e3  # the scene's mu, which ipc never runs with (a probe, stop 61)
    capsys.readouterr()
    assert main(["bench", "contact", "--eps", "0.5", "--gaps", "0.1", "--subdivisions", "0", "--repeats", "1", "--out", str(tmp_path / "c")]) == 2
    assert "pip install 'warpcontact[ipc]' (test); or leave out the ipc rows (ipc_dhat=None; --ipc-dhat 0 on the command line)" in capsys.readouterr().err


def test_bench_results_name_the_host_cpu(monkeypatch):
    """The results' host was platform.processor(), on Linux only "x86_64" (a probe)."""
    import io as text_io

    from warpcontact import bench

    monkeypatch.setattr(bench, "open", lambda *args, **kwargs: text_io.StringIO("processor\t: 0\nmodel name\t: Test CPU 9000 @ 3 GHz\n"), raising=False)
    monkeypatch.setattr(bench.os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    bench._host.cache_clear()
    try:
        assert bench._host() == "Test CPU 9000 @ 3 GHz, 3 logical cores"
    finally:
        bench._host.cache_clear()  # the real host for later tests


def test_the_strike_is_set_up_across_the_stage_up_axis():
    """bench frame's strike on a Y-up scene: the same set-up as on the Z-up scene, turned
    (it moved the rod along y, part way up, and launched it partly vertically); a striker
    straight above its target is an error naming both (it divided by zero and then blamed
    the scene file for a NaN pose)."""
    from warpcontact import bench, scenes
    from warpcontact.rotation import quat_mul, quat_rotate

    z_up = scenes.build_scene("push")
    y_up = scenes.build_scene("push")
    turn = np.array([-np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])  # -90 degrees about x: z -> y
    y_up.up_axis = "Y"
    for body in y_up.bodies:
        body.pose = np.array([*quat_rotate(turn, body.pose[:3]), *quat_mul(turn, body.pose[3:])])
    setups = [bench.strike_setup(scene, gap=0.02, speed=1.0) for scene in (z_up, y_up)]
    rod_z, rod_y = (scene.body("rod") for scene in (z_up, y_up))
    np.testing.assert_allclose(rod_y.pose[:3], quat_rotate(turn, rod_z.pose[:3]), atol=1e-12)
    np.testing.assert_allclose(rod_y.linear_velocity, quat_rotate(turn, rod_z.linear_velocity), atol=1e-12)
    np.testing.assert_allclose(setups[1]["control_target"], quat_rotate(turn, np.array(setups[0]["control_target"])), atol=1e-12)
    assert setups[0]["struck"] == setups[1]["struck"] and rod_z.linear_velocity[2] == 0.0

    above = scenes.build_scene("push")
    above.body("rod").pose[:2] = above.body(setups[0]["struck"]).pose[:2]
    with pytest.raises(ValueError, match="the striker 'rod' stands straight above or below 'box'"):
        bench.strike_setup(above, gap=0.02, speed=1.0)
    # A static striker was given a velocity it never had, and the results recorded a strike
    # it never made; a striker alone failed in min() (a probe, stop 65).
    static = scenes.build_scene("push")
    static.body("rod").static = True
    with pytest.raises(ValueError, match=r"the striker 'rod' is static \(a collider without a rigid body\): it cannot strike"):
        bench.strike_setup(static, gap=0.02, speed=1.0)
    alone = scenes.build_scene("push")
    alone.body("box").static = True
    with pytest.raises(ValueError, match="no dynamic body besides the striker 'rod' to strike"):
        bench.strike_setup(alone, gap=0.02, speed=1.0)
    # Placed as a free body, a jointed striker left its joint's axis, refused only when its
    # model was built, after the scenes before it were timed (a probe, stop 65).
    jointed = scenes.build_scene("push")
    jointed.joints = [io.JointSpec("slider", "/World/slider", "prismatic", None, "rod", np.array([0.0, 0.0, 0.33, 0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]), np.array([[1.0, 0.0, 0.0]]))]
    with pytest.raises(ValueError, match="the striker 'rod' is held by joint 'slider'; the strike places it as a free body"):
        bench.strike_setup(jointed, gap=0.02, speed=1.0)


def test_bench_frame_times_brute_contact_only_above_the_cap(tmp_path):
    args = ["bench", "frame", "--scenes", str(_tiny_billiards(tmp_path)), "--models", "bsh", "brute", "--frames", "1", "--warmup", "0", "--brute-max-triangles", "0", "--out", str(tmp_path)]
    assert main(args) == 0
    brute = json.loads((tmp_path / "frame.json").read_text())["rows"][1]
    assert brute["model"] == "brute" and brute["frames"] == 0 and brute["forward_seconds"] is None and brute["forward_seconds_mean"] is None and brute["frame_seconds_mean"] is None and brute["contact_seconds"] > 0


def test_bench_frame_rows_do_not_depend_on_the_order_of_models(tmp_path, capsys):
    """Brute force above the cap is timed at bsh's frames: listed before bsh its row was
    dropped without a word; with nothing to time at, it is a row saying why, and a run
    without a drawable row leaves no plot (an earlier run's stayed beside the new results)."""
    scene = str(_tiny_billiards(tmp_path))
    args = ["bench", "frame", "--scenes", scene, "--frames", "1", "--warmup", "0", "--brute-max-triangles", "0", "--out", str(tmp_path)]
    # A scene or model named twice is timed once (a probe: the scene was timed twice).
    assert main([*args[:4], scene, *args[4:], "--models", "brute", "bsh", "bsh"]) == 0
    rows = json.loads((tmp_path / "frame.json").read_text())["rows"]
    assert [r["model"] for r in rows] == ["bsh", "brute"] and rows[1]["contact_seconds"] > 0
    assert (tmp_path / "frame.png").is_file()
    capsys.readouterr()
    # Nothing measured: the results say why, and the exit status says so (it was 0, a probe).
    assert main([*args, "--models", "brute", "--overwrite"]) == 1
    (row,) = json.loads((tmp_path / "frame.json").read_text())["rows"]
    assert row["error"] == "skipped: 24 dynamic triangles above --brute-max-triangles 0, and no bsh frames to evaluate at (bsh not in --models, or its frames failed)"
    assert not (tmp_path / "frame.png").exists()
    captured = capsys.readouterr()
    assert "skipped: 24 dynamic triangles" in captured.out and "not frame.png (no rows to plot)" in captured.out
    assert "error: no frame was measured: skipped: 24 dynamic triangles" in captured.err


def test_bench_frame_default_scenes_take_the_peer_rack_only_where_its_meshes_are(tmp_path, capsys, monkeypatch):
    """The paper's meshes are not shipped: a plain ``bench frame`` failed on every install
    without them (a probe). Named in --scenes, a missing mesh stays an error (the test below)."""
    from warpcontact import bench

    asked = []

    def record(*, scenes, **_):
        asked.append(list(scenes))
        return [{"frames": 1, "contact_seconds": 0.0}]

    monkeypatch.setattr(bench, "run_frame_benchmark", record)
    plain = ["billiards_512", "billiards_1280", "billiards_2560", "billiards_6208", "gather_bunny"]
    assert main(["bench", "frame", "--peer-meshes", str(tmp_path / "none"), "--out", str(tmp_path / "a")]) == 0
    assert asked[-1] == plain
    assert f"note: peer_billiards_6208 left out of the default scenes: {tmp_path / 'none' / '196.obj'} not found" in capsys.readouterr().out
    (tmp_path / "peer").mkdir()
    (tmp_path / "peer" / "196.obj").write_text("")
    assert main(["bench", "frame", "--peer-meshes", str(tmp_path / "peer"), "--out", str(tmp_path / "b")]) == 0
    assert asked[-1] == [*plain, "peer_billiards_6208"]
    assert "left out" not in capsys.readouterr().out


def test_bench_frame_reads_every_scene_before_timing_any(tmp_path, capsys):
    args = ["bench", "frame", "--scenes", str(_tiny_billiards(tmp_path)), "peer_billiards_512", "--peer-meshes", str(tmp_path / "none"), "--models", "bsh", "--frames", "1", "--out", str(tmp_path / "b")]
    assert main(args) == 2
    assert "error: peer_billiards_512: " in capsys.readouterr().err
    assert not (tmp_path / "b" / "frame.json").exists()  # the first scene was not run
    # Another size's ball in a file's place was timed under this size's name (a probe).
    from warpcontact import bench

    (tmp_path / "swapped").mkdir()
    (tmp_path / "swapped" / "18.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")  # a tetrahedron
    with pytest.raises(ValueError, match=r"peer_billiards_512: .*18.obj has 4 faces, a rack of 64 triangles, not 512"):
        bench.frame_scene("peer_billiards_512", peer_meshes=tmp_path / "swapped")


def _interrupt_second_timing(monkeypatch):
    """Make the benches' second timed measurement raise KeyboardInterrupt, as Ctrl-C there
    would; returns a function that starts the count again."""
    from warpcontact import bench

    median, calls = bench._median_seconds, [0]

    def interrupted_second(fn, repeats):
        calls[0] += 1
        if calls[0] == 2:
            raise KeyboardInterrupt
        return median(fn, repeats)

    monkeypatch.setattr(bench, "_median_seconds", interrupted_second)
    return lambda: calls.__setitem__(0, 0)


def test_interrupted_benches_keep_their_finished_rows(tmp_path, capsys, monkeypatch):
    """contact, scaling and leaf wrote their results only at the end: Ctrl-C lost every row,
    with a traceback."""
    restart = _interrupt_second_timing(monkeypatch)
    assert main(["bench", "scaling", "--points", "8", "12", "--repeats", "1", "--out", str(tmp_path)]) == 130
    assert f"interrupted; the rows finished before it are in {tmp_path}" in capsys.readouterr().err
    interrupted = json.loads((tmp_path / "scaling.json").read_text())
    (row,) = interrupted["rows"]
    assert row["mode"] == "bsh" and row["triangles"] == 16 * 12 and _csv_rows(tmp_path / "scaling.csv") == 1
    # A stopped run's file says so: it read like a finished one's (a probe, stop 58).
    assert interrupted["complete"] is False
    restart()
    args = ["bench", "contact", "--eps", "0.5", "--gaps", "0.1", "--subdivisions", "0", "--repeats", "1", "--ipc-dhat", "0", "--out", str(tmp_path)]
    assert main(args) == 130
    stopped = json.loads((tmp_path / "contact.json").read_text())
    assert [r["mode"] for r in stopped["rows"]] == ["brute"] and stopped["complete"] is False
    monkeypatch.undo()
    assert main([*args, "--overwrite"]) == 0
    finished = json.loads((tmp_path / "contact.json").read_text())
    assert [r["mode"] for r in finished["rows"]] == ["brute", "bsh"] * 2 and finished["complete"] is True  # two scenes


def test_an_overwriting_bench_interrupted_before_its_first_row_leaves_no_earlier_rows(tmp_path, capsys, monkeypatch):
    """With --overwrite, a bench interrupted before its first row kept the earlier run's rows
    (and lost their plot), as if they were its own."""
    args = ["bench", "scaling", "--points", "8", "--repeats", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    assert (tmp_path / "scaling.json").exists() and (tmp_path / "scaling.csv").exists()
    from warpcontact import bench

    def interrupted(fn, repeats):
        raise KeyboardInterrupt

    monkeypatch.setattr(bench, "_median_seconds", interrupted)
    assert main([*args, "--overwrite"]) == 130
    assert not any((tmp_path / name).exists() for name in ("scaling.json", "scaling.csv", "scaling.png"))
    # It said the finished rows were kept, and left the folder it had made.
    assert "interrupted; no row was finished (the earlier run's scaling.json, scaling.csv" in capsys.readouterr().err
    fresh = tmp_path / "fresh"
    assert main([*args[:-1], str(fresh)]) == 130
    assert "interrupted; no row was finished" in capsys.readouterr().err and not fresh.exists()


def test_a_folder_another_running_command_writes_to_is_refused(tmp_path, capsys):
    """Two runs into one folder both passed their start checks, and the later one's results
    replaced the other's without --overwrite. A lock file whose process ended (killed) is
    taken over, with the temporaries that process left; other hidden files are the user's."""
    import fcntl
    import os

    from warpcontact._files import LOCK_NAME

    args = ["bench", "scaling", "--points", "8", "--repeats", "1", "--out", str(tmp_path)]
    lock = tmp_path / LOCK_NAME
    lock.write_text("4242\n")
    with lock.open("r+") as held:  # a running command's lock
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert main(args) == 2
        assert "another warpcontact command (process 4242) is writing there" in capsys.readouterr().err
    assert lock.exists() and not (tmp_path / "scaling.json").exists()
    (tmp_path / ".warpcontact-tmp-abc").mkdir()  # what the killed holder was writing
    (tmp_path / ".warpcontact-tmp-def.json").write_text("{")
    (tmp_path / ".tmp-notes.txt").write_text("mine")
    assert main(args) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tmp-notes.txt", "scaling.csv", "scaling.json", "scaling.png"]
    os.close(os.open(lock, os.O_CREAT | os.O_WRONLY))  # empty: its process ended before it wrote
    assert main([*args, "--overwrite"]) == 0 and not lock.exists()


def test_an_overwriting_bench_with_a_bad_argument_keeps_the_earlier_results(tmp_path, capsys):
    """--overwrite removed the earlier run's outputs before the arguments were checked: a
    mistyped device or scene name lost them."""
    args = ["bench", "scaling", "--points", "8", "--repeats", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    before = {name: (tmp_path / name).read_bytes() for name in ("scaling.json", "scaling.csv")}
    assert main([*args, "--device", "cuda:7", "--overwrite"]) == 2
    assert "device: 'cuda:7' is not available" in capsys.readouterr().err
    assert {name: (tmp_path / name).read_bytes() for name in before} == before


def test_results_are_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    """compare.json, metrics.json and a bench's JSON and CSV were rewritten in place: a full
    disk left them truncated, every finished model or row in them lost. A NaN (a ratio to an
    infinite reference) was written as a bare NaN token, which JSON parsers refuse."""
    from warpcontact import _files

    path = tmp_path / "results.json"
    _files.replace_json(path, {"rows": [1.0, float("nan"), np.float64("inf"), np.array([2.0, np.nan])]})
    assert json.loads(path.read_text()) == {"rows": [1.0, None, None, [2.0, None]]}

    def full_disk(self, text):
        Path.write_bytes(self, text[: len(text) // 2].encode())
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full_disk)
    with pytest.raises(OSError, match="No space left"):
        _files.replace_json(path, {"rows": list(range(100))})
    monkeypatch.undo()
    assert json.loads(path.read_text())["rows"][1] is None  # the earlier file, whole
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]  # no temporary left
    # A folder where no file can be made: the error named the temporary file (a probe, stop 64).
    with pytest.raises(OSError, match=r"^\[Errno 2\] /proc/results.json: no file can be created in /proc \(No such file or directory\)$"):
        _files.replace_json("/proc/results.json", {})


def test_bench_frame_refuses_bad_pickles_and_strikerless_scenes_before_timing(tmp_path, capsys):
    """A pickle of something else was a traceback (exit 1), a missing one exit 1 where a missing
    .usda is 2, and a scene with no cue or rod was refused only after the scenes before it."""
    import pickle

    (tmp_path / "dict.pkl").write_bytes(pickle.dumps({"bodies": []}))
    (tmp_path / "text.pkl").write_text("not a pickle")
    for scene, message in (
        (tmp_path / "dict.pkl", "holds a dict, not a pickled warpcontact Scene"),
        (tmp_path / "text.pkl", "not a pickled Scene (UnpicklingError"),
        (tmp_path / "missing.pkl", "missing.pkl: file not found"),
    ):
        assert main(["bench", "frame", "--scenes", str(scene), "--models", "bsh", "--frames", "1", "--out", str(tmp_path / "b"), "--overwrite"]) == 2
        assert message in capsys.readouterr().err
    assert main(["bench", "frame", "--scenes", "billiards_512", "ant_push", "--models", "bsh", "--frames", "1", "--warmup", "0", "--out", str(tmp_path / "c")]) == 2
    assert "ant_push.usda: no 'cue' or 'rod' body to strike with" in capsys.readouterr().err
    assert not (tmp_path / "c" / "frame.json").exists()  # nothing was timed


def test_frame_plot_draws_the_papers_points_at_the_papers_triangle_counts(tmp_path, monkeypatch):
    """The paper's Gather-Bunny frame costs were drawn at our 2,702 triangles, not its 2,784."""
    from warpcontact import bench

    plt = bench.optional_pyplot()
    if plt is None:
        pytest.skip("matplotlib not installed")
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to read it
    row = {"model": "bsh", "scene": "gather_bunny", "triangles": 2702, "contact_seconds": 0.1, "forward_seconds": 1.0, "backward_seconds": 0.1, "frame_seconds_mean": 1.3}
    assert bench._plot_frame_benchmark([row], tmp_path / "frame.png")
    lines = {line.get_label(): dict(zip(line.get_xdata(), line.get_ydata())) for line in figures[0].axes[0].get_lines()}
    assert lines["paper bsh (CPU, mean forward + backward)"] == {512: 0.6, 6208: 3.18, 2784: 3.89}
    # The paper's figures are means of forward + backward: ours drawn beside them are too
    # (the plot compared them with our median forward step alone; a probe, stop 62).
    assert lines["bsh mean forward + backward"] == {2702: 1.3}


def test_a_failing_plot_does_not_hide_an_interruption(tmp_path, capsys, monkeypatch):
    """The plot is drawn in a finally: an error there (a zero gradient's missing cosine) replaced
    Ctrl-C with a traceback."""
    from warpcontact import bench

    def broken(rows, path):
        raise TypeError("unsupported operand type(s) for -: 'float' and 'NoneType'")

    monkeypatch.setattr(bench, "_plot_scaling", broken)
    _interrupt_second_timing(monkeypatch)
    with pytest.warns(UserWarning, match="scaling.png not drawn: TypeError"):
        assert main(["bench", "scaling", "--points", "8", "12", "--repeats", "1", "--out", str(tmp_path)]) == 130
    assert "interrupted; the rows finished before it are in" in capsys.readouterr().err
    assert not (tmp_path / "scaling.png").exists()


def test_bench_accuracy_errors_are_named_and_failed_rows_shown(tmp_path, capsys, monkeypatch):
    from warpcontact import bench
    from warpcontact.solver import SolverError

    base = ["bench", "accuracy", "--points", "8", "--frames", "1", "--eps", "0.5", "--tolerances", "1e-6", "--precisions", "float64", "--out", str(tmp_path)]
    assert main([*base, "--balls", "16"]) == 2
    assert "error: balls: the rack has 15 balls besides the cue, got 16" in capsys.readouterr().err
    # A reference looser than the rows it judges was accepted (a probe, stop 65).
    assert main([*base, "--balls", "1", "--reference-tolerance", "1e-3"]) == 2
    assert "error: reference_tolerance: 0.001 is looser than the tightest tolerance measured (1e-10, of 1e-10 .. 1e-06); the reference must be at least as tight" in capsys.readouterr().err
    assert not (tmp_path / "accuracy.json").exists()
    run = bench._accuracy_run

    def failing(scene, controls, *, tolerance, **kwargs):
        if tolerance in (1e-12, 1e-6):  # the reference and the tolerance sweep's row
            raise SolverError("implicit step: no convergence after 500 Newton iterations")
        return run(scene, controls, tolerance=tolerance, **kwargs)

    monkeypatch.setattr(bench, "_accuracy_run", failing)
    assert main([*base, "--balls", "1"]) == 2
    assert "error: the reference run (brute force, --reference-tolerance 1e-12) failed: implicit step: no convergence" in capsys.readouterr().err
    assert main([*base, "--balls", "1", "--reference-tolerance", "1e-11", "--overwrite"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"tolerance\s+bsh\s+0.5\s+1e-06 .* implicit step: no convergence", out)
    rows = json.loads((tmp_path / "accuracy.json").read_text())["rows"]
    assert [r["sweep"] for r in rows] == ["reference", "eps", "eps", "tolerance", "precision"] and rows[3]["error"]
    assert re.search(r"precision\s+bsh\s+0.5\s+\S+\s+float64", out)  # the table had no precision column


def test_bench_accuracy_writes_results_and_plot(tmp_path):
    args = ["bench", "accuracy", "--balls", "1", "--points", "8", "--frames", "1", "--eps", "0.5", "2", "--tolerances", "1e-6", "--out", str(tmp_path)]
    assert main(args) == 0
    data = json.loads((tmp_path / "accuracy.json").read_text())
    assert data["module_load_seconds"] >= 0
    assert data["gap_m"] == 0.02 and data["speed_m_per_s"] == 1.0  # the strike, recorded nowhere before
    rows = data["rows"]
    assert [(r["sweep"], r["model"], r["eps"], r["tolerance"], r["leaf_precision"]) for r in rows] == [
        ("reference", "brute", None, 1e-12, "float64"),
        ("eps", "bsh", 0.5, 1e-10, "float64"),
        ("eps", "bsh", 2.0, 1e-10, "float64"),
        ("eps", "brute", None, 1e-10, "float64"),
        ("tolerance", "bsh", 0.5, 1e-6, "float64"),
        ("precision", "bsh", 0.5, 1e-10, "float64"),
        ("precision", "bsh", 0.5, 1e-10, "float32"),
    ]
    # Float32 plane searches finished in float64 leave the motion and the task gradient as
    # they are to the solvers' tolerances.
    float64, float32 = rows[-2:]
    assert float32["trajectory_deviation_max"] == pytest.approx(float64["trajectory_deviation_max"], abs=1e-9)
    assert float32["gradient_relative_error"] == pytest.approx(float64["gradient_relative_error"], abs=1e-6)
    assert rows[0]["trajectory_deviation_max"] == 0.0 and rows[0]["gradient_cosine"] == pytest.approx(1.0)
    for r in rows:
        assert r["error"] is None and r["forward_seconds"] > 0 and r["newton_iterations"] >= 1
        assert len(r["gradient"]) == 4 and -1.0 <= r["gradient_cosine"] <= 1.0
        assert r["trajectory_deviation_max"] >= 0 and 0 <= r["force_error_max"]
    # Where each converged: 1e-6 of the table's size is over the acceleration cap 1e-5 dt^2,
    # which rows above ~6e-9 all share (a probe, stop 62: 1e-4 to 1e-8 gave one row).
    dt = 0.04
    assert rows[4]["converged_step_m"] == pytest.approx(1e-5 * dt * dt, rel=1e-12)
    assert rows[1]["converged_step_m"] < rows[4]["converged_step_m"]
    assert _csv_rows(tmp_path / "accuracy.csv") == len(rows)
    assert (tmp_path / "accuracy.png").stat().st_size > 1000


@pytest.mark.parametrize(
    "argv, message",
    [
        (["demo", "--gaps", "-1"], "--gaps: must be a positive finite number, got -1"),
        (["demo", "--gaps", "x"], "--gaps: must be a positive finite number, got 'x'"),
        (["bench", "leaf", "--pairs", "0"], "--pairs: must be a whole number from 1 to 10,000,000, got 0"),
        (["simulate", "push", "--frames", "2.5"], "--frames: must be a whole number from 1 to 1,000,000, got '2.5'"),
        (["run", "push", "--model", "gb", "--seed", "-1"], "--seed: must be a whole number >= 0, got -1"),
        (["bench", "contact", "--eps", "nan"], "--eps: must be a positive finite number, got nan"),
        (["bench", "frame", "--frames", "0"], "--frames: must be a whole number from 1 to 1,000,000, got 0"),
        # Accepted before: a negative warm-up, a negative or NaN IPC support.
        (["bench", "frame", "--warmup", "-1"], "--warmup: must be a whole number from 0 to 2,147,483,647, got -1"),
        (["bench", "frame", "--brute-max-triangles", "-5"], "--brute-max-triangles: must be a whole number from 0 to 2,147,483,647, got -5"),
        (["bench", "contact", "--ipc-dhat", "-0.01"], "--ipc-dhat: must be a finite number >= 0, got -0.01"),
        (["bench", "contact", "--ipc-dhat", "nan"], "--ipc-dhat: must be a finite number >= 0, got nan"),
        (["bench", "accuracy", "--eps", "-1"], "--eps: must be a positive finite number, got -1"),
        # Found by a probe: numpy's MemoryError traceback (6.55 TiB), 12 GB and growing, frames
        # kept until the process was killed; a tolerance refused after the other rows were
        # written (naming "tolerance"); --points 3 refused as "num_points".
        (["bench", "leaf", "--pairs", "100000000000"], "--pairs: must be a whole number from 1 to 10,000,000, got 100000000000"),
        (["bench", "accuracy", "--points", "100000000"], "--points: must be a whole number from 4 to 100,000, got 100000000"),
        (["bench", "scaling", "--points", "18", "3"], "--points: must be a whole number from 4 to 100,000, got 3"),
        (["simulate", "push", "--frames", "99999999999"], "--frames: must be a whole number from 1 to 1,000,000, got 99999999999"),
        (["bench", "accuracy", "--tolerances", "1e-6", "1e300"], "--tolerances: must be a number in (0, 1), got 1e300"),
        (["bench", "accuracy", "--reference-tolerance", "1"], "--reference-tolerance: must be a number in (0, 1), got 1"),
        (["run", "push", "--out", ""], '--out: must name a folder ("." for the current one), got an empty name'),
        # A probe (stop 57): checked by the model only when its row came, after earlier rows
        # had replaced a previous run's; ipc's stiffness was named contact_stiffness.
        (["bench", "contact", "--eps", "0.5", "1e200"], "--eps: must lie in [1e-150, 1e+150] (its square and inverse must be representable), got 1e200"),
        (["bench", "accuracy", "--tolerance-eps", "1e200"], "--tolerance-eps: must lie in [1e-150, 1e+150]"),
        (["bench", "frame", "--ipc-stiffness", "1e-200"], "--ipc-stiffness: must lie in [1e-150, 1e+150]"),
        (["compare", "push", "--ipc-stiffness", "1e200"], "--ipc-stiffness: must lie in [1e-150, 1e+150]"),
        # A probe (stop 58): refused inside ipc, naming "dhat".
        (["bench", "contact", "--ipc-dhat", "1e7"], "--ipc-dhat: must be 0 or a distance of at most 1e+06 m, got 1e7"),
    ],
)
def test_bad_arguments_exit_with_usage_error(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_gaps_that_float64_positions_cannot_hold_are_refused_before_any_row(tmp_path, capsys):
    """Found by a probe: bench contact at --gaps 1e-17 placed the balls touching and wrote
    rows labelled 1e-17 (value ratio NaN, force errors as if all were well), and 1e300 failed
    only after the other gaps' rows were written; demo called 1e-300 unsolved pairs."""
    for gaps, message in ((["0.01", "1e-17"], "error: gaps: 1e-17 m rounds to 0 m beside 1 m of body, below what float64 positions resolve"), (["0.01", "1e300"], "error: gaps: 1e+300 m is beyond the 1e+27 m up to which leaf planes are solved")):
        assert main(["bench", "contact", "--gaps", *gaps, "--eps", "0.5", "--repeats", "1", "--ipc-dhat", "0", "--out", str(tmp_path / "c")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "c" / "contact.json").exists()
    assert main(["demo", "--gaps", "1.0", "1e-300", "--out", str(tmp_path / "d")]) == 2
    assert "error: --gaps: 1e-300 m rounds to 0 m beside 1 m of body" in capsys.readouterr().err
    # Beyond the leaf planes' reach: refused before any gap, as bench contact does (it was
    # "400 triangle pairs did not solve" after the finished gaps, an empty --out left behind).
    assert main(["demo", "--subdivisions", "0", "--gaps", "1.0", "1e28", "--out", str(tmp_path / "d2")]) == 2
    assert "error: --gaps: 1e+28 m is beyond the 1e+27 m up to which leaf planes are solved" in capsys.readouterr().err
    assert not (tmp_path / "d2").exists()


def test_bad_device_is_a_clear_error(tmp_path, capsys):
    assert main(["bench", "leaf", "--pairs", "10", "--device", "cuda:7", "--out", str(tmp_path)]) == 2
    assert "device" in capsys.readouterr().err


def test_a_refused_command_leaves_no_output_folder_it_created(tmp_path, capsys):
    """Found by a probe: run, simulate, compare and demo created --out (and its parents)
    before refusing a bad device or scene, leaving empty folders; a scene path that is a
    symlink loop ended in a traceback (RuntimeError: Symlink loop)."""
    (tmp_path / "loop.usda").symlink_to("loop.usda")
    (tmp_path / "kept").mkdir()
    for argv, message in (
        (["run", "push", "--device", "bogus", "--out", str(tmp_path / "new" / "run")], "device: 'bogus' is not available"),
        (["simulate", str(tmp_path / "loop.usda"), "--out", str(tmp_path / "new" / "sim")], "loop.usda: file not found"),
        (["simulate", str(tmp_path / "loop.usda"), "--out", str(tmp_path / "kept")], "loop.usda: file not found"),
    ):
        assert main(argv) == 2
        assert message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept", "loop.usda"]  # an existing folder stays


def test_an_output_folder_that_cannot_be_looked_at_is_an_error_not_a_traceback(tmp_path, monkeypatch, capsys):
    """Looking for the folders a command would create raised PermissionError outside the
    command's error handling (an --out inside a folder the user may not read; found by a
    review)."""
    locked = tmp_path / "locked"
    real_exists = Path.exists

    def exists(path, *args, **kwargs):
        if locked in (path, *path.parents) and path != locked:
            raise PermissionError(13, "Permission denied", str(path))
        return real_exists(path, *args, **kwargs)

    monkeypatch.setattr(Path, "exists", exists)
    assert main(["bench", "leaf", "--pairs", "4", "--out", str(locked / "x")]) in (1, 2)
    assert "Permission denied" in capsys.readouterr().err


SCENES = Path(__file__).resolve().parents[1] / "scenes"


def test_simulate_writes_trajectory_and_summary(tmp_path, capsys):
    if not SCENES.is_dir():
        pytest.skip("scenes/ not found next to tests/")
    args = ["simulate", str(SCENES / "push.usda"), "--frames", "3", "--out", str(tmp_path)]
    assert main(args) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"] == 3 and summary["newton_iterations_max"] >= 1
    assert set(summary["targets"]) == {"box"}
    stage = Usd.Stage.Open(str(tmp_path / "trajectory.usda"))
    assert stage.GetEndTimeCode() == 3
    assert main(args) == 2  # never overwrites without --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(args + ["--overwrite"]) == 0
    by_name = ["simulate", "push", "--frames", "1", "--out", str(tmp_path / "named")]
    assert main(by_name) == 0
    from warpcontact.scenes import shipped_scene

    assert json.loads((tmp_path / "named" / "summary.json").read_text())["scene"] == str(shipped_scene("push"))


def test_simulate_reads_a_usdz_package(tmp_path):
    """load_scene reads .usdz, but the CLI refused the name ("not a .usda file")."""
    from pxr import UsdUtils

    if not SCENES.is_dir():
        pytest.skip("scenes/ not found next to tests/")
    assert UsdUtils.CreateNewUsdzPackage(str(SCENES / "push.usda"), str(tmp_path / "push.usdz"))
    assert main(["simulate", str(tmp_path / "push.usdz"), "--frames", "1", "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "trajectory.usda").is_file()


def test_scene_names_are_read_whatever_the_case_of_their_suffix(tmp_path):
    # pxr opens "BALL.USDA"; the CLI refused it as "not a .usda file and not a shipped scene".
    if not SCENES.is_dir():
        pytest.skip("scenes/ not found next to tests/")
    (tmp_path / "PUSH.USDA").write_text((SCENES / "push.usda").read_text())
    assert main(["simulate", str(tmp_path / "PUSH.USDA"), "--frames", "1", "--out", str(tmp_path / "out")]) == 0


def test_simulate_writes_the_frames_before_a_failed_step(tmp_path, capsys, monkeypatch):
    """A step that fails (here the third) ends the simulation with its earlier frames written
    and the failure named in summary.json and on stderr, exit status 1."""
    from warpcontact.solver import ImplicitSolver, SolverError

    step, calls = ImplicitSolver.step, []

    def third_fails(error):
        def failing(self, *args, **kwargs):
            calls.append(1)
            if len(calls) == 3:
                raise error
            return step(self, *args, **kwargs)

        return failing

    monkeypatch.setattr(ImplicitSolver, "step", third_fails(SolverError("implicit step: no convergence after 500 Newton iterations")))
    assert main(["simulate", "push", "--frames", "5", "--out", str(tmp_path)]) == 1
    assert "error: the step from frame 2 to 3 failed: implicit step: no convergence after 500 Newton iterations; the outputs hold frames 0 to 2" in capsys.readouterr().err
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["stopped"] == {"frame": 2, "error": "implicit step: no convergence after 500 Newton iterations"}
    assert Usd.Stage.Open(str(tmp_path / "trajectory.usda")).GetEndTimeCode() == 2
    calls.clear()
    calls.extend([1, 1])  # the first step fails: the start alone is written
    assert main(["simulate", "push", "--frames", "5", "--out", str(tmp_path / "first")]) == 1
    summary = json.loads((tmp_path / "first" / "summary.json").read_text())
    assert summary["frames"] == 0 and summary["newton_iterations_mean"] is None and summary["stopped"]["frame"] == 0
    # A later step's ValueError (a state the simulation produced that a check refuses) lost
    # every frame, exit 2 (a probe, stop 58); the first step's is the scene's, an error.
    monkeypatch.setattr(ImplicitSolver, "step", third_fails(ValueError("poses: 1e+150 at index (0, 0) is beyond the +-1e+150 m")))
    calls.clear()
    assert main(["simulate", "push", "--frames", "5", "--out", str(tmp_path / "later")]) == 1
    assert json.loads((tmp_path / "later" / "summary.json").read_text())["stopped"] == {"frame": 2, "error": "poses: 1e+150 at index (0, 0) is beyond the +-1e+150 m"}
    calls.clear()
    calls.extend([1, 1])
    assert main(["simulate", "push", "--frames", "5", "--out", str(tmp_path / "start")]) == 2
    assert not (tmp_path / "start").exists()


def test_simulate_interrupted_by_hand_writes_the_frames_it_simulated(tmp_path, capsys, monkeypatch):
    """Ctrl-C used to end `simulate` with a traceback and nothing written."""
    from warpcontact.solver import ImplicitSolver

    interrupt_call(monkeypatch, ImplicitSolver, "step", 4)
    assert main(["simulate", "push", "--frames", "6", "--out", str(tmp_path)]) == 130
    assert "error: interrupted during the step from frame 3 to 4; the outputs hold frames 0 to 3" in capsys.readouterr().err
    assert json.loads((tmp_path / "summary.json").read_text())["stopped"] == {"frame": 3, "error": "interrupted"}
    assert Usd.Stage.Open(str(tmp_path / "trajectory.usda")).GetEndTimeCode() == 3


def test_simulate_interrupted_outside_the_step_keeps_its_frames(tmp_path, capsys, monkeypatch):
    """Only the step was guarded: Ctrl-C while the next state was allocated lost every frame.
    Here it comes after the fourth step returned, when its diagnostics are read: that frame
    was simulated and is kept."""
    from warpcontact.solver import ImplicitSolver

    real_step, calls = ImplicitSolver.step, []

    class InterruptedInfo:
        @property
        def iterations(self):
            raise KeyboardInterrupt

    def step(self, *args, **kwargs):
        info = real_step(self, *args, **kwargs)
        calls.append(1)
        return InterruptedInfo() if len(calls) == 4 else info

    monkeypatch.setattr(ImplicitSolver, "step", step)
    assert main(["simulate", "push", "--frames", "6", "--out", str(tmp_path)]) == 130
    assert json.loads((tmp_path / "summary.json").read_text())["stopped"] == {"frame": 4, "error": "interrupted"}
    assert Usd.Stage.Open(str(tmp_path / "trajectory.usda")).GetEndTimeCode() == 4


def test_a_command_interrupted_before_it_writes_leaves_no_folder(tmp_path, capsys, monkeypatch):
    """A probe: Ctrl-C while run started up (loading the scene) left the empty --out folder
    it had made; the benches already removed theirs. A folder with anything in it stays."""
    from warpcontact import io as wc_io

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(wc_io, "load_scene", interrupted)
    for command in (["run", "push", "--quick"], ["simulate", "push", "--frames", "2"]):
        out = tmp_path / command[0] / "new"
        assert main([*command, "--out", str(out)]) == 130
        assert not out.exists() and not out.parent.exists()
    monkeypatch.undo()
    from warpcontact.tasks import TaskProblem

    # Interrupted in its first Adam iteration, before a checkpoint: run and compare catch it
    # themselves (a review found the folder left there).
    monkeypatch.setattr(TaskProblem, "optimize", interrupted)
    for command in (["run", "push", "--quick"], ["compare", "push", "--quick", "--models", "gb"]):
        out = tmp_path / command[0] / "early"
        assert main([*command, "--out", str(out)]) == 130
        assert not out.exists() and not out.parent.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    assert main(["run", "push", "--quick", "--out", str(kept)]) == 130
    assert (kept / "notes.txt").read_text() == "mine"


def test_simulate_interrupted_while_writing_keeps_every_frame(tmp_path, capsys, monkeypatch):
    """Ctrl-C after the last step, while the outputs were written, ended with "interrupted"
    and no outputs at all: every simulated frame was lost."""
    import signal

    from warpcontact import io as wc_io

    real = wc_io.model_to_scene_poses

    def interrupted(*args, **kwargs):
        signal.raise_signal(signal.SIGINT)  # a real Ctrl-C, not a raised exception
        return real(*args, **kwargs)

    monkeypatch.setattr(wc_io, "model_to_scene_poses", interrupted)
    # As a terminal's Ctrl-C finds it, whatever started the tests (a job started with & by a
    # script ignores SIGINT, and this test failed there; that case is checked below).
    started_with = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert main(["simulate", "push", "--frames", "3", "--out", str(tmp_path)]) == 130
        assert "interrupted while the outputs were written" in capsys.readouterr().err
        summary = json.loads((tmp_path / "summary.json").read_text())
        assert summary["frames"] == 3 and "stopped" not in summary
        assert Usd.Stage.Open(str(tmp_path / "trajectory.usda")).GetEndTimeCode() == 3
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # given back
        # A process that ignores SIGINT (a job started with & by a script) still ignores it: it
        # ended with "interrupted" and exit status 130.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        assert main(["simulate", "push", "--frames", "1", "--out", str(tmp_path / "ignored")]) == 0
        assert "interrupted" not in capsys.readouterr().err
    finally:
        signal.signal(signal.SIGINT, started_with)


def test_a_write_refused_by_the_system_is_an_error_line(tmp_path, capsys, monkeypatch):
    """A folder that passes the writability check can still refuse the write (sysfs as root,
    a full disk): the run ended in a traceback."""
    from warpcontact import io as wc_io

    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / "trajectory.usda"))

    monkeypatch.setattr(wc_io, "export_trajectory", refused)
    assert main(["simulate", "push", "--frames", "1", "--out", str(tmp_path)]) == 1
    assert "error: [Errno 13] Permission denied" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv",
    [["demo", "--gaps", "0.1"], ["simulate", "push", "--frames", "1"], ["bench", "leaf", "--pairs", "2"], ["bench", "scaling", "--points", "18"], ["run", "push", "--quick", "--iters", "1"], ["compare", "push", "--quick", "--iters", "1", "--models", "sdrs"]],
)
def test_commands_check_their_output_folder_before_any_work(tmp_path, capsys, argv):
    """An uncreatable folder, a file in its place, and earlier results (kept unless
    --overwrite) all stop a command before it starts."""
    blocker = tmp_path / "file"
    blocker.write_text("keep")
    assert main(argv + ["--out", str(blocker / "sub")]) == 2
    assert "cannot create the output folder" in capsys.readouterr().err
    assert main(argv + ["--out", str(blocker)]) == 2
    assert "output path exists and is not a folder" in capsys.readouterr().err
    assert blocker.read_text() == "keep"
    out = tmp_path / "out"
    assert main(argv + ["--out", str(out)]) == 0
    written = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert main(argv + ["--out", str(out)]) == 2
    assert "holds an earlier run's results (use --overwrite)" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == written
    assert main(argv + ["--out", str(out), "--overwrite"]) == 0


@pytest.mark.parametrize(
    "argv, earlier",
    [
        (["simulate", "billiards", "--frames", "1"], ("metrics.json", "trajectory.usda", "convergence.png")),
        (["run", "push", "--quick", "--iters", "1"], ("trajectory.usda", "summary.json")),
    ],
)
def test_overwriting_a_shared_name_does_not_mix_two_commands_results(tmp_path, capsys, argv, earlier):
    """run and simulate both write trajectory.usda: a simulate --overwrite into a run's
    folder replaced it and left the run's metrics.json and convergence.png beside another
    scene's trajectory (a run, simulate's summary.json)."""
    for name in earlier:
        (tmp_path / name).write_text(f"earlier {name}")
    assert main(argv + ["--out", str(tmp_path), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'trajectory.usda'} belongs with" in err and "choose another --out" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(earlier)
    assert all((tmp_path / name).read_text() == f"earlier {name}" for name in earlier)


def test_simulate_refuses_an_unfinished_runs_folder(tmp_path, capsys):
    """A simulate into the folder of an interrupted run (its checkpoint.npz) wrote its
    trajectory there, and the run's own --resume, with or without --overwrite, was then
    refused: the run could not be continued in place (a probe, stop 63)."""
    (tmp_path / "checkpoint.npz").write_bytes(b"an unfinished run")
    for extra in ([], ["--overwrite"]):
        assert main(["simulate", "push", "--frames", "1", "--out", str(tmp_path), *extra]) == 2
        assert "an unfinished run's progress" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.npz"]


def test_simulate_keeps_its_frames_when_stdout_fails_and_names_its_scene_absolutely(tmp_path, capsys, monkeypatch):
    """A progress line that could not be written (a full disk under a redirected stdout) ended
    the run with every frame lost; and summary.json named the scene as typed, relative to
    wherever the command ran, beside a trajectory that records it absolutely (a probe, stop
    63)."""
    import io as std_io
    import shutil

    from warpcontact.scenes import shipped_scene

    class FullDisk(std_io.StringIO):
        def write(self, text):
            if text.startswith("  frame"):  # the progress lines, while the disk is full
                raise OSError(28, "No space left on device")
            return super().write(text)

    shutil.copy(shipped_scene("push"), tmp_path / "mine.usda")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "stdout", FullDisk())
    assert main(["simulate", "mine.usda", "--frames", "2", "--out", "out"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["scene"] == str((tmp_path / "mine.usda").resolve())
    assert Usd.Stage.Open(str(tmp_path / "out" / "trajectory.usda")).GetEndTimeCode() == 2


@pytest.mark.parametrize("command", [["run", "--quick", "--iters", "1"], ["simulate", "--frames", "1"]])
def test_a_scene_that_is_one_of_the_outputs_is_refused(tmp_path, monkeypatch, capsys, command):
    """A scene saved as OUT/trajectory.usda was called "an earlier run's results", and with
    --overwrite the run replaced it with its trajectory (the next run found no bodies)."""
    from warpcontact.scenes import shipped_scene

    scene = tmp_path / "trajectory.usda"
    scene.write_bytes(shipped_scene("push").read_bytes())
    original = scene.read_bytes()
    monkeypatch.chdir(tmp_path)
    for given in (str(scene), "trajectory.usda"):
        assert main([command[0], given, *command[1:], "--out", str(tmp_path), "--overwrite"]) == 2
        assert "the input scene is this command's output trajectory.usda" in capsys.readouterr().err
    assert scene.read_bytes() == original


def test_shipped_scenes_are_found_from_any_folder(tmp_path, monkeypatch, capsys):
    """A task name means the scene installed with the package, not ./scenes of the caller."""
    from warpcontact.scenes import SCENE_NAMES, shipped_scene

    monkeypatch.chdir(tmp_path)
    for name in SCENE_NAMES:
        path = cli._resolve_scene_path(name)
        assert path == shipped_scene(name) and path.is_file() and path.is_absolute()
    assert io.load_scene(cli._resolve_scene_path("push")).task.name == "push"
    assert main(["list"]) == 0
    assert str(shipped_scene("gather")) in capsys.readouterr().out
    # Misspelt, a name got the whole list and no hint (a probe).
    for misspelt, meant in (("pushh", "push"), ("psuh", "push"), ("Billiard", "billiards")):
        with pytest.raises(ValueError, match=rf"'{misspelt}': not a USD file \(\.usda, \.usd, \.usdc, \.usdz\) and not a shipped scene \(known: .*\); did you mean '{meant}'\?"):
            cli._resolve_scene_path(misspelt)
    with pytest.raises(ValueError, match=r"'zzzz': not a USD file \(\.usda, \.usd, \.usdc, \.usdz\) and not a shipped scene \(known: [^)]*\)$"):
        cli._resolve_scene_path("zzzz")
    assert main(["bench", "frame", "--scenes", "push", "--scene-dir", str(tmp_path), "--frames", "1", "--out", str(tmp_path / "b")]) == 2
    assert f"{tmp_path / 'push.usda'} not found" in capsys.readouterr().err
    # Any NAME.usda of the folder, as its help says (a probe: only the shipped names loaded).
    from warpcontact import bench

    (tmp_path / "custom.usda").write_bytes(shipped_scene("push").read_bytes())
    assert [b.name for b in bench.frame_scene("custom", scene_dir=tmp_path).bodies] == ["ground", "box", "rod"]
    with pytest.raises(ValueError, match=rf"'other' is not a scene name \(.*\), a NAME.usda in {re.escape(str(tmp_path))}, peer_billiards_T"):
        bench.frame_scene("other", scene_dir=tmp_path)


def test_simulate_reports_bad_scene_paths(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "missing.usda"), "--out", str(tmp_path)]) == 2
    assert "file not found" in capsys.readouterr().err


def _two_ball_task(tmp_path) -> Path:
    """A cue ball (initial vx, vy optimised) 0.5 m from a target ball in space, as a .usda."""
    import numpy as np
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=0, radius=0.5)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    cue = io.BodySpec("cue", "/World/cue", V, F, np.array([0, 0, 0, 0, 0, 0, 1.0]), density=100.0, control_dofs=("vx", "vy"))
    target = io.BodySpec("target", "/World/target", V, F, np.array([1.5, 0.3, 0, 0, 0, 0, 1.0]), density=100.0)
    target.target_position, target.target_tolerance = np.array([3.0, 0.8, 0.0]), 0.1
    scene = io.Scene(
        bodies=[cue, target],
        gravity=np.zeros(3),
        settings=io.SimulationSettings(time_step=0.04, frames=3, contact_stiffness=1e-4),
        task=io.TaskSpec(name="two_balls", control="initial_state", horizon=3, iterations=1, learning_rate=0.3),
    )
    path = tmp_path / "two_balls.usda"
    io.save_scene(scene, path)
    return path


def test_ipc_stiffness_reaches_the_ipc_model_only(tmp_path, monkeypatch):
    """run/compare give ipc --ipc-stiffness as its barrier stiffness (the scenes' mu is sized
    for ours and far too soft for IPC's barrier); the other models keep the scene's mu."""
    from warpcontact.tasks import TaskProblem

    seen = {}
    real = TaskProblem.optimize

    def optimize(self, **kwargs):
        seen[self.scene.settings.contact_mode] = float(self.model.contact_stiffness.numpy()[0])
        return real(self, **kwargs)

    monkeypatch.setattr(TaskProblem, "optimize", optimize)
    scene = _two_ball_task(tmp_path)
    assert main(["run", str(scene), "--model", "ipc", "--ipc-stiffness", "1234", "--iters", "1", "--out", str(tmp_path / "run")]) == 0
    assert seen == {"ipc": 1234.0}
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["ipc_stiffness"] == 1234.0
    seen.clear()
    assert main(["compare", str(scene), "--models", "ours,ipc", "--iters", "1", "--out", str(tmp_path / "cmp")]) == 0
    assert seen == {"bsh": 1e-4, "ipc": cli.IPC_TASK_STIFFNESS}
    assert json.loads((tmp_path / "cmp" / "compare.json").read_text())["ipc_stiffness"] == cli.IPC_TASK_STIFFNESS
    with pytest.raises(SystemExit):
        main(["run", str(scene), "--model", "ipc", "--ipc-stiffness", "0", "--out", str(tmp_path / "bad")])


def test_convergence_plots_use_a_log_axis_only_across_decades():
    """Found by a probe: stalled baselines at 6.21 beside ours at 6.2100005 drew a log axis
    whose every tick read "6.21x10^0"."""
    from warpcontact.cli import _loss_axis_scale

    assert _loss_axis_scale({"ours": [6.2100005, 6.2100003], "ipc": [6.21, 6.21]}) == "linear"
    assert _loss_axis_scale({"ours": [6.21, 0.5, 0.0], "ipc": [6.21]}) == "log"
    assert _loss_axis_scale({"ours": [0.0, 0.0], "ipc": []}) is None
    assert _loss_axis_scale({}) is None


def test_bench_module_load_time_covers_the_traversal_round_kernels(monkeypatch):
    """Found by a probe: the traversal round kernels are modules of their own, which compiled
    untimed inside the first model's build (7 s on a cold cache) and were missing from
    module_load_seconds."""
    import warp as wp

    from warpcontact import bench
    from warpcontact._runtime import resolve_device
    from warpcontact.kernels import traversal

    loaded = []
    real = wp.load_module
    monkeypatch.setattr(wp, "load_module", lambda module, device=None: loaded.append(module) or real(module, device=device))
    bench._load_kernel_modules(resolve_device("cpu"))
    names = [getattr(module, "name", getattr(module, "__name__", "")) for module in loaded]
    for budget in (traversal.HOST_SIZED_VISIT_BUDGET, traversal.SYNC_FREE_VISIT_BUDGET):
        assert traversal.traverse_round_kernel(budget).module.name in names
    assert "warpcontact.kernels.leaf" in names


def test_bench_library_runners_refuse_bad_settings_before_any_row(tmp_path):
    """The CLI checks eps, ipc_dhat and ipc_stiffness when it parses; called from Python, the
    runners failed only when the bad value's row came, after the rows before it had replaced
    an earlier run's files (a probe, stop 58)."""
    from warpcontact import bench

    earlier = tmp_path / "contact.json"
    earlier.write_text('{"earlier": true}')
    calls = [
        ("eps: must be positive and finite, got -1.0", lambda: bench.run_contact_benchmark(eps_values=[0.5, -1.0], gaps=[1e-2], subdivisions=0, repeats=1, device="cpu", out_dir=tmp_path, ipc_dhat=None)),
        ("ipc_dhat: must be a positive finite distance", lambda: bench.run_contact_benchmark(eps_values=[0.5], gaps=[1e-2], subdivisions=0, repeats=1, device="cpu", out_dir=tmp_path, ipc_dhat=-1.0)),
        ("eps: must be positive and finite, got -1.0", lambda: bench.run_scaling_benchmark(points_per_ball=[12], eps=-1.0, brute_max_triangles=0, repeats=1, device="cpu", out_dir=tmp_path)),
        ("ipc_stiffness: must lie in", lambda: bench.run_frame_benchmark(scenes=["billiards_512"], models=["ipc"], frames=1, warmup=0, ipc_stiffness=1e300, device="cpu", out_dir=tmp_path)),
        ("eps: must be positive and finite, got nan", lambda: bench.run_accuracy_benchmark(eps_values=[float("nan")], device="cpu", out_dir=tmp_path)),
    ]
    for message, call in calls:
        with pytest.raises(ValueError, match=message):
            call()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["contact.json"] and earlier.read_text() == '{"earlier": true}'


def test_bench_sweeps_measure_a_value_given_twice_once(tmp_path):
    """``--eps 0.5 0.5`` measured and wrote 0.5 twice (a probe, stop 58)."""
    args = ["bench", "contact", "--eps", "0.5", "0.5", "--gaps", "0.1", "0.1", "--subdivisions", "0", "--repeats", "1", "--ipc-dhat", "0", "--out", str(tmp_path / "c")]
    assert main(args) == 0
    rows = json.loads((tmp_path / "c" / "contact.json").read_text())["rows"]
    assert [(r["scene"], r["mode"]) for r in rows] == [("two_icospheres", "brute"), ("two_icospheres", "bsh"), ("rack16", "brute"), ("rack16", "bsh")]
    assert main(["bench", "scaling", "--points", "8", "8", "--repeats", "1", "--out", str(tmp_path / "s")]) == 0
    assert [r["mode"] for r in json.loads((tmp_path / "s" / "scaling.json").read_text())["rows"]] == ["bsh", "brute"]


def test_python_dash_m_runs_the_command(tmp_path):
    """``python -m warpcontact`` said the package cannot be executed directly (a probe). Run
    outside the repository: there ``-m`` would find its source tree first, whose kernels the
    install maps into the package."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "warpcontact", "list"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "push" in done.stdout and "billiards" in done.stdout



def test_a_ctrl_c_while_trimesh_imports_is_not_lost(tmp_path):
    """trimesh's optional imports catch every exception, KeyboardInterrupt included: a Ctrl-C
    in a command's first ~0.3 s was lost, and the command ran on and replaced its earlier
    results (a probe, stop 64). A stand-in trimesh that receives SIGINT while importing and
    swallows it as trimesh does, then hands over to the real one: importing the package
    ends in the interruption instead of going on."""
    import subprocess
    import sys

    (tmp_path / "trimesh").mkdir()
    (tmp_path / "trimesh" / "__init__.py").write_text(
        "import importlib, os, signal, sys, time\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    time.sleep(1.0)\n"
        "except BaseException:\n"
        "    pass\n"
        "here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))\n"
        "sys.path[:] = [p for p in sys.path if os.path.abspath(p or '.') != here]\n"
        "del sys.modules['trimesh']\n"
        "sys.modules['trimesh'] = importlib.import_module('trimesh')\n"
    )
    script = "import signal; signal.signal(signal.SIGINT, signal.default_int_handler)\nimport warpcontact\nprint('ran on')"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert "ran on" not in done.stdout and "KeyboardInterrupt" in done.stderr, (done.stdout, done.stderr)


def test_a_commands_warnings_print_on_one_line(tmp_path):
    """The package's warnings printed its source file and line, then that line of code
    ("warpcontact/cli.py:214: UserWarning: ..." and "scene = io.load_scene(scene_path)") to a
    user who wrote no code (a probe, stop 64)."""
    import subprocess
    import sys

    text = (Path(__file__).resolve().parents[1] / "scenes" / "push.usda").read_text()
    damped = text.replace("custom double warpcontact:pd:kpAngular", "float physxRigidBody:angularDamping = 0.05\n        custom double warpcontact:pd:kpAngular", 1)
    assert damped != text
    scene = tmp_path / "damped.usda"
    scene.write_text(damped)
    command = [sys.executable, "-m", "warpcontact", "simulate", str(scene), "--frames", "1", "--out", str(tmp_path / "sim")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    line = next(line for line in done.stderr.splitlines() if "not modelled" in line)
    assert line.startswith(f"warning: {scene}: not modelled, so ignored: ") and "angularDamping 0.05" in line, done.stderr
    assert "UserWarning" not in done.stderr and "load_scene(" not in done.stderr, done.stderr


def test_a_reader_that_closes_the_pipe_early_loses_nothing(tmp_path):
    """A probe at stop 61: `simulate ... | head -1` ended with "error: [Errno 32] Broken pipe"
    and no outputs (the progress line's write raised in the frame loop), and `list | head -1`
    exited 1. The command now finishes, writes its outputs and exits 0."""
    import subprocess
    import sys

    command = [sys.executable, "-m", "warpcontact", "simulate", "push", "--frames", "30", "--out", str(tmp_path / "sim")]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path)
    process.stdout.readline()
    process.stdout.close()  # as head does once it has its line
    _, errors = process.communicate(timeout=300)
    assert process.returncode == 0, errors.decode()
    assert (tmp_path / "sim" / "trajectory.usda").is_file() and json.loads((tmp_path / "sim" / "summary.json").read_text())["frames"] == 30
    assert b"Broken pipe" not in errors


def test_a_set_of_results_is_replaced_whole_when_a_rename_fails(tmp_path, monkeypatch):
    """A rename that failed part way (a trajectory.usda that had become a folder) left the new
    metrics.json beside no trajectory, which the --resume the error advised then refused as an
    earlier run's results (a probe, stop 65)."""
    from warpcontact import _files

    names = ("metrics.json", "trajectory.usda", "convergence.png")
    for name in names[:2]:
        (tmp_path / name).write_text(f"earlier {name}")
    real_replace = os.replace

    def failing_replace(source, target):
        if Path(target).name == "trajectory.usda" and Path(source).parent.name.startswith(".warpcontact-tmp"):
            raise OSError(28, "No space left on device")
        return real_replace(source, target)

    monkeypatch.setattr(_files.os, "replace", failing_replace)
    with pytest.raises(OSError, match="No space left"):
        with _files.replace_files(tmp_path, names) as staged:
            for name in names:
                (staged / name).write_text(f"new {name}")
    monkeypatch.undo()
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == {name: f"earlier {name}" for name in names[:2]}
    # A folder where a result goes is refused before anything moves, and kept whole.
    (tmp_path / "trajectory.usda").unlink()
    (tmp_path / "trajectory.usda").mkdir()
    (tmp_path / "trajectory.usda" / "keep").write_text("kept")
    with pytest.raises(IsADirectoryError, match=r"trajectory.usda: not a file \(a folder, or another kind of entry\) where a result file goes; remove or rename it, or choose another --out"):
        with _files.replace_files(tmp_path, names) as staged:
            for name in names:
                (staged / name).write_text(f"new {name}")
    assert (tmp_path / "metrics.json").read_text() == "earlier metrics.json" and (tmp_path / "trajectory.usda" / "keep").read_text() == "kept"
    (tmp_path / "trajectory.usda" / "keep").unlink()
    (tmp_path / "trajectory.usda").rmdir()
    # A rollback that fails too keeps the earlier files where they were moved aside, and says
    # where (deleted with the staging folder, they were lost; a review, stop 65).
    (tmp_path / "trajectory.usda").write_text("earlier trajectory.usda")
    failed = []

    def failing_twice(source, target):
        if Path(target).name == "trajectory.usda" and not failed:
            failed.append("move in")
            raise OSError(28, "No space left on device")
        if Path(source).parent.name == ".earlier" and len(failed) == 1:
            failed.append("restore")
            raise OSError(5, "Input/output error")
        return real_replace(source, target)

    monkeypatch.setattr(_files.os, "replace", failing_twice)
    with pytest.raises(OSError, match=r"replacing the results failed \(OSError\(28, 'No space left on device'\)\), and so did putting back metrics.json: the earlier files are kept in .*warpcontact-earlier-results-\d+$") as failure:
        with _files.replace_files(tmp_path, names) as staged:
            for name in names:
                (staged / name).write_text(f"new {name}")
    monkeypatch.undo()
    kept = Path(str(failure.value).rsplit("kept in ", 1)[1])
    assert (kept / "metrics.json").read_text() == "earlier metrics.json" and (tmp_path / "trajectory.usda").read_text() == "earlier trajectory.usda"
    assert kept.parent == tmp_path and not list(tmp_path.glob(".warpcontact-tmp*"))
    import shutil

    shutil.rmtree(kept)
    (tmp_path / "metrics.json").write_text("earlier metrics.json")
    # Replaced: a name the block did not write is left without a file.
    with _files.replace_files(tmp_path, names) as staged:
        (staged / "metrics.json").write_text("new metrics.json")
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == {"metrics.json": "new metrics.json"}
