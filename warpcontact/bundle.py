"""First-order gradient bundles (Suh, Pang and Tedrake 2022, "Bundled gradients through
contact via randomized smoothing"): the "gb" baseline of the task runner.

The bundled gradient at decision variables x is the Monte-Carlo average of exact gradients
at Gaussian perturbations,

    g(x) = 1/N sum_i grad f(x + sigma_t w_i),   w_i ~ N(0, I),

an unbiased estimate of the gradient of the smoothed loss E[f(x + sigma_t w)] while every
sample's rollout is feasible. It feeds the same Adam as the exact gradient
(``tasks._descend``); only the gradient changes.

Choices (docs/architecture.md explains them):

- N = 8 samples per iteration (``BundleSettings.samples``; ``--quick`` uses 4).
- sigma_t decays geometrically over a window's Adam updates from 10 to 1 times the task's
  learning rate (the distance ten Adam steps, then one, move a decision variable), in the
  decision variables' own units (m, m/s, rad). It restarts with every receding-horizon
  window.
- Samples come from one ``numpy.random.Generator`` seeded by ``BundleSettings.seed``, so a
  run is reproducible.
- A sample whose rollout is infeasible (bodies intersecting at the start, or a failed step),
  or whose gradient is not finite, is dropped from the average; with no feasible sample the gradient is zero. The average
  then leans away from where rollouts fail (a cue placed into the ball it should strike):
  the drawn and dropped samples are counted (``tally``; a task run's ``extra`` and
  metrics.json, ``bundle_samples`` and ``bundle_samples_dropped``).
- The reported loss is f(x) itself (one extra rollout without gradient), so loss histories
  compare directly with exact-gradient runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validate import is_real, is_whole
from .solver import SolverError

__all__ = ["BundleSettings", "bundled_gradient"]


@dataclass
class BundleSettings:
    """Gradient-bundle settings. Sigmas are in the decision variables' units; None scales
    them with the learning rate (10x at a window's first Adam update, 1x at its last)."""

    samples: int = 8
    initial_sigma: float | None = None
    final_sigma: float | None = None
    seed: int = 0

    def check(self) -> None:
        """Raises ValueError for a sample count below 1 or a seed below 0 (or not whole), or
        a sigma that is not None or a positive finite number. That the schedule decays needs
        the learning rate (``sigmas``); a task problem checks it when it is made, before any
        rollout."""
        for name, value, low in (("samples", self.samples, 1), ("seed", self.seed, 0)):
            if not is_whole(value) or value < low:
                raise ValueError(f"{name}: must be a whole number >= {low}, got {value!r}")
        for name in ("initial_sigma", "final_sigma"):
            value = getattr(self, name)
            if value is not None and not (is_real(value) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be None (scaled with the learning rate) or a positive finite number, got {value!r}")

    def sigmas(self, iterations: int, learning_rate: float) -> np.ndarray:
        """(iterations,) geometric sigma schedule of one optimisation window's ``iterations``
        Adam updates (at least one sigma)."""
        self.check()
        first = 10.0 * learning_rate if self.initial_sigma is None else self.initial_sigma
        last = learning_rate if self.final_sigma is None else self.final_sigma
        if not (np.isfinite(first) and np.isfinite(last) and 0 < last <= first):
            raise ValueError(f"sigma: the schedule must decay from a positive initial sigma to a positive final one, got {first!r} and {last!r} (learning rate {learning_rate!r})")
        return np.geomspace(first, last, max(iterations, 1))


def bundled_gradient(rollout, *, sigmas: np.ndarray, samples: int, rng: np.random.Generator, tally: dict | None = None):
    """Wrap ``rollout(values, gradient=True) -> (loss, grad, trajectory)`` so that its k-th
    feasible call asking for a gradient (one per Adam update) returns the bundled gradient
    with sigma = sigmas[k] (the last sigma once the schedule is used up), and the loss and
    trajectory at ``values`` itself. A call with ``gradient=False`` (the descent's last
    iterate, which is only evaluated) runs the one rollout at ``values``, draws nothing and
    returns no gradient; one whose loss there is 0 (success, where the descent stops) runs
    only that rollout, draws nothing (the generator does not advance) and returns a zero
    gradient. A call whose rollout at ``values`` fails (an update the descent then
    halves back) takes no place in the schedule: it used to, so each one skipped a sigma. The
    count of bundles drawn so far is the attribute ``calls`` (a checkpoint saves and
    restores it). ``tally``, if given, counts the samples drawn (``bundle_samples``) and
    those dropped as infeasible or with a gradient that is not finite
    (``bundle_samples_dropped``)."""

    def estimate(values, gradient=True):
        sigma = float(sigmas[min(estimate.calls, len(sigmas) - 1)])
        loss, _, trajectory = rollout(values, gradient=False)
        if not gradient:
            return loss, None, trajectory
        if loss == 0.0:
            # Success: the descent stops here, and a bundle (samples rollouts with their
            # backward passes) would only be drawn to be dropped; none is counted.
            return loss, np.zeros(np.shape(values)), trajectory
        estimate.calls += 1
        total = np.zeros_like(values, dtype=np.float64)
        feasible = 0
        for _ in range(samples):
            try:
                _, grad, _ = rollout(values + sigma * rng.standard_normal(np.shape(values)))
            except (ValueError, SolverError):
                continue
            if not np.isfinite(grad).all():  # dropped like a failed sample: averaged in, it made the bundle NaN
                continue
            total += grad
            feasible += 1
        if tally is not None:
            tally["bundle_samples"] = tally.get("bundle_samples", 0) + samples
            tally["bundle_samples_dropped"] = tally.get("bundle_samples_dropped", 0) + samples - feasible
        return loss, total / max(feasible, 1), trajectory

    estimate.calls = 0
    return estimate
