"""Writing files that a crash cannot leave half-written, and one writer per data folder.

Every file segmo writes into a dataset or model folder goes through `atomic_open` /
`write_atomic`: the data goes to a temporary file beside the target, is flushed to disk,
and replaces the target in one `os.replace`. A reader therefore sees the old file or the
new one, never a part; a killed writer leaves at most a ``.<name>.<pid>.<n>.tmp`` file,
which `remove_temporaries` clears under the folder's lock. Files get the permissions of a
plain `open` (0666 minus the umask), not `mkstemp`'s 0600.

`replacing_folder` writes a whole folder (a model directory, a bundle) the same way: it is
built beside the target and renamed into its place, so no file of an earlier folder lingers
in it; `foreign_entries` names what such a replacement would delete that its writer would
not write back.

`FolderLock` makes the "one writer per data folder" rule an enforced one: `segment-texts`,
`encode-texts` and `synth` hold ``DIR/.segmo-writer.lock`` while they write. A second
writer fails at once with `FolderBusyError` naming the holder's PID and command, and
nothing is lost. The lock is an OS file lock (``flock``), so the kernel releases it when
its process dies, kill -9 included: a stale lock recovers by itself.

    with FolderLock(data, "segmo encode-texts"):
        write_atomic(data / "index.json", text)
"""

from __future__ import annotations

import argparse
import glob
import itertools
import json
import logging
import math
import os
import shutil
import socket
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import IO, Any

from segmo.errors import FolderBusyError, SegmoError

log = logging.getLogger(__name__)

LOCK_FILE = ".segmo-writer.lock"
_counter = itertools.count()


def _temporary_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.{next(_counter)}.tmp")


@contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", encoding: str | None = "utf-8"
                ) -> Iterator[IO[Any]]:
    """Open a temporary file for writing that replaces `path` when the block ends without
    an exception (and is removed when it raises). `mode` is "w" or "wb"."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open: mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    tmp = _temporary_path(path)
    # os.open with 0o666 lets the umask decide the permissions, as a plain open() does.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with open(fd, mode, encoding=None if "b" in mode else encoding) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside `path`, for a writer that needs a name (another program):
    the file written there replaces `path` when the block ends without an exception, and
    is removed when it raises."""
    path = Path(path)
    tmp = _temporary_path(path)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_atomic(path: str | os.PathLike, data: str | bytes) -> Path:
    """Write `data` (text as UTF-8, or bytes) to `path` atomically; returns the path."""
    with atomic_open(path, "wb" if isinstance(data, bytes) else "w") as f:
        f.write(data)
    return Path(path)


def json_text(value: Any, indent: int | None = None) -> str:
    """`value` as strict JSON (RFC 8259, what JavaScript's JSON.parse reads), with NaN and
    ±inf written as null: `json.dumps` would write them as bare NaN/Infinity, which only
    Python and a few lenient readers accept. segmo's readers take such a null as NaN."""
    def finite(x: Any) -> Any:
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: finite(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [finite(v) for v in x]
        return x

    return json.dumps(finite(value), indent=indent, allow_nan=False)


def remove_stale_temporaries(path: str | os.PathLike) -> None:
    """Delete the temporaries that writers of `path`, killed before they finished, left
    beside it (`atomic_open`'s ``.NAME.<pid>.<n>.tmp`` of processes that are gone)."""
    path = Path(path)
    for leftover in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        pid = leftover.name[len(path.name) + 2:].split(".")[0]
        if pid.isdecimal() and not pid_alive(int(pid)):
            leftover.unlink(missing_ok=True)


def remove_temporaries(folder: str | os.PathLike) -> int:
    """Delete the temporary files killed writers left in `folder`; returns how many.

    Call it only while holding the folder's `FolderLock`: another writer's temporaries
    are live files."""
    removed = 0
    for leftover in Path(folder).glob(".*.tmp"):
        leftover.unlink(missing_ok=True)
        removed += 1
    return removed


@contextmanager
def replacing_folder(folder: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temporary folder beside `folder` that takes its place whole (an
    existing `folder` is deleted) when the block ends without an exception, and is deleted
    when it raises. A reader finds the old folder or the new one, never a mix of both; a
    killed writer leaves ``NAME.tmp-<pid>-<n>`` (or ``NAME.old-<pid>-<n>``) beside it,
    which the next writer of `folder` clears up (`_recover`)."""
    check_replaceable_place(folder)
    target = Path(folder).resolve()  # a symbolic link keeps pointing at the new folder
    _recover(target)
    suffix = f"{os.getpid()}-{next(_counter)}"
    tmp = target.with_name(f"{target.name}.tmp-{suffix}")
    tmp.mkdir(parents=True)
    try:
        yield tmp
        if target.exists():
            old = target.with_name(f"{target.name}.old-{suffix}")
            target.rename(old)
            tmp.rename(target)
            shutil.rmtree(old)
        else:
            tmp.rename(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def check_replaceable_place(folder: str | os.PathLike) -> None:
    """Refuse a `folder` that must never be replaced whole: the current folder or one above
    it (``--out ""`` is the current folder), the home folder or one above it (the root).
    Replacing one deletes everything the user has there, not just an earlier output."""
    target = Path(folder).resolve()
    for place, name in ((Path.cwd().resolve(), "the current folder"),
                        (Path.home().resolve(), "your home folder")):
        if target == place:
            raise SegmoError(f"{folder}: is {name}; a folder written whole "
                             "replaces all it holds: name a new folder")
        if target in place.parents:
            raise SegmoError(f"{folder}: holds {name}; a folder written whole "
                             "replaces all it holds: name a new folder")


def _recover(target: Path) -> None:
    """Clear what killed `replacing_folder` writers of `target` left beside it: their
    half-written ``.tmp-`` folders go; an ``.old-`` folder is put back when the kill came
    between the two renames (so `target` was missing), and goes otherwise."""
    for kind in ("old", "tmp"):
        for leftover in sorted(target.parent.glob(f"{target.name}.{kind}-*-*")):
            pid = leftover.name.removeprefix(f"{target.name}.{kind}-").split("-")[0]
            if not (pid.isdecimal() and leftover.is_dir() and not leftover.is_symlink()) \
                    or pid_alive(int(pid)):
                continue  # a folder of the user's named alike, or a writer at work
            if kind == "old" and not target.exists():
                leftover.rename(target)
            else:
                shutil.rmtree(leftover, ignore_errors=True)


def pid_alive(pid: int) -> bool:
    """Whether a process `pid` runs on this machine (one we may not signal counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


NPY_MAGIC = b"\x93NUMPY"  # how every .npy file begins


def read_npy_shape(path: str | os.PathLike) -> tuple[int, ...]:
    """Shape from a ``.npy`` header without reading the data; ValueError when the file is
    not a .npy file or holds fewer bytes than the header claims (a cut file, or a header
    claiming 2e9 frames, which `np.load` would try to allocate before it failed)."""
    import math

    import numpy as np  # on use: most commands read no arrays

    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        held = os.fstat(f.fileno()).st_size - f.tell()
    claimed = math.prod(shape) * dtype.itemsize
    if not dtype.hasobject and held < claimed:
        raise ValueError(f"its header claims {shape} values of {dtype} ({claimed:,} bytes) but "
                         f"the file holds {held:,} bytes")
    return shape


def read_npy(path: str | os.PathLike) -> Any:
    """The array of real numbers in a .npy file, or SegmoError naming the file: not a .npy
    file (an .npz archive, text, a pickle), a header claiming more bytes than the file
    holds, values that are not real numbers (objects, strings, complex)."""
    import numpy as np

    path = Path(path)
    try:
        with open(path, "rb") as f:
            magic = f.read(len(NPY_MAGIC))
    except OSError as error:  # a folder, a file this user may not read
        raise SegmoError(f"{path}: not a readable .npy array ({error.strerror or error})") from None
    if magic != NPY_MAGIC:
        kind = "an .npz archive" if magic.startswith(b"PK") else "not a .npy file"
        raise SegmoError(f"{path}: {kind}; save one array with numpy.save")
    try:
        read_npy_shape(path)
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise SegmoError(f"{path}: not a readable .npy array ({error})") from None
    if array.dtype.kind not in "iuf":
        raise SegmoError(f"{path}: holds {array.dtype} values, not real numbers")
    return array


def file_above(path: str | os.PathLike) -> Path | None:
    """The nearest existing folder of `path` when it is a file (a path through a file cannot
    be written), else None; checked before any work."""
    above = next((p for p in Path(path).absolute().parents if p.exists()), None)
    return above if above is not None and not above.is_dir() else None


def foreign_entries(folder: str | os.PathLike, expected: Iterable[str]) -> list[str]:
    """What `folder` holds besides the `expected` files (POSIX paths relative to it), as
    paths relative to it: a whole subfolder no expected file lies in is one entry."""
    expected = set(expected)
    parents = {str(parent) for path in expected for parent in PurePosixPath(path).parents} - {"."}
    found: list[str] = []

    def walk(directory: Path, prefix: str) -> None:
        for entry in sorted(directory.iterdir()):
            name = prefix + entry.name
            if name in parents and entry.is_dir() and not entry.is_symlink():
                walk(entry, name + "/")
            elif name not in expected or not entry.is_file():
                found.append(name)

    walk(Path(folder), "")
    return found


class FolderLock:
    """Exclusive writer lock on a data folder (``DIR/.segmo-writer.lock``).

    Re-entrant within a process (the demo's steps, or a writer calling another, share
    one lock), exclusive between processes. Use as a context manager; `acquire` raises
    `FolderBusyError` when another process holds the lock: at once, or with ``wait``
    seconds, when a process running the same ``command`` (a peer doing the same job, such
    as two fits building one motion-token cache) still holds it after them; one line says
    whom it waits for. Any other writer is refused at once.
    """

    _held: dict[str, list] = {}  # resolved folder -> [open lock file, depth], this process

    def __init__(self, folder: str | os.PathLike, command: str, wait: float = 0.0) -> None:
        self.folder = Path(folder)
        self.command = command
        self.wait = wait

    @property
    def path(self) -> Path:
        return self.folder / LOCK_FILE

    def acquire(self) -> None:
        key = str(self.folder.resolve())
        if key in self._held:
            self._held[key][1] += 1
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        # No O_TRUNC: a process that fails to get the lock must not erase the holder's note.
        handle = open(os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666), "r+", encoding="utf-8")
        deadline, told = time.monotonic() + self.wait, False
        while not _try_lock(handle):
            holder = _read_holder(handle)
            if time.monotonic() >= deadline or f"({self.command}," not in holder:
                handle.close()
                raise FolderBusyError(f"{self.folder} is being written by {holder}; wait for it to "
                                      "finish or stop it (one writer per data folder)")
            if not told:
                log.warning("%s: waiting for %s to finish writing it", self.folder, holder)
                told = True
            time.sleep(min(1.0, max(deadline - time.monotonic(), 0.0)))
        handle.seek(0)
        handle.truncate()
        handle.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                 "command": self.command,
                                 "since": time.strftime("%Y-%m-%d %H:%M:%S")}) + "\n")
        handle.flush()
        self._held[key] = [handle, 1]

    def release(self) -> None:
        key = str(self.folder.resolve())
        entry = self._held.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] == 0:
            del self._held[key]
            entry[0].close()  # closing the file releases the OS lock

    def __enter__(self) -> FolderLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _try_lock(handle: IO[str]) -> bool:
    try:  # imported here: which module exists depends on the platform
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        try:
            msvcrt.locking(handle.fileno(), msvcrt.LK_NBLCK, 1)
        except OSError:
            return False
        return True
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _read_holder(handle: IO[str]) -> str:
    """The holder's note as "PID 123 (segmo encode-texts, since ...)", as far as readable."""
    try:
        handle.seek(0)
        note = json.loads(handle.read() or "{}")
    except (OSError, ValueError):
        note = {}
    if "pid" not in note:
        return "another process"
    host = f" on {note['host']}" if note.get("host") not in (None, socket.gethostname()) else ""
    return f"PID {note['pid']}{host} ({note.get('command', '?')}, since {note.get('since', '?')})"


def output_folder(text: str) -> str:
    """argparse type of an --out folder that a command writes files into (the text as
    given). An empty string (an unset shell variable, quoted) would be the current folder
    without the user saying so."""
    if not text:
        raise argparse.ArgumentTypeError("expected a folder, got an empty string (an unset "
                                         "variable?)")
    return text


def replaced_folder(text: str) -> str:
    """argparse type of an --out folder that a command writes whole, replacing what it
    held (export, bundle, synth): `output_folder`, and never the current folder, the home
    folder or one above either (`check_replaceable_place`)."""
    output_folder(text)
    try:
        check_replaceable_place(text)
    except SegmoError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def npy_argument(parser: argparse.ArgumentParser, flag: str, path: str | os.PathLike):
    """The numeric array of the .npy file an argument names, or the one-line error of
    `parser` naming the argument and the file (missing, a folder, a pickle, not numbers)."""
    path = Path(path)
    if path.is_dir():
        parser.error(f"{flag} {path}: is a directory, not a .npy file")
    if not path.is_file():
        parser.error(f"{flag} {path}: no such file")
    try:
        return read_npy(path)
    except SegmoError as error:
        parser.error(f"{flag} {error}")
