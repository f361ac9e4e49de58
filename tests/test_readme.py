"""The README's Python examples run as written."""

import re
import runpy
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_examples_run(tmp_path, monkeypatch):
    if not README.exists():  # installed-package test runs without the source tree
        pytest.skip("README.md not found next to tests/")
    # Outside the checkout, as a user runs them: "scenes/push.usda" was found only from its root.
    monkeypatch.chdir(tmp_path)
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    # Warp reads kernel source with inspect, so the examples must live in a real file.
    script = tmp_path / "readme_examples.py"
    script.write_text("\n".join(blocks))
    namespace = runpy.run_path(str(script))
    assert namespace["out"].ok
    assert namespace["loss"].numpy()[0] > 0
    # The puck reaches the crate: the loss depends on the initial velocity.
    assert abs(namespace["velocity"].grad.numpy()[1, 0]) > 1e-3


SCENE_FORMAT = Path(__file__).resolve().parents[1] / "docs" / "scene_format.md"


def test_the_scene_format_names_every_attribute_and_its_example_is_a_task(tmp_path):
    """docs/scene_format.md is the reference for writing a scene: it names every
    warpcontact: attribute the loader reads and no other, and its minimal task loads and
    starts at the loss its goal gives (a probe at stop 64 could write a working scene only by
    copying a shipped one: the attributes were listed in io.py's docstring alone)."""
    if not SCENE_FORMAT.exists():
        pytest.skip("docs/scene_format.md not found next to tests/")
    import numpy as np

    from warpcontact import io
    from warpcontact.tasks import TaskProblem, TaskSettings

    text = SCENE_FORMAT.read_text()
    documented = set(re.findall(r"warpcontact:([A-Za-z]+(?::[A-Za-z]+)*)", text))
    read = set(io._SCENE_PRIM_NAMES) | set(io._BODY_PRIM_NAMES)
    assert documented == read, (sorted(read - documented), sorted(documented - read))
    scene_path = tmp_path / "my_push.usda"
    scene_path.write_text(re.search(r"```usda\n(.*?)```", text, re.S).group(1))
    scene = io.load_scene(scene_path)
    problem = TaskProblem(scene, settings=TaskSettings.from_task(scene, quick=True))
    loss, grad, _ = problem.rollout(problem.initial_values(8), problem.start, 8)
    # The box 0.5 m from its goal, 0.1 m tolerance: 0.5^2 - 0.1^2, plus its 1 mm above it.
    assert loss == pytest.approx(0.24, abs=1e-5) and np.isfinite(grad).all()
