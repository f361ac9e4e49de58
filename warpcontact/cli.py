"""Command-line entry point: warpcontact run | compare | list | simulate | demo | bench ..."""

import argparse
import dataclasses
import difflib
import json
import logging
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import warp as wp

from ._files import hold_folder, interrupts_held, replace_file, replace_files, replace_json
from ._validate import MAX_BARRIER_SUPPORT, MAX_COUNT, MAX_FRAMES, check_barrier_support
from .builder import contact_setting_problem
from .contact import CENTRED_WEIGHTS
from .leaf import LEAF_PRECISIONS
from .tasks import IPC_TASK_STIFFNESS, MAX_ITERATIONS, MODELS

__all__ = ["main"]

# The file in a run's output folder that keeps its progress (``tasks.TaskCheckpoint``).
CHECKPOINT_NAME = "checkpoint.npz"
# The results of run and simulate, which share trajectory.usda (``_refuse_mixed_results``).
RUN_OUTPUTS = ("metrics.json", "trajectory.usda", "convergence.png")
SIMULATE_OUTPUTS = ("trajectory.usda", "summary.json")


def _demo(args) -> int:
    import trimesh

    from .leaf import leaf_gap_problem, triangle_pair_potential

    sphere = trimesh.creation.icosphere(subdivisions=args.subdivisions, radius=0.5)
    V = np.asarray(sphere.vertices, dtype=np.float64)
    F = np.asarray(sphere.faces)
    tris = V[F]
    nt = len(F)
    rows = []
    for gap in args.gaps:
        problem = leaf_gap_problem(gap, V[:, 2].max() - V[:, 2].min())
        if problem is not None:  # it was reported as triangle pairs that did not solve, after the finished gaps
            raise ValueError(f"--gaps: {problem}")
    # The first timed gap included compiling and loading the leaf kernels (a probe, stop 58);
    # and a device that is not there is refused before the table's header.
    triangle_pair_potential(tris[:1], tris[:1] + np.array([0.0, 0.0, 2.0]), device=args.device)
    print(f"Brute-force leaf potential between two icospheres ({nt} triangles each, {nt * nt} pairs), device {args.device}")
    print(f"{'gap [m]':>10} {'P':>16} {'net force on A [N/mu]':>24} {'Newton it (mean)':>17} {'seconds':>8}")
    for gap in args.gaps:
        # Sphere B sits below A: A's lowest point is `gap` above B's highest point.
        shift = V[:, 2].max() - V[:, 2].min() + gap
        tris_a = np.repeat(tris + np.array([0.0, 0.0, shift]), nt, axis=0)
        tris_b = np.tile(tris, (nt, 1, 1))
        start = time.perf_counter()
        res = triangle_pair_potential(tris_a, tris_b, device=args.device)
        seconds = time.perf_counter() - start
        if not res.ok.all():
            bad = int((~res.ok).sum())
            print(f"error: {bad} triangle pairs did not solve at gap {gap}", file=sys.stderr)
            return 1
        force = -res.grad[:, 0].sum(axis=(0, 1))
        rows.append(
            {
                "gap": gap,
                "potential": float(res.value.sum()),
                "net_force_on_a": force.tolist(),
                "mean_newton_iterations": float(res.iterations.mean()),
                "seconds": seconds,
            }
        )
        print(f"{gap:10.1e} {res.value.sum():16.6e} {force[2]:24.6e} {res.iterations.mean():17.2f} {seconds:8.3f}")
    out = Path(args.out)
    payload = {"triangles_per_body": nt, "device": args.device, "results": rows}
    replace_json(out / "demo.json", payload)
    print(f"wrote {out / 'demo.json'}")
    return 0


def _simulate(args) -> int:
    import warp as wp

    from . import io
    from .solver import ImplicitSolver, SolverError
    from .types import set_body_velocity

    out = Path(args.out)
    trajectory = out / "trajectory.usda"
    scene_path = _resolve_scene_path(args.scene)
    scene = io.load_scene(scene_path)
    frames = args.frames or scene.settings.frames
    model = scene.build_model(device=args.device)
    solver = ImplicitSolver(model)
    dt = scene.settings.time_step
    lin, ang = scene.initial_velocities()
    # Two states in turn and the poses on the host: a state kept per frame grew by ~2 MB/s.
    state, following = model.state(requires_grad=False), model.state(requires_grad=False)
    set_body_velocity(state, wp.array(lin, dtype=wp.vec3d, device=model.device), wp.array(ang, dtype=wp.vec3d, device=model.device), dt, body_names=model.body_names)
    poses = [state.body_q.numpy().copy()]
    control = model.control(requires_grad=False)
    iterations = []
    stopped = None
    start = time.perf_counter()
    print(f"{scene_path}: {model.num_bodies} bodies, {frames} frames of {dt} s on {model.device}")
    for frame in range(frames):
        try:
            info = solver.step(state, following, control, dt)
            poses.append(following.body_q.numpy().copy())
            state, following = following, state
            iterations.append(info.iterations)
            if (frame + 1) % max(1, frames // 10) == 0 or frame + 1 == frames:
                try:
                    print(f"  frame {frame + 1:4d}/{frames}  Newton iterations {info.iterations:3d}  min separation {info.min_separation:.2e} m")
                except OSError:
                    pass  # a full or closed stdout lost every frame simulated (a probe, stop 63)
        except (SolverError, ValueError) as exc:
            # The frames before it are written: they are what one looks at to see why. A later
            # step's ValueError is the simulation's, not the scene's (a state it produced that
            # a check refuses): every frame was lost (a probe, stop 58).
            if isinstance(exc, ValueError) and frame == 0:
                raise
            stopped = {"frame": frame, "error": str(exc)}
            break
        except KeyboardInterrupt:
            # A long run stopped by hand keeps what it simulated, wherever in the frame the
            # interruption came (outside the step it lost every frame).
            stopped = {"frame": len(poses) - 1, "error": "interrupted"}
            break
    seconds = time.perf_counter() - start
    # Held from the first read back: an interruption anywhere in the write lost every frame.
    with interrupts_held() as interrupted:
        q = np.array(poses)
        targets = {
            b.name: {"target": b.target_position.tolist(), "final": q[-1, i, :3].tolist(), "distance": float(np.linalg.norm(q[-1, i, :3] - b.target_position))}
            for i, b in enumerate(scene.bodies)
            if b.target_position is not None
        }
        summary = {
            "scene": _recorded_scene(scene_path),
            "device": str(model.device),
            "frames": len(poses) - 1,
            "time_step": dt,
            "seconds": seconds,
            "newton_iterations_mean": float(np.mean(iterations)) if iterations else None,
            "newton_iterations_max": int(np.max(iterations)) if iterations else None,
            "targets": targets,
            **({"stopped": stopped} if stopped else {}),
        }
        with replace_files(out, ("trajectory.usda", "summary.json")) as staged:
            io.export_trajectory(scene, io.model_to_scene_poses(scene, model, q), staged / "trajectory.usda")
            replace_json(staged / "summary.json", summary)
    newton = f", mean {np.mean(iterations):.1f} Newton iterations per frame" if iterations else ""
    print(f"wrote {trajectory} and {out / 'summary.json'} ({seconds:.1f} s{newton})")
    if stopped:
        # "frame 2" read as the third step, after the progress line "frame 2/8" (a probe).
        step = f"the step from frame {stopped['frame']} to {stopped['frame'] + 1}"
        what = f"interrupted during {step}" if stopped["error"] == "interrupted" else f"{step} failed: {stopped['error']}"
        print(f"error: {what}; the outputs hold frames 0 to {stopped['frame']}", file=sys.stderr)
        return 130 if stopped["error"] == "interrupted" else 1
    if interrupted:
        print("interrupted while the outputs were written: they were finished first and hold every frame", file=sys.stderr)
        return 130
    return 0


def _resolve_scene_path(name: str) -> Path:
    """A .usda path, or the name of a shipped scene (installed with the package)."""
    from . import io

    path = Path(name)
    if path.suffix.lower() in io.USD_READ_SUFFIXES:
        return path
    from .scenes import SCENE_NAMES, shipped_scene

    if name not in SCENE_NAMES:
        # A misspelt name got the whole list and no hint, where a misspelt USD attribute gets one.
        close = difflib.get_close_matches(name.lower(), SCENE_NAMES, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ValueError(f"{name!r}: not a USD file ({', '.join(io.USD_READ_SUFFIXES)}) and not a shipped scene (known: {', '.join(SCENE_NAMES)}){hint}")
    return shipped_scene(name)


def _recorded_scene(path) -> str:
    """A scene's path as the JSON outputs record it: absolute, as a trajectory records its
    source (summary.json named it as typed, relative to where the command ran; a probe, stop 63)."""
    return str(Path(path).resolve())


def _output_folder(path: str) -> Path:
    """The output folder, created if needed; ValueError if it cannot be created or written."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: output path exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    if not os.access(out, os.W_OK):
        raise ValueError(f"{out}: output folder is not writable")
    return out


def _load_task(args):
    """(scene path, scene, TaskSettings) of a run or compare, after checking the device,
    the output folder and the scene's task metadata, so bad input fails before any work."""
    from . import io
    from ._runtime import resolve_device
    from .tasks import TaskSettings, sample_box, validate_task

    resolve_device(args.device)
    scene_path = _resolve_scene_path(args.task)
    scene = io.load_scene(scene_path)
    validate_task(scene)
    settings = TaskSettings.from_task(scene, quick=args.quick, iterations=args.iters, receding_stride=args.stride)
    if args.init_samples:
        sample_box(scene, args.init_samples)
        settings.initial_samples, settings.sample_seed = args.init_samples, args.seed
    return scene_path, scene, settings


def _refuse_earlier_results(out: Path, names: tuple, overwrite: bool):
    """FileExistsError when OUT holds an earlier run's results and --overwrite is not given:
    a task run or a GPU benchmark can take hours, and its results are not to be replaced by
    accident."""
    for name in names:
        if (out / name).exists() and not overwrite:
            raise FileExistsError(f"{out / name} holds an earlier run's results")


def _refuse_input_among_outputs(args, out: Path):
    """ValueError when the scene a command reads is one of the files it writes: a run on
    OUT/trajectory.usda called the scene an earlier run's results, and with --overwrite
    replaced it with the trajectory (no physics schemas: the next run had no bodies)."""
    inputs = [getattr(args, name, None) for name in ("task", "scene")] + list(getattr(args, "scenes", None) or [])
    # An output is replaced as a file (os.replace): a link there is replaced, not followed.
    outputs = {out.resolve() / name: name for name in args.outputs}
    for given in inputs:
        if given is None:
            continue
        try:
            resolved = Path(given).resolve()
        except (OSError, RuntimeError):
            continue  # a symlink loop: no output's path, and reading it says what is wrong (a traceback here)
        if resolved in outputs:
            raise ValueError(f"{given}: the input scene is this command's output {outputs[resolved]} in {out}, which it would replace; choose another --out")


def _refuse_mixed_results(out: Path, names: tuple):
    """ValueError when a file this command replaces belongs with another command's results
    in OUT: run and simulate both write trajectory.usda, and a simulate --overwrite into a
    run's folder left the run's metrics.json and convergence.png beside another trajectory
    (a run, simulate's summary.json), without a word."""
    if names != RUN_OUTPUTS and set(names) & set(RUN_OUTPUTS) and (out / CHECKPOINT_NAME).exists():
        # A simulate there blocked the run from resuming in place (a probe, stop 63).
        raise ValueError(f"{out / CHECKPOINT_NAME}: an unfinished run's progress, which this command's results would keep from resuming; continue it with run --resume, or choose another --out")
    for others in (RUN_OUTPUTS, SIMULATE_OUTPUTS):
        shared = [name for name in others if name in names and (out / name).exists()]
        companions = [name for name in others if name not in names and (out / name).exists()]
        if shared and companions:
            raise ValueError(f"{out / shared[0]} belongs with {', '.join(companions)} in {out}, another command's results, which would be left beside this command's {shared[0]}; remove them or choose another --out")


def _refuse_unwritable_names(out: Path, names: tuple):
    """ValueError when an output's name in OUT is taken by a folder (or anything but a file),
    found before the work rather than when its results are written."""
    for name in names:
        if (out / name).exists() and not (out / name).is_file():
            raise ValueError(f"{out / name}: exists and is not a file; the results cannot be written there")


def _task_problem(scene, settings, model: str, args):
    """The TaskProblem of one model; gb's bundle is seeded by --seed (4 samples with --quick);
    ipc's barrier stiffness is --ipc-stiffness in place of the scene's mu."""
    from .bundle import BundleSettings
    from .tasks import TaskProblem

    bundle = BundleSettings(samples=4 if args.quick else 8, seed=args.seed) if model == "gb" else None
    return TaskProblem(scene, device=args.device, settings=settings, model=model, bundle=bundle, ipc_stiffness=args.ipc_stiffness)


def _progress(label: str):
    def progress(i, n, loss):
        bar = "#" * int(30 * i / n)
        print(f"\r{label}[{bar:<30}] {i}/{n} loss {loss:.6g}", end="", flush=True)

    return progress


def _sample_progress():
    """Prints each initial-sample draw as it finishes, on one line: a CPU took minutes over
    Billiards' eight in silence (a probe, stop 63)."""
    best = [None]

    def progress(i, n, loss):
        if loss is not None and (best[0] is None or loss < best[0]):
            best[0] = loss
        end = "\n" if i == n else ""
        print(f"\rinitial samples: {i}/{n} drawn, loss {_loss_text(loss)}{'' if loss is not None else ' (infeasible)'}, best {_loss_text(best[0])}   ", end=end, flush=True)

    return progress


def _loss_text(loss) -> str:
    """A loss for messages; None is an initial loss the trivial plan could not reach."""
    return "n/a" if loss is None else f"{loss:.6g}"


def _result_metrics(result, problem) -> dict:
    """A descent's results and the contact model its ``TaskProblem`` ran ("ours" runs the
    scene's own, which a scene may set to sdrs or ipc: the outputs did not say): its mode,
    stiffness and, for the locally supported barriers, their dhat (no output recorded them)."""
    settings = problem.scene.settings
    return {
        **result.extra,  # first: the run's own results are never written over
        "loss_history": result.loss_history,
        "initial_loss": result.initial_loss,
        "final_loss": result.final_loss,
        "success": result.success,
        "seconds": result.seconds,
        "iterations": result.iterations,
        "contact_mode": settings.contact_mode,
        "contact_stiffness": settings.contact_stiffness,
        **({"dhat_m": problem.model.contact.dhat} if settings.contact_mode in ("ipc", "sdrs") else {}),
    }


def _settings_metrics(settings, args, models) -> dict:
    """The optimisation settings of a run or compare, with ipc's stiffness when ipc runs."""
    return {
        "horizon": settings.horizon,
        "receding_horizon": settings.receding_horizon,
        # The window each descent optimised: the horizon where the receding horizon is 0 or
        # not shorter (an authored 10 over 6 frames read as a receding run of stride 2).
        "window": settings.window,
        "receding_stride": settings.receding_stride if settings.receding else None,
        "learning_rate": settings.learning_rate,
        # The Adam iterations asked for per window; "iterations" counts those run.
        "iterations_per_window": settings.iterations,
        **({"ipc_stiffness": args.ipc_stiffness} if "ipc" in models else {}),
    }


def _settings_line(settings) -> str:
    stride = f" executed {settings.receding_stride} frame(s) at a time" if settings.receding else ""
    return f"horizon {settings.horizon}, window {settings.window}{stride}, {settings.iterations} iterations, lr {settings.learning_rate}"


def _run(args) -> int:
    from . import io
    from .solver import SolverError
    from .tasks import TaskCheckpoint

    scene_path, scene, settings = _load_task(args)
    out = Path(args.out)
    checkpoint = TaskCheckpoint(out / CHECKPOINT_NAME)
    if checkpoint.exists() and not args.resume:
        try:
            saved = checkpoint.describe()
        except ValueError as exc:  # a file of the user's, which no option replaces
            raise ValueError(f"{exc}: remove or rename it, or choose another --out") from None
        raise ValueError(f"{checkpoint.path} holds an unfinished run ({saved}): continue it with --resume, or remove the file to start over")
    problem = _task_problem(scene, settings, args.model, args)
    if args.resume:
        problem.resumable(checkpoint.path)  # refused before the header says it resumes
    resumed = f", resumed from {checkpoint.path} ({checkpoint.describe()})" if args.resume else ""
    t = scene.task
    print(f"{scene_path}: task {t.name}, model {args.model}, control {t.control} of {problem.dof_names}, {_settings_line(settings)}{resumed}")
    try:
        result = problem.optimize(progress=_progress(""), sample_progress=_sample_progress(), checkpoint=checkpoint.path, resume=args.resume, keep_checkpoint=True)
    except KeyboardInterrupt:
        kept = f"progress kept in {checkpoint.path} ({checkpoint.describe()}); continue with the same command and --resume" if checkpoint.exists() else "nothing to keep yet"
        print(f"\ninterrupted: {kept}", file=sys.stderr)
        return 130
    except SolverError as exc:
        # The trivial guess failed (later rollouts are halved back, later windows stop the run
        # with their executed frames): there is nothing to write.
        kept = f"; the progress before it is in {checkpoint.path} ({checkpoint.describe()})" if checkpoint.exists() else ""
        print(f"\nerror: the simulation failed: {exc}{kept}", file=sys.stderr)
        return 1
    print()
    metrics = {
        "task": t.name,
        "scene": _recorded_scene(scene_path),
        "model": args.model,
        "device": str(problem.model.device),
        "seed": args.seed,
        "quick": bool(args.quick),
        "init_samples": settings.initial_samples,
        **_settings_metrics(settings, args, [args.model]),
        **_result_metrics(result, problem),
    }
    # The checkpoint goes only once the results are written: an interrupted or failed
    # write is resumed (the finished descent replays its last state), not run again.
    try:
        with replace_files(out, ("metrics.json", "convergence.png", "trajectory.usda")) as staged:
            replace_json(staged / "metrics.json", metrics)
            plotted = _plot_convergence({args.model: result.loss_history}, staged / "convergence.png", title=f"{t.name} ({args.model})")
            io.export_trajectory(scene, io.model_to_scene_poses(scene, problem.model, result.trajectory), staged / "trajectory.usda")
    except KeyboardInterrupt:
        print(f"\ninterrupted while writing the results: the run is kept in {checkpoint.path}; write them with the same command and --resume", file=sys.stderr)
        return 130
    except (OSError, ValueError) as exc:
        print(f"error: writing the results failed ({exc}); the run is kept in {checkpoint.path}: write them with the same command and --resume", file=sys.stderr)
        return 1
    checkpoint.remove()
    print(f"loss {_loss_text(result.initial_loss)} -> {result.final_loss:.6g}, success {result.success}, {result.seconds:.1f} s; wrote {out}/metrics.json, trajectory.usda, {_plot_name('convergence.png', plotted)}")
    stalls = result.extra.get("stalled", [])
    if stalls:
        first = stalls[0]
        where = f"window at frame {first['frame']}, " if "frame" in first else ""
        print(f"note: {len(stalls)} descent(s) stopped before their iterations were done (the first: {where}iteration {first['iteration']}, {first['error']}); metrics.json lists them under stalled", file=sys.stderr)
    stopped = result.extra.get("stopped")
    if stopped:
        print(f"error: the run stopped at frame {stopped['frame']} of {settings.horizon}: the simulation failed: {stopped['error']}; its outputs hold the frames executed before it", file=sys.stderr)
        return 1
    return 0


def _compare(args) -> int:
    from .solver import SolverError

    scene_path, scene, settings = _load_task(args)
    out = Path(args.out)
    if args.frictionless:
        scene.settings.friction = 0.0
    t = scene.task
    print(f"{scene_path}: task {t.name}, models {', '.join(args.models)}, {_settings_line(settings)}")
    results = {}
    payload = {
        "task": t.name,
        "scene": _recorded_scene(scene_path),
        "device": args.device,
        "seed": args.seed,
        "quick": bool(args.quick),
        "init_samples": settings.initial_samples,
        "frictionless": bool(args.frictionless),
        **_settings_metrics(settings, args, args.models),
        "complete": False,
        "models": results,
    }
    if settings.initial_samples:
        # One start for every model: each model choosing the best draw by its own loss
        # started them from different draws (a probe, stop 62). The paper's model scores them.
        chooser = "ours" if "ours" in args.models else args.models[0]
        try:
            values, samples = _task_problem(scene, settings, chooser, args).best_initial_sample(progress=_sample_progress())
        except (ValueError, SolverError) as exc:
            print(f"error: {chooser} could not score the initial samples: {exc}", file=sys.stderr)
            return 1
        payload["initial_samples"] = {"scored_by": chooser, "samples": samples, "start": values.tolist()}
        settings = dataclasses.replace(settings, initial_samples=0, initial_values=tuple(float(v) for v in values))
        print(f"start: the best of {len(samples)} draws by {chooser}'s loss, {_loss_text(min(x['loss'] for x in samples if x['loss'] is not None))}, for every model")
    interrupted = None
    for model in args.models:
        # A model that cannot run this scene (ipc off the CPU or without ipctk, a failed step
        # at the initial guess) is reported and the others still run.
        try:
            problem = _task_problem(scene, settings, model, args)
            payload["device"] = str(problem.model.device)
            result = problem.optimize(progress=_progress(f"{model:>5} "))
        except KeyboardInterrupt:
            # Stopped by hand: the finished models are still plotted and tabled.
            interrupted = model
            break
        except (ValueError, SolverError) as exc:
            print(f"\n{model}: skipped: {exc}", file=sys.stderr)
            results[model] = {"error": str(exc)}
        else:
            print()
            results[model] = _result_metrics(result, problem)
        # Rewritten after every model, so an interrupted comparison keeps the finished ones;
        # "complete" is false until every model is in (one stopped after its first model read
        # as a finished comparison of that model alone, as the benches' results did).
        payload["complete"] = len(results) == len(args.models)
        if len(results) == 1:
            # An earlier comparison's plot goes with the first of this one's compare.json: it
            # stood beside it while the other models ran, and for good when the command was
            # killed (a probe, stop 64).
            (out / "compare.png").unlink(missing_ok=True)
        replace_json(out / "compare.json", payload)
    if not results:
        # Stopped during the first model: an earlier comparison's compare.json was announced
        # as this one's, beside a plot of "loss 0 at every iteration".
        earlier = [name for name in ("compare.json", "compare.png") if (out / name).exists()]
        left = f" ({', '.join(earlier)} in {out} are an earlier run's, left as they were)" if earlier else ""
        print(f"\ninterrupted during {interrupted} before any model finished: nothing written{left}", file=sys.stderr)
        return 130
    ran = {m: r["loss_history"] for m, r in results.items() if "error" not in r}
    # This comparison's plot or none: a Ctrl-C while it was drawn left an earlier run's
    # compare.png beside this compare.json (a probe).
    (out / "compare.png").unlink(missing_ok=True)
    try:
        plotted = _plot_convergence(ran, out / "compare.png", title=f"{t.name}: loss from the same initial guess")
    except KeyboardInterrupt:
        print(f"\ninterrupted while drawing compare.png: {out}/compare.json holds the finished models ({', '.join(results)}), without a plot", file=sys.stderr)
        return 130
    print(f"{'model':>6} {'initial loss':>13} {'final loss':>13} {'success':>8} {'seconds':>8}")
    for model, r in results.items():
        if "error" in r:
            print(f"{model:>6} {'skipped (see compare.json)':>44}")
        else:
            stopped = f"  stopped at frame {r['stopped']['frame']} (see compare.json)" if "stopped" in r else ""
            print(f"{model:>6} {_loss_text(r['initial_loss']):>13} {r['final_loss']:13.6g} {r['success']!s:>8} {r['seconds']:8.1f}{stopped}")
    print(f"wrote {out}/compare.json, {_plot_name('compare.png', plotted) if ran else 'not compare.png (no model ran)'}")
    if interrupted is not None:
        print(f"\ninterrupted during {interrupted}: the models before it are in {out}/compare.json", file=sys.stderr)
        return 130
    if not ran:
        print("error: no model could run this scene", file=sys.stderr)
        return 1
    return 0


def _bench_plot_name(args, name: str) -> str:
    """A bench plot's name in its "wrote ..." line, or why there is none: a bench removes an
    earlier run's plot that it cannot replace, so the file is there only when drawn."""
    from .bench import optional_pyplot

    if (Path(args.out) / name).is_file() or optional_pyplot() is None:
        return _plot_name(name, (Path(args.out) / name).is_file())
    return f"not {name} (no rows to plot)"


def _plot_name(name: str, plotted: bool) -> str:
    """A plot's name in a "wrote ..." line, or why it was not written."""
    return name if plotted else f"not {name} (matplotlib is not installed: pip install 'warpcontact[plot]')"


def _loss_axis_scale(histories: dict) -> str | None:
    """"log" for losses spanning a factor of 10 or more (as the paper's figures), "linear"
    below (on a log axis within one decade every tick read "6.21x10^0", and the stalled
    baselines' 6.21 could not be told from 6.2100005), None where no loss is positive."""
    positive = np.concatenate([np.asarray(h, dtype=np.float64).ravel() for h in histories.values()] or [np.zeros(0)])
    positive = positive[positive > 0]
    if not positive.size:
        return None
    return "log" if positive.max() >= 10.0 * positive.min() else "linear"


def _plot_convergence(histories: dict, path: Path, *, title: str) -> bool:
    """Loss against optimiser iteration, one line per model, on a log scale (as the paper's
    figures) where the losses span a factor of 10 or more (``_loss_axis_scale``).

    A loss of exactly 0 (every target within tolerance) has no place on a log axis; such
    points are left out and the legend says the model reached 0. Where nothing is drawn (no
    history, no matplotlib) an earlier run's plot at ``path`` is removed: it stayed beside
    the new results (with no history it became "loss 0 at every iteration").
    """
    from .bench import optional_pyplot

    plt = optional_pyplot()
    if plt is None or not histories:
        path.unlink(missing_ok=True)
        return False
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    # Stalled baselines share one flat line; distinct dashes and markers keep each visible.
    styles = [("-", "o"), ("--", "s"), ("-.", "^"), (":", "x")]
    longest = 0
    for index, (label, history) in enumerate(histories.items()):
        loss = np.asarray(history, dtype=np.float64)
        longest = max(longest, len(loss))
        reached = bool(len(loss)) and loss.min() == 0.0
        dash, marker = styles[index % len(styles)]
        ax.plot(np.arange(1, len(loss) + 1), np.where(loss > 0, loss, np.nan), linestyle=dash, marker=marker, markersize=4, label=f"{label} (reached 0)" if reached else label)
    scale = _loss_axis_scale(histories)
    if scale == "log":
        ax.set_yscale("log")
    elif scale is None:
        # Every loss 0 (the targets met from the start): an empty log axis told nothing.
        ax.text(0.5, 0.5, "loss 0 at every iteration", transform=ax.transAxes, ha="center", va="center")
    if longest:
        ax.set_xlim(0.5, longest + 0.5)
    ax.set_xlabel("optimiser iteration")
    # Short: the longer "its values span less than a factor of 10" was clipped at both ends.
    ax.set_ylabel("loss (linear axis: spans < 10x)" if scale == "linear" else "loss")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    if histories:
        ax.legend()
    fig.tight_layout()
    replace_file(path, lambda temporary: fig.savefig(temporary, dpi=120))
    plt.close(fig)
    return True


def _list(args) -> int:
    from .scenes import SCENE_NAMES, shipped_scene

    print("tasks and scenes (run with: warpcontact run NAME | PATH.usda):")
    for name in SCENE_NAMES:
        print(f"  {name:16s} {shipped_scene(name)}")
    print("models (run --model, compare --models):")
    print("  ours   the paper's contact model (long-range, twice differentiable)")
    print("  ipc    IPC log barrier through ipctk, with IPC's lagged friction (CPU)")
    print("  sdrs   separating planes with a locally supported log barrier")
    print("  gb     gradient bundles over sdrs (seeded by --seed)")
    print("every model applies the scene's friction; compare --frictionless sets it to 0 for all")
    return 0


def _bench_leaf(args) -> int:
    from .bench import run_leaf_benchmark

    result = run_leaf_benchmark(num_pairs=args.pairs, repeats=args.repeats, device=args.device, out_dir=Path(args.out), precisions=args.precisions)
    print(json.dumps(result, indent=2))
    print(f"wrote {Path(args.out) / 'leaf.json'}, leaf.csv")
    return 0


def _bench_contact(args) -> int:
    from .bench import run_contact_benchmark

    rows = run_contact_benchmark(
        eps_values=args.eps,
        gaps=args.gaps,
        subdivisions=args.subdivisions,
        repeats=args.repeats,
        device=args.device,
        out_dir=Path(args.out),
        ipc_dhat=args.ipc_dhat or None,
        centred_weights=args.centred_weights,
    )
    print(f"{'scene':>15} {'gap':>8} {'mode':>6} {'weight':>6} {'eps':>6} {'seconds':>9} {'value/brute':>11} {'far':>7} {'blend':>7} {'leaf':>7} {'F err med':>10} {'F err max':>10} {'F cos min':>10} {'T err max':>10}")
    for r in rows:
        eps = "-" if r["eps"] is None else f"{r['eps']:g}"
        print(
            f"{r['scene']:>15} {r['gap']:8.0e} {r['mode']:>6} {r['centred_weight'] or '-':>6} {eps:>6} {r['median_seconds']:9.4f} {_fmt(r['value_ratio'], '11.4f')} {_fmt(r['num_far'], '7d')} {_fmt(r['num_blend'], '7d')} "
            f"{_fmt(r['num_leaf'], '7d')} {_fmt(r['force_error_median'], '10.2e')} {_fmt(r['force_error_max'], '10.2e')} {_fmt(r['force_cosine_min'], '10.6f')} {_fmt(r['torque_error_max'], '10.2e')}"
        )
    print(f"wrote {Path(args.out) / 'contact.json'}, contact.csv, {_bench_plot_name(args, 'contact.png')} (ipc rows: median_seconds is ipctk's collision build + barrier value/gradient/Hessian in vertex coordinates, median_seconds_rigid "
          "the same projected to rigid-body coordinates as ours are, ipc_active_collisions its pairs within dhat)")
    return 0


def _bench_scaling(args) -> int:
    from .bench import run_scaling_benchmark

    rows = run_scaling_benchmark(
        points_per_ball=args.points,
        eps=args.eps,
        brute_max_triangles=args.brute_max_triangles,
        repeats=args.repeats,
        device=args.device,
        out_dir=Path(args.out),
    )
    print(f"{'triangles':>9} {'mode':>6} {'seconds':>9} {'us/triangle':>11} {'far':>7} {'blend':>7} {'leaf':>8}")
    for r in rows:
        print(f"{r['triangles']:9d} {r['mode']:>6} {r['median_seconds']:9.4f} {1e6 * r['seconds_per_triangle']:11.2f} {r['num_far']:7d} {r['num_blend']:7d} {r['num_leaf']:8d}")
    print(f"wrote {Path(args.out) / 'scaling.json'}, scaling.csv, {_bench_plot_name(args, 'scaling.png')}")
    return 0


def _fmt(value, spec: str) -> str:
    """A number formatted by ``spec``, or '-' where a benchmark has none."""
    return "-" if value is None else format(value, spec)


# bench frame's default scenes. The paper code base's meshes are not shipped: a plain `bench
# frame` failed on every install without them (a probe), so their rack joins the defaults only
# where the --peer-meshes folder holds its ball; named in --scenes, a missing mesh is an error.
_FRAME_SCENES = ("billiards_512", "billiards_1280", "billiards_2560", "billiards_6208", "gather_bunny")
_PEER_FRAME_TRIANGLES = 6208
_PEER_FRAME_SCENE = f"peer_billiards_{_PEER_FRAME_TRIANGLES}"


def _default_frame_scenes(peer_meshes: Path) -> tuple[list[str], str | None]:
    """bench frame's scenes when --scenes is not given, and a note when the peer rack is left out."""
    from .bench import peer_ball_path

    ball = peer_ball_path(_PEER_FRAME_TRIANGLES, peer_meshes)
    if ball.is_file():
        return [*_FRAME_SCENES, _PEER_FRAME_SCENE], None
    return list(_FRAME_SCENES), f"note: {_PEER_FRAME_SCENE} left out of the default scenes: {ball} not found (pass --peer-meshes DIR, the paper code base's meshes)"


def _bench_frame(args) -> int:
    from .bench import run_frame_benchmark

    # Medians over the frames, then the means the paper's per-frame figures are. Printed with
    # the first row: a scene name that is none was refused under the header.
    header = [
        f"{'scene':>20} {'tri':>5} {'model':>5} {'frames':>6} {'forward s':>10} {'Newton it':>9} {'s/iter':>8} {'contact s':>10} {'backward s':>10} "
        f"{'fwd mean s':>10} {'frame mean s':>12}  note"
    ]

    def show(r):
        if header:
            print(header.pop())
        print(
            f"{r['scene']:>20} {r['triangles']:5d} {r['model']:>5} {r['frames']:6d} {_fmt(r['forward_seconds'], '10.4f')} {_fmt(r['newton_iterations'], '9.1f')} "
            f"{_fmt(r['forward_seconds_per_iteration'], '8.4f')} {_fmt(r['contact_seconds'], '10.5f')} {_fmt(r['backward_seconds'], '10.5f')} "
            f"{_fmt(r['forward_seconds_mean'], '10.4f')} {_fmt(r['frame_seconds_mean'], '12.4f')}  {r['error'] or ''}",
            flush=True,
        )

    scenes = args.scenes
    if scenes is None:
        scenes, left_out = _default_frame_scenes(Path(args.peer_meshes))
        if left_out:
            print(left_out, flush=True)
    rows = run_frame_benchmark(
        scenes=scenes,
        models=args.models,
        frames=args.frames,
        warmup=args.warmup,
        eps=args.eps,
        gap=args.gap,
        speed=args.speed,
        brute_max_triangles=args.brute_max_triangles,
        brute_eval_max_triangles=args.brute_eval_max_triangles,
        ipc_stiffness=args.ipc_stiffness,
        leaf_precision=args.leaf_precision,
        device=args.device,
        out_dir=Path(args.out),
        scene_dir=None if args.scene_dir is None else Path(args.scene_dir),
        peer_meshes=Path(args.peer_meshes),
        progress=show,
    )
    print(f"wrote {Path(args.out) / 'frame.json'}, frame.csv, {_bench_plot_name(args, 'frame.png')}")
    if all(r["frames"] == 0 and r["contact_seconds"] is None for r in rows):  # it exited 0 with nothing measured
        print(f"error: no frame was measured: {rows[0]['error'] if rows else 'no scenes'}", file=sys.stderr)
        return 1
    return 0


def _bench_accuracy(args) -> int:
    from .bench import run_accuracy_benchmark

    print(f"{'sweep':>9} {'model':>5} {'eps':>5} {'tol':>7} {'leaf':>7} {'forward s':>9} {'Newton it':>9} {'backward s':>10} {'traj dev m':>10} {'F err max':>9} {'F cos min':>9} {'grad cos':>12}  note")

    def show(r):
        print(
            f"{r['sweep']:>9} {r['model']:>5} {_fmt(r['eps'], '5g')} {r['tolerance']:7.0e} {r['leaf_precision']:>7} {_fmt(r.get('forward_seconds'), '9.4f')} {_fmt(r.get('newton_iterations'), '9.1f')} "
            f"{_fmt(r.get('backward_seconds'), '10.5f')} {_fmt(r.get('trajectory_deviation_max'), '10.2e')} {_fmt(r.get('force_error_max'), '9.2e')} "
            f"{_fmt(r.get('force_cosine_min'), '9.5f')} {_fmt(r.get('gradient_cosine'), '12.9f')}  {r.get('error') or ''}",
            flush=True,
        )

    run_accuracy_benchmark(
        eps_values=args.eps,
        tolerances=args.tolerances,
        precisions=args.precisions,
        eps=args.tolerance_eps,
        reference_tolerance=args.reference_tolerance,
        frames=args.frames,
        balls=args.balls,
        points_per_ball=args.points,
        gap=args.gap,
        speed=args.speed,
        device=args.device,
        out_dir=Path(args.out),
        progress=show,
    )
    print(f"wrote {Path(args.out) / 'accuracy.json'}, accuracy.csv, {_bench_plot_name(args, 'accuracy.png')}")
    return 0


def _whole_number(low: int, high: int | None = MAX_COUNT):
    """An argparse type: a whole number from ``low`` to ``high`` (None: no bound)."""
    wanted = f"a whole number >= {low}" if high is None else f"a whole number from {low} to {high:,}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {wanted}, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {wanted}, got {value}")
        return value

    return parse


_positive_int = _whole_number(1)
_non_negative_int = _whole_number(0)
_seed = _whole_number(0, None)  # numpy takes any whole number >= 0
# Bounds of what a benchmark or a simulation is asked to hold in memory: --pairs 1e11 failed
# with numpy's MemoryError traceback (6.55 TiB), --points 1e8 grew past 12 GB, and simulate
# kept 1e11 frames' poses (a task's horizon has the same bound).
_frame_count = _whole_number(1, MAX_FRAMES)
_pair_count = _whole_number(1, 10_000_000)
# The task settings' own bound (it was 2,147,483,647 here and 10,000,000 there; a probe, stop 65).
_iteration_count = _whole_number(1, MAX_ITERATIONS)
_points_per_ball = _whole_number(4, 100_000)


def _finite_number(*, zero: bool):
    """An argparse type: a finite number > 0, or >= 0 with ``zero``."""
    wanted = "a finite number >= 0" if zero else "a positive finite number"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {wanted}, got {text!r}") from None
        if not np.isfinite(value) or value < 0 or (value == 0 and not zero):
            raise argparse.ArgumentTypeError(f"must be {wanted}, got {text}")
        return value

    return parse


def _fraction(text: str) -> float:
    """An argparse type: a number in (0, 1), as solver tolerances are (a tolerance of 1e300
    was refused only after the other rows of ``bench accuracy`` had been written)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number in (0, 1), got {text!r}") from None
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"must be a number in (0, 1), got {text}")
    return value


_positive_float = _finite_number(zero=False)
_non_negative_float = _finite_number(zero=True)


def _contact_setting(name: str):
    """An argparse type: a value of the model's contact setting ``name`` (eps,
    contact_stiffness), by the builder's rule, checked before any work (``bench contact --eps
    0.5 1e200`` wrote its 0.5 rows over an earlier run's and then failed; ``compare
    --ipc-stiffness 1e200`` ran every other model first and named contact_stiffness)."""

    def parse(text: str) -> float:
        value = _positive_float(text)
        problem = contact_setting_problem(name, value)
        if problem is not None:
            raise argparse.ArgumentTypeError(f"{problem}, got {text}")
        return value

    return parse


_eps = _contact_setting("eps")
_stiffness = _contact_setting("contact_stiffness")


def _ipc_dhat(text: str) -> float:
    """An argparse type: an IPC barrier support (m) by ipc's rule, or 0 (no ipc rows); above
    1e6 m it was refused inside ipc naming "dhat" (a probe, stop 58)."""
    value = _non_negative_float(text)
    try:
        if value:
            check_barrier_support(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be 0 or a distance of at most {MAX_BARRIER_SUPPORT:g} m, got {text}") from None
    return value


def _model_list(text: str) -> list:
    models = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in models if m not in MODELS]
    if unknown or not models:
        raise argparse.ArgumentTypeError(f"unknown model(s) {unknown or [text]}; choose from {','.join(MODELS)}")
    return list(dict.fromkeys(models))


def _add_task_arguments(parser):
    parser.add_argument("task", help="a shipped scene's name (warpcontact list) or a .usda with task metadata")
    parser.add_argument("--iters", type=_iteration_count, default=None, help="optimiser iterations (per window)")
    parser.add_argument(
        "--stride",
        type=_positive_int,
        default=None,
        help="frames executed per receding window, at most the window (receding-window tasks only; default: the scene's; the paper's settings execute 1)",
    )
    parser.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    parser.add_argument("--quick", action="store_true", help="the scene's quick preset (warpcontact:task:quick:*), else the task's settings capped at 24 frames, windows of 8 and 8 iterations (minutes on a CPU)")
    parser.add_argument("--seed", type=_seed, default=0, help="seed of the gb model's samples and of --init-samples")
    parser.add_argument(
        "--init-samples",
        type=_positive_int,
        default=None,
        help="start from the best of N initial-state controls drawn from the scene's box (warpcontact:task:sampleLow/High) instead of the trivial guess",
    )
    parser.add_argument(
        "--ipc-stiffness",
        type=_stiffness,
        default=IPC_TASK_STIFFNESS,
        help=f"barrier stiffness of the ipc model, in place of the scene's mu (sized for ours; far too soft for IPC's barrier); default {IPC_TASK_STIFFNESS:g}",
    )


def _folder_name(text: str) -> str:
    """An argparse type: a folder's name, not empty (--out "" wrote into the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must name a folder (\".\" for the current one), got an empty name")
    return text


def _writes(parser, default_out: str, *outputs: str):
    """--out (default ``default_out``) and --overwrite of a command that writes ``outputs``
    there; ``main`` refuses to replace them unless told."""
    parser.add_argument("--out", type=_folder_name, default=default_out, help=f"output folder (default: {default_out})")
    parser.add_argument("--overwrite", action="store_true", help=f"replace an earlier run's {', '.join(outputs)} in OUT")
    parser.set_defaults(outputs=outputs)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="warpcontact", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="leaf potential between two icospheres at several gaps")
    demo.add_argument("--subdivisions", type=int, default=1, choices=range(0, 4), help="icosphere subdivisions of the two balls (default: 1, 80 triangles each)")
    demo.add_argument("--gaps", type=_positive_float, nargs="+", default=[1.0, 0.1, 1e-2, 1e-4], help="surface gaps between the balls (m; default: 1 0.1 0.01 0.0001)")
    demo.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    _writes(demo, "outputs/demo", "demo.json")
    demo.set_defaults(func=_demo)

    run = sub.add_parser("run", help="optimise a task by gradient descent through the simulator")
    _add_task_arguments(run)
    _writes(run, "outputs/run", *RUN_OUTPUTS)
    run.add_argument("--model", default="ours", choices=MODELS)
    run.add_argument(
        "--resume",
        action="store_true",
        help=f"continue the interrupted run whose progress is in OUT/{CHECKPOINT_NAME} (rewritten before every Adam iteration, removed once the results are written)",
    )
    run.set_defaults(func=_run)

    compare = sub.add_parser("compare", help="optimise a task with several models from the same initial guess; one convergence plot")
    _add_task_arguments(compare)
    _writes(compare, "outputs/compare", "compare.json", "compare.png")
    compare.add_argument("--models", type=_model_list, default=list(MODELS), help=f"comma-separated subset of {','.join(MODELS)} (default: all)")
    compare.add_argument("--frictionless", action="store_true", help="set the scene's friction to 0 for every model")
    compare.set_defaults(func=_compare)

    listing = sub.add_parser("list", help="list tasks, scenes and contact models")
    listing.set_defaults(func=_list)

    simulate = sub.add_parser("simulate", help="simulate a USD scene and export its trajectory")
    simulate.add_argument("scene", help="a shipped scene's name (warpcontact list) or a USD scene (.usda, .usd, .usdc, .usdz)")
    simulate.add_argument("--frames", type=_frame_count, default=None, help="default: the scene's warpcontact:frames, else 100")
    simulate.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    _writes(simulate, "outputs/simulate", *SIMULATE_OUTPUTS)
    simulate.set_defaults(func=_simulate)

    bench = sub.add_parser("bench", help="benchmarks writing JSON results")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    leaf = bench_sub.add_parser("leaf", help="leaf solves per second and Newton iterations")
    leaf.add_argument("--pairs", type=_pair_count, default=100_000)
    leaf.add_argument("--repeats", type=_positive_int, default=5)
    leaf.add_argument("--precisions", nargs="+", choices=LEAF_PRECISIONS, default=list(LEAF_PRECISIONS), help="plane search precisions; rows after the first give errors against it")
    leaf.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    _writes(leaf, "outputs/bench", "leaf.json", "leaf.csv")
    leaf.set_defaults(func=_bench_leaf, saves_rows=True)
    contact = bench_sub.add_parser("contact", help="BSH speed vs force error against brute force (eps sweep)")
    contact.add_argument("--eps", type=_eps, nargs="+", default=[0.01, 0.1, 0.5, 1.0, 2.0, 10.0])
    contact.add_argument("--gaps", type=_positive_float, nargs="+", default=[1e-3, 1e-2, 1e-1])
    contact.add_argument("--subdivisions", type=int, default=1, choices=range(0, 4))
    contact.add_argument("--repeats", type=_positive_int, default=3)
    contact.add_argument("--ipc-dhat", type=_ipc_dhat, default=1e-2, help="IPC Toolkit barrier support (m) for the side-by-side ipc rows (CPU); 0 skips them")
    contact.add_argument("--centred-weights", nargs="+", choices=CENTRED_WEIGHTS, default=["paper"], help="centred-term weights of the bsh rows (docs/architecture.md, 'Centred weights')")
    contact.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    _writes(contact, "outputs/bench", "contact.json", "contact.csv", "contact.png")
    contact.set_defaults(func=_bench_contact, saves_rows=True)
    scaling = bench_sub.add_parser("scaling", help="contact cost against triangle count (16-ball rack)")
    scaling.add_argument("--points", type=_points_per_ball, nargs="+", default=[18, 42, 82, 196], help="points per ball (2N-4 faces)")
    scaling.add_argument("--eps", type=_eps, default=0.5)
    scaling.add_argument("--brute-max-triangles", type=_non_negative_int, default=2560)
    scaling.add_argument("--repeats", type=_positive_int, default=3)
    scaling.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    _writes(scaling, "outputs/bench", "scaling.json", "scaling.csv", "scaling.png")
    scaling.set_defaults(func=_bench_scaling, saves_rows=True)
    frame = bench_sub.add_parser("frame", help="per-frame forward, contact, Newton iterations and backward on task scenes")
    frame.add_argument(
        "--scenes",
        nargs="+",
        default=None,
        help=f"scene names, peer_billiards_T (T in 512 1472 3008 4544 6208), .usda or pickled-Scene .pkl paths (default: {' '.join(_FRAME_SCENES)}, "
        f"and {_PEER_FRAME_SCENE} where --peer-meshes holds its meshes)",
    )
    frame.add_argument("--models", nargs="+", choices=["bsh", "brute", "ipc"], default=["bsh", "brute", "ipc"])
    frame.add_argument("--frames", type=_frame_count, default=3, help="timed frames (medians over them)")
    frame.add_argument("--warmup", type=_non_negative_int, default=1, help="untimed frames first, from the same start")
    frame.add_argument("--eps", type=_eps, default=None, help="BSH blend margin (default: each scene's)")
    frame.add_argument("--gap", type=_positive_float, default=0.02, help="striker's start gap to the struck body (m), between their bounding circles across the up axis (their surfaces are farther apart)")
    frame.add_argument("--speed", type=_positive_float, default=1.0, help="striker's speed into it (m/s)")
    frame.add_argument("--brute-max-triangles", type=_non_negative_int, default=512, help="brute force runs whole frames up to this many dynamic triangles")
    frame.add_argument("--brute-eval-max-triangles", type=_non_negative_int, default=6208, help="above that, only its contact evaluation is timed, up to this many")
    frame.add_argument("--ipc-stiffness", type=_stiffness, default=1e3, help="IPC barrier stiffness (replaces the scene's mu for ipc)")
    frame.add_argument("--leaf-precision", choices=LEAF_PRECISIONS, default="float64", help="plane search precision of bsh and brute (ipc: float64)")
    frame.add_argument("--scene-dir", default=None, help="folder of NAME.usda scenes (default: the shipped scenes)")
    frame.add_argument("--peer-meshes", default="../shared/peer-meshes", help="folder of the paper code base's meshes (18.obj ... 196.obj)")
    frame.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    _writes(frame, "outputs/bench", "frame.json", "frame.csv", "frame.png")
    frame.set_defaults(func=_bench_frame, saves_rows=True)
    accuracy = bench_sub.add_parser("accuracy", help="time against error (eps, solver tolerance) on a small billiards case")
    accuracy.add_argument("--eps", type=_eps, nargs="+", default=[0.25, 0.5, 1.0, 2.0, 4.0])
    accuracy.add_argument("--tolerances", type=_fraction, nargs="+", default=[1e-9, 1e-10, 1e-11], help="Newton tolerances swept at --tolerance-eps (above ~6e-9 they converge alike, under the 1e-5 dt^2 cap: converged_step_m)")
    accuracy.add_argument("--tolerance-eps", type=_eps, default=0.5, help="eps of the tolerance and precision sweeps")
    accuracy.add_argument("--precisions", nargs="+", choices=LEAF_PRECISIONS, default=list(LEAF_PRECISIONS), help="leaf plane search precisions swept at --tolerance-eps")
    accuracy.add_argument("--reference-tolerance", type=_fraction, default=1e-12, help="Newton tolerance of the brute-force reference run")
    accuracy.add_argument("--frames", type=_frame_count, default=3)
    accuracy.add_argument("--balls", type=_positive_int, default=3, help="rack balls besides the cue")
    accuracy.add_argument("--points", type=_points_per_ball, default=18, help="points per ball (2N-4 faces)")
    accuracy.add_argument("--gap", type=_positive_float, default=0.02)
    accuracy.add_argument("--speed", type=_positive_float, default=1.0)
    accuracy.add_argument("--device", default="cpu", help="cpu or cuda:N (default: cpu)")
    _writes(accuracy, "outputs/bench", "accuracy.json", "accuracy.csv", "accuracy.png")
    accuracy.set_defaults(func=_bench_accuracy, saves_rows=True)
    return parser


def _signature(path: Path) -> tuple | None:
    """What tells a file from its replacement (a new file, renamed into place), or None."""
    try:
        stat = path.stat()
    except FileNotFoundError:
        return None
    return stat.st_ino, stat.st_mtime_ns, stat.st_size


def _earlier_files(args) -> dict:
    """A bench's outputs that an earlier run left in OUT, which --overwrite replaces: path
    -> ``_signature``; empty for other commands and without --overwrite."""
    if not (getattr(args, "saves_rows", False) and args.overwrite):
        return {}
    paths = [Path(args.out) / name for name in args.outputs]
    return {path: _signature(path) for path in paths if path.is_file()}


def _missing_folders(path: Path) -> list:
    """The folders of ``path`` that do not exist yet, deepest first (none past one that
    cannot be looked at: creating the folder then says why)."""
    missing = []
    while path != path.parent:
        try:
            if path.exists():
                break
        except OSError:
            return []
        missing.append(path)
        path = path.parent
    return missing


def _remove_empty(folders: list) -> None:
    """Remove the folders a command created, deepest first, while they are empty: a command
    refused for a mistyped device or scene left an empty --out folder behind."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


class _ReaderTolerantStream:
    """A text stream that, once its reader has gone (a pipe closed early: ``| head``), drops
    what is printed to it instead of raising: `simulate | head -1` lost the whole simulation
    to a BrokenPipeError from its progress line, and `list | head -1` ended in an error (a
    probe)."""

    def __init__(self, stream):
        self._stream = stream
        self._reader_gone = False

    def write(self, text: str) -> int:
        if not self._reader_gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._drop()
        return len(text)

    def flush(self) -> None:
        if not self._reader_gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._drop()

    def _drop(self) -> None:
        self._reader_gone = True
        try:  # the interpreter's own last flush at exit goes nowhere too, without a report
            os.dup2(os.open(os.devnull, os.O_WRONLY), self._stream.fileno())
        except (OSError, ValueError, AttributeError):
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv=None) -> int:
    """The ``warpcontact`` command; exit status 0, 1 (failed), 2 (refused input) or 130 (interrupted)."""
    stdout, formatwarning = sys.stdout, warnings.formatwarning
    sys.stdout = _ReaderTolerantStream(stdout)
    warnings.formatwarning = _command_warning(formatwarning)
    try:
        return _main(argv)
    finally:
        sys.stdout, warnings.formatwarning = stdout, formatwarning


def _command_warning(formatwarning):
    """Python's warning format with UserWarnings (the package's name the file, prim or
    setting) on one line, "warning: ...": they printed the package's source file and line
    ("warpcontact/cli.py:214: UserWarning: ...", then the line of code) to a user who wrote no
    code (a probe, stop 64). A command's user has no use for any package's source line."""

    def format_warning(message, category, filename, lineno, line=None):
        if issubclass(category, UserWarning):
            return f"warning: {message}\n"
        return formatwarning(message, category, filename, lineno, line)

    return format_warning


def _main(argv) -> int:
    args = build_parser().parse_args(argv)
    # Module-load chatter would drown the progress and results; warnings and errors still show.
    wp.config.log_level = logging.WARNING
    earlier = {}
    created = _missing_folders(Path(args.out)) if getattr(args, "out", None) is not None else []
    release = None
    try:
        try:
            if getattr(args, "out", None) is not None:
                # Every command that writes checks its folder and earlier results before any
                # work, a resumed run too (the same command with --resume: it skipped the
                # check, and replaced a trajectory that a simulate had written there since); a
                # resume with no checkpoint is told that by the command instead. The folder is
                # held until the command ends, so that no other command writes there meanwhile.
                out = _output_folder(args.out)
                release = hold_folder(out)
                _refuse_unwritable_names(out, args.outputs)
                _refuse_input_among_outputs(args, out)
                if not getattr(args, "resume", False) or (out / CHECKPOINT_NAME).exists():
                    _refuse_earlier_results(out, args.outputs, args.overwrite)
                    _refuse_mixed_results(out, args.outputs)
            earlier = _earlier_files(args)
            status = args.func(args)
        finally:
            if release is not None:
                release()
        if status == 130:
            # Interrupted inside run or compare, which keep what they had: before their first
            # checkpoint that was nothing, and the folder they were given stayed, empty.
            _remove_empty(created)
        return status
    except KeyboardInterrupt:
        # run, compare and simulate keep their own partial results; the benches save a row at a time.
        kept = ""
        if getattr(args, "saves_rows", False):
            # Interrupted before its first row, a bench with --overwrite left the earlier run's
            # results as if they were its own. They go only now: removed before the run, a
            # mistyped device or scene name lost them.
            stale = [path for path, signature in earlier.items() if _signature(path) == signature]
            for path in stale:
                path.unlink()
            removed = f" (the earlier run's {', '.join(p.name for p in stale)} removed)" if stale else ""
            if any((Path(args.out) / name).exists() for name in args.outputs):
                kept = f"; the rows finished before it are in {args.out}{removed}"
            else:
                # It said the rows were kept when there were none, and left the folder it made.
                kept = f"; no row was finished{removed}"
        # Interrupted before it wrote anything (while it started up), a command left the
        # folder it made; only folders still empty go.
        _remove_empty(created)
        print(f"\ninterrupted{kept}", file=sys.stderr)
        return 130
    except FileExistsError as exc:
        print(f"error: {exc} (use --overwrite)", file=sys.stderr)
        return 2
    except OSError as exc:
        # A folder that passed the writability check can still refuse the write (sysfs, a
        # full disk, a read-only mount): a traceback before.
        _remove_empty(created)
        # On a line of its own: it was printed after a run's progress bar, on its line.
        print(f"\nerror: {exc}", file=sys.stderr)
        return 1
    except ValueError as exc:
        _remove_empty(created)
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
