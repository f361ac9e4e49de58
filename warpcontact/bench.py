"""Benchmarks that write their results to files (never timed tests)."""

import copy
import csv
import functools
import json
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np
import warp as wp

from . import ipc
from ._files import interrupts_held, json_ready, replace_file, replace_json
from .contact import ContactModel
from .hull import convex_hull_mesh
from .kernels import leaf as leaf_kernels
from ._runtime import resolve_device
from ._validate import MAX_COORDINATE, check_barrier_support, gap_problem
from .builder import check_contact_setting
from .leaf import DEFAULT_MAX_ITERATIONS, LEAF_PRECISIONS, float32_search, leaf_gap_problem, leaf_solve_buffers, leaf_solve_bytes_per_pair
from .rotation import quat_rotate

__all__ = [
    "leaf_benchmark_pairs",
    "run_leaf_benchmark",
    "contact_benchmark_scenes",
    "run_contact_benchmark",
    "run_scaling_benchmark",
    "PAPER_FRAME_SECONDS",
    "PEER_BALLS",
    "peer_ball_path",
    "frame_scene",
    "strike_setup",
    "run_frame_benchmark",
    "accuracy_scene",
    "run_accuracy_benchmark",
]


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


@functools.cache  # written with every saved row: read once a process
def _host() -> str:
    """The CPU's model name where the system gives it (Linux: /proc/cpuinfo), with the
    logical cores this process may use; else Python's processor or machine name (which on
    Linux is only "x86_64": a probe)."""
    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as info:
            name = next((line.split(":", 1)[1].strip() for line in info if line.startswith("model name")), name)
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return f"{name}, {cores} logical cores"


def _write_results(out_dir: Path, name: str, device, repeats: int | None, fields: dict, *, complete: bool = False) -> dict:
    """Write out_dir/NAME.json with the common header (benchmark, device, host, date, the
    ``repeats`` of a benchmark that repeats its measurements (frame and accuracy measure
    frames, which their headers count, and had "repeats" hold the frame count and 1; a probe,
    stop 64), and ``complete``: False while rows are still to come, so that the files of a run
    stopped early say so; a stop-58 probe found them indistinguishable from a finished run's),
    and out_dir/NAME.csv with one line per entry of ``fields["rows"]`` when there is one."""
    payload = {
        "benchmark": name,
        "device": str(device),
        "device_name": device.name,
        "host": _host(),
        "date": time.strftime("%Y-%m-%d"),
        **({"repeats": repeats} if repeats is not None else {}),
        "complete": complete,
        **fields,
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    with interrupts_held() as interrupted:
        replace_json(out_dir / f"{name}.json", payload)
        if "rows" in fields:
            _write_csv(out_dir / f"{name}.csv", fields["rows"])
    if interrupted:
        raise KeyboardInterrupt  # after both files hold the same rows
    return payload


def _plot_at_end(path: Path, plot, rows: list[dict]) -> None:
    """Draw a bench's plot once its rows are final, also when the run is interrupted (the
    JSON and CSV are rewritten after every row, so an interrupted run keeps its rows). A plot
    that cannot be drawn (no drawable rows, no matplotlib) removes an earlier run's, which a
    rerun with --overwrite used to leave beside the new results. A run that wrote no row
    leaves an earlier run's plot beside its JSON and CSV, which it did not replace either (a
    refused --overwrite run deleted the plot alone)."""
    if not rows:
        return
    try:
        drawn = plot(rows, path)
    except Exception as exc:  # noqa: BLE001 - in a finally: it must not replace the run's own exception (Ctrl-C)
        warnings.warn(f"{path.name} not drawn: {type(exc).__name__}: {exc}", stacklevel=2)
        drawn = False
    if not drawn:
        path.unlink(missing_ok=True)


def _write_csv(path: Path, rows: list[dict]):
    """One line per row; columns are the union of the rows' keys in first-seen order."""
    columns = list(dict.fromkeys(key for row in rows for key in row))

    def write(temporary):
        with temporary.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns, restval="")
            writer.writeheader()
            for row in rows:
                # Non-finite numbers are empty cells, as they are null in the JSON (the CSV had nan and inf).
                cells = json_ready(row)
                writer.writerow({k: ("" if v is None else json.dumps(v, allow_nan=False) if isinstance(v, (list, dict)) else v) for k, v in cells.items()})

    replace_file(path, write)


def _median_seconds(fn, repeats: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return float(np.median(samples))


def _relative_errors(approx: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """(median, max) over pairs of |approx - reference| / |reference| (row norms)."""
    a = approx.reshape(approx.shape[0], -1)
    r = reference.reshape(reference.shape[0], -1)
    err = np.linalg.norm(a - r, axis=1) / np.maximum(np.linalg.norm(r, axis=1), np.finfo(float).tiny)
    return (float(np.median(err)), float(err.max())) if err.size else (0.0, 0.0)


def _distinct(values) -> list:
    """The values of a sweep, each once, in order: a value given twice was measured and
    written twice (``--eps 0.5 0.5``, a probe at stop 58)."""
    return list(dict.fromkeys(values))


def _check_settings(*, eps_values=(), ipc_dhat=None, ipc_stiffness=None) -> None:
    """ValueError naming the first bad eps, IPC barrier support or stiffness, before any work:
    the CLI checks them when it parses, but a library caller's bad value failed only when its
    row came, after the rows before it had replaced an earlier run's files (a probe, stop 58)."""
    for eps in eps_values:
        if eps is not None:
            check_contact_setting("eps", eps)
    if ipc_dhat is not None:
        check_barrier_support(ipc_dhat, "ipc_dhat")
    if ipc_stiffness is not None:
        check_contact_setting("contact_stiffness", ipc_stiffness, "ipc_stiffness")


def run_leaf_benchmark(*, num_pairs: int, repeats: int, device, out_dir: Path, seed: int = 0, precisions=("float64",)) -> dict:
    """Time batched leaf solves (value only, and value + gradient + Hessian) for each plane
    search precision; rows after the first also give their errors against the first
    (float64 unless asked otherwise) on the same pairs. Writes leaf.json and leaf.csv."""
    dev = resolve_device(device)
    precisions = _distinct(precisions)
    flags = [float32_search(p) for p in precisions]
    A, B = leaf_benchmark_pairs(num_pairs, seed=seed)
    with wp.ScopedDevice(dev):
        try:
            tri_a, tri_b, value, plane, status, iterations, grad, hess = leaf_solve_buffers(A, B, 6)
        except (RuntimeError, MemoryError):
            # The largest --pairs (10 million) needs 29 GB: a traceback on a machine with less.
            per_pair = leaf_solve_bytes_per_pair(6)
            raise ValueError(f"pairs: {num_pairs} pairs need {num_pairs * per_pair / 1e9:.3g} GB of buffers on {dev} ({per_pair} bytes a pair), more than it could allocate; ask for fewer") from None

        def launch(search32: bool, derivatives: bool):
            wp.launch(
                leaf_kernels.leaf_potential_kernel,
                dim=num_pairs,
                inputs=[0.0, tri_a, tri_b, DEFAULT_MAX_ITERATIONS, search32, derivatives],
                outputs=[value, plane, status, iterations, grad, hess],
            )
            wp.synchronize_device()

        compile_start = time.perf_counter()
        wp.load_module(leaf_kernels, device=dev)
        compile_seconds = time.perf_counter() - compile_start
        rows, reference = [], None
        header = {"num_pairs": num_pairs, "module_load_seconds": compile_seconds, "reference_precision": precisions[0]}
        for precision, search32 in zip(precisions, flags):
            launch(search32, True)  # warm-up, excluded
            value_only = _median_seconds(lambda: launch(search32, False), repeats)
            full = _median_seconds(lambda: launch(search32, True), repeats)
            iters = iterations.numpy()
            ok = status.numpy() == 0
            # Copies: on a CPU .numpy() is a view of the buffers the next precision's launches
            # overwrite (float32 rows were compared with themselves: errors of 0).
            result = (value.numpy().copy(), grad.numpy().copy(), hess.numpy().copy(), ok)
            row = {
                "precision": precision,
                "median_seconds_value": value_only,
                "median_seconds_value_grad_hessian": full,
                "solves_per_second_value": num_pairs / value_only,
                "solves_per_second_value_grad_hessian": num_pairs / full,
                "mean_newton_iterations": float(iters.mean()),
                "max_newton_iterations": int(iters.max()),
                "fraction_ok": float(ok.mean()),
            }
            if reference is None:
                reference = result
            else:
                both = ok & reference[3]
                for name, k in (("value", 0), ("gradient", 1), ("hessian", 2)):
                    median, worst = _relative_errors(result[k][both], reference[k][both])
                    row[f"{name}_error_median"] = median
                    row[f"{name}_error_max"] = worst
            rows.append(row)
            _write_results(out_dir, "leaf", dev, repeats, {**header, "rows": rows})
    return _write_results(out_dir, "leaf", dev, repeats, {**header, "rows": rows}, complete=True)


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
    from .scenes import rack_centres

    spacing = 2 * radius + gap
    centres = [[x, y, radius] for x, y in rack_centres(spacing)]
    centres.append([-6 * spacing, 0.0, radius])
    return np.array(centres)


def contact_benchmark_scenes(*, subdivisions: int, gaps) -> list[dict]:
    """Two icospheres and a 16-ball rack, each at the given surface gaps (m); balls of radius
    0.5 m. The pair's gap is exact at every subdivision. The rack's is its closest
    neighbours' (10 of its 30 neighbouring pairs, from 1 subdivision on); its 20 diagonal
    pairs meet edge to edge, farther apart (0.0631 m at 1 subdivision, 0.0151 m at 2, for a
    nominal 1e-2 m); at 0 subdivisions an icosahedron's faces stand 0.075 m inside its
    circumscribed sphere and every pair is farther."""
    ball = _icosphere(subdivisions, 0.5)
    reach = float(ball[0][:, 0].max())  # the balls' extent along x, their line of centres
    scenes = []
    for gap in gaps:
        # Every gap before any row is timed or written: 1e300 m failed after the others' rows.
        # Beyond the leaf planes' reach brute force, the reference, does not solve: rows were
        # written from a reference of value inf and zero forces, and the run exited 0.
        problem = leaf_gap_problem(gap, 2.0 * reach)
        if problem is not None:
            raise ValueError(f"gaps: {problem}")
        two = _identity_poses([[0.0, 0.0, 0.0], [2.0 * reach + gap, 0.0, 0.0]])
        # Turned about the line of centres, which keeps the facing features on it: the pair's
        # symmetry is broken and the surfaces stay ``gap`` apart (a turn about z had moved
        # them 2.9 cm apart at a nominal 1 mm).
        two[1, 3:] = [np.sin(0.35), 0.0, 0.0, np.cos(0.35)]
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
    *, eps_values, gaps, subdivisions: int, repeats: int, device, out_dir: Path, ipc_dhat: float | None = 1e-2, centred_weights=("paper",)
) -> list[dict]:
    """Time per evaluate (value + gradient + Hessian) and force/torque error against brute force.

    ``bsh`` rows run for every eps and every centred weight (``ContactModel``,
    ``centred_weight``); ``value_ratio`` is each row's potential over brute force's.

    With ``ipc_dhat`` on the CPU, each scene also gets an ``ipc`` row timing, side by side on
    the same geometry, the IPC Toolkit's collision build + barrier value, gradient and
    Hessian (``median_seconds``; vertex coordinates, as ipctk computes them) and the whole
    rigid-coordinate ``IpcContactModel.evaluate`` (``median_seconds_rigid``); its error
    fields are None (a different potential). Writes contact.json, contact.csv and, when
    matplotlib is installed, contact.png (time vs error).
    """
    eps_values, gaps, centred_weights = _distinct(eps_values), _distinct(gaps), _distinct(centred_weights)
    _check_settings(eps_values=eps_values, ipc_dhat=ipc_dhat)
    dev = resolve_device(device)
    with_ipc = ipc_dhat is not None and dev.is_cpu
    missing = ipc.toolkit_problem() if with_ipc else None
    if missing is not None:  # before any row replaces an earlier run's
        raise ValueError(f"{missing}; or leave out the ipc rows (ipc_dhat=None; --ipc-dhat 0 on the command line)")
    # Compile time apart, as the other benchmarks report it (these two left it out; a probe, stop 64).
    module_seconds = _load_kernel_modules(dev)
    rows = []

    def save(*, complete=False):
        _write_results(out_dir, "contact", dev, repeats, {"module_load_seconds": module_seconds, "rows": rows}, complete=complete)

    try:
        for scene in contact_benchmark_scenes(subdivisions=subdivisions, gaps=gaps):
            if with_ipc:
                rows.append(_ipc_contact_row(scene, ipc_dhat, repeats))
                save()
            reference = None
            for mode, eps, weight in [("brute", None, None)] + [("bsh", e, w) for w in centred_weights for e in eps_values]:
                model = ContactModel(scene["meshes"], mode=mode, eps=eps or 1.0, centred_weight=weight or "paper", device=dev)
                result = model.evaluate(scene["poses"])  # warm-up: compile and size buffers
                if not result.ok or not np.isfinite(result.value):
                    # Rows were written from an unsolved reference (value inf, forces 0) and the run exited 0.
                    raise ValueError(f"gaps: at {scene['gap']:g} m, {mode}'s evaluation of {scene['scene']} is not finite (unsolved pairs: {result.unsolved_pairs[:3]})")
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
                        "centred_weight": weight,
                        "median_seconds": seconds,
                        "value_ratio": result.value / reference.value,
                        "num_far": result.num_far,
                        "num_blend": result.num_blend,
                        "num_leaf": result.num_leaf,
                        **_force_errors(result.grad, reference.grad, radius),
                    }
                )
                save()
        save(complete=True)
    finally:
        _plot_at_end(out_dir / "contact.png", _plot_contact_benchmark, rows)
    return rows


def _ipc_contact_row(scene: dict, dhat: float, repeats: int) -> dict:
    from .ipc import IpcContactModel

    model = IpcContactModel(scene["meshes"], dhat=dhat)
    poses = scene["poses"]
    _, collisions = model.vertex_terms(poses)  # warm-up
    model.evaluate(poses)
    return {
        "scene": scene["scene"],
        "gap": scene["gap"],
        "triangles": int(sum(len(f) for _, f in scene["meshes"])),
        "mode": "ipc",
        "eps": None,
        "centred_weight": None,
        "ipc_dhat": dhat,
        "median_seconds": _median_seconds(lambda: model.vertex_terms(poses), repeats),
        "value_ratio": None,
        "median_seconds_rigid": _median_seconds(lambda: model.evaluate(poses), repeats),
        # ipctk's active collisions within dhat, in a column of their own: they are no leaf
        # solves (they were reported as num_leaf, a probe, stop 62).
        "num_far": None,
        "num_blend": None,
        "num_leaf": None,
        "ipc_active_collisions": collisions,
        "force_error_median": None,
        "force_error_max": None,
        "force_cosine_min": None,
        "torque_error_max": None,
    }


def _plot_contact_benchmark(rows: list[dict], path: Path) -> bool:
    plt = optional_pyplot()
    if plt is None or not any(r["mode"] == "bsh" for r in rows):
        return False
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, len(scenes), figsize=(6 * len(scenes), 4.5), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for gap in sorted({r["gap"] for r in rows}):
            brute = next((r for r in rows if r["scene"] == scene and r["gap"] == gap and r["mode"] == "brute"), None)
            if brute is None:  # a run cut short before this gap's reference
                continue
            for weight in sorted({r["centred_weight"] for r in rows if r["mode"] == "bsh"}):
                sel = [r for r in rows if r["scene"] == scene and r["gap"] == gap and r["mode"] == "bsh" and r["centred_weight"] == weight]
                errors = [max(r["force_error_max"], 1e-16) for r in sel]
                times = [r["median_seconds"] / brute["median_seconds"] for r in sel]
                ax.loglog(times, errors, "o-" if weight == "paper" else "s--", label=f"gap {gap:g} m, {weight}")
                for r, t, e in zip(sel, times, errors):
                    ax.annotate(f"{r['eps']:g}", (t, e), fontsize=7)
        ax.set_xlabel("time per evaluate / brute force")
        ax.set_ylabel("max per-body force error / max brute force")
        ax.set_title(f"{scene}: eps sweep (labels)")
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:  # a run saved before this scene's bsh rows
            ax.legend(fontsize=8)
    fig.tight_layout()
    replace_file(path, lambda temporary: fig.savefig(temporary, dpi=120))
    plt.close(fig)
    return True


def run_scaling_benchmark(*, points_per_ball, eps: float, brute_max_triangles: int, repeats: int, device, out_dir: Path) -> list[dict]:
    """Time per contact evaluate (value + gradient + Hessian) of a 16-ball rack as the balls
    get finer; writes scaling.json and, with matplotlib, scaling.png.

    Balls are the scenes' Fibonacci hulls (2 N - 4 faces), racked 0.05 m apart.
    """
    from .scenes import fibonacci_ball

    points_per_ball = _distinct(points_per_ball)
    _check_settings(eps_values=(eps,))
    dev = resolve_device(device)
    module_seconds = _load_kernel_modules(dev)
    rows = []

    def save(*, complete=False):
        # The cap explains the missing brute rows (recorded nowhere before stop 58).
        _write_results(out_dir, "scaling", dev, repeats, {"module_load_seconds": module_seconds, "brute_max_triangles": brute_max_triangles, "rows": rows}, complete=complete)

    try:
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
                        "eps": eps if mode == "bsh" else None,  # brute force has no blend margin
                        "median_seconds": seconds,
                        "seconds_per_triangle": seconds / triangles,
                        "num_far": result.num_far,
                        "num_blend": result.num_blend,
                        "num_leaf": result.num_leaf,
                    }
                )
                save()
        save(complete=True)
    finally:
        _plot_at_end(out_dir / "scaling.png", _plot_scaling, rows)
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
    first = min((r for r in rows if r["mode"] == "bsh"), key=lambda r: r["triangles"])
    ax.loglog(t, first["median_seconds"] * t / first["triangles"], "k:", label="linear")
    ax.set_xlabel("triangles (16 balls)")
    ax.set_ylabel("seconds per evaluate (value, gradient, Hessian)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    replace_file(path, lambda temporary: fig.savefig(temporary, dpi=120))
    plt.close(fig)
    return True


# --- per-frame cost of whole implicit steps (issue 8) ---------------------------------------

# The paper's per-frame CPU seconds (appendix "Computational efficiency"): billiards at 512 and
# 6208 triangles (hierarchy, brute force, IPC) and Gather-Bunny.
PAPER_FRAME_SECONDS = {
    "billiards_512": {"bsh": 0.6, "brute": 3.35, "ipc": 0.5},
    "billiards_6208": {"bsh": 3.18, "brute": 604.5, "ipc": 0.5},
    "gather_bunny": {"bsh": 3.89, "brute": 309.62, "ipc": 3.14},
}
# The paper's triangle counts of those scenes (its Gather-Bunny has "2784 triangles in total";
# ours has 2,702 dynamic ones), where frame.png draws its points.
PAPER_FRAME_TRIANGLES = {"billiards_512": 512, "billiards_6208": 6208, "gather_bunny": 2784}

# The paper code base's ball meshes (../shared/peer-meshes) by 16-ball triangle count.
PEER_BALLS = {512: "18.obj", 1472: "48.obj", 3008: "96.obj", 4544: "144.obj", 6208: "196.obj"}


def peer_ball_path(triangles: int, peer_meshes: Path) -> Path:
    """The file of the paper code base's ball whose 16-ball rack has ``triangles`` triangles."""
    return Path(peer_meshes) / PEER_BALLS[triangles]


def _peer_ball(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A peer ball mesh, centred, with its faces re-oriented outward.

    The files' faces are not consistently oriented (their signed volumes are near zero), and
    the points are in convex position, so the convex hull is the same surface with outward
    faces; it must have the file's face count, else the file is not such a ball.
    """
    import trimesh

    mesh = trimesh.load(path, process=False, force="mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if len(vertices) < 4:  # an empty or broken file: the hull's error named neither it nor the scene
        raise ValueError(f"{path}: not a ball mesh ({len(vertices)} vertices read)")
    hull_vertices, hull_faces = convex_hull_mesh(vertices - vertices.mean(axis=0))
    if len(hull_faces) != len(mesh.faces):
        raise ValueError(f"{path}: not a ball in convex position ({len(mesh.faces)} faces, hull {len(hull_faces)})")
    return hull_vertices, hull_faces.astype(np.int64)


def frame_scene(spec: str, *, scene_dir: Path | None = None, peer_meshes: Path = Path("../shared/peer-meshes")):
    """The ``Scene`` named by ``spec``.

    ``spec`` is a shipped scene name (the shipped scene, or ``scene_dir``/NAME.usda, when usd-core
    is installed, otherwise built by ``warpcontact.scenes``), any other NAME of a
    ``scene_dir``/NAME.usda, ``peer_billiards_T`` (billiards with the paper code base's balls, T
    in ``PEER_BALLS``, from ``peer_meshes``), a .usda path, or a .pkl path (a pickled ``Scene``,
    for machines without usd-core).
    """
    from . import io
    from .scenes import RACK_BALLS, SCENE_NAMES, benchmark_rack, build_scene, shipped_scene

    path = Path(spec)
    if path.suffix == ".pkl":
        import pickle

        if not path.is_file():
            raise ValueError(f"{spec}: file not found")
        try:
            with path.open("rb") as f:
                scene = pickle.load(f)
        except Exception as exc:  # pickle raises many kinds for a file that is not one
            raise ValueError(f"{spec}: not a pickled Scene ({type(exc).__name__}: {exc})") from None
        if not isinstance(scene, io.Scene):
            raise ValueError(f"{spec}: holds a {type(scene).__name__}, not a pickled warpcontact Scene")
        return scene
    if path.suffix.lower() in io.USD_READ_SUFFIXES:
        return io.load_scene(path)
    if spec.startswith("peer_billiards_"):
        count = spec.rsplit("_", 1)[1]
        triangles = int(count) if count.isdigit() else None  # int("abc") was the whole message
        if triangles not in PEER_BALLS:
            raise ValueError(f"{spec}: peer billiards come in {sorted(PEER_BALLS)} triangles")
        file = peer_ball_path(triangles, peer_meshes)
        if not file.is_file():
            raise ValueError(f"{spec}: {file} not found (pass the peer-mesh folder)")
        ball = _peer_ball(file)
        if (RACK_BALLS + 1) * len(ball[1]) != triangles:  # another ball (or a tetrahedron) was timed as this size
            raise ValueError(f"{spec}: {file} has {len(ball[1])} faces, a rack of {(RACK_BALLS + 1) * len(ball[1])} triangles, not {triangles}")
        scene = benchmark_rack(*ball)
        scene.source = spec
        return scene
    if spec not in SCENE_NAMES:
        own = None if scene_dir is None else Path(scene_dir) / f"{spec}.usda"
        if own is not None and own.is_file():
            return io.load_scene(own)  # any NAME.usda of the folder, not only the shipped names
        where = f", a NAME.usda in {scene_dir}" if scene_dir is not None else ""
        raise ValueError(f"scene: {spec!r} is not a scene name ({', '.join(SCENE_NAMES)}){where}, peer_billiards_T, .usda or .pkl")
    try:
        import pxr  # noqa: F401
    except ImportError:
        pass  # machines without usd-core (GPU leases) build the same scene in memory
    else:
        usda = shipped_scene(spec) if scene_dir is None else Path(scene_dir) / f"{spec}.usda"
        if not usda.is_file():
            raise ValueError(f"scene {spec!r}: {usda} not found")
        return io.load_scene(usda)
    scene = build_scene(spec)
    scene.source = spec
    return scene


def _horizontal(vectors: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Vectors' components across the stage's up axis (a unit axis vector: exact for Z and Y)."""
    return vectors - np.multiply.outer(vectors @ up, up)


def _horizontal_radius(body, up: np.ndarray) -> float:
    """Largest horizontal distance of a body's vertices from its prim origin (m)."""
    world = quat_rotate(body.pose[3:], body.vertices)
    return float(np.linalg.norm(_horizontal(world, up), axis=1).max())


def strike_setup(scene, *, gap: float, speed: float) -> dict:
    """Put the scene's striker (``cue``, else ``rod``) ``gap`` metres (horizontal bounding
    circles, across the stage's up axis) in front of the dynamic body nearest to it, moving
    into it at ``speed`` m/s, so the frames that follow involve contact. A PD-actuated striker
    (the rod) gets its target on the far side of that body, so it keeps pushing.

    Returns a description (striker, struck body, gap, speed, direction) and sets
    ``control_target`` (prim-frame translation of the striker's PD target, or None).
    ValueError when the striker is static or held by a joint, when no other dynamic body is there to strike, or
    when the striker stands straight above or below that body (no horizontal direction to
    strike along).
    """
    names = [b.name for b in scene.bodies]
    striker_name = "cue" if "cue" in names else "rod" if "rod" in names else None
    if striker_name is None:
        raise ValueError(f"{scene.source or '<scene>'}: no 'cue' or 'rod' body to strike with")
    striker = scene.body(striker_name)
    where = scene.source or "<scene>"
    if striker.static:
        # Given a velocity it never had, it stood still while the results recorded a strike
        # at the speed asked for (a probe, stop 65).
        raise ValueError(f"{where}: the striker {striker_name!r} is static (a collider without a rigid body): it cannot strike")
    jointed = [j.name for j in scene.joints if striker_name in (j.parent, j.child)]
    if jointed:
        # Moved beside the struck body as a free body, it left its joint's axis, and the model
        # was refused only when built, after the scenes before it were timed (a probe, stop 65).
        raise ValueError(f"{where}: the striker {striker_name!r} is held by joint {jointed[0]!r}; the strike places it as a free body")
    others = [b for b in scene.bodies if not b.static and b is not striker]
    if not others:
        # min() of no bodies: "min() arg is an empty sequence" (a probe, stop 65).
        raise ValueError(f"{where}: no dynamic body besides the striker {striker_name!r} to strike")
    # The horizontal plane is the stage's: a Y-up scene's rod was moved along y, part way up.
    up = np.array([0.0, 1.0, 0.0]) if scene.up_axis == "Y" else np.array([0.0, 0.0, 1.0])
    struck = min(others, key=lambda b: np.linalg.norm(_horizontal(b.pose[:3] - striker.pose[:3], up)))
    offset = _horizontal(struck.pose[:3] - striker.pose[:3], up)
    reach = _horizontal_radius(striker, up) + _horizontal_radius(struck, up)
    # Before the gap is placed: at 1e-30 m the two stood 1.1e-16 m into each other while the
    # results recorded the gap asked for; at 1e200 m the error named the striker's pose.
    problem = gap_problem(gap, float(np.abs(struck.pose[:3]).max()) + reach)
    if problem is None and not reach + gap <= MAX_COORDINATE:
        problem = f"{gap:g} m puts the striker beyond the +-{MAX_COORDINATE:g} m of a body's coordinates"
    if problem is not None:
        raise ValueError(f"gap: {problem}")
    # A step's travel at it must stay a coordinate: 1e200 m/s was refused naming
    # state_in.body_q_prev (a probe).
    travel = speed * scene.settings.time_step
    if not reach + gap + travel <= MAX_COORDINATE:
        raise ValueError(f"speed: {speed:g} m/s moves the striker {travel:g} m a step of {scene.settings.time_step:g} s, beyond the +-{MAX_COORDINATE:g} m of a body's coordinates")
    if np.linalg.norm(offset) <= 1e-9 * reach:
        raise ValueError(f"{where}: the striker {striker_name!r} stands straight above or below {struck.name!r}: there is no horizontal direction to strike it along")
    direction = offset / np.linalg.norm(offset)
    striker.pose[:3] = _horizontal(struck.pose[:3], up) - direction * (reach + gap) + (striker.pose[:3] @ up) * up
    striker.linear_velocity = speed * direction
    striker.angular_velocity = np.zeros(3)
    pd = bool(np.any(striker.kp_linear > 0))
    target = striker.pose[:3] + direction * (2 * reach + gap)
    return {
        "striker": striker_name,
        "struck": struck.name,
        "gap_m": gap,
        "speed_m_per_s": speed,
        "direction": direction.tolist(),
        "control_target": target.tolist() if pd else None,
    }


def _load_kernel_modules(dev) -> float:
    """Load (compile, or read from Warp's kernel cache) every warpcontact kernel module, and
    the traversal round kernels of both visit budgets (modules of their own: they compiled
    untimed inside the first model's build, 7 s on a cold cache); seconds."""
    import importlib
    import pkgutil

    from . import kernels
    from .kernels import traversal

    start = time.perf_counter()
    for info in pkgutil.iter_modules(kernels.__path__):
        wp.load_module(importlib.import_module(f"{kernels.__name__}.{info.name}"), device=dev)
    for budget in (traversal.HOST_SIZED_VISIT_BUDGET, traversal.SYNC_FREE_VISIT_BUDGET):
        wp.load_module(traversal.traverse_round_kernel(budget).module, device=dev)
    return time.perf_counter() - start


def _scene_triangles(scene) -> tuple[int, int]:
    """(dynamic triangles, all triangles) of a scene."""
    dynamic = sum(len(b.faces) for b in scene.bodies if not b.static)
    return dynamic, sum(len(b.faces) for b in scene.bodies)


def _timed(fn, dev):
    start = time.perf_counter()
    result = fn()
    wp.synchronize_device(dev)
    return result, time.perf_counter() - start


def _simulate_frames(scene, setup: dict, *, mode: str, frames: int, warmup: int, dev, eps: float | None, ipc_stiffness: float = 1e3, leaf_precision: str = "float64"):
    """Simulate ``frames`` timed frames of ``scene`` under contact ``mode`` after ``warmup``
    untimed ones from the same start; per frame: forward step on a tape, contact evaluation
    at the step's solution, and the tape's backward. Returns (row, solved poses per frame,
    the ``Model``)."""
    from .solver import ImplicitSolver, SolverError
    from .types import set_body_velocity

    scene.settings.contact_mode = mode
    scene.settings.leaf_precision = leaf_precision
    if eps is not None:
        scene.settings.eps = eps
    if mode == "ipc":
        scene.settings.friction = 0.0  # ipc frames are timed without friction (as measured in docs/performance.md)
        # The scenes' mu is sized for the separating-plane potential; on IPC's barrier it is
        # so soft that the balls sink ~dhat into the table over hundreds of Newton iterations.
        scene.settings.contact_stiffness = ipc_stiffness
    model = scene.build_model(device=dev)
    solver = ImplicitSolver(model)
    dt = scene.settings.time_step
    control = model.control(requires_grad=False)
    if setup["control_target"] is not None:
        striker = model.body_names.index(setup["striker"])
        targets = model.initial_q.copy()
        targets[striker, :3] += np.asarray(setup["control_target"]) - scene.body(setup["striker"]).pose[:3]
        control.body_target.assign(targets)
    lin, ang = scene.initial_velocities()
    start = model.state(requires_grad=True)
    set_body_velocity(start, wp.array(lin, dtype=wp.vec3d, device=dev), wp.array(ang, dtype=wp.vec3d, device=dev), dt, body_names=model.body_names)
    samples = {"forward": [], "iterations": [], "contact": [], "backward": [], "leaf": []}
    poses, error, first = [], None, None

    def frame(state):
        nxt = model.state(requires_grad=True)
        tape = wp.Tape()

        def forward():
            with tape:
                return solver.step(state, nxt, control, dt)

        info, t_forward = _timed(forward, dev)
        q = nxt.body_q.numpy()
        contact, t_contact = _timed(lambda: model.contact.evaluate(q), dev)
        seed = wp.array(np.ones((model.num_bodies, 7)), dtype=wp.transformd, device=dev)
        _, t_backward = _timed(lambda: tape.backward(grads={nxt.body_q: seed}), dev)
        return nxt, info, contact, (t_forward, t_contact, t_backward)

    try:
        for _ in range(warmup):
            _, _, _, (t_forward, _, t_backward) = frame(start)
            # A frame as frame_seconds counts one: forward and backward, not the extra
            # contact evaluation (it was in, a probe at stop 57).
            first = first if first is not None else t_forward + t_backward
        state = start
        for _ in range(frames):
            state, info, contact, (t_forward, t_contact, t_backward) = frame(state)
            samples["forward"].append(t_forward)
            samples["iterations"].append(info.iterations)
            samples["contact"].append(t_contact)
            samples["backward"].append(t_backward)
            samples["leaf"].append(contact.num_leaf)
            poses.append(state.body_q.numpy())
    except SolverError as exc:
        error = str(exc)

    def median(key):
        return float(np.median(samples[key])) if samples[key] else None

    per_iteration = [t / max(i, 1) for t, i in zip(samples["forward"], samples["iterations"])]
    row = {
        "model": mode,
        "eps": scene.settings.eps if mode == "bsh" else None,
        "leaf_precision": leaf_precision,
        "friction": scene.settings.friction,
        "contact_stiffness": scene.settings.contact_stiffness,
        "frames": len(samples["forward"]),
        "first_frame_seconds": first,
        "forward_seconds": median("forward"),
        # Issue 8's GPU target is the Newton step to tolerance alone, over whole strikes.
        "forward_seconds_mean": float(np.mean(samples["forward"])) if samples["forward"] else None,
        "forward_seconds_per_frame": samples["forward"],
        "newton_iterations": median("iterations"),
        "newton_iterations_per_frame": samples["iterations"],
        "forward_seconds_per_iteration": float(np.median(per_iteration)) if per_iteration else None,
        "contact_seconds": median("contact"),
        # ipc's evaluations count ipctk's active collisions, no leaf solves.
        ("ipc_active_collisions" if mode == "ipc" else "leaf_terms"): median("leaf"),
        "backward_seconds": median("backward"),
        "frame_seconds": (median("forward") + median("backward")) if samples["forward"] else None,
        # The paper's per-frame figures are averages over its optimisation runs, not medians.
        "frame_seconds_mean": float(np.mean(np.add(samples["forward"], samples["backward"]))) if samples["forward"] else None,
        "error": error,
    }
    return row, poses, model


def _contact_only_row(model, poses: list, *, mode: str, dev) -> dict:
    """Contact evaluation (value, gradient, Hessian) under ``mode`` of a simulation ``Model``'s
    bodies at given configurations (its body-frame poses)."""
    from .contact import ContactModel

    contact = ContactModel(
        model.body_meshes, eps=model.contact.eps, centred_weight=model.contact.centred_weight, mode=mode, leaf_precision=model.contact.leaf_precision, static=model.static, device=dev
    )
    contact.evaluate(poses[0])  # warm-up: buffers and kernels
    times, leaves = [], []
    for q in poses:
        result, seconds = _timed(lambda q=q: contact.evaluate(q), dev)
        times.append(seconds)
        leaves.append(result.num_leaf)
    return {
        **_empty_frame_row(mode),
        "eps": None if mode == "brute" else contact.eps,
        "leaf_precision": contact.leaf_precision,
        "friction": float(model.friction.numpy()[0]),
        "contact_seconds": float(np.median(times)),
        "leaf_terms": float(np.median(leaves)),
        "error": "contact evaluation only (frames above --brute-max-triangles)",
    }


def _empty_frame_row(mode: str) -> dict:
    """A frame row's fields with nothing timed."""
    return {
        "model": mode,
        "eps": None,
        "leaf_precision": None,
        "friction": None,
        "frames": 0,
        "first_frame_seconds": None,
        "forward_seconds": None,
        "forward_seconds_mean": None,
        "forward_seconds_per_frame": [],
        "newton_iterations": None,
        "newton_iterations_per_frame": [],
        "forward_seconds_per_iteration": None,
        "contact_seconds": None,
        "leaf_terms": None,
        "backward_seconds": None,
        "frame_seconds": None,
        "frame_seconds_mean": None,
        "error": None,
    }


def run_frame_benchmark(
    *,
    scenes,
    models=("bsh", "brute", "ipc"),
    frames: int,
    warmup: int = 1,
    eps: float | None = None,
    gap: float = 0.02,
    speed: float = 1.0,
    brute_max_triangles: int = 512,
    brute_eval_max_triangles: int = 6208,
    ipc_stiffness: float = 1e3,
    leaf_precision: str = "float64",
    device,
    out_dir: Path,
    scene_dir: Path | None = None,
    peer_meshes: Path = Path("../shared/peer-meshes"),
    progress=None,
) -> list[dict]:
    """Per-frame cost of whole implicit steps with contact; writes frame.json, frame.csv and,
    with matplotlib, frame.png (the JSON and CSV rewritten after every row, so a run cut short
    keeps its rows; the plot drawn at the end).

    For each scene (see ``frame_scene``) the striker is set up by ``strike_setup`` (cue
    ``gap`` m in front of the rack's apex ball at ``speed`` m/s; the rod into the nearest
    object), then per model: ``warmup`` untimed frames, then ``frames`` timed frames from
    the same start, each timed as forward step on a ``wp.Tape`` (Newton to tolerance),
    contact evaluation (value, gradient, Hessian) at its solution, and ``tape.backward``
    (implicit-function theorem). Rows hold medians over the frames (s), each frame's forward
    seconds and their mean ``forward_seconds_mean``, and ``frame_seconds_mean``, the mean
    forward + backward time a frame: the statistic of the paper's per-frame figures
    (``paper_frame_seconds``), which average whole optimisation runs; ``--frames 100``
    follows a strike for a whole billiards horizon. Brute force runs
    whole frames only up to ``brute_max_triangles`` dynamic triangles and is timed at the
    BSH run's configurations (contact evaluation only) up to ``brute_eval_max_triangles``;
    ipc (ipctk, CPU only) runs on the CPU, frictionless, with barrier stiffness
    ``ipc_stiffness`` in place of the scene's mu. ``eps`` None keeps each scene's.
    ``leaf_precision`` is the plane search precision of bsh and brute (ipc: float64).
    """
    float32_search(leaf_precision)
    _check_settings(eps_values=(eps,), ipc_stiffness=ipc_stiffness)
    dev = resolve_device(device)
    module_seconds = _load_kernel_modules(dev)
    rows: list[dict] = []
    header = {
        "module_load_seconds": module_seconds,
        "frames": frames,
        "warmup_frames": warmup,
        "strike_gap_m": gap,
        "strike_speed_m_per_s": speed,
        "paper_frame_seconds": PAPER_FRAME_SECONDS,
    }

    def save(*, complete=False):
        _write_results(out_dir, "frame", dev, None, {**header, "rows": rows}, complete=complete)

    # Every scene is read before any is timed: a bad name or a missing peer-mesh folder used
    # to end the default run after hours of the scenes before it.
    from .io import USD_READ_SUFFIXES

    scenes = _distinct(scenes)  # a scene named twice was timed twice, as models no longer are
    built = {spec: frame_scene(spec, scene_dir=scene_dir, peer_meshes=peer_meshes) for spec in scenes}
    # and set up for its strike, once (a scene without a striker failed after the others' timing)
    setups = {spec: strike_setup(scene, gap=gap, speed=speed) for spec, scene in built.items()}
    # bsh first: brute force above --brute-max-triangles is timed at bsh's solved poses (listed
    # after it, brute's rows were dropped without a word).
    models = sorted(_distinct(models), key=lambda mode: mode != "bsh")
    ipc_missing = ipc.toolkit_problem() if "ipc" in models and dev.is_cpu else None
    try:
        for spec in scenes:
            solved = None  # (bsh Model, its solved poses) for contact-only rows
            for mode in models:
                scene = copy.deepcopy(built[spec])  # each model sets its own contact settings
                setup = setups[spec]
                dynamic, total = _scene_triangles(scene)
                from_file = Path(spec).suffix.lower() in (".pkl", *USD_READ_SUFFIXES)
                base = {
                    # Labelled by the file's name, its path kept: rows of two push.usda files
                    # were told apart by nothing, and a .usdc row was labelled by its whole path
                    # (a probe, stop 65).
                    "scene": Path(spec).stem if from_file else spec,
                    "source": str(Path(spec).resolve()) if from_file else None,
                    "triangles": dynamic,
                    "all_triangles": total,
                    "bodies": len(scene.bodies),
                    "time_step": scene.settings.time_step,
                    # A skipped ipc row said the scene's mu, which ipc never runs with.
                    "contact_stiffness": ipc_stiffness if mode == "ipc" else scene.settings.contact_stiffness,
                    # Only the hierarchy has centred terms (the pair-weighted ones change the potential several-fold).
                    "centred_weight": scene.settings.centred_weight if mode == "bsh" else None,
                    "setup": f"{setup['striker']} {gap:g} m (bounding circles) from {setup['struck']} at {speed:g} m/s",
                    "direction": setup["direction"],
                }
                if mode == "ipc" and not dev.is_cpu:
                    row = {**_empty_frame_row(mode), "error": f"skipped: ipc (ipctk) runs on the CPU only, not on {dev}"}
                elif mode == "ipc" and ipc_missing is not None:
                    # The rows after it were lost: the run stopped at the first ipc row.
                    row = {**_empty_frame_row(mode), "error": f"skipped: {ipc_missing}"}
                elif mode == "brute" and dynamic > brute_max_triangles:
                    if dynamic > brute_eval_max_triangles or solved is None:
                        why = f"above --brute-eval-max-triangles {brute_eval_max_triangles}" if dynamic > brute_eval_max_triangles else "no bsh frames to evaluate at (bsh not in --models, or its frames failed)"
                        row = {**_empty_frame_row(mode), "error": f"skipped: {dynamic} dynamic triangles above --brute-max-triangles {brute_max_triangles}, and {why}"}
                    else:
                        row = _contact_only_row(solved[0], solved[1], mode="brute", dev=dev)
                else:
                    precision = "float64" if mode == "ipc" else leaf_precision
                    row, poses, model = _simulate_frames(
                        scene, setup, mode=mode, frames=frames, warmup=warmup, dev=dev, eps=eps if mode == "bsh" else None, ipc_stiffness=ipc_stiffness, leaf_precision=precision
                    )
                    if mode == "bsh" and poses:
                        solved = (model, poses)
                rows.append({**base, **row})
                if progress:
                    progress(rows[-1])
                save()
    finally:
        _plot_at_end(out_dir / "frame.png", _plot_frame_benchmark, rows)
    save(complete=True)
    return rows


def _plot_frame_benchmark(rows: list[dict], path: Path) -> bool:
    plt = optional_pyplot()
    if plt is None or all(r["contact_seconds"] is None for r in rows):
        return False
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for mode, marker in (("bsh", "o"), ("brute", "s"), ("ipc", "^")):
        sel = sorted((r for r in rows if r["model"] == mode and r["contact_seconds"] is not None), key=lambda r: r["triangles"])
        framed = [r for r in sel if r["forward_seconds"] is not None]
        if framed:
            line = axes[0].loglog([r["triangles"] for r in framed], [r["forward_seconds"] for r in framed], marker, label=f"{mode} forward")[0]
            axes[0].loglog([r["triangles"] for r in framed], [r["backward_seconds"] for r in framed], marker, mfc="none", color=line.get_color(), label=f"{mode} backward")
            for r in framed:
                axes[0].annotate(r["scene"], (r["triangles"], r["forward_seconds"]), fontsize=6)
            # The paper's figures are means of forward + backward over its runs' frames: these
            # compare with them (the medians above do not).
            averaged = [r for r in framed if r["frame_seconds_mean"] is not None]
            if averaged:
                axes[0].loglog([r["triangles"] for r in averaged], [r["frame_seconds_mean"] for r in averaged], marker, mfc="none", mew=2, ms=9, color=line.get_color(), label=f"{mode} mean forward + backward")
        if sel:
            axes[1].loglog([r["triangles"] for r in sel], [r["contact_seconds"] for r in sel], marker, label=mode)
        paper = [(PAPER_FRAME_TRIANGLES[k], v[mode]) for k, v in PAPER_FRAME_SECONDS.items()]
        axes[0].loglog(*zip(*paper), marker, mfc="none", color="gray", label=f"paper {mode} (CPU, mean forward + backward)")
    axes[0].set_ylabel("seconds per frame (medians; means where marked)")
    axes[1].set_ylabel("seconds per contact evaluation (value, gradient, Hessian)")
    for ax in axes:
        ax.set_xlabel("dynamic triangles")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    replace_file(path, lambda temporary: fig.savefig(temporary, dpi=120))
    plt.close(fig)
    return True


# --- time against error (issue 8) -------------------------------------------------------------


def accuracy_scene(*, balls: int = 3, points_per_ball: int = 18, gap: float = 0.02, speed: float = 1.0):
    """A small billiards case: the cue and the rack's first ``balls`` balls of
    ``warpcontact.scenes.benchmark_rack`` (Fibonacci balls of ``points_per_ball`` points),
    on a two-triangle table reaching 1 m beyond them; the cue starts ``gap`` m in front of
    the apex ball moving into it at ``speed`` m/s (``strike_setup``). Each struck ball's goal is 1 m
    beyond it (alternately 0.5 m left and right) with zero tolerance, so the task loss has a
    gradient. Returns (scene, the cue's initial-state controls (x, y, vx, vy))."""
    from .scenes import RACK_BALLS, benchmark_rack, fibonacci_ball, ground_rectangle

    if not 1 <= balls <= RACK_BALLS:
        # More were cut to the rack's 15 while the results reported the number asked for.
        raise ValueError(f"balls: the rack has {RACK_BALLS} balls besides the cue, got {balls}")
    scene = benchmark_rack(*fibonacci_ball(points_per_ball))
    keep = {"ground", "cue", *(f"ball{i:02d}" for i in range(balls))}
    scene.bodies = [b for b in scene.bodies if b.name in keep]
    strike_setup(scene, gap=gap, speed=speed)
    for i, b in enumerate(b for b in scene.bodies if b.name.startswith("ball")):
        b.target_position = b.pose[:3] + np.array([1.0, 0.5 * (-1) ** i, 0.0])
        b.target_tolerance = 0.0
    centres = np.array([b.pose[:2] for b in scene.bodies if not b.static])
    lo, hi = centres.min(axis=0) - 1.0, centres.max(axis=0) + 1.0
    ground = ground_rectangle(*(hi - lo), centre=(lo + hi) / 2)
    scene.bodies = [ground if b.name == "ground" else b for b in scene.bodies]
    cue = scene.body("cue")
    controls = np.array([0.0, 0.0, *cue.linear_velocity[:2]])  # the rack is Z-up
    cue.linear_velocity = np.zeros(3)  # the controls carry it (initial-state task)
    return scene, controls


def _accuracy_run(scene, controls, *, mode: str, eps: float, tolerance: float, frames: int, dev, leaf_precision: str = "float64"):
    """One rollout with its task gradient: (loss, d loss / d controls, trajectory (frames+1,
    nbodies, 7), forward seconds per frame, Newton iterations per frame, backward seconds, the
    problem)."""
    from .solver import ImplicitSolver
    from .tasks import TaskProblem

    class TimedSolver(ImplicitSolver):
        def step(self, *args, **kwargs):
            info, seconds = _timed(lambda: super(TimedSolver, self).step(*args, **kwargs), self.model.device)
            self.seconds.append(seconds)
            self.iterations.append(info.iterations)
            return info

    scene.settings.contact_mode = mode
    scene.settings.eps = eps
    scene.settings.leaf_precision = leaf_precision
    problem = TaskProblem(scene, device=dev)
    problem.solver = TimedSolver(problem.model, tolerance=tolerance)
    problem.solver.seconds, problem.solver.iterations = [], []
    q0 = problem.model.initial_q
    timings = {}
    loss, grad, trajectory = problem.rollout(controls, (q0, q0), frames, timings=timings)
    # The backward alone: the rollout's time beyond its forward steps also counted the
    # states' allocation, the loss and the trajectory's read back (31-41% more).
    return loss, grad.reshape(-1), trajectory, problem.solver.seconds, problem.solver.iterations, timings["backward_seconds"], problem


def run_accuracy_benchmark(
    *,
    eps_values=(0.25, 0.5, 1.0, 2.0, 4.0),
    tolerances=(1e-9, 1e-10, 1e-11),
    precisions=LEAF_PRECISIONS,
    eps: float = 0.5,
    default_tolerance: float = 1e-10,
    reference_tolerance: float = 1e-12,
    frames: int = 3,
    balls: int = 3,
    points_per_ball: int = 18,
    gap: float = 0.02,
    speed: float = 1.0,
    device,
    out_dir: Path,
    progress=None,
) -> list[dict]:
    """Time against error on the small billiards case of ``accuracy_scene``.

    The reference is brute force (the exact sum) at ``reference_tolerance``. Configurations:
    BSH at each of ``eps_values`` and brute force, at ``default_tolerance``; BSH at ``eps``
    at each of ``tolerances``; BSH at ``eps`` and ``default_tolerance`` with each of
    ``precisions`` for the leaf plane searches. Each simulates ``frames`` frames on a tape and takes the
    gradient of the task loss (squared distances of the struck balls to their goals) with
    respect to the cue's initial (x, y, vx, vy). Per configuration: forward seconds per frame
    (median) and Newton iterations, backward seconds per frame; trajectory deviation from the
    reference (largest centre-of-mass distance over bodies and frames, m, and relative to the
    reference's largest displacement); contact force / torque errors against brute force at
    the reference's configurations (worst over frames, as in ``bench contact``); and the
    task gradient's cosine and relative error against the reference's; ``converged_step_m``,
    the Newton step length each configuration converged under (``ImplicitSolver.converged_step``:
    tolerances above its acceleration cap, ~6e-9 here, converge alike, so the defaults
    sweep below it; 1e-4 to 1e-8 gave one row three times, a probe, stop 62). Everything but the
    precision sweep's float32 plane searches is float64. Writes accuracy.json, accuracy.csv,
    accuracy.png.
    """
    from .solver import SolverError

    eps_values, tolerances, precisions = _distinct(eps_values), _distinct(tolerances), _distinct(precisions)
    _check_settings(eps_values=(*eps_values, eps))
    loosest = max((default_tolerance, *tolerances))
    tightest = min((default_tolerance, *tolerances))
    if not reference_tolerance <= tightest:
        # A reference looser than the rows it judged was accepted: a 1e-10 row's deviation was
        # measured against a 1e-3 "reference" (a probe, stop 65).
        raise ValueError(f"reference_tolerance: {reference_tolerance:g} is looser than the tightest tolerance measured ({tightest:g}, of {tightest:g} .. {loosest:g}); the reference must be at least as tight")
    dev = resolve_device(device)
    accuracy_scene(balls=balls, points_per_ball=points_per_ball, gap=gap, speed=speed)  # its errors before any work
    module_seconds = _load_kernel_modules(dev)  # so the first configuration's times exclude compilation
    for precision in precisions:
        float32_search(precision)
    configs = [("reference", "brute", 1.0, reference_tolerance, "float64")]
    configs += [("eps", "bsh", e, default_tolerance, "float64") for e in eps_values]
    configs += [("eps", "brute", 1.0, default_tolerance, "float64")]
    configs += [("tolerance", "bsh", eps, t, "float64") for t in tolerances]
    configs += [("precision", "bsh", eps, default_tolerance, p) for p in precisions]
    rows: list[dict] = []
    reference = None
    header = {
        "module_load_seconds": module_seconds,
        "frames": frames,
        "balls": balls,
        "points_per_ball": points_per_ball,
        # The strike: --gap and --speed were recorded nowhere (a probe, stop 58).
        "gap_m": gap,
        "speed_m_per_s": speed,
        "reference": f"brute force, tolerance {reference_tolerance:g}",
    }

    def save(*, complete=False):
        _write_results(out_dir, "accuracy", dev, None, {**header, "rows": rows}, complete=complete)

    def finish(row):
        rows.append(row)
        if progress:
            progress(row)
        save()

    try:
        for sweep, mode, e, tol, precision in configs:
            scene, controls = accuracy_scene(balls=balls, points_per_ball=points_per_ball, gap=gap, speed=speed)
            row = {"sweep": sweep, "model": mode, "eps": e if mode == "bsh" else None, "tolerance": tol, "leaf_precision": precision, "triangles": _scene_triangles(scene)[0], "frames": frames}
            try:
                loss, grad, trajectory, forward, iterations, backward, problem = _accuracy_run(scene, controls, mode=mode, eps=e, tolerance=tol, frames=frames, dev=dev, leaf_precision=precision)
            except SolverError as exc:
                if reference is None:
                    raise ValueError(f"the reference run (brute force, --reference-tolerance {reference_tolerance:g}) failed: {exc}") from None
                finish({**row, "error": str(exc)})  # failed rows were left out of the table
                continue
            if reference is None:
                ref_grads = [problem.model.contact.evaluate(q).grad for q in trajectory]
                reference = {"grad": grad, "trajectory": trajectory, "contact_grads": ref_grads}
            com = trajectory[:, :, :3]
            ref_com = reference["trajectory"][:, :, :3]
            deviation = np.linalg.norm(com - ref_com, axis=2)
            motion = np.linalg.norm(ref_com - ref_com[0], axis=2).max()
            radius = problem.model.body_radius
            errors = [_force_errors(problem.model.contact.evaluate(q).grad, g, radius) for q, g in zip(reference["trajectory"], reference["contact_grads"])]
            g_ref = reference["grad"]
            finish({
                **row,
                "forward_seconds": float(np.median(forward)),
                "newton_iterations": float(np.mean(iterations)),
                "backward_seconds": backward / frames,
                "converged_step_m": problem.solver.converged_step(problem.dt),
                "loss": loss,
                "trajectory_deviation_max": float(deviation.max()),
                "trajectory_deviation_final": float(deviation[-1].max()),
                "trajectory_deviation_relative": float(deviation.max() / motion) if motion > 0 else None,
                "force_error_max": max(x["force_error_max"] for x in errors),
                "force_cosine_min": min(x["force_cosine_min"] for x in errors),
                "torque_error_max": max(x["torque_error_max"] for x in errors),
                "gradient": grad.tolist(),
                # Clipped: rounding gave the reference's own row 1.0000000000000002.
                "gradient_cosine": float(np.clip(grad @ g_ref / (np.linalg.norm(grad) * np.linalg.norm(g_ref)), -1.0, 1.0)) if np.linalg.norm(grad) * np.linalg.norm(g_ref) > 0 else None,
                "gradient_relative_error": float(np.linalg.norm(grad - g_ref) / np.linalg.norm(g_ref)) if np.linalg.norm(g_ref) > 0 else None,
                "error": None,
            })
        save(complete=True)
    finally:
        _plot_at_end(out_dir / "accuracy.png", _plot_accuracy, rows)
    return rows


def _accuracy_plot_value(row: dict, key: str) -> float:
    """A row's error on a log axis: 1 - cosine for the gradient, floored at 1e-16; a missing
    value (a zero gradient has no cosine) at the floor."""
    value = row[key]
    if value is not None and key == "gradient_cosine":
        value = 1.0 - value
    return max(value if value is not None else 1e-16, 1e-16)


def _plot_accuracy(rows: list[dict], path: Path) -> bool:
    plt = optional_pyplot()
    ok = [r for r in rows if r.get("error") is None and r["sweep"] != "reference"]
    if plt is None or not ok:
        return False
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    panels = (
        ("trajectory_deviation_max", "max centre-of-mass deviation from reference (m)"),
        ("force_error_max", "max contact force error / max brute-force force"),
        ("gradient_cosine", "1 - cos(task gradient, reference)"),
    )
    for ax, (key, label) in zip(axes, panels):
        for sweep, style in (("eps", "o-"), ("tolerance", "s-"), ("precision", "^-")):
            sel = [r for r in ok if r["sweep"] == sweep and r["model"] == "bsh"]
            if not sel:
                continue
            values = [_accuracy_plot_value(r, key) for r in sel]
            times = [r["forward_seconds"] for r in sel]
            ax.loglog(times, values, style, label=f"bsh, {sweep} sweep")
            for r, t, v in zip(sel, times, values):
                note = {"eps": f"{r['eps']:g}", "tolerance": f"{r['tolerance']:.0e}", "precision": r["leaf_precision"]}[sweep]
                ax.annotate(note, (t, v), fontsize=7)
        for r in ok:
            if r["model"] == "brute":
                ax.loglog([r["forward_seconds"]], [_accuracy_plot_value(r, key)], "k*", ms=9, label="brute force")
        ax.set_xlabel("forward seconds per frame")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    replace_file(path, lambda temporary: fig.savefig(temporary, dpi=120))
    plt.close(fig)
    return True
