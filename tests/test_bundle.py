"""Gradient bundles (the gb baseline) and one short optimisation per model."""

import numpy as np
import pytest
from test_tasks import space_billiards

from warpcontact.bundle import BundleSettings, bundled_gradient
from warpcontact.tasks import MODELS, TaskProblem, TaskSettings


def quadratic(values, gradient=True):
    return float(np.sum(values**2)), 2.0 * values if gradient else None, "trajectory"


def test_sigma_schedule_decays_from_ten_to_one_learning_rate():
    np.testing.assert_allclose(BundleSettings().sigmas(5, 0.01), [0.1, 0.1 * 10**-0.25, 0.1 * 10**-0.5, 0.1 * 10**-0.75, 0.01])
    np.testing.assert_allclose(BundleSettings(initial_sigma=2.0, final_sigma=0.5).sigmas(3, 0.01), [2.0, 1.0, 0.5])
    with pytest.raises(ValueError, match="samples: must be a whole number >= 1, got 0"):
        BundleSettings(samples=0).sigmas(3, 0.01)
    with pytest.raises(ValueError, match="samples: must be a whole number >= 1, got 2.5"):
        BundleSettings(samples=2.5).sigmas(3, 0.01)  # was a TypeError deep in numpy
    with pytest.raises(ValueError, match="seed: must be a whole number >= 0, got -1"):
        BundleSettings(seed=-1).check()  # was numpy's "expected non-negative integer"
    with pytest.raises(ValueError, match="sigma"):
        BundleSettings(final_sigma=-1.0).sigmas(3, 0.01)
    # Bad sigmas were accepted until the descent began (after --init-samples' rollouts), a
    # text sigma was numpy's TypeError, and a rising schedule ran though sigma decays.
    for settings, message in (
        (BundleSettings(initial_sigma=-1.0), r"initial_sigma: must be None \(scaled with the learning rate\) or a positive finite number, got -1.0"),
        (BundleSettings(final_sigma=float("nan")), "final_sigma: must be None .* got nan"),
        (BundleSettings(initial_sigma="0.5"), "initial_sigma: .* got '0.5'"),
        (BundleSettings(initial_sigma=True), "initial_sigma: .* got True"),
        (BundleSettings(initial_sigma=1e-3, final_sigma=10.0), r"sigma: the schedule must decay from a positive initial sigma to a positive final one, got 0.001 and 10.0"),
    ):
        with pytest.raises(ValueError, match=message):
            TaskProblem(space_billiards(), settings=TaskSettings(horizon=5, receding_horizon=0, iterations=2, learning_rate=0.3), model="gb", bundle=settings)
    with pytest.raises(ValueError, match=r"sigma: the schedule must decay .* got 0.5 and 1.0"):
        BundleSettings(initial_sigma=0.5).sigmas(3, 1.0)  # the final sigma, the learning rate, above it
    # The same when the task problem is made (it rose, refused only once the descent began).
    with pytest.raises(ValueError, match=r"sigma: the schedule must decay .* got 0.01 and 0.3"):
        TaskProblem(space_billiards(), settings=TaskSettings(horizon=5, receding_horizon=0, iterations=2, learning_rate=0.3), model="gb", bundle=BundleSettings(initial_sigma=0.01))


def test_a_checkpoint_without_sample_counts_says_they_start_at_the_resume(tmp_path):
    """A gb checkpoint written before the counts existed resumed with them from zero, as if
    the samples before it had never been drawn."""
    import json

    def problem():
        settings = TaskSettings(horizon=5, receding_horizon=0, iterations=5, learning_rate=0.3)
        return TaskProblem(space_billiards(), settings=settings, model="gb", bundle=BundleSettings(samples=2, seed=1))

    def stop(done, total, loss):
        if done >= 3:
            raise KeyboardInterrupt

    checkpoint = tmp_path / "run.npz"
    with pytest.raises(KeyboardInterrupt):
        problem().optimize(checkpoint=checkpoint, progress=stop)
    saved = dict(np.load(checkpoint))
    meta = json.loads(str(saved["meta"]))
    assert meta["extra"]["bundle_samples"] > 0
    resumed = problem().optimize(checkpoint=checkpoint, resume=True)
    assert resumed.extra["bundle_samples"] == 8 and "bundle_samples_counted_since_resume" not in resumed.extra  # as uninterrupted
    with pytest.raises(KeyboardInterrupt):
        problem().optimize(checkpoint=checkpoint, progress=stop)
    for key in ("bundle_samples", "bundle_samples_dropped"):
        del meta["extra"][key]
    np.savez(checkpoint, **{**saved, "meta": np.array(json.dumps(meta))})
    older = problem().optimize(checkpoint=checkpoint, resume=True)
    assert older.extra["bundle_samples_counted_since_resume"] is True and older.extra["bundle_samples"] < 8


def test_bundle_averages_perturbed_gradients_reproducibly():
    x = np.array([[1.0, -2.0]])
    estimate = bundled_gradient(quadratic, sigmas=np.array([0.5]), samples=4, rng=np.random.default_rng(7))
    loss, grad, trajectory = estimate(x)
    w = np.random.default_rng(7).standard_normal((4, 1, 2))
    assert loss == 5.0 and trajectory == "trajectory"  # at x itself
    np.testing.assert_allclose(grad, np.mean(2.0 * (x + 0.5 * w), axis=0))


def test_infeasible_samples_are_dropped():
    def rollout(values, gradient=True):
        if gradient and values[0, 0] > 1.0:
            raise ValueError("bodies intersect at the start")
        return quadratic(values, gradient)

    x = np.array([[1.0]])
    tally = {}
    _, grad, _ = bundled_gradient(rollout, sigmas=np.array([1.0]), samples=64, rng=np.random.default_rng(0), tally=tally)(x)
    w = np.random.default_rng(0).standard_normal((64, 1, 1))
    kept = (x + w)[(x + w)[:, 0, 0] <= 1.0]
    np.testing.assert_allclose(grad, np.mean(2.0 * kept, axis=0))
    # The dropped samples bias the average, so they are counted (they went unrecorded).
    assert tally == {"bundle_samples": 64, "bundle_samples_dropped": 64 - len(kept)} and 0 < len(kept) < 64
    nothing = bundled_gradient(rollout, sigmas=np.array([1e-9]), samples=4, rng=np.random.default_rng(0))
    assert np.all(nothing(np.array([[2.0]]))[1] == 0.0)

    # Found by a probe: a sample whose gradient is not finite was averaged in (the bundle NaN, none counted dropped).
    def rollout_nan(values, gradient=True):
        loss, grad, trajectory = quadratic(values, gradient)
        return loss, (np.full_like(grad, np.nan) if gradient and values[0, 0] > 1.0 else grad), trajectory

    tally = {}
    _, grad, _ = bundled_gradient(rollout_nan, sigmas=np.array([1.0]), samples=64, rng=np.random.default_rng(0), tally=tally)(x)
    np.testing.assert_allclose(grad, np.mean(2.0 * kept, axis=0))
    assert tally == {"bundle_samples": 64, "bundle_samples_dropped": 64 - len(kept)}


def test_an_infeasible_iterate_takes_no_place_in_the_sigma_schedule():
    """The descent halves an update whose rollout fails and calls the estimate again: each
    failed call used to consume a sigma, so the schedule ran ahead of the iterations."""
    def rollout(values, gradient=True):
        if values[0, 0] > 1.0:
            raise ValueError("bodies intersect at the start")
        return quadratic(values, gradient)

    sigmas = np.array([0.5, 0.25, 0.125])
    estimate = bundled_gradient(rollout, sigmas=sigmas, samples=2, rng=np.random.default_rng(3))
    estimate(np.array([[0.5]]))
    with pytest.raises(ValueError):
        estimate(np.array([[2.0]]))
    assert estimate.calls == 1
    _, grad, _ = estimate(np.array([[0.5]]))
    rng = np.random.default_rng(3)
    rng.standard_normal((2, 1, 1))
    np.testing.assert_allclose(grad, np.mean(2.0 * (0.5 + sigmas[1] * rng.standard_normal((2, 1, 1))), axis=0))


def test_a_zero_loss_draws_no_bundle():
    """A zero loss is success, where the descent stops: its bundle (samples rollouts, each
    with a backward pass) was drawn to be dropped (a probe)."""
    rng = np.random.default_rng(7)
    generator = rng.bit_generator.state
    estimate = bundled_gradient(quadratic, sigmas=np.array([0.5, 0.25]), samples=4, rng=rng)
    state = estimate.__dict__.copy()
    loss, grad, _ = estimate(np.array([[0.0, 0.0]]))
    assert loss == 0.0 and np.array_equal(grad, np.zeros((1, 2)))
    assert estimate.calls == 0 and estimate.__dict__ == state and rng.bit_generator.state == generator


def test_a_loss_only_call_draws_no_bundle():
    estimate = bundled_gradient(quadratic, sigmas=np.array([0.5, 0.25]), samples=4, rng=np.random.default_rng(7))
    state = estimate.__dict__.copy()
    assert estimate(np.array([[1.0, -2.0]]), gradient=False) == (5.0, None, "trajectory")
    assert estimate.calls == 0 and estimate.__dict__ == state
    reference = bundled_gradient(quadratic, sigmas=np.array([0.5, 0.25]), samples=4, rng=np.random.default_rng(7))
    np.testing.assert_array_equal(estimate(np.array([[1.0, -2.0]]))[1], reference(np.array([[1.0, -2.0]]))[1])


def test_gb_draws_no_bundle_at_a_window_s_last_iterate(monkeypatch):
    """3 iterations, 2 samples: 3 rollouts at the iterates and 2 x 2 samples for the two
    updates (the last iterate's bundle, drawn and dropped, made it 9)."""
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("vx", "vy")
    settings = TaskSettings(horizon=6, receding_horizon=0, iterations=3, learning_rate=0.3)
    problem = TaskProblem(scene, settings=settings, model="gb", bundle=BundleSettings(samples=2))
    rollout, asked = problem.rollout, []

    def counting(*args, gradient=True, **kwargs):
        asked.append(gradient)
        return rollout(*args, gradient=gradient, **kwargs)

    monkeypatch.setattr(problem, "rollout", counting)
    assert len(problem.optimize().loss_history) == 3
    assert asked == [False, True, True, False, True, True, False]


@pytest.mark.parametrize("model", MODELS)
def test_each_model_runs_a_short_optimisation(model):
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("vx", "vy")
    settings = TaskSettings(horizon=15, receding_horizon=0, iterations=2, learning_rate=0.3)
    bundle = BundleSettings(samples=2, seed=1) if model == "gb" else None
    result = TaskProblem(scene, settings=settings, model=model, bundle=bundle).optimize()
    assert len(result.loss_history) == 2 and np.isfinite(result.loss_history).all()
    if model == "ours":
        assert result.loss_history[1] < result.loss_history[0]  # the long-range gradient moves it
    if model in ("ipc", "sdrs"):
        assert result.loss_history[1] == result.loss_history[0]  # zero gradient from rest
    if model == "gb":
        # One Adam update: its sigma is the schedule's first, 10 lr.
        assert result.extra["bundle"] == {"samples": 2, "initial_sigma": None, "final_sigma": None, "seed": 1, "sigma_schedule": [10 * settings.learning_rate] * 2}
        assert result.extra["bundle_samples"] == 2 and result.extra["bundle_samples_dropped"] == 0  # one update's bundle


def test_the_sigma_schedule_spans_a_window_s_adam_updates(monkeypatch):
    # N iterations make N - 1 updates; the schedule spanned N, so its last sigma (the
    # learning rate) was bundled at the final iterate and never applied.
    from warpcontact import tasks

    used = []
    real = tasks.bundled_gradient

    def recording(rollout, *, sigmas, samples, rng, tally):
        estimate = real(rollout, sigmas=sigmas, samples=samples, rng=rng, tally=tally)

        def call(values, gradient=True):
            if gradient:
                used.append(float(sigmas[min(estimate.calls, len(sigmas) - 1)]))
            return estimate(values, gradient=gradient)

        return call

    monkeypatch.setattr(tasks, "bundled_gradient", recording)
    scene = space_billiards()
    scene.bodies[0].control_dofs = ("vx", "vy")
    settings = TaskSettings(horizon=6, receding_horizon=0, iterations=3, learning_rate=0.3)
    TaskProblem(scene, settings=settings, model="gb", bundle=BundleSettings(samples=2)).optimize()
    np.testing.assert_allclose(used, [3.0, 0.3])  # the two updates: 10 lr, then lr


def test_gb_finds_descent_near_contact_where_sdrs_sees_nothing():
    """5 cm apart (beyond SDRS's 2 cm support) the SDRS gradient is zero; gradient bundles
    with sigma = 3 m/s sample shots that hit, and descend (measured: 4.04 -> 3.67 in 3 steps)."""
    scene = space_billiards(gap=0.05)
    scene.bodies[0].control_dofs = ("vx", "vy")
    settings = TaskSettings(horizon=15, receding_horizon=0, iterations=3, learning_rate=0.3)
    sdrs = TaskProblem(scene, settings=settings, model="sdrs").optimize()
    gb = TaskProblem(scene, settings=settings, model="gb", bundle=BundleSettings(samples=4)).optimize()
    assert sdrs.final_loss == sdrs.initial_loss
    assert gb.loss_history[-1] < 0.95 * gb.loss_history[0]


def test_model_errors_are_clear():
    scene = space_billiards()
    with pytest.raises(ValueError, match="not one of"):
        TaskProblem(scene, model="mujoco")
    with pytest.raises(ValueError, match="only the gb model"):
        TaskProblem(scene, model="ours", bundle=BundleSettings())
    scene.settings.friction = 0.5
    assert TaskProblem(scene, model="gb").model.friction.numpy()[0] == 0.5  # gb's sdrs has friction
