"""Host runtime helpers: concurrent CPU launches and recorded launches."""

import multiprocessing

import numpy as np
import pytest
import warp as wp

from warpcontact._runtime import LaunchCache, resolve_device, run_concurrently


@wp.struct
class _Offset:
    value: wp.float64


@wp.kernel
def _add_kernel(values: wp.array(dtype=wp.float64), scale: wp.float64, offset: _Offset, out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = scale * values[i] + offset.value


@wp.kernel
def _subtract_kernel(values: wp.array(dtype=wp.float64), scale: wp.float64, offset: _Offset, out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = scale * values[i] - offset.value


def test_recorded_launches_see_every_changed_argument():
    # A site's recorded launch packs again what changed: a number, an array, the launch
    # size, a struct whose field was reassigned in place, and the kernel itself.
    device = resolve_device("cpu")
    cache = LaunchCache(device)
    values = wp.array([1.0, 2.0, 3.0], dtype=wp.float64, device=device)
    other = wp.array([10.0, 20.0, 30.0], dtype=wp.float64, device=device)
    out = wp.zeros(3, dtype=wp.float64, device=device)
    offset = _Offset()
    offset.value = 0.5

    def run(kernel, array, scale, dim):
        out.zero_()
        cache.launch("site", kernel, dim=dim, inputs=[array, scale, offset], outputs=[out])
        return out.numpy().tolist()

    assert run(_add_kernel, values, 2.0, 3) == [2.5, 4.5, 6.5]
    assert run(_add_kernel, values, 2.0, 3) == [2.5, 4.5, 6.5]  # replayed as recorded
    assert run(_add_kernel, values, 3.0, 3) == [3.5, 6.5, 9.5]
    assert run(_add_kernel, other, 3.0, 2) == [30.5, 60.5, 0.0]
    offset.value = -1.0
    assert run(_add_kernel, other, 3.0, 3) == [29.0, 59.0, 89.0]
    assert run(_subtract_kernel, other, 3.0, 3) == [31.0, 61.0, 91.0]
    other.assign(np.array([1.0, 1.0, 1.0]))  # an array's contents are read at launch
    assert run(_subtract_kernel, other, 3.0, 3) == [4.0, 4.0, 4.0]
    # 0.0 == -0.0, but they differ: a change of a zero's sign was not packed again.
    offset.value = -0.0
    assert not np.signbit(run(_add_kernel, other, 0.0, 1)[0])  # 0 x 1 + -0 = +0
    assert np.signbit(run(_add_kernel, other, -0.0, 1)[0])  # -0 x 1 + -0 = -0


def test_a_recorded_launch_interrupted_while_it_is_repacked_is_packed_again(monkeypatch):
    """Ctrl-C between the command's new size and its record's left the record at the old
    size: the next launch at that size replayed the interrupted one's (wrong sums)."""
    from warp._src import context

    device = resolve_device("cpu")
    cache = LaunchCache(device)
    values = wp.array([1.0, 2.0, 3.0], dtype=wp.float64, device=device)
    out = wp.zeros(3, dtype=wp.float64, device=device)
    offset = _Offset()
    offset.value = 0.0
    cache.launch("site", _add_kernel, dim=2, inputs=[values, 1.0, offset], outputs=[out])
    set_dim = context.Launch.set_dim

    def interrupted(self, dim):
        set_dim(self, dim)
        raise KeyboardInterrupt

    monkeypatch.setattr(context.Launch, "set_dim", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cache.launch("site", _add_kernel, dim=3, inputs=[values, 1.0, offset], outputs=[out])
    monkeypatch.undo()
    out.zero_()
    cache.launch("site", _add_kernel, dim=2, inputs=[values, 1.0, offset], outputs=[out])
    assert out.numpy().tolist() == [1.0, 2.0, 0.0]


def test_concurrent_tasks_all_run_and_raise_the_first_error():
    done = []
    run_concurrently([lambda i=i: done.append(i) for i in range(5)])
    assert sorted(done) == list(range(5))

    def fail():
        raise RuntimeError("chunk 1 failed")

    done.clear()
    with pytest.raises(RuntimeError, match="chunk 1 failed"):
        run_concurrently([lambda: done.append(0), fail, lambda: done.append(2)])
    assert sorted(done) == [0, 2]  # the others still ran to the end


def _run_two_tasks_and_exit():
    done = []
    run_concurrently([lambda: done.append(0), lambda: done.append(1)])
    raise SystemExit(0 if sorted(done) == [0, 1] else 1)


def test_concurrent_tasks_run_in_a_forked_child():
    # A child forked after the pool started inherits the pool but not its threads.
    run_concurrently([lambda: None, lambda: None])
    child = multiprocessing.get_context("fork").Process(target=_run_two_tasks_and_exit)
    child.start()
    child.join(timeout=60)
    if child.is_alive():
        child.kill()
        pytest.fail("run_concurrently hung in a forked child")
    assert child.exitcode == 0


def test_the_library_leaves_warps_log_level_to_its_user(monkeypatch):
    """Found by a probe: resolving a device set wp.config.log_level to WARNING, silencing a
    user's own choice (module loads never showed). Only the CLI quiets Warp."""
    import logging

    import warpcontact as wc
    from warpcontact import _runtime
    from warpcontact.cli import main

    monkeypatch.setattr(wp.config, "log_level", logging.DEBUG)
    _runtime._init_warp.cache_clear()
    builder = wc.ModelBuilder()
    builder.add_box((1.0, 1.0, 1.0), density=1.0)
    builder.finalize()
    assert wp.config.log_level == logging.DEBUG
    assert main(["list"]) == 0
    assert wp.config.log_level == logging.WARNING
