"""Warp initialisation and device resolution for the host API."""

import contextlib
import functools
import logging

import warp as wp

__all__ = ["paused_tape", "resolve_device"]


@functools.cache
def _init_warp():
    # Module-load chatter would drown the CLI output; warnings and errors still show.
    wp.config.log_level = logging.WARNING
    wp.init()


def resolve_device(device) -> wp.Device:
    """Return the Warp device for ``device`` ("cpu", "cuda", "cuda:0", a Device or None)."""
    _init_warp()
    try:
        return wp.get_device(device)
    except Exception as exc:
        available = ", ".join(str(d) for d in wp.get_devices())
        raise ValueError(f"device: {device!r} is not available (available: {available}); {exc}") from None


@contextlib.contextmanager
def paused_tape():
    """Suspend tape recording; yields the paused tape (or None).

    The implicit step's internal launches (Newton iterations) must not be recorded: its
    backward is the implicit-function-theorem function it records itself.
    """
    from warp._src import context

    runtime = getattr(context, "runtime", None)
    tape = getattr(runtime, "tape", None)
    if tape is not None:
        runtime.tape = None
    try:
        yield tape
    finally:
        if tape is not None:
            runtime.tape = tape
