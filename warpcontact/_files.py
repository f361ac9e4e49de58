"""Output files written whole: a failed or interrupted write leaves the earlier file."""

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["LOCK_NAME", "hold_folder", "json_ready", "replace_file", "replace_files", "replace_json", "replace_text"]

# The file a command holds in its output folder while it writes there (``hold_folder``).
LOCK_NAME = ".warpcontact-lock"


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def hold_folder(folder):
    """Claim ``folder`` for one command: create its LOCK_NAME exclusively, holding this
    process's id; returns the function that releases it. ValueError naming the other process
    while a running one holds it: two runs into one folder passed their checks for earlier
    results at their starts, and the later one's results replaced the other's without a word.
    A lock whose process has ended (killed) is taken over, and what that process was writing
    (hidden ``.results-*`` folders and ``.tmp-*`` files, ``replace_files``, ``replace_file``)
    is removed."""
    folder = Path(folder)
    lock = folder / LOCK_NAME
    while True:
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            try:
                holder = int(lock.read_text().split()[0])
            except (OSError, ValueError, IndexError):  # being written, or unreadable
                holder = None
            if holder is None or (holder != os.getpid() and _running(holder)):
                who = f"process {holder}" if holder is not None else f"a process (see {lock})"
                raise ValueError(f"{folder}: another warpcontact command ({who}) is writing there; wait for it to finish or choose another --out") from None
            lock.unlink(missing_ok=True)
    with os.fdopen(fd, "w") as f:
        f.write(f"{os.getpid()}\n")
    for leftover in [*folder.glob(".results-*"), *folder.glob(".tmp-*")]:
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
        else:
            leftover.unlink(missing_ok=True)
    return lambda: lock.unlink(missing_ok=True)


def replace_file(path, write) -> None:
    """Write ``path`` by ``write(temporary)``, a fresh name beside it (not yet a file, with
    the same suffix), then rename it into place. A write that fails or is interrupted (a
    full disk, Ctrl-C) leaves the earlier file as it was: results rewritten in place were
    left truncated, and every finished row or model in them lost."""
    path = Path(path)
    if not path.parent.is_dir():
        # mkstemp named its temporary file, not the output.
        raise FileNotFoundError(f"{path}: its folder does not exist")
    fd, temporary = tempfile.mkstemp(suffix=path.suffix, prefix=".tmp-", dir=path.parent)
    os.close(fd)
    os.unlink(temporary)  # some writers (Usd.Stage.CreateNew) refuse an existing file
    try:
        write(Path(temporary))
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


@contextlib.contextmanager
def replace_files(folder, names):
    """Replace a command's results in ``folder`` as one set: yields a hidden folder inside it
    to write the files ``names`` in; once the block finishes, each is renamed into ``folder``,
    and an earlier file of a name the block did not write is removed. A block that fails or
    is interrupted changes nothing in ``folder`` (only the renames that follow it, one short
    loop, can be cut between two files): written one by one, a failed trajectory left a new
    metrics.json beside an earlier run's trajectory.usda."""
    folder = Path(folder)
    staged = Path(tempfile.mkdtemp(prefix=".results-", dir=folder))
    try:
        yield staged
        for name in names:
            if (staged / name).exists():
                os.replace(staged / name, folder / name)
            else:
                (folder / name).unlink(missing_ok=True)
    finally:
        shutil.rmtree(staged, ignore_errors=True)


def replace_text(path, text: str) -> None:
    """``replace_file`` for a text file."""
    replace_file(path, lambda temporary: temporary.write_text(text))


def replace_json(path, payload) -> None:
    """``replace_text`` of ``payload`` as strict JSON, indented: numpy values as numbers and
    lists, and a NaN or infinity (a ratio to an infinite reference, a failed loss) as null;
    ``json.dumps`` wrote them as bare NaN and Infinity tokens, which JSON parsers refuse."""
    replace_text(path, json.dumps(json_ready(payload), indent=2, allow_nan=False) + "\n")


def json_ready(value):
    """``value`` with numpy arrays and scalars as Python lists and numbers, and every float
    that is not finite as None."""
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.tolist()
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
