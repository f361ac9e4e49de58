"""Output files written whole: a failed or interrupted write leaves the earlier file."""

import contextlib
import errno
import json
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path

import numpy as np

try:
    import fcntl
except ImportError:  # not POSIX
    fcntl = None

__all__ = ["LOCK_NAME", "hold_folder", "json_ready", "replace_file", "replace_files", "replace_json", "replace_text"]

# The file a command holds in its output folder while it writes there (``hold_folder``), and
# the prefix of the temporaries the writers below leave only if they are killed.
LOCK_NAME = ".warpcontact-lock"
_TEMPORARY_PREFIX = ".warpcontact-tmp-"


def _holder(fd: int) -> str:
    """Who holds a lock file, as its text (a process id) says."""
    text = os.pread(fd, 64, 0).decode(errors="replace").strip()
    return f"process {text}" if text.isdigit() else "a running process"


def hold_folder(folder):
    """Claim ``folder`` for one command: lock its LOCK_NAME (``fcntl.flock``, which the
    kernel releases when the process ends, however it ends), writing this process's id in it;
    returns the function that releases it and removes the file. ValueError naming the other
    process while a running one holds it: two runs into one folder passed their checks for
    earlier results at their starts, and the later one's results replaced the other's
    without a word. A lock file left by a process that ended without releasing it (killed)
    is taken over, and the temporaries such a process was writing (``replace_file``,
    ``replace_files``) are removed. Without ``fcntl`` (not POSIX) nothing is locked."""
    if fcntl is None:
        return lambda: None
    folder = Path(folder)
    lock = folder / LOCK_NAME
    while True:
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o644)
            left_behind = False
        except FileExistsError:
            try:
                fd = os.open(lock, os.O_RDWR)
            except FileNotFoundError:  # released meanwhile
                continue
            left_behind = True
        except OSError as exc:
            # Root passes os.access where the file system still refuses (/sys): the error
            # named this lock file, not the folder the user gave.
            raise ValueError(f"{folder}: output folder is not writable ({exc.strerror or exc})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise ValueError(f"{folder}: another warpcontact command ({holder}) is writing there; wait for it to finish or choose another --out") from None
        try:
            current = os.stat(lock).st_ino
        except FileNotFoundError:
            current = None
        if current == os.fstat(fd).st_ino:
            break
        os.close(fd)  # its holder released and removed it while this one opened it: again
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    if left_behind:
        for leftover in folder.glob(f"{_TEMPORARY_PREFIX}*"):
            if leftover.is_dir():
                shutil.rmtree(leftover, ignore_errors=True)
            else:
                leftover.unlink(missing_ok=True)

    def release():
        lock.unlink(missing_ok=True)
        os.close(fd)

    return release


def replace_file(path, write) -> None:
    """Write ``path`` by ``write(temporary)``, a fresh name beside it (not yet a file, with
    the same suffix), then rename it into place. A write that fails or is interrupted (a
    full disk, Ctrl-C) leaves the earlier file as it was: results rewritten in place were
    left truncated, and every finished row or model in them lost."""
    path = Path(path)
    if not path.parent.is_dir():
        # mkstemp named its temporary file, not the output.
        raise FileNotFoundError(f"{path}: its folder does not exist")
    try:
        fd, temporary = tempfile.mkstemp(suffix=path.suffix, prefix=_TEMPORARY_PREFIX, dir=path.parent)
    except OSError as exc:
        # Named the temporary file (/proc: "No such file or directory: '/proc/.warpcontact-tmp-...'").
        raise OSError(exc.errno, f"{path}: no file can be created in {path.parent} ({exc.strerror})") from None
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
    to write the files ``names`` in; once the block finishes, each earlier file of those names
    is moved aside, each written file renamed into ``folder``, and the earlier files then
    dropped (a name the block did not write is left without a file). A block that fails or is
    interrupted changes nothing in ``folder``, and neither does a rename that fails: the files
    already moved are put back (written one by one, a failed trajectory left a new
    metrics.json beside an earlier run's trajectory.usda; renamed one by one, a trajectory.usda
    that had become a folder left the new metrics.json beside no trajectory, which the next
    command then took for an earlier run's results; a probe, stop 65). A folder where a result
    file goes is refused before anything moves."""
    folder = Path(folder)
    staged = Path(tempfile.mkdtemp(prefix=_TEMPORARY_PREFIX, dir=folder))
    try:
        yield staged
        for name in names:
            target = folder / name
            if target.exists() and not (target.is_file() or target.is_symlink()):
                # Moved aside, it would have been deleted with the staging folder.
                raise IsADirectoryError(errno.EISDIR, f"{target}: not a file (a folder, or another kind of entry) where a result file goes; remove or rename it, or choose another --out")
        # Dot-named, so that no result's name can be this folder's.
        earlier = staged / ".earlier"
        earlier.mkdir()
        moved_aside, moved_in = [], []
        try:
            for name in names:
                if (folder / name).exists() or (folder / name).is_symlink():
                    os.replace(folder / name, earlier / name)
                    moved_aside.append(name)
            for name in names:
                if (staged / name).exists():
                    os.replace(staged / name, folder / name)
                    moved_in.append(name)
        except BaseException as failure:
            # Every file is put back, whatever interrupts one of them (a second Ctrl-C
            # stopped the loop, and the staging folder went with the files not yet back).
            unrestored = []
            for source, target in [(folder / name, staged / name) for name in moved_in] + [(earlier / name, folder / name) for name in moved_aside]:
                try:
                    os.replace(source, target)
                except BaseException:
                    unrestored.append(target.name)
            if unrestored:
                # The earlier files are then kept where they were moved aside, under a name no
                # later command takes for its own leftovers (a review, stop 65).
                kept = folder / f"warpcontact-earlier-results-{os.getpid()}"
                os.replace(earlier, kept)
                raise OSError(errno.EIO, f"{folder}: replacing the results failed ({failure!r}), and so did putting back {', '.join(unrestored)}: the earlier files are kept in {kept}") from failure
            raise
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


@contextlib.contextmanager
def interrupts_held():
    """Ctrl-C held back until the block ends, for writes of results already computed (an
    interruption while ``simulate`` wrote its trajectory lost every simulated frame, and one
    between a bench's JSON and CSV left them disagreeing). Yields a list that is not empty if
    one came."""
    came = []
    # Only the main thread may set handlers (and only it gets SIGINT); a SIGINT the process
    # ignores (a job started with & by a script) or handles its own way stays so.
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield came
        return
    previous = signal.signal(signal.SIGINT, lambda signum, frame: came.append(signum))
    try:
        yield came
    finally:
        signal.signal(signal.SIGINT, previous)
