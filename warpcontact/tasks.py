"""Task optimisation (paper, section "Evaluation"): gradient descent through the simulator.

A task is a ``Scene`` with target bodies (``target_position``, ``target_tolerance``) and one
controlled body whose ``control_dofs`` are the decision variables:

- control ``"initial_state"`` (Billiards): one row of offsets to the controlled body's
  initial pose and velocity (e.g. x, y, vx, vy);
- control ``"pd_targets"`` (Push, Sort, Gather): one row per frame of offsets to the PD
  target pose (translations, rotation vector or yaw), optimised over a receding horizon of
  ``receding_horizon`` frames; the first ``receding_stride`` actions (the paper: 1) are
  applied and the window shifts by as many frames (the rows that enter the window start
  as copies of the last planned one). A window whose carried-over plan cannot be simulated
  ends the run early with the frames executed so far (``extra["stopped"]``: the frame and
  the simulator's error; no success);
- control ``"joint_sine"`` (Ant-Push): every actuated joint coordinate (one with a PD gain)
  follows its rest value plus ``SINE_WAVES`` accumulated sine waves; the decision variables
  are each wave's amplitude, frequency and phase (after ChainQueen, as in the paper). The
  trivial guess has zero amplitudes, frequencies of 1..4 Hz and zero phases.

With ``TaskSettings.initial_samples`` (initial-state control only) the descent starts from
the lowest-loss of that many controls drawn uniformly from the scene's box
(``TaskSpec.sample_low`` / ``sample_high``): the paper's random-sampling initialisation.

Loss: sum over targets of ReLU(|x_com - x*|^2 - tolerance^2) at the window's last frame.
Gradients come from ``wp.Tape`` through the implicit steps; the optimiser is Adam with the
paper's betas (0.3, 0.5). Trivial initial guess: all offsets zero.

Models (``MODELS``), all with the same optimiser from the same guess: ``"ours"`` (the
scene's own contact mode, by default the paper's model), the baselines ``"ipc"`` and
``"sdrs"`` (locally supported barriers, each with friction lagged from its own normal
forces, so a frictional scene is the same problem for every model), and ``"gb"``: gradient
bundles (``bundle.py``) over the SDRS model.

Long runs keep their progress in a ``TaskCheckpoint`` (``optimize(checkpoint=...)``) and
continue from it bit for bit on a CPU (``optimize(checkpoint=..., resume=True)``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from ._files import replace_file
from ._validate import MAX_COORDINATE, MAX_FRAMES, beyond_coordinates, check_finite_poses, checked_flag, is_gain, is_positive_finite, is_real, is_whole, real_array
from .builder import check_contact_setting
from .bundle import BundleSettings, bundled_gradient
from .io import TASK_ATTRIBUTES, TaskSpec, check_scene_type, target_problem
from .kernels import task as task_kernels
from .solver import ImplicitSolver, SolverError
from .types import State, set_body_velocity

__all__ = ["CONTROL_KINDS", "IPC_TASK_STIFFNESS", "MODELS", "SINE_WAVES", "TaskCheckpoint", "TaskProblem", "TaskResult", "TaskSettings", "adam", "sample_box", "validate_task"]

CONTROL_KINDS = ("initial_state", "pd_targets", "joint_sine")
SINE_WAVES = 4
MODELS = ("ours", "ipc", "sdrs", "gb")
# Contact mode each baseline simulates with. gb bundles gradients of the SDRS model: it is
# locally supported like IPC (so far-apart samples give zero gradients, the failure the
# paper reports), but twice differentiable, so every sample's implicit-function-theorem
# gradient is exact, and it runs on every device; gb vs sdrs isolates the estimator.
_BASELINE_CONTACT_MODE = {"ipc": "ipc", "sdrs": "sdrs", "gb": "sdrs"}
# IPC's barrier stiffness for task runs. The scenes' contact_stiffness (mu 1e-6 .. 5e-9) is
# sized for the paper's 1/x potential; on IPC's (unnormalised) log barrier it is so soft
# that resting bodies sink to gaps of ~1e-8 m and ipctk's CCD takes seconds a step. The
# default gives gaps of ~1e-4 m on the shipped scenes (docs/tasks.md).
IPC_TASK_STIFFNESS = 1e5


# The --quick preset of a scene without its own (warpcontact:task:quick:*): caps only.
GENERIC_QUICK_HORIZON = 24
GENERIC_QUICK_WINDOW = 8
GENERIC_QUICK_ITERATIONS = 8


# The --quick preset's attributes (warpcontact:task:quick:*, as io reads them) by settings
# field, and the values a scene that leaves one out reads.
_QUICK_PRESET_ATTRIBUTES = {field.removeprefix("quick_"): name.removeprefix("task:quick:") for name, (field, _) in TASK_ATTRIBUTES.items() if field.startswith("quick_")}
_QUICK_PRESET_DEFAULTS = {field: getattr(TaskSpec(), f"quick_{field}") for field in _QUICK_PRESET_ATTRIBUTES}
_QUICK_PRESET_HINT = f"a --quick preset is warpcontact:task:quick:{', '.join(list(_QUICK_PRESET_ATTRIBUTES.values())[:-1])} and {list(_QUICK_PRESET_ATTRIBUTES.values())[-1]}, authored together"


@dataclass
class TaskSettings:
    """Optimisation settings (defaults from the scene's task metadata)."""

    horizon: int
    receding_horizon: int
    iterations: int
    learning_rate: float
    receding_stride: int = 1
    betas: tuple = (0.3, 0.5)
    # Random-sampling initialisation (the paper's Billiards, "random sampling"): the descent
    # starts from the best of this many initial-state controls drawn uniformly from the
    # scene's box (warpcontact:task:sampleLow/High) with ``sample_seed``; 0: the trivial guess.
    initial_samples: int = 0
    sample_seed: int = 0
    # Initial-state control: the descent's first iterate (one value per control DOF) instead
    # of the trivial guess; ``warpcontact compare --init-samples`` gives every model the draw
    # one model's sampling chose (``TaskProblem.best_initial_sample``). None: the trivial guess.
    initial_values: tuple | None = None

    @property
    def window(self) -> int:
        """Frames per optimised window: ``receding_horizon`` when it is shorter than the
        horizon, otherwise the whole horizon (one window)."""
        return self.receding_horizon if 0 < self.receding_horizon < self.horizon else self.horizon

    @property
    def receding(self) -> bool:
        """Whether the horizon is planned in receding windows shorter than it (else one window)."""
        return self.window < self.horizon

    def window_at(self, frame: int) -> int:
        """Frames of the window planned at ``frame``: the window, ending at the horizon at the
        latest, where the task's loss is measured (the last windows optimised the bodies'
        state after it, and kept a plan better at frame 32 over one better at the horizon's
        frame 20; a probe, stop 59)."""
        return min(self.window, self.horizon - frame)

    @classmethod
    def from_task(cls, scene, *, quick: bool = False, iterations: int | None = None, receding_stride: int | None = None) -> TaskSettings:
        """The settings a scene's task metadata asks for.

        Args:
            scene: a task ``Scene``; a horizon of 0 means the scene's frame count.
            quick: the scene's ``--quick`` preset (``warpcontact:task:quick:*``), or, for a
                scene without one, the paper settings capped at GENERIC_QUICK_HORIZON frames,
                windows of GENERIC_QUICK_WINDOW and GENERIC_QUICK_ITERATIONS iterations.
            iterations: overrides the iteration count (per window for receding tasks).
            receding_stride: overrides the frames executed per receding window; an error
                for a task optimised as one window, where it would do nothing.

        Raises ValueError naming the attribute when a value is out of range.
        """
        quick = checked_flag(quick, "quick")  # "yes" read as true (a probe, stop 64)
        t = scene.task
        source = scene.source or "<scene>"
        if quick:
            # The task's own settings as well: a negative learning rate ran under --quick
            # (its preset, or the caps, replace it), and the scene failed its real run.
            cls.from_task(scene)
        preset = {field: getattr(t, f"quick_{field}") for field in _QUICK_PRESET_DEFAULTS}
        authored = [field for field, default in _QUICK_PRESET_DEFAULTS.items() if field != "horizon" and preset[field] != default]
        if quick and not t.quick_horizon and authored:
            # The generic caps ran instead, at the task's learning rate, without a word.
            names = ", ".join(f"warpcontact:task:quick:{_QUICK_PRESET_ATTRIBUTES[field]}" for field in authored)
            raise ValueError(f"{source}: {names} {'is' if len(authored) == 1 else 'are'} authored but warpcontact:task:quick:horizon is {t.quick_horizon} (none): {_QUICK_PRESET_HINT}, its horizon at least 1; remove them for the generic --quick caps")
        if quick and t.quick_horizon:
            settings = cls(t.quick_horizon, t.quick_receding_horizon, t.quick_iterations, t.quick_learning_rate, t.quick_receding_stride)
            prefix = "task:quick:"
        else:
            settings = cls(t.horizon or scene.settings.frames, t.receding_horizon, t.iterations, t.learning_rate, t.receding_stride)
            prefix = "task:"
            if quick:
                one_window = not settings.receding
                settings.horizon = min(settings.horizon, GENERIC_QUICK_HORIZON)
                # A task optimised as one window stays one: a window authored longer than
                # the horizon became a receding one of GENERIC_QUICK_WINDOW frames.
                settings.receding_horizon = 0 if one_window else min(settings.receding_horizon, GENERIC_QUICK_WINDOW)
                settings.iterations = min(settings.iterations, GENERIC_QUICK_ITERATIONS)
                settings.receding_stride = min(settings.receding_stride, settings.window)
        iterations_name = f"warpcontact:{prefix}iterations"
        if iterations is not None:
            settings.iterations, iterations_name = iterations, "iterations (--iters)"
        stride_name = f"warpcontact:{prefix}recedingStride"
        if receding_stride is not None:
            if not settings.receding:
                raise ValueError(f"{source}: --stride applies to receding-window tasks; this one optimises a single window of {settings.horizon} frame{'' if settings.horizon == 1 else 's'}")
            settings.receding_stride, stride_name = receding_stride, "--stride"
        names = {
            # Without a task horizon the scene's frames are the horizon.
            "horizon": f"warpcontact:{prefix}horizon" if prefix == "task:quick:" or t.horizon else "warpcontact:frames (the horizon: no warpcontact:task:horizon)",
            "receding_horizon": f"warpcontact:{prefix}recedingHorizon",
            "receding_stride": stride_name,
            "iterations": iterations_name,
            "learning_rate": f"warpcontact:{prefix}learningRate",
        }
        failed = []

        def where(field):
            failed.append((field, names.get(field, field)))
            return f"{source}: {failed[-1][1]}"

        try:
            settings.check(where)
        except ValueError as exc:
            field, name = failed[-1]
            # A preset with some attributes left out read them as their defaults, and the
            # error named an attribute the scene never authored; an authored value out of
            # range is only that (the hint misled on a complete preset).
            if prefix != "task:quick:" or name.startswith("--") or preset.get(field) != _QUICK_PRESET_DEFAULTS.get(field):
                raise
            raise ValueError(f"{exc} ({_QUICK_PRESET_HINT})") from None
        return settings

    def check(self, where=lambda field: f"settings.{field}") -> None:
        """Raises ValueError for the first setting out of range, named by ``where(field)``:
        the one rule for settings read from a scene and settings built directly."""

        def unit_interval(value) -> bool:
            return is_real(value) and 0.0 <= value < 1.0

        window = self.window if is_whole(self.horizon) and is_whole(self.receding_horizon) else None
        receding = window is not None and window < self.horizon
        betas = tuple(self.betas) if isinstance(self.betas, (tuple, list, np.ndarray)) else ()
        for name, rule, ok in (
            ("horizon", f"a whole number from 1 to {MAX_FRAMES:,}", is_whole(self.horizon) and 1 <= self.horizon <= MAX_FRAMES),
            ("receding_horizon", "a whole number >= 0", is_whole(self.receding_horizon) and self.receding_horizon >= 0),
            # At most the window where windows recede; a single window executes no stride, and
            # one longer than it was refused there while the same stride passed on a longer
            # horizon (a probe, stop 64).
            (
                "receding_stride",
                f"a whole number >= 1 and at most the window ({window})" if receding else "a whole number >= 1",
                is_whole(self.receding_stride) and 1 <= self.receding_stride and (not receding or self.receding_stride <= window),
            ),
            ("iterations", f"a whole number from 1 to {MAX_ITERATIONS:,}", is_whole(self.iterations) and 1 <= self.iterations <= MAX_ITERATIONS),
            ("learning_rate", "positive and finite", is_positive_finite(self.learning_rate)),
            ("betas", "two numbers in [0, 1)", len(betas) == 2 and all(unit_interval(b) for b in betas)),
            ("initial_samples", "a whole number >= 0", is_whole(self.initial_samples) and self.initial_samples >= 0),
            ("sample_seed", "a whole number >= 0", is_whole(self.sample_seed) and self.sample_seed >= 0),
            ("initial_values", "None or a tuple of finite numbers, and None with initial_samples", _start_values_ok(self.initial_values, self.initial_samples)),
        ):
            if not ok:
                raise ValueError(f"{where(name)} must be {rule}, got {getattr(self, name)!r}")


def _start_values_ok(values, samples) -> bool:
    if values is None:
        return True
    return isinstance(values, tuple) and not (is_whole(samples) and samples > 0) and all(is_real(v) and np.isfinite(v) for v in values)


@dataclass
class TaskResult:
    loss_history: list
    initial_loss: float | None  # None: the trivial plan cannot be simulated to the final loss's frame (extra["initial_loss_error"])
    final_loss: float
    success: bool
    iterations: int
    seconds: float
    values: np.ndarray
    trajectory: np.ndarray  # (frames + 1, nbodies, 7) centre-of-mass poses; the executed ones when extra["stopped"]
    extra: dict = field(default_factory=dict)


# Far more than any run can finish (a rollout each); gb's sigma schedule holds one number per
# iteration, and 1e12 of them died in a 7.3 TiB MemoryError.
MAX_ITERATIONS = 10_000_000

# Long-range gradients can be ~1e-9 (far objects, small mu); a customary eps of 1e-8 would
# then shrink Adam's steps by orders of magnitude. In float64 a tiny eps keeps steps
# scale-free, and a zero gradient still gives a zero step.
ADAM_EPS = 1e-30


# Rollouts an infeasible Adam update gets before the descent stops: the update itself, then
# its halves down to 2^-19 of it.
FEASIBLE_HALVINGS = 20


def adam(betas, learning_rate):
    """Adam step function with state: update(x, g) -> x (in place); ``update.learning_rate``
    may be changed between steps; ``update.state`` holds the moments m, v and the step
    count t (a checkpoint saves and restores them)."""
    b1, b2 = betas
    state = {"m": None, "v": None, "t": 0}

    def update(x, g):
        if state["m"] is None:
            state["m"], state["v"] = np.zeros_like(x), np.zeros_like(x)
        state["t"] += 1
        state["m"] = b1 * state["m"] + (1 - b1) * g
        state["v"] = b2 * state["v"] + (1 - b2) * g * g
        m_hat = state["m"] / (1 - b1 ** state["t"])
        v_hat = state["v"] / (1 - b2 ** state["t"])
        x -= update.learning_rate * m_hat / (np.sqrt(v_hat) + ADAM_EPS)
        return x

    update.learning_rate = learning_rate
    update.state = state
    return update


def _descend(rollout, values, settings, history, progress=None, total=None, first=None, resume=None, save=None, stalled=None):
    """Adam iterations on ``values`` (in place); returns (best loss, best values, its trajectory).
    ``rollout(values, gradient=...)`` returns (loss, gradient, trajectory); it is asked for no
    gradient (None) at the last iteration, which is only evaluated. ``first``:
    ``rollout(values)``'s result when the caller already has it. ``save(state)``,
    if given, receives the descent's state (``_descent_state``) before every iteration;
    ``resume``: such a state to continue from instead of starting at ``values``.

    An update that makes the rollout infeasible (bodies intersecting at the start, or a step
    that fails) is halved back towards the last feasible values, up to FEASIBLE_HALVINGS
    times, and the descent stops if none is feasible (``stalled(iteration, error)``, if given,
    is told: it ended silently before, a run with 1 of 400 iterations); the learning rate is kept, so one
    infeasible neighbourhood does not slow every later step. A zero loss stops the descent:
    every target is within its tolerance (success), and further Adam steps, carried by
    momentum alone, could only move the solution off it.
    """
    step = adam(settings.betas, settings.learning_rate)

    def stepped_from(iteration: int) -> bool:
        # The last iterate is only evaluated: its gradient (a backward pass, or gb's whole
        # bundle of rollouts) would never be used.
        return iteration + 1 < settings.iterations

    if resume is None:
        start = 0
        best = (np.inf, values.copy(), None)
        # The start must be feasible: its errors propagate.
        result = first or rollout(values, gradient=stepped_from(0))
    else:
        start = resume["iteration"]
        values[:] = resume["values"]
        if resume["adam_t"]:
            step.state.update(m=resume["adam_m"], v=resume["adam_v"], t=resume["adam_t"])
        best = (resume["best_loss"], resume["best_values"], resume["best_trajectory"] if resume["best_trajectory"].size else None)
        result = (resume["loss"], resume["gradient"] if resume["gradient"].size else None, resume["trajectory"])
    for it in range(start, settings.iterations):
        if save is not None:
            save(_descent_state(it, values, step.state, best, result))
        loss, grad, trajectory = result
        history.append(loss)
        if loss < best[0]:
            best = (loss, values.copy(), trajectory)
        if progress and total is None:
            progress(it + 1, settings.iterations, loss)
        if loss == 0.0 or it + 1 == settings.iterations:
            break
        feasible = values.copy()
        step(values, grad)
        move = values - feasible
        for _ in range(FEASIBLE_HALVINGS):
            try:
                result = rollout(values, gradient=stepped_from(it + 1))
                break
            except (ValueError, SolverError) as exc:
                failure = exc
                move *= 0.5
                values[:] = feasible + move
        else:
            values[:] = feasible
            if stalled is not None:
                stalled(it + 1, f"no feasible Adam update: it and its halves down to 2^-{FEASIBLE_HALVINGS - 1} failed ({failure})")
            break
    return best


def _stall_note(extra: dict, **where):
    """A ``_descend`` ``stalled`` callback that notes where its descent stopped in
    ``extra["stalled"]`` (metrics.json; ``where``: the receding window's frame)."""
    return lambda iteration, error: extra.setdefault("stalled", []).append({**where, "iteration": iteration, "error": error})


def _descent_state(iteration, values, adam_state, best, result) -> dict:
    """What a descent needs to continue at the top of ``iteration`` (``_descend``'s resume)."""
    loss, gradient, trajectory = result
    none = np.zeros((0,))
    return {
        "iteration": iteration,
        "values": values.copy(),
        "adam_m": none if adam_state["m"] is None else adam_state["m"].copy(),
        "adam_v": none if adam_state["v"] is None else adam_state["v"].copy(),
        "adam_t": adam_state["t"],
        "best_loss": float(best[0]),
        "best_values": best[1].copy(),
        "best_trajectory": none if best[2] is None else best[2],
        "loss": float(loss),
        "gradient": none if gradient is None else gradient,
        "trajectory": trajectory,
    }


# Version of the checkpoint file format; a file of another version is refused.
CHECKPOINT_VERSION = 1
_CHECKPOINT_ARRAYS = ("plan", "executed", "history", "values", "adam_m", "adam_v", "best_values", "best_trajectory", "gradient", "trajectory")


def _json_scalar(value):
    """JSON for a numpy scalar (a setting given as np.int64, a count computed from one)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _fingerprint_value(value):
    """A fingerprint's JSON for what JSON does not take: numpy scalars as numbers (so that
    np.int64(1) and 1 match), anything else as its text."""
    try:
        return _json_scalar(value)
    except TypeError:
        return str(value)


# What every checkpoint's meta holds, and what a receding run's adds (``optimize``'s saver).
_CHECKPOINT_KEYS = ("version", "fingerprint", "history", "seconds", "receding", "extra", "iteration", "values", "adam_m", "adam_v", "adam_t", "best_loss", "best_values", "best_trajectory", "loss", "gradient", "trajectory", "rng", "bundle_calls")
_RECEDING_CHECKPOINT_KEYS = ("frame", "plan", "executed")
# What a run notes in ``extra`` while it runs (the rest, "stopped" and "initial_loss_error",
# once it ends): an altered checkpoint's other keys, "success" or "final_loss", were written
# over the computed ones in metrics.json.
_CHECKPOINT_EXTRA_KEYS = ("bundle", "bundle_samples", "bundle_samples_dropped", "bundle_samples_counted_since_resume", "stalled", "initial_samples")


def _damaged_checkpoint_entry(state: dict) -> str | None:
    """What is wrong with a checkpoint's entries' types and values, or None (their shapes
    against a problem: ``TaskProblem._check_saved_shapes``). An altered file gave tracebacks (a
    list for the fingerprint, an iteration of 3.5) or ran on silently (NaN values stopped the
    descent at iteration 41 of 400; an iteration of -5 ran extra ones, and a gb run's altered
    generator state or bundle count a traceback or a silently shifted count)."""
    def count(value):
        return is_whole(value) and value >= 0

    def loss(value):
        return is_real(value) and not np.isnan(value)

    def generator_state(value):
        if value is None:
            return True
        try:  # the bundle's kind of generator takes it, or says why not
            np.random.PCG64(0).state = value
        except (TypeError, ValueError, KeyError, OverflowError):
            return False
        return True

    def fingerprint(value):
        # What ``TaskCheckpoint.describe`` reads, for the messages of a run that finds one: a
        # fingerprint without them was a KeyError traceback.
        settings = value.get("settings") if isinstance(value, dict) else None
        return isinstance(settings, dict) and is_whole(settings.get("horizon")) and isinstance(value.get("task"), str) and isinstance(value.get("model"), str)

    def extra(value):
        # The stalls that run reports after writing its results (a string there was a TypeError
        # traceback once metrics.json held it).
        stalls = value.get("stalled", []) if isinstance(value, dict) else None
        return isinstance(stalls, list) and set(value) <= set(_CHECKPOINT_EXTRA_KEYS) and all(isinstance(s, dict) and {"iteration", "error"} <= set(s) for s in stalls)

    rules = {
        "fingerprint": (fingerprint, "a JSON object of the task, model and settings"),
        "extra": (extra, f"a JSON object of at most {', '.join(_CHECKPOINT_EXTRA_KEYS)}, its stalled a list of objects with iteration and error"),
        "receding": (lambda v: isinstance(v, bool), "true or false"),
        "iteration": (count, "a whole number >= 0"),
        "adam_t": (count, "a whole number >= 0"),
        "seconds": (lambda v: is_real(v) and 0.0 <= v < np.inf, "a finite number >= 0"),
        "loss": (loss, "a number"),
        "best_loss": (loss, "a number"),
        "bundle_calls": (count, "a whole number >= 0"),
        "rng": (generator_state, "null or a PCG64 generator state"),
    }
    if state["receding"] is True:
        rules["frame"] = (count, "a whole number >= 0")
    for key, (valid, expected) in rules.items():
        if not valid(state[key]):
            return f"its {key} is {state[key]!r}, expected {expected}"
    for key in _CHECKPOINT_ARRAYS:
        if key in state:
            values = state[key]
            if values.dtype.kind != "f" or np.isnan(values).any() or (key != "history" and np.isinf(values).any()):
                return f"its array {key!r} is not all finite numbers"
    if state["history"].ndim != 1:
        return f"its loss history has shape {state['history'].shape}, expected one loss per iteration"
    return None


class TaskCheckpoint:
    """A file that keeps a task optimisation's progress, so that a run interrupted (a
    time limit, Ctrl-C, a lost machine) continues where it stopped instead of starting
    over: ``TaskProblem.optimize(checkpoint=path)`` rewrites it before every Adam
    iteration, and ``optimize(checkpoint=path, resume=True)`` continues from it, bit for
    bit on a CPU.

    It holds the descent's state (decision variables, Adam's moments, the best iterate and
    the pending rollout's loss, gradient and trajectory), the receding horizon's state (the
    frames executed so far and the plan), gb's random generator and bundle count, the loss
    history and the seconds spent, and a fingerprint of the problem (``TaskProblem``'s
    ``_fingerprint``: task, model, settings, controlled DOFs, simulation settings, a digest of
    the bodies and joints): resuming another problem is refused, naming what differs. Written as a .npz (no pickles) through a temporary file
    and an atomic rename, so an interruption while writing leaves the previous one intact.
    """

    def __init__(self, path):
        self.path = Path(path)

    def exists(self) -> bool:
        """Whether a checkpoint is there; ValueError when the path is taken by a folder or
        another non-file, which the first save could not replace."""
        if self.path.exists() and not self.path.is_file():
            raise ValueError(f"{self.path}: exists and is not a file; a checkpoint cannot be written there")
        return self.path.is_file()

    def save(self, fingerprint: dict, state: dict) -> None:
        """Writes ``state`` (a descent's arrays and metadata) with the problem's
        ``fingerprint``, whole, through a temporary file and a rename."""
        meta = {k: v for k, v in state.items() if k not in _CHECKPOINT_ARRAYS}
        meta.update(version=CHECKPOINT_VERSION, fingerprint=fingerprint)
        arrays = {k: np.asarray(state[k], dtype=np.float64) for k in _CHECKPOINT_ARRAYS if k in state}
        def write(temporary):
            with temporary.open("wb") as f:
                np.savez(f, meta=np.array(json.dumps(meta, default=_json_scalar)), **arrays)

        try:
            replace_file(self.path, write)
        except OSError as exc:
            # A full disk named neither the file nor what was kept ("[Errno 28] No space left on device").
            kept = "the previous one is kept" if self.path.exists() else "no earlier one was written"
            raise OSError(f"{self.path}: saving the checkpoint failed ({exc.strerror or exc}); {kept}") from None

    def load(self, fingerprint: dict | None = None) -> dict:
        """The saved state; ValueError naming the file when it is missing, unreadable, of
        another format version, or (given ``fingerprint``) of another problem."""
        if not self.exists():
            raise ValueError(f"{self.path}: no checkpoint to resume")
        try:
            with open(self.path, "rb") as file:
                magic = file.read(6)
            if magic == b"\x93NUMPY":
                raise ValueError("a single array, not an .npz archive")
            if magic[:4] != b"PK\x03\x04":
                # numpy read other bytes as a pickle it refused, and advised loading it
                # unsafely (a probe, stop 65).
                raise ValueError("not an .npz archive")
            data = np.load(self.path, allow_pickle=False)
            with data:
                state = json.loads(str(data["meta"]))
                if not isinstance(state, dict):
                    raise ValueError("its meta is not a JSON object")
                state.update({k: data[k] for k in _CHECKPOINT_ARRAYS if k in data.files})
        except Exception as exc:  # noqa: BLE001 - whatever a damaged archive raises (a flipped flag bit: NotImplementedError)
            raise ValueError(f"{self.path}: not a readable checkpoint ({exc})") from None
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{self.path}: checkpoint format {state.get('version')!r}, expected {CHECKPOINT_VERSION}")
        missing = [k for k in _CHECKPOINT_KEYS + (_RECEDING_CHECKPOINT_KEYS if state.get("receding") else ()) if k not in state]
        if missing:
            raise ValueError(f"{self.path}: not a complete checkpoint (missing {', '.join(missing)})")
        damaged = _damaged_checkpoint_entry(state)
        if damaged:
            raise ValueError(f"{self.path}: not a readable checkpoint ({damaged})")
        if fingerprint is not None:
            saved = state["fingerprint"]
            differ = sorted(k for k in set(saved) | set(fingerprint) if saved.get(k) != fingerprint.get(k))
            if differ:
                detail = "; ".join(f"{k}: {saved.get(k)!r} saved, {fingerprint.get(k)!r} now" for k in differ)
                raise ValueError(f"{self.path}: checkpoint of another problem ({detail})")
        return state

    def describe(self) -> str:
        """One line on the saved run, for messages: task, model and how far it got."""
        state = self.load()
        fp = state["fingerprint"]
        horizon = fp["settings"]["horizon"]
        where = f"frame {state['frame']} of {horizon}, " if state.get("receding") else ""
        done = len(state["history"])
        return f"task {fp['task']}, model {fp['model']}, {where}{done} Adam iteration{'' if done == 1 else 's'}, {state['seconds']:.0f} s"

    def remove(self) -> None:
        """Deletes the checkpoint file, if there is one."""
        self.path.unlink(missing_ok=True)


def sample_box(scene, samples: int) -> tuple:
    """(low, high) arrays, one bound per control DOF, of the box a task's ``samples``
    initial samples are drawn from (``TaskSettings.initial_samples``).

    Raises ValueError naming the attribute for a negative sample count, a task whose control
    is not ``initial_state``, a missing box, a box of the wrong length, non-finite bounds or
    a low bound above its high one (and what ``validate_task`` rejects).
    """
    source = scene.source or "<scene>"
    controlled, _ = validate_task(scene)
    task = scene.task
    if samples < 0:
        raise ValueError(f"initial samples: must be >= 0, got {samples}")
    if task.control != "initial_state":
        raise ValueError(f"{source}: initial samples draw initial-state controls; this task's control is {task.control!r}")
    if not task.sample_low or not task.sample_high:
        dofs = tuple(scene.bodies[controlled].control_dofs)
        raise ValueError(f"{source}: initial samples need warpcontact:task:sampleLow and warpcontact:task:sampleHigh (one bound per control DOF {dofs})")
    # validate_task checked the authored box.
    return np.asarray(task.sample_low, dtype=np.float64), np.asarray(task.sample_high, dtype=np.float64)


def _checked_sample_box(scene, controlled: int) -> tuple:
    """(low, high) of an initial_state task's authored sample box; ValueError naming the
    attribute for a box of the wrong length, non-finite bounds or bounds beyond MAX_COORDINATE,
    or a low bound above its high one."""
    source = scene.source or "<scene>"
    task = scene.task
    dofs = tuple(scene.bodies[controlled].control_dofs)
    low, high = np.asarray(task.sample_low, dtype=np.float64), np.asarray(task.sample_high, dtype=np.float64)
    for name, bound in (("sampleLow", low), ("sampleHigh", high)):
        if bound.shape != (len(dofs),):
            raise ValueError(f"{source}: warpcontact:task:{name} has {bound.size} values for the {len(dofs)} control DOFs {dofs}")
        # Beyond the coordinates' range numpy's draw overflowed (a traceback at +-1e308), or
        # every draw was refused as "not feasible" (1e199; a probe, stop 63).
        if not np.all(np.isfinite(bound)) or np.abs(bound).max(initial=0.0) > MAX_COORDINATE:
            raise ValueError(f"{source}: warpcontact:task:{name} must be finite and within +-{MAX_COORDINATE:g}, got {bound.tolist()}")
    if np.any(low > high):
        raise ValueError(f"{source}: warpcontact:task:sampleLow {low.tolist()} exceeds warpcontact:task:sampleHigh {high.tolist()}")
    return low, high


def validate_task(scene) -> tuple:
    """(controlled body index or None for joint_sine tasks, target body indices) of a task scene.

    Raises ValueError when the scene has no task metadata, no target bodies, a target
    position that is not 3 finite numbers or a tolerance that is negative or not finite, no
    or several controlled bodies, a static target or controlled body, an unknown control
    kind, or control dofs that are unknown, repeated, (for PD targets) velocities or
    coordinates without PD stiffness, given to a joint_sine task, or (initial_state) on a
    body a joint links; and a random-sampling box (sampleLow, sampleHigh) on another task
    than initial_state, or one of the wrong length, non-finite or inverted.
    """
    source = scene.source or "<scene>"
    task = scene.task
    if not task.name:
        raise ValueError(f"{source}: no task metadata (warpcontact:task:name on the PhysicsScene prim)")
    if task.control not in CONTROL_KINDS:
        got = f"is {task.control!r}" if task.control else "is not authored"
        raise ValueError(f"{source}: warpcontact:task:control (on the PhysicsScene prim) {got}; it must be one of {', '.join(CONTROL_KINDS)}")
    controlled = [i for i, b in enumerate(scene.bodies) if b.control_dofs]
    if task.control == "joint_sine" and controlled:
        # They were accepted and never read: the sine waves drive the joints only.
        raise ValueError(
            f"{source}: prim {scene.bodies[controlled[0]].path}: warpcontact:control:dofs is not read by a joint_sine task, "
            "whose sine waves drive the joints' PD targets; remove it"
        )
    if task.control != "joint_sine" and len(controlled) != 1:
        found = f"found {len(controlled)}: {', '.join(str(scene.bodies[i].path or scene.bodies[i].name) for i in controlled)}" if controlled else "found none"
        raise ValueError(f"{source}: a {task.control} task controls exactly one body, the one with warpcontact:control:dofs; {found}")
    if controlled:
        body = scene.bodies[controlled[0]]
        _check_control_dofs(body, task.control, source, scene.up_axis)
        joint = next((j for j in scene.joints if body.name in (j.child, j.parent)), None) if task.control == "initial_state" else None
        if joint is not None:
            # Its velocities moved nothing (the joints' coordinates did not follow) and its
            # offsets pulled the joint apart at every step of Adam (a probe).
            raise ValueError(
                f"{source}: prim {body.path}: warpcontact:control:dofs: an initial_state control sets a free body's start pose and velocity, "
                f"but joint {joint.path} links {body.name!r} and its coordinates would not follow; control a body without joints (or drive the joints: joint_sine)"
            )
    targets = [i for i, b in enumerate(scene.bodies) if b.target_position is not None]
    if not targets:
        raise ValueError(f"{source}: no target bodies (warpcontact:target:position)")
    for i in targets:
        # load_scene checks these in USD; a Scene built in Python reaches here unchecked,
        # and a NaN target would make every loss NaN.
        problem = target_problem(scene.bodies[i])
        if problem:
            raise ValueError(f"{source}: prim {scene.bodies[i].path}: {problem}")
    # A static body never moves: its loss term, or its controls, could never change.
    for label, indices in (("target", targets), ("controlled", controlled)):
        for i in indices:
            if scene.bodies[i].static:
                raise ValueError(f"{source}: prim {scene.bodies[i].path}: a {label} body must be dynamic, but it is static (kinematic or disabled)")
    if task.sample_low or task.sample_high:
        # A box on another kind of task, or a malformed one, ran without a word unless
        # --init-samples asked for it (a probe).
        if task.control != "initial_state":
            raise ValueError(f"{source}: warpcontact:task:sampleLow and sampleHigh bound random initial-state controls; this task's control is {task.control!r}, which never reads them: remove them")
        if not (task.sample_low and task.sample_high):
            given, missing = ("sampleLow", "sampleHigh") if task.sample_low else ("sampleHigh", "sampleLow")
            raise ValueError(f"{source}: warpcontact:task:{given} is authored without warpcontact:task:{missing}; a random-sampling box needs both")
        _checked_sample_box(scene, controlled[0])
    return (controlled[0] if controlled else None), targets


_POSITION_DOFS = ("x", "y", "z")
_VELOCITY_DOFS = ("vx", "vy", "vz")
_ROTATION_DOFS = ("rx", "ry", "rz", "yaw")


# The control dofs a body may name: the kernels' coordinates and ``yaw``.
_CONTROL_DOFS = (*task_kernels.DOF_CODES, "yaw")


def _coordinate(dof: str, up_axis: str) -> str:
    """The coordinate a control dof moves: ``yaw`` turns about the stage's up axis, rz, or ry
    on a Y-up stage (it turned about z there, a horizontal axis)."""
    return ("ry" if up_axis == "Y" else "rz") if dof == "yaw" else dof


def _check_control_dofs(body, control: str, source: str, up_axis: str = "Z"):
    """Every decision variable of ``body`` must move something: known, not repeated (``yaw``
    is the rotation about the up axis, ``rz`` or on a Y-up stage ``ry``), and for PD targets
    a position or rotation the body's PD gains drive."""
    where = f"{source}: prim {body.path}: warpcontact:control:dofs"
    if isinstance(body.control_dofs, str):  # "xy" ran as ("x", "y"), "yaw" as unknown "y", "a", "w"
        raise ValueError(f"{where}: expected a sequence of dof names, got the string {body.control_dofs!r}")
    dofs = tuple(body.control_dofs)
    unknown = [d for d in dofs if d not in _CONTROL_DOFS]
    if unknown:
        raise ValueError(f"{where}: unknown control dofs {unknown} (known: {', '.join(_CONTROL_DOFS)})")
    axes = [_coordinate(d, up_axis) for d in dofs]
    repeated = sorted({d for d, a in zip(dofs, axes) if axes.count(a) > 1})
    if repeated:
        raise ValueError(f"{where}: {repeated} control the same coordinate more than once")
    if control != "pd_targets":
        return
    velocities = [d for d in dofs if d in _VELOCITY_DOFS]
    if velocities:
        raise ValueError(f"{where}: {velocities} are initial velocities, which pd_targets control does not use")
    kp_linear = np.broadcast_to(np.asarray(body.kp_linear, dtype=np.float64), (3,))
    stiffness = {d: float(body.kp_angular if d in _ROTATION_DOFS else kp_linear[_POSITION_DOFS.index(d)]) for d in dofs}
    invalid = {d: kp for d, kp in stiffness.items() if not is_gain(kp)}
    if invalid:
        # It was reported as moving nothing "without a positive PD stiffness" (a probe, stop 64).
        raise ValueError(f"{where}: a PD stiffness must be finite and >= 0 (warpcontact:pd:kpLinear / kpAngular), got {invalid}")
    undriven = {d: kp for d, kp in stiffness.items() if not kp > 0}
    if undriven:
        raise ValueError(
            f"{where}: the PD targets of {list(undriven)} move nothing without a positive PD stiffness there "
            f"(warpcontact:pd:kpLinear / kpAngular), got {undriven}"
        )


class TaskProblem:
    """A scene's optimisation problem: rollouts with loss and gradient, and the optimiser.

    Args:
        scene: a ``Scene`` with task metadata (see ``validate_task``).
        device: Warp device.
        settings: optimisation settings (default: the scene's task metadata).
        model: one of ``MODELS``. ``"ours"`` simulates with the scene's own contact mode
            (``SimulationSettings.contact_mode``, the paper's "bsh" unless the scene says
            otherwise); the baselines replace it.
        bundle: gradient-bundle settings of the ``"gb"`` model (default ``BundleSettings()``).
        ipc_stiffness: the ``"ipc"`` model's barrier stiffness, in place of the scene's mu.

    The model, the start and the targets' goals are taken from the scene here: edit the scene
    before making the problem (a goal moved afterwards would not be the loss's, while the
    checkpoints' fingerprint and the initial-sample box, read at ``optimize``, would see it).

    Raises ValueError for scenes ``validate_task`` rejects, unknown models and an
    ``ipc_stiffness`` out of a contact stiffness's range (whatever the model).
    """

    def __init__(
        self,
        scene,
        *,
        device="cpu",
        settings: TaskSettings | None = None,
        model: str = "ours",
        bundle: BundleSettings | None = None,
        ipc_stiffness: float = IPC_TASK_STIFFNESS,
    ):
        check_scene_type(scene)
        # A dict failed with an AttributeError ('dict' has no 'check'; a probe, stop 64).
        if settings is not None and not isinstance(settings, TaskSettings):
            raise ValueError(f"settings: expected a TaskSettings (or None for the scene's own), got {type(settings).__name__}")
        source = scene.source or "<scene>"
        task = scene.task
        controlled, targets = validate_task(scene)
        if model not in MODELS:
            raise ValueError(f"model: {model!r} is not one of {MODELS}")
        if bundle is not None and not isinstance(bundle, BundleSettings):  # a dict failed later, naming 'sigmas'
            raise ValueError(f"bundle: expected a BundleSettings, got {type(bundle).__name__}")
        if bundle is not None and model != "gb":
            raise ValueError(f"bundle: only the gb model uses bundle settings, not {model!r}")
        # By the builder's rule for a stiffness, named, whatever the model: 1e200 was named as
        # contact_stiffness, and -1 passed for the other models (a probe, stop 58).
        check_contact_setting("contact_stiffness", ipc_stiffness, "ipc_stiffness")
        if model in _BASELINE_CONTACT_MODE:
            overrides = {"contact_mode": _BASELINE_CONTACT_MODE[model]}
            if model == "ipc":
                overrides["contact_stiffness"] = ipc_stiffness
            scene = dataclasses.replace(scene, settings=dataclasses.replace(scene.settings, **overrides))
        self.scene = scene
        self.model_name = model
        self.bundle = (bundle or BundleSettings()) if model == "gb" else None
        self.kind = task.control
        if settings is not None:
            settings.check()
        self.settings = settings or TaskSettings.from_task(scene)
        self.model = scene.build_model(device=device)
        self.solver = ImplicitSolver(self.model)
        # The PD targets of an initial_state rollout's frames (a control each frame uploaded the
        # same poses again, every rollout).
        self._scene_control = self.model.control(requires_grad=False) if task.control == "initial_state" else None
        self.dt = scene.settings.time_step
        device = self.model.device
        art = self.model.articulation
        # The scene's authored velocities start every rollout, as they start `simulate` (task
        # runs used to start at rest whatever the scene said).
        self._initial_velocity = scene.initial_velocities()
        if np.any(self._initial_velocity[0]) or np.any(self._initial_velocity[1]):
            if not art.identity:
                raise ValueError(f"{source}: task rollouts of articulated scenes start at rest; remove the bodies' authored velocities (physics:velocity, physics:angularVelocity)")
            state = self.model.state(requires_grad=False)
            set_body_velocity(state, *(wp.array(v, dtype=wp.vec3d, device=device) for v in self._initial_velocity), self.dt, body_names=self.model.body_names)
            self.start = (self.model.initial_q.copy(), state.body_q_prev.numpy().copy())
        else:
            self.start = (self.model.initial_q.copy(), self.model.initial_q.copy())
        if self.kind == "joint_sine":
            actuated = np.flatnonzero(art.kp > 0)
            if actuated.size == 0:
                raise ValueError(f"{source}: joint_sine control needs joints with drives (PD gains); none found")
            self.dof_names = tuple(art.coordinate_names[c] for c in actuated)
            self._actuated = wp.array(actuated.astype(np.int32), dtype=wp.int32, device=device)
            # The sine waves play about each coordinate's default target (a USD drive's target, else its initial value).
            self._rest = wp.array(art.default_targets, dtype=wp.float64, device=device)
        else:
            self.body = controlled
            body = scene.bodies[self.body]
            self.dof_names = tuple(body.control_dofs)
            self.base_pose = self.model.initial_q[self.body].copy()
            self._dof_codes = wp.array([task_kernels.DOF_CODES[_coordinate(d, scene.up_axis)] for d in self.dof_names], dtype=wp.int32, device=device)
        self._target_body = wp.array(targets, dtype=wp.int32, device=device)
        # Copies, as of construction, for the rollouts' loss kernel and the host's _loss_at: a
        # goal moved on the scene afterwards reached only the host's, and a run reported
        # success at loss 0 beside a history of 2.48 (a probe).
        self._target_position_host = np.array([scene.bodies[i].target_position for i in targets], dtype=np.float64).reshape(-1, 3)
        self._target_tolerance_host = np.array([scene.bodies[i].target_tolerance for i in targets], dtype=np.float64)
        self._target_position = wp.array(self._target_position_host, dtype=wp.vec3d, device=device)
        self._target_tolerance = wp.array(self._target_tolerance_host, dtype=wp.float64, device=device)
        self.targets = targets
        self._check_settings()

    def _check_settings(self) -> None:
        """Checks ``self.settings`` against this problem; ``optimize`` checks again, as the
        settings may be changed after construction (0 iterations then ended in an
        IndexError, a negative learning rate ran uphill without a word)."""
        source = self.scene.source or "<scene>"
        s = self.settings
        s.check()
        if self.bundle is not None:
            # The schedule itself, with the learning rate that sets its defaults: a sigma given
            # below the default final one (the learning rate) rose, refused only once the
            # descent began.
            self.bundle.sigmas(s.iterations - 1, s.learning_rate)
        # A window at least the horizon is one window (``TaskSettings.receding``): refused, it
        # ran under --quick, whose caps reset the window.
        if self.model.articulation.num_coordinates and s.receding:
            raise ValueError(f"{source}: receding-horizon control of articulated scenes is not supported (set warpcontact:task:recedingHorizon to 0)")
        if self.kind != "pd_targets" and s.receding:
            # Only per-frame PD targets can be planned window by window; the run used to
            # optimise one window of the whole horizon while reporting the receding settings.
            raise ValueError(f"{source}: receding-horizon control applies to pd_targets tasks, and this task's control is {self.kind} (set warpcontact:task:recedingHorizon to 0)")
        self._sample_box = sample_box(self.scene, s.initial_samples) if s.initial_samples else None
        if s.initial_values is not None and (self.kind != "initial_state" or len(s.initial_values) != len(self.dof_names)):
            raise ValueError(f"{source}: settings.initial_values must hold one value per control DOF ({', '.join(self.dof_names)}) of an initial_state task; this task's control is {self.kind}, got {len(s.initial_values)} values")

    # --- rollouts -------------------------------------------------------------------------

    def _state(self, q, q_prev) -> State:
        shape = (self.model.num_bodies, 7)
        for label, poses in (("start q", q), ("start q_prev", q_prev)):
            if np.shape(poses) != shape:
                # Warp's assign copies what it is given: two poses of three left the third as it was.
                raise ValueError(f"{label}: expected {shape} poses (px, py, pz, qx, qy, qz, qw), one per body, got shape {np.shape(poses)}")
            # It was blamed on zero velocities ("velocities give a non-finite previous pose").
            check_finite_poses(np.asarray(poses, dtype=np.float64), label, self.model.body_names)
        if self.model.num_joint_coordinates and not (np.array_equal(q, self.start[0]) and np.array_equal(q_prev, self.start[1])):
            # Its joint coordinates would stay the initial ones while the poses moved (the
            # solver refuses such a state); base coordinates cannot be recovered from poses.
            raise ValueError("start: an articulated scene's rollouts start from its initial poses at rest")
        state = self.model.state()
        state.body_q.assign(q)
        state.body_q_prev.assign(q_prev)
        return state

    def initial_values(self, rows: int) -> np.ndarray:
        """The trivial guess: zero offsets, or zero sine amplitudes at 1..SINE_WAVES Hz."""
        if not is_whole(rows) or rows < 0:  # -1 was numpy's "negative dimensions" (a probe, stop 64)
            raise ValueError(f"rows: must be a whole number >= 0, got {rows!r}")
        if self.kind != "joint_sine":
            return np.zeros((rows, len(self.dof_names)))
        values = np.zeros((len(self.dof_names), 3 * SINE_WAVES))
        values[:, 1::3] = 2 * np.pi * np.arange(1, SINE_WAVES + 1)
        return values

    def _value_name(self, row: int, column: int) -> str:
        """What entry (row, column) of ``rollout``'s values is: a dof's value at a frame, or
        (joint_sine, whose rows are the coordinates) a coordinate's wave parameter; a
        joint_sine error named the dof of its column, and past the last one raised IndexError."""
        if self.kind == "joint_sine":
            wave, parameter = divmod(column, 3)
            return f"row {row} (coordinate {self.dof_names[row]!r}), column {column} (the {('amplitude', 'frequency', 'phase')[parameter]} of sine wave {wave})"
        return f"row {row}, dof {self.dof_names[column]!r}"

    def rollout(self, values: np.ndarray, start: tuple, frames: int, *, gradient: bool = True, timings: dict | None = None):
        """Simulate ``frames`` frames from ``start`` = (q, q_prev), each (nbodies, 7), under ``values``.

        ``values``: pd_targets, one row per frame of the control dofs' offsets (at least
        ``frames`` rows); initial_state, one row; joint_sine, ``initial_values``' shape.
        An initial_state control sets the start's velocities itself: every body's is the
        scene's (the controlled body's plus the control's offsets), so ``q_prev`` is not read,
        and the controlled body's pose in ``q`` must be the scene's (the control offsets it).
        Returns (loss, d loss / d values or None, trajectory (frames + 1, nbodies, 7)).
        ``timings``, if given, receives ``backward_seconds``: the tape's backward and the
        gradient's read back (benchmarks).
        """
        device = self.model.device
        gradient = checked_flag(gradient, "gradient")  # "no" returned a gradient (a probe, stop 64)
        if not is_whole(frames) or frames < 0:
            raise ValueError(f"frames: must be a whole number >= 0, got {frames!r}")
        shape = np.shape(values)
        given = real_array(values)
        if given is None:  # np.asarray(..., dtype=float64) read text such as "1" as numbers
            raise ValueError(f"values: must be real numbers (integers or floats), got {np.asarray(values).dtype} values")
        values = np.atleast_2d(given)
        # The control kernels index the rows by frame and dof: a smaller array was read out
        # of bounds (a crash, "corrupted double-linked list").
        rows, columns = self.initial_values(1).shape
        if self.kind == "pd_targets":
            rows = max(frames, 1)
            fits = values.ndim == 2 and values.shape[0] >= rows and values.shape[1] == columns
        else:
            fits = values.shape == (rows, columns)
        if not fits:
            wanted = f"at least {rows}" if self.kind == "pd_targets" else str(rows)
            raise ValueError(f"values: {self.kind} control over {frames} frames needs {wanted} rows of {columns} values ({', '.join(self.dof_names)}), got shape {values.shape}")
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:  # an initial state's NaN was blamed on the scene's finite velocities
            row, column = (int(i) for i in bad[0])
            raise ValueError(f"values: {self._value_name(row, column)} is {float(values[row, column])!r}; decision variables must be finite")
        far = beyond_coordinates(values)
        if far is not None:  # 1e200 was blamed on control.body_target, an array the caller never sees
            row, column = far
            raise ValueError(f"values: {self._value_name(row, column)} is {float(values[row, column])!r}, beyond the +-{MAX_COORDINATE:g} that the simulation's coordinates represent")
        if not (isinstance(start, (tuple, list)) and len(start) == 2):
            # None was "_state() argument after * must be an iterable" (a probe, stop 64).
            raise ValueError(f"start: expected (q, q_prev), two (nbodies, 7) pose arrays (TaskProblem.start), got {type(start).__name__}")
        start_state = self._state(*start)
        if self.kind == "initial_state" and not np.array_equal(np.asarray(start[0], dtype=np.float64)[self.body], self.base_pose):
            # The control places its body at the scene's pose plus its offsets: another pose
            # given for it was replaced without a word.
            raise ValueError(f"start: an initial_state control places body {self.model.body_names[self.body]!r} itself (the scene's pose plus the control's offsets); start's pose for it must be the scene's, {self.base_pose.tolist()}")
        values_arr = wp.array(values, dtype=wp.float64, device=device, requires_grad=True)
        # The solver writes every output state's poses; only the start needs filling.
        states = [start_state] + [self.model.state() for _ in range(frames)]
        # Every kind holds PD-driven bodies at the scene's targets, as `simulate` does: an
        # initial_state rollout without a control let each spring follow its body (only its
        # damping acted), so a run optimised other physics than `simulate` showed (a probe).
        # Its targets never change: every frame steps with the one control the problem made.
        controls = [self._scene_control] * frames if self.kind == "initial_state" else [self.model.control() for _ in range(frames)]
        loss = wp.zeros(1, dtype=wp.float64, device=device, requires_grad=True)
        tape = wp.Tape()
        base = wp.transformd(*map(float, self.base_pose)) if self.kind != "joint_sine" else None
        with tape:
            if self.kind == "initial_state":
                # The controlled body's velocity is its authored one plus the control's offset.
                velocity = wp.array(self._initial_velocity[0], dtype=wp.vec3d, device=device, requires_grad=True)
                base_velocity = wp.vec3d(*map(float, self._initial_velocity[0][self.body]))
                wp.launch(task_kernels.initial_state_kernel, dim=1, inputs=[self.body, base, base_velocity, self._dof_codes, values_arr], outputs=[states[0].body_q, velocity], device=device)
                set_body_velocity(states[0], velocity, wp.array(self._initial_velocity[1], dtype=wp.vec3d, device=device, requires_grad=True), self.dt, body_names=self.model.body_names)
            for f in range(frames):
                if self.kind == "pd_targets":
                    wp.launch(task_kernels.pd_target_kernel, dim=1, inputs=[self.body, base, self._dof_codes, values_arr, f], outputs=[controls[f].body_target], device=device)
                elif self.kind == "joint_sine":
                    wp.launch(
                        task_kernels.joint_sine_target_kernel,
                        dim=self._actuated.shape[0],
                        inputs=[self._actuated, self._rest, values_arr, wp.float64((f + 1) * self.dt)],
                        outputs=[controls[f].joint_target],
                        device=device,
                    )
                self.solver.step(states[f], states[f + 1], controls[f], self.dt)
            wp.launch(
                task_kernels.target_loss_kernel,
                dim=len(self.targets),
                inputs=[self._target_body, self._target_position, self._target_tolerance, states[-1].body_q],
                outputs=[loss],
                device=device,
            )
        grad = None
        loss_value = float(loss.numpy()[0])
        if gradient and loss_value == 0.0:
            # Every target's ReLU term is 0: so is the gradient, without a backward pass (a
            # descent stops there; each receding window after success ran one).
            grad = np.zeros(shape)
            if timings is not None:
                timings["backward_seconds"] = 0.0
        elif gradient:
            backward_start = time.perf_counter()
            tape.backward(loss)
            grad = values_arr.grad.numpy().reshape(shape)
            if timings is not None:
                timings["backward_seconds"] = time.perf_counter() - backward_start
        trajectory = np.array([s.body_q.numpy() for s in states])
        return loss_value, grad, trajectory

    # --- optimisation ---------------------------------------------------------------------

    def _objective(self, start: tuple, frames: int, rng, tally: dict | None = None):
        """values -> (loss, gradient or its bundled estimate, trajectory) of one window;
        gb counts its samples into ``tally``."""

        def exact(values, gradient=True):
            return self.rollout(values, start, frames, gradient=gradient)

        if self.bundle is None:
            return exact
        # N iterations make N - 1 Adam updates (the last iterate is only evaluated): the
        # schedule spans the updates, so the final sigma drives the last one.
        sigmas = self.bundle.sigmas(self.settings.iterations - 1, self.settings.learning_rate)
        return bundled_gradient(exact, sigmas=sigmas, samples=self.bundle.samples, rng=rng, tally=tally)

    def optimize(self, *, progress=None, sample_progress=None, checkpoint=None, resume: bool = False, keep_checkpoint: bool = False) -> TaskResult:
        """Gradient descent from the trivial guess (zero offsets); see the module docstring.

        The result's ``initial_loss`` is the trivial guess's loss where ``final_loss`` is
        measured: for a receding horizon, at the horizon's last frame of the trivial plan's
        rollout (one extra forward rollout), not at the first window's end.

        Args:
            progress: callback (done, total, loss) after every iteration (one window) or
                every executed stride (receding horizon).
            sample_progress: callback (done, total, loss or None where infeasible) after
                every draw of ``settings.initial_samples`` (``best_initial_sample``).
            checkpoint: path of a ``TaskCheckpoint`` rewritten before every Adam iteration
                and removed when the optimisation returns; an existing file is refused
                unless ``resume`` is set, so no run's progress is overwritten.
            resume: continue from ``checkpoint`` (ValueError when it is missing or belongs
                to another problem).
            keep_checkpoint: leave the checkpoint for the caller to remove once the result
                is stored (the CLI does, after writing its outputs: a failed write can then
                be resumed instead of run again).
        """
        self._check_settings()
        # resume="no" resumed (a probe).
        resume, keep_checkpoint = checked_flag(resume, "resume"), checked_flag(keep_checkpoint, "keep_checkpoint")
        store = None if checkpoint is None else TaskCheckpoint(checkpoint)
        if store is None and resume:
            raise ValueError("resume: needs the checkpoint to resume from")
        fingerprint = None if store is None else self._fingerprint()
        saved = None
        if store is not None:
            if resume:
                saved = self.resumable(store.path)
            elif store.exists():
                raise ValueError(f"{store.path}: holds an unfinished run ({store.describe()}); resume it, or remove the file to start over")
        start_time = time.perf_counter() - (saved["seconds"] if saved else 0.0)
        s = self.settings
        history = [float(loss) for loss in saved["history"]] if saved else []
        rng = np.random.default_rng(self.bundle.seed) if self.bundle else None
        if saved and rng is not None:
            if saved["rng"] is None:
                raise ValueError(f"{store.path}: not a readable checkpoint (its rng is None, and the gb bundle needs its generator's state)")
            rng.bit_generator.state = saved["rng"]
        # gb's sample counts from the start: a run that drew no bundle (--iters 1) wrote none.
        extra = saved["extra"] if saved else ({"bundle": self._bundle_record(), "bundle_samples": 0, "bundle_samples_dropped": 0} if self.bundle else {})
        if saved and self.bundle is not None and "bundle_samples" not in extra:
            # A checkpoint from before the sample counts: they start at this resume.
            extra["bundle_samples_counted_since_resume"] = True
        receding = self.kind == "pd_targets" and s.receding

        def saver(objective, **outer):
            """``_descend``'s save callback: the descent's state with the run's around it."""
            if store is None:
                return None

            def save(descent):
                state = {**outer, **descent, "history": history, "extra": extra, "receding": receding, "seconds": time.perf_counter() - start_time}
                state["rng"] = None if rng is None else rng.bit_generator.state
                state["bundle_calls"] = getattr(objective, "calls", 0)
                store.save(fingerprint, state)

            return save

        def objective_at(start, frames, resumed):
            """The window's objective; a resumed window's gb bundles continue their count."""
            objective = self._objective(start, frames, rng, extra)
            if resumed is not None and hasattr(objective, "calls"):
                objective.calls = resumed["bundle_calls"]
            return objective

        if not receding:
            values = self.initial_values(1 if self.kind == "initial_state" else s.horizon) if s.initial_values is None else np.array([s.initial_values], dtype=np.float64)
            first = None
            if s.initial_samples and not saved:
                values, extra["initial_samples"], first = self._best_sample(self.start, s.horizon, sample_progress)
            objective = objective_at(self.start, s.horizon, saved)
            final, values, traj = _descend(objective, values, s, history, progress, first=first, resume=saved, save=saver(objective), stalled=_stall_note(extra))
            result = TaskResult(history, history[0], final, final == 0.0, len(history), time.perf_counter() - start_time, values, traj, extra)
        else:
            result = self._receding(saved, history, extra, progress, objective_at, saver, start_time)
        if store is not None and not keep_checkpoint:
            store.remove()
        return result

    def resumable(self, checkpoint) -> dict:
        """The state saved in ``checkpoint`` when it is a readable checkpoint of this problem;
        ValueError naming the file otherwise (``optimize(resume=True)`` starts with this)."""
        store = TaskCheckpoint(checkpoint)
        saved = store.load(self._fingerprint())
        self._check_saved_shapes(saved, store.path)
        return saved

    def _check_saved_shapes(self, saved: dict, path) -> None:
        """ValueError naming the checkpoint when its arrays or counts do not fit this problem
        (its fingerprint matched, so the file was altered)."""
        s = self.settings
        receding = saved["receding"]
        # A frame past the horizon is refused below, by name.
        rows = s.window_at(min(saved.get("frame", 0), s.horizon - 1)) if receding else (1 if self.kind == "initial_state" else s.horizon)
        shape = self.initial_values(rows).shape
        expected = {"values": shape, "best_values": shape}
        if receding:
            expected["plan"] = (s.horizon + s.window + s.receding_stride, len(self.dof_names))
        # Adam's moments and the pending gradient: none yet (size 0), or one per value.
        expected.update({name: shape for name in ("adam_m", "adam_v", "gradient") if saved[name].size})
        if receding:
            expected["executed"] = (max(len(np.atleast_1d(saved["executed"])), 1), self.model.num_bodies, 7)
        for name, wanted in expected.items():
            if np.shape(saved[name]) != wanted:
                raise ValueError(f"{path}: checkpoint array {name!r} has shape {np.shape(saved[name])}, expected {wanted} for this problem")
        for name, value, end in (("iteration", saved["iteration"], s.iterations), ("frame", saved.get("frame", 0), s.horizon)):
            if value >= end:
                raise ValueError(f"{path}: checkpoint {name} {value} is past this problem's {end}")
        # One loss per iteration run: this window's, after the earlier windows' (each stops at
        # loss 0, so at most ``iterations`` of them). Five losses saved at iteration 1 were
        # taken, and metrics.json reported 7 iterations of a 3-iteration run and a made-up
        # initial loss.
        losses, iteration = len(saved["history"]), saved["iteration"]
        earlier = -(-saved["frame"] // s.receding_stride) * s.iterations if receding else 0
        if not iteration <= losses <= iteration + earlier:
            window = f" of the window at frame {saved['frame']}" if receding else ""
            raise ValueError(f"{path}: not a readable checkpoint (its loss history holds {losses} losses at iteration {iteration}{window})")

    def _receding(self, saved, history, extra, progress, objective_at, saver, start_time) -> TaskResult:
        """Receding horizon: optimise a window, apply its first actions, shift (from the
        checkpoint's frame when ``saved``)."""
        s = self.settings
        q0 = self.model.initial_q.copy()
        window, stride = s.window, s.receding_stride
        if saved:
            t, plan, executed = saved["frame"], saved["plan"], list(saved["executed"])
        else:
            # Since windows end at the horizon the ``window`` rows past it are never read; kept,
            # as checkpoints hold the plan at this shape.
            t, plan, executed = 0, np.zeros((s.horizon + window + stride, len(self.dof_names))), [q0]
        resume = saved
        stopped = None
        while t < s.horizon:
            # The state at the window's start: the last two executed frames.
            current = (executed[-1], executed[-2]) if len(executed) > 1 else self.start
            frames = s.window_at(t)
            values = plan[t : t + frames].copy()
            objective = objective_at(current, frames, resume)
            save = saver(objective, frame=t, plan=plan, executed=np.array(executed))
            try:
                best = _descend(objective, values, s, history, progress, total=s.horizon, resume=resume, save=save, stalled=_stall_note(extra, frame=t))
            except (ValueError, SolverError) as exc:
                if not t:
                    raise  # the trivial guess itself cannot be simulated
                # The frames this window adds beyond the last one fail under the plan carried
                # into it; nothing feasible is left to descend from. The executed frames are
                # the run's result, not lost with it; resuming would fail the same way.
                stopped = {"frame": t, "error": str(exc)}
                break
            resume = None
            plan[t : t + frames] = best[1]
            # The rows entering the next window hold the last planned action; zero would
            # send the body's target back to its start pose at the end of every window.
            plan[t + frames : t + frames + stride] = best[1][-1]
            # The applied actions' frames are the best window rollout's first frames.
            applied = min(stride, s.horizon - t)
            executed.extend(best[2][1 : applied + 1])
            t += applied
            if progress:
                # The kept plan's window loss (the last iterate's, which the descent may have
                # discarded for a better one, was shown).
                progress(t, s.horizon, best[0])
        trajectory = np.array(executed)
        final = self._loss_at(trajectory[-1])
        initial_loss = self._trivial_loss(len(executed) - 1, extra)
        if stopped:
            extra["stopped"] = stopped
        return TaskResult(history, initial_loss, final, final == 0.0 and not stopped, len(history), time.perf_counter() - start_time, plan[: s.horizon], trajectory, extra)

    def _trivial_loss(self, frames: int, extra: dict) -> float | None:
        """A receding run's ``initial_loss``: the trivial plan's loss at the frame where the
        final loss is measured (the last executed frame: the horizon's, or the frame a
        stopped run reached). The first window's loss, at its own last frame, also counted
        what bodies do unpushed (settling cubes: 2.48851 -> 2.48247 was reported for a gain
        of 1.1e-4 over the trivial plan). None, with the reason in
        ``extra["initial_loss_error"]``, when the trivial plan cannot be simulated that far."""
        try:
            return self.rollout(np.zeros((max(frames, 1), len(self.dof_names))), self.start, frames, gradient=False)[0]
        except (ValueError, SolverError) as exc:
            extra["initial_loss_error"] = f"the trivial plan cannot be simulated to frame {frames}: {exc}"
            return None

    def _fingerprint(self) -> dict:
        """What makes two optimisations the same problem (a checkpoint's identity): the task,
        model and settings, and a digest of the scene's bodies and joints (whatever file or
        path they were loaded from)."""
        scene = self.scene
        digest = hashlib.sha256()
        for part in [*scene.bodies, *scene.joints]:
            for f in dataclasses.fields(part):
                value = getattr(part, f.name)
                digest.update(np.ascontiguousarray(value).tobytes() if isinstance(value, np.ndarray) else repr(value).encode())
        digest.update(np.ascontiguousarray(scene.gravity, dtype=np.float64).tobytes())
        return json.loads(
            json.dumps(
                {
                    "task": scene.task.name,
                    "model": self.model_name,
                    "control": self.kind,
                    "dofs": list(self.dof_names),
                    "settings": dataclasses.asdict(self.settings),
                    "simulation": dataclasses.asdict(scene.settings),
                    "bundle": dataclasses.asdict(self.bundle) if self.bundle else None,
                    # Only where the run samples, so that checkpoints written without the key
                    # (runs that do not sample) still resume.
                    **({"sample_box": [b.tolist() for b in self._sample_box]} if self.settings.initial_samples else {}),
                    # A yaw turns about the stage's up axis: a Z-up run's checkpoint resumed into
                    # the Y-up scene. Only where not Z, so that earlier Z-up checkpoints resume.
                    **({"up_axis": scene.up_axis} if scene.up_axis != "Z" else {}),
                    "bodies": digest.hexdigest(),
                },
                default=_fingerprint_value,
            )
        )

    def _bundle_record(self) -> dict:
        """gb's settings as a run's results record them, with the sigmas each window's
        schedule runs from and to (None in the settings stands for 10 and 1 times the learning
        rate, and the results said only null; a probe, stop 62)."""
        schedule = self.bundle.sigmas(self.settings.iterations - 1, self.settings.learning_rate)
        return {**dataclasses.asdict(self.bundle), "sigma_schedule": [float(schedule[0]), float(schedule[-1])]}

    def best_initial_sample(self, *, progress=None) -> tuple[np.ndarray, list]:
        """(the lowest-loss draw's values, one per control DOF; every draw's values and
        loss) of ``settings.initial_samples`` draws: the start ``optimize`` takes.
        ``warpcontact compare`` scores the draws once, with one model, and starts every model
        there (``TaskSettings.initial_values``). ``progress``: callback (done, total, loss or
        None where infeasible) after every draw. ValueError when every draw is infeasible."""
        self._check_settings()
        if not self.settings.initial_samples:
            raise ValueError("settings.initial_samples: 0 draws to choose from")
        values, samples, _ = self._best_sample(self.start, self.settings.horizon, progress)
        return values[0], samples

    def _best_sample(self, start: tuple, frames: int, progress=None):
        """(the lowest-loss sample, every sample's values and loss, the lowest-loss rollout
        for the descent's first step or None) of ``settings.initial_samples`` draws from
        the scene's box; infeasible draws (bodies intersecting at the start, a failed step)
        are recorded with loss None.

        With exact gradients each draw's rollout also runs backward (a small fraction of its
        forward cost), so the descent starts from the best draw without simulating it again;
        gb's first gradient is a bundle, so its draws run forward only.

        Raises ValueError when every draw is infeasible.
        """
        low, high = self._sample_box
        rng = np.random.default_rng(self.settings.sample_seed)
        exact = self.bundle is None
        samples, best = [], None
        for _ in range(self.settings.initial_samples):
            values = rng.uniform(low, high)[None, :]
            try:
                result = self.rollout(values, start, frames, gradient=exact)
            except (ValueError, SolverError):
                result = None
            samples.append({"values": values[0].tolist(), "loss": None if result is None else result[0]})
            if result is not None and (best is None or result[0] < best[1][0]):
                best = (values, result)
            if progress is not None:
                progress(len(samples), self.settings.initial_samples, samples[-1]["loss"])
        if best is None:
            raise ValueError(f"{self.scene.source or '<scene>'}: none of the {len(samples)} initial samples is feasible (bodies intersect at the start, or a step fails)")
        return best[0], samples, (best[1] if exact else None)

    def _loss_at(self, q: np.ndarray) -> float:
        total = 0.0
        for i, position, tolerance in zip(self.targets, self._target_position_host, self._target_tolerance_host):
            total += max(float(np.sum((q[i, :3] - position) ** 2)) - float(tolerance) ** 2, 0.0)
        return total
