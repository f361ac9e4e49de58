"""Benchmarks that write their results to files (never timed tests)."""

import json
import platform
import time
from pathlib import Path

import numpy as np
import warp as wp

from .kernels import leaf as leaf_kernels
from ._runtime import resolve_device
from .leaf import DEFAULT_MAX_ITERATIONS

__all__ = ["leaf_benchmark_pairs", "run_leaf_benchmark"]


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
    result = {
        "benchmark": "leaf",
        "device": str(dev),
        "device_name": dev.name,
        "host": platform.processor() or platform.machine(),
        "num_pairs": num_pairs,
        "repeats": repeats,
        "date": time.strftime("%Y-%m-%d"),
        "module_load_seconds": compile_seconds,
        "median_seconds_value": value_only,
        "median_seconds_value_grad_hessian": full,
        "solves_per_second_value": num_pairs / value_only,
        "solves_per_second_value_grad_hessian": num_pairs / full,
        "mean_newton_iterations": float(iters.mean()),
        "max_newton_iterations": int(iters.max()),
        "fraction_ok": float(ok.mean()),
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "leaf.json").write_text(json.dumps(result, indent=2) + "\n")
    return result
