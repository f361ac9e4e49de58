"""CLI commands run end to end on tiny cases and write well-formed output."""

import json
from pathlib import Path

import pytest
from pxr import Usd

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
    assert data["num_pairs"] == 200 and data["fraction_ok"] == 1.0
    assert data["solves_per_second_value"] > 0 and data["solves_per_second_value_grad_hessian"] > 0
    assert 1 <= data["mean_newton_iterations"] <= data["max_newton_iterations"] <= 100


def test_bench_contact_writes_results_and_plot(tmp_path):
    args = ["bench", "contact", "--eps", "0.5", "--gaps", "0.1", "--subdivisions", "0", "--repeats", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    data = json.loads((tmp_path / "contact.json").read_text())
    rows = data["rows"]
    assert {(r["scene"], r["mode"]) for r in rows} == {(s, m) for s in ("two_icospheres", "rack16") for m in ("brute", "bsh")}
    for r in rows:
        assert r["median_seconds"] > 0
        if r["mode"] == "brute":
            assert r["force_error_max"] == 0.0 and r["num_far"] == 0
        else:
            assert r["num_far"] + r["num_blend"] + r["num_leaf"] > 0
            assert 0 < r["force_cosine_min"] <= 1.0 + 1e-12
    assert (tmp_path / "contact.png").stat().st_size > 1000


def test_bench_scaling_writes_results(tmp_path):
    assert main(["bench", "scaling", "--points", "8", "12", "--repeats", "1", "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "scaling.json").read_text())["rows"]
    assert [(r["triangles"], r["mode"]) for r in rows] == [(192, "bsh"), (192, "brute"), (320, "bsh"), (320, "brute")]
    assert all(r["median_seconds"] > 0 for r in rows)
    assert (tmp_path / "scaling.png").stat().st_size > 1000


@pytest.mark.parametrize("argv", [["demo", "--gaps", "-1"], ["bench", "leaf", "--pairs", "0"], ["bench", "contact", "--eps", "nan"]])
def test_bad_arguments_exit_with_usage_error(argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2


def test_bad_device_is_a_clear_error(tmp_path, capsys):
    assert main(["bench", "leaf", "--pairs", "10", "--device", "cuda:7", "--out", str(tmp_path)]) == 2
    assert "device" in capsys.readouterr().err


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


def test_simulate_reports_bad_scene_paths(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "missing.usda"), "--out", str(tmp_path)]) == 2
    assert "file not found" in capsys.readouterr().err
