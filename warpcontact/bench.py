"""Benchmarks that write their results to files (never timed tests)."""

import json
import platform
import time
from pathlib import Path

import numpy as np
import warp as wp

from .contact import ContactModel
from .kernels import leaf as leaf_kernels
from ._runtime import resolve_device
from .leaf import DEFAULT_MAX_ITERATIONS

__all__ = ["leaf_benchmark_pairs", "run_leaf_benchmark", "contact_benchmark_scenes", "run_contact_benchmark", "run_scaling_benchmark"]


def leaf_benchmark_pairs(num_pairs: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Disjoint triangle pairs of unit size, their gaps log-uniform in [1e-6, 1e2] (m).

    Each pair is a random triangle A above a random triangle B whose highest vertex is
    ``gap`` below A's lowest, so every pair is separated and the mix spans near contact
    (many Newton iterations) to far field (few).
    """
    rng = np.random.default_rng(seed)
    A = rng.uniform(-0.5, 0.5, size=(num_pairs, 3, 3))
    B = rng.uniform(-0.5, 0.5, size=(num_pairs, 3, 3))
    gaps = 10.0 ** rng.uniform(-6, 2, size=num_pairs)
    lift = B[:, :, 2].max(axis=1) - A[:, :, 2].min(axis=1) + gaps
    A[:, :, 2] += lift[:, None]
    return A, B


def optional_pyplot():
    """matplotlib.pyplot with a file backend, or None without matplotlib (plots are optional)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def _write_results(out_dir: Path, name: str, device, repeats: int, fields: dict) -> dict:
    """Write out_dir/NAME.json with the common header (benchmark, device, host, date, repeats)."""
    payload = {
        "benchmark": name,
        "device": str(device),
        "device_name": device.name,
        "host": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d"),
        "repeats": repeats,
        **fields,
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{name}.json").write_text(json.dumps(payload, indent=2) + "\n")
    return payload


def _median_seconds(fn, repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return float(np.median(samples))


def run_leaf_benchmark(*, num_pairs: int, repeats: int, device, out_dir: Path, seed: int = 0) -> dict:
    """Time batched leaf solves (value only, and value + gradient + Hessian); write leaf.json."""
    dev = resolve_device(device)
    A, B = leaf_benchmark_pairs(num_pairs, seed=seed)
    with wp.ScopedDevice(dev):
        tri_a = wp.array(A, dtype=wp.mat33d)
        tri_b = wp.array(B, dtype=wp.mat33d)
        value = wp.empty(num_pairs, dtype=wp.float64)
        plane = wp.empty(num_pairs, dtype=wp.vec4d)
        status = wp.empty(num_pairs, dtype=wp.int32)
        iterations = wp.empty(num_pairs, dtype=wp.int32)
        grad = wp.empty((num_pairs, 6), dtype=wp.vec3d)
        hess = wp.empty((num_pairs, 6, 6), dtype=wp.mat33d)

        def launch(derivatives: bool):
            wp.launch(
                leaf_kernels.leaf_potential_kernel,
                dim=num_pairs,
                inputs=[tri_a, tri_b, DEFAULT_MAX_ITERATIONS, derivatives],
                outputs=[value, plane, status, iterations, grad, hess],
            )
            wp.synchronize_device()

        compile_start = time.perf_counter()
        wp.load_module(leaf_kernels, device=dev)
        compile_seconds = time.perf_counter() - compile_start
        launch(True)  # warm-up, excluded
        value_only = _median_seconds(lambda: launch(False), repeats)
        full = _median_seconds(lambda: launch(True), repeats)
    iters = iterations.numpy()
    ok = status.numpy() == 0
    return _write_results(out_dir, "leaf", dev, repeats, {
        "num_pairs": num_pairs,
        "module_load_seconds": compile_seconds,
        "median_seconds_value": value_only,
        "median_seconds_value_grad_hessian": full,
        "solves_per_second_value": num_pairs / value_only,
        "solves_per_second_value_grad_hessian": num_pairs / full,
        "mean_newton_iterations": float(iters.mean()),
        "max_newton_iterations": int(iters.max()),
        "fraction_ok": float(ok.mean()),
    })


def _icosphere(subdivisions: int, radius: float):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(sphere.vertices, dtype=np.float64), np.asarray(sphere.faces, dtype=np.int64)


def _identity_poses(positions) -> np.ndarray:
    poses = np.zeros((len(positions), 7))
    poses[:, :3] = positions
    poses[:, 6] = 1.0
    return poses


def rack_positions(*, radius: float, gap: float) -> np.ndarray:
    """Centres of a 15-ball triangle rack (gap ``gap`` between neighbours) plus a cue ball, in the z = radius plane."""
    spacing = 2 * radius + gap
    centres = []
    for row in range(5):
        for k in range(row + 1):
            centres.append([row * spacing * np.sqrt(3) / 2, (k - row / 2) * spacing, radius])
    centres.append([-6 * spacing, 0.0, radius])
    return np.array(centres)


def contact_benchmark_scenes(*, subdivisions: int, gaps) -> list[dict]:
    """Two icospheres and a 16-ball rack, each at the given surface gaps (m); balls of radius 0.5 m."""
    ball = _icosphere(subdivisions, 0.5)
    scenes = []
    for gap in gaps:
        two = _identity_poses([[0.0, 0.0, 0.0], [1.0 + gap, 0.0, 0.0]])
        two[1, 3:] = [0.0, 0.0, np.sin(0.35), np.cos(0.35)]  # break the symmetry of the pair
        scenes.append({"scene": "two_icospheres", "gap": gap, "meshes": [ball, ball], "poses": two})
        scenes.append({"scene": "rack16", "gap": gap, "meshes": [ball] * 16, "poses": _identity_poses(rack_positions(radius=0.5, gap=gap))})
    return scenes


def _force_errors(grad: np.ndarray, reference: np.ndarray, body_radius: np.ndarray) -> dict:
    """Errors of per-body net forces and torques (-grad) against the reference.

    Errors are normalised by the largest reference force in the scene (torques by that force
    times each body's bounding radius), since bodies whose reference force nearly cancels by
    symmetry make per-body relative errors meaningless; direction cosines are taken over
    bodies carrying at least 1% of that force.
    """
    f, f_ref = -grad[:, :3], -reference[:, :3]
    t, t_ref = -grad[:, 3:], -reference[:, 3:]
    scale = np.linalg.norm(f_ref, axis=1).max()
    force_err = np.linalg.norm(f - f_ref, axis=1) / scale
    torque_err = np.linalg.norm(t - t_ref, axis=1) / (scale * body_radius)
    loaded = np.linalg.norm(f_ref, axis=1) >= 0.01 * scale
    cosine = np.einsum("ij,ij->i", f[loaded], f_ref[loaded]) / (
        np.linalg.norm(f[loaded], axis=1) * np.linalg.norm(f_ref[loaded], axis=1)
    )
    return {
        "force_error_median": float(np.median(force_err)),
        "force_error_max": float(force_err.max()),
        "force_cosine_min": float(cosine.min()),
        "torque_error_max": float(torque_err.max()),
    }


def run_contact_benchmark(
    *, eps_values, gaps, subdivisions: int, repeats: int, device, out_dir: Path
) -> list[dict]:
    """Time per evaluate (value + gradient + Hessian) and force/torque error against brute force.

    Writes contact.json and, when matplotlib is installed, contact.png (time vs error).
    """
    dev = resolve_device(device)
    rows = []
    for scene in contact_benchmark_scenes(subdivisions=subdivisions, gaps=gaps):
        reference = None
        for mode, eps in [("brute", None)] + [("bsh", e) for e in eps_values]:
            model = ContactModel(scene["meshes"], mode=mode, eps=eps or 1.0, device=dev)
            result = model.evaluate(scene["poses"])  # warm-up: compile and size buffers
            seconds = _median_seconds(lambda: model.evaluate(scene["poses"]), repeats)
            if reference is None:
                reference = result
            radius = np.array([np.linalg.norm(v, axis=1).max() for v, _ in scene["meshes"]])
            rows.append(
                {
                    "scene": scene["scene"],
                    "gap": scene["gap"],
                    "triangles": int(sum(len(f) for _, f in scene["meshes"])),
                    "mode": mode,
                    "eps": eps,
                    "median_seconds": seconds,
                    "num_far": result.num_far,
                    "num_blend": result.num_blend,
                    "num_leaf": result.num_leaf,
                    **_force_errors(result.grad, reference.grad, radius),
                }
            )
    _write_results(out_dir, "contact", dev, repeats, {"rows": rows})
    _plot_contact_benchmark(rows, out_dir / "contact.png")
    return rows


def _plot_contact_benchmark(rows: list[dict], path: Path) -> bool:
    plt = optional_pyplot()
    if plt is None:
        return False
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, len(scenes), figsize=(6 * len(scenes), 4.5), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for gap in sorted({r["gap"] for r in rows}):
            sel = [r for r in rows if r["scene"] == scene and r["gap"] == gap and r["mode"] == "bsh"]
            brute = next(r for r in rows if r["scene"] == scene and r["gap"] == gap and r["mode"] == "brute")
            errors = [max(r["force_error_max"], 1e-16) for r in sel]
            times = [r["median_seconds"] / brute["median_seconds"] for r in sel]
            ax.loglog(times, errors, "o-", label=f"gap {gap:g} m")
            for r, t, e in zip(sel, times, errors):
                ax.annotate(f"{r['eps']:g}", (t, e), fontsize=7)
        ax.set_xlabel("time per evaluate / brute force")
        ax.set_ylabel("max per-body force error / max brute force")
        ax.set_title(f"{scene}: eps sweep (labels)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def run_scaling_benchmark(*, points_per_ball, eps: float, brute_max_triangles: int, repeats: int, device, out_dir: Path) -> list[dict]:
    """Time per contact evaluate (value + gradient + Hessian) of a 16-ball rack as the balls
    get finer; writes scaling.json and, with matplotlib, scaling.png.

    Balls are the scenes' Fibonacci hulls (2 N - 4 faces), racked 0.05 m apart.
    """
    from .scenes import fibonacci_ball

    dev = resolve_device(device)
    rows = []
    for n in points_per_ball:
        ball = fibonacci_ball(n)
        poses = _identity_poses(rack_positions(radius=0.5, gap=0.05))
        triangles = 16 * len(ball[1])
        for mode in ("bsh", "brute"):
            if mode == "brute" and triangles > brute_max_triangles:
                continue
            model = ContactModel([ball] * 16, mode=mode, eps=eps, device=dev)
            result = model.evaluate(poses)
            seconds = _median_seconds(lambda: model.evaluate(poses), repeats)
            rows.append(
                {
                    "triangles": triangles,
                    "mode": mode,
                    "eps": eps,
                    "median_seconds": seconds,
                    "seconds_per_triangle": seconds / triangles,
                    "num_far": result.num_far,
                    "num_blend": result.num_blend,
                    "num_leaf": result.num_leaf,
                }
            )
    _write_results(out_dir, "scaling", dev, repeats, {"rows": rows})
    _plot_scaling(rows, out_dir / "scaling.png")
    return rows


def _plot_scaling(rows: list[dict], path: Path) -> bool:
    plt = optional_pyplot()
    if plt is None:
        return False
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for mode in ("bsh", "brute"):
        sel = [r for r in rows if r["mode"] == mode]
        if sel:
            ax.loglog([r["triangles"] for r in sel], [r["median_seconds"] for r in sel], "o-", label=mode)
    t = np.array(sorted({r["triangles"] for r in rows}), dtype=float)
    first = next(r for r in rows if r["mode"] == "bsh")
    ax.loglog(t, first["median_seconds"] * t / t[0], "k:", label="linear")
    ax.set_xlabel("triangles (16 balls)")
    ax.set_ylabel("seconds per evaluate (value, gradient, Hessian)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True
