"""Warp initialisation and device resolution for the host API."""

import concurrent.futures
import contextlib
import functools
import math
import os
import threading
import weakref

import numpy as np
import warp as wp

__all__ = ["HostReadback", "LaunchCache", "host_buffer", "paused_tape", "resolve_device", "run_concurrently"]


@functools.cache
def _init_warp():
    # The library leaves Warp's settings to its user (it set log_level to WARNING here, which
    # silenced a user's own choice); the CLI quiets module-load chatter itself.
    wp.init()


def resolve_device(device) -> wp.Device:
    """Return the Warp device for ``device`` ("cpu", "cuda", "cuda:0", a Device or None)."""
    _init_warp()
    try:
        return wp.get_device(device)
    except Exception as exc:
        available = ", ".join(str(d) for d in wp.get_devices())
        raise ValueError(f"device: {device!r} is not available (available: {available}); {exc}") from None


@functools.cache
def _cpu_workers(pid: int) -> concurrent.futures.ThreadPoolExecutor | None:
    """The worker pool of process ``pid``: a forked child inherits its parent's pool object
    but not its threads, and would wait forever on it."""
    workers = (os.cpu_count() or 1) - 1
    return concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="warpcontact-cpu") if workers else None


def run_concurrently(tasks, *, modules=(), device=None) -> None:
    """Runs the callables ``tasks`` at once, the first on this thread and the others on a
    pool of one thread per further CPU core, and returns when all have finished (re-raising
    the first exception). Warp runs a CPU kernel on the launching thread and releases the
    GIL while it runs, so launches on disjoint outputs from several threads use several
    cores. With one core the tasks run in order.

    Warp loads (compiles) a kernel's module on its first launch, without a lock, so the
    Warp ``modules`` whose kernels the tasks launch are loaded on ``device`` first."""
    tasks = list(tasks)
    pool = _cpu_workers(os.getpid())
    if pool is None or len(tasks) < 2:
        for task in tasks:
            task()
        return
    for module in modules:
        wp.load_module(module, device=device)
    futures = [pool.submit(task) for task in tasks[1:]]
    try:
        tasks[0]()
    finally:
        errors = [f.exception() for f in futures]
    for error in errors:
        if error is not None:
            raise error


def _repack(new, old) -> bool:
    """Whether a launch parameter must be packed again: arrays by identity (an array never
    changes where it points), numbers by value and sign (0.0 == -0.0, but 1 / -0.0 is -inf),
    anything else (structs, whose fields may have been reassigned) always."""
    if isinstance(new, wp.array):
        return new is not old
    if isinstance(new, (bool, int, float)):
        return type(new) is not type(old) or new != old or math.copysign(1.0, new) != math.copysign(1.0, old)
    return True


class LaunchCache:
    """``wp.launch`` for call sites that launch the same kernels many times (every Newton
    iteration) with mostly the same arguments.

    ``wp.launch`` packs every parameter on every call: 80-120 us of Python for a kernel
    of 13 parameters on this project's 2-core CPU, as long as many small kernels run. On a
    CPU, each site (``site``, a key chosen by the caller; one per thread that launches at
    once) keeps its recorded launch (``record_cmd=True``) and packs again only the
    parameters that changed, then replays it (10-40 us measured). Launches record nothing on a ``wp.Tape``:
    use it only where the tape is paused or never needed. On a GPU it launches plainly
    (evaluations there replay CUDA graphs).
    """

    def __init__(self, device: wp.Device):
        self.device = device
        self._records: dict = {}

    def launch(self, site, kernel, *, dim, inputs, outputs=()):
        if not self.device.is_cpu:
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device)
            return
        params = [*inputs, *outputs]
        record = self._records.get(site)
        if record is None or record[0] is not kernel:
            command = wp.launch(kernel, dim=dim, inputs=params, device=self.device, record_cmd=True)
            self._records[site] = [kernel, command, params, dim]
        else:
            _, command, packed, packed_dim = record
            try:
                for index, value in enumerate(params):
                    if _repack(value, packed[index]):
                        command.set_param_at_index(index, value)
                        packed[index] = value
                # set_dim validates and rebuilds the launch bounds (~9 us): only when they change.
                if dim != packed_dim:
                    command.set_dim(dim)
                    record[3] = dim
            except BaseException:
                # Interrupted between the command and its record (Ctrl-C), the record kept the
                # old values, and later launches replayed the command's new ones: wrong sums.
                del self._records[site]
                raise
        command.launch()


def host_buffer(shape, dtype, device: wp.Device) -> wp.array:
    """A host array to upload from: pinned for a GPU, so that the copy to the device is
    asynchronous and a CUDA graph can capture it. Write it only while no copy from it is in
    flight (after a synchronisation)."""
    return wp.empty(shape, dtype=dtype, device="cpu", pinned=device.is_cuda)


class HostReadback:
    """Host copies of device arrays, read after one synchronisation.

    On a GPU, ``enqueue`` copies each array into its pinned host twin on the device's stream
    (asynchronously, so a CUDA graph can capture the copies) and ``wait`` synchronises once;
    ``read`` then returns a numpy view of the twin, valid until the next ``enqueue`` of that
    name. On a CPU the arrays are read in place: nothing is copied and ``wait`` is free.
    A twin is reallocated when its array's shape changes; a graph that captured the old
    twin must not be replayed after that (the owners drop their graphs whenever they
    reallocate a captured array).
    """

    def __init__(self, device: wp.Device):
        self.device = device
        self._twins: dict[str, wp.array] = {}

    def enqueue(self, **arrays: wp.array):
        for name, array in arrays.items():
            if self.device.is_cpu:
                self._twins[name] = array
                continue
            twin = self._twins.get(name)
            if twin is None or twin.shape != array.shape or twin.dtype != array.dtype:
                twin = self._twins[name] = host_buffer(array.shape, array.dtype, self.device)
            wp.copy(twin, array)

    def wait(self):
        if not self.device.is_cpu:
            wp.synchronize_stream(self.device.stream)

    def read(self, name: str) -> np.ndarray:
        """The values of the array last enqueued under ``name``, as of that ``enqueue``
        (call ``wait`` in between)."""
        return self._twins[name].numpy()


# The thread whose step first met each recording tape. Warp keeps one recording tape for the
# whole process, whichever thread entered it: another thread's steps were recorded on it, or
# hid it from its own thread's steps, and gradients came back wrong without an error (a probe,
# stop 64).
_TAPE_THREADS: "weakref.WeakKeyDictionary[wp.Tape, threading.Thread]" = weakref.WeakKeyDictionary()


@contextlib.contextmanager
def paused_tape():
    """Suspend tape recording; yields the paused tape (or None).

    The implicit step's internal launches (Newton iterations) must not be recorded: its
    backward is the implicit-function-theorem function it records itself. RuntimeError when
    the recording tape is one another, still running thread's steps met first (Warp's tape is
    the process's, not the thread's).
    """
    from warp._src import context

    runtime = getattr(context, "runtime", None)
    tape = getattr(runtime, "tape", None)
    if tape is not None:
        owner = _TAPE_THREADS.get(tape)
        if owner is None or not owner.is_alive():
            owner = _TAPE_THREADS[tape] = threading.current_thread()
        if owner is not threading.current_thread():
            raise RuntimeError(
                f"wp.Tape: thread {owner.name!r} is recording a wp.Tape, and Warp records every thread's launches on the one tape a process "
                "has: this step would be recorded on it (or hide it from that thread's steps); record tapes in one thread at a time, "
                "and step other threads' models only while none records"
            )
    try:
        # Inside the try: a Ctrl-C right after it must still give the tape back (Warp then
        # raised "ended tape capture, but tape not present" over the interrupt).
        if tape is not None:
            runtime.tape = None
        yield tape
    finally:
        if tape is not None:
            runtime.tape = tape
