"""Writing outputs whole; every writer goes through here.

A file or folder is written under a hidden temporary name next to its target
(``.NAME.tmp-PID``), flushed to disk (file contents, then the folder entry), then renamed
into place, so a reader sees the old output or the new one and a failed write (a full
disk, a read-only folder) raises and leaves the target as it was. A folder being replaced
is first moved to ``.NAME.old-PID``. Temporaries left by a process that died (``kill -9``)
are removed the next time something is written into their folder. Files get the mode
``open()`` gives (0666 less the umask), whichever writer made them.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from urhead.errors import InvalidArgumentError

_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-(?P<pid>\d+)(?:\.[^.]*)?$")
LOCK_FILE = ".urhead.lock"


def temporary_name(path: Path, kind: str = "tmp") -> Path:
    """``.STEM.KIND-PID.SUFFIX`` next to ``path`` (writers pick formats by the suffix)."""
    return path.with_name(f".{path.stem}.{kind}-{os.getpid()}{path.suffix}")


def write_file_atomically(path: str | os.PathLike, write: Callable[[Path], None]) -> None:
    """Calls ``write(tmp_path)``, flushes the file to disk, then renames it to ``path``.
    Raises whatever the write raised (``OSError`` naming ``path`` for a failed flush)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path.parent)
    tmp = temporary_name(path)
    try:
        try:
            write(tmp)
        except OSError as e:
            code = e.errno or errno.EIO
            raise OSError(code, f"{path}: cannot be written ({os.strerror(code)})") from None
        _fsync_file(tmp, path)
        os.replace(tmp, path)
        _fsync_folder(path.parent)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes_atomically(path: str | os.PathLike, data: bytes) -> None:
    write_file_atomically(path, lambda tmp: write_bytes(tmp, data))


def write_bytes(path: Path, data: bytes) -> None:
    """Writes ``data`` to ``path`` through Python's file I/O (any path, even one that is not
    valid UTF-8); a short write or a full disk raises ``OSError`` naming ``path``."""
    try:
        with open(path, "wb") as f:
            f.write(data)
    except OSError as e:
        raise OSError(e.errno, f"{path}: cannot be written ({os.strerror(e.errno or 0)})") from None


def write_directory_atomically(path: str | os.PathLike, fill: Callable[[Path], None]) -> None:
    """Calls ``fill(tmp_dir)`` on a fresh sibling folder, flushes every file in it, then
    renames it to ``path`` (replacing an existing ``path``). A failure leaves ``path`` as
    it was."""
    tmp = temporary_folder(path)
    try:
        fill(tmp)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if e.filename is not None or str(path) in str(e):
            raise
        # A write deep inside a writer (a full disk) raises without a file name.
        code = e.errno or errno.EIO
        raise OSError(code, f"{path}: cannot be written ({os.strerror(code)})") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    commit_folder(tmp, path)


def temporary_folder(path: str | os.PathLike) -> Path:
    """A fresh, empty ``.NAME.tmp-PID`` beside ``path`` to fill, then :func:`commit_folder`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path.parent)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    return tmp


def commit_folder(tmp: Path, path: str | os.PathLike) -> None:
    """Flushes every file under ``tmp`` to disk and renames ``tmp`` to ``path``, replacing
    an existing ``path``; on failure ``tmp`` is removed and ``path`` left as it was."""
    path = Path(path)
    old = path.with_name(f".{path.name}.old-{os.getpid()}")
    try:
        for f in tmp.rglob("*"):
            if f.is_file():
                _fsync_file(f, path / f.relative_to(tmp))
        _fsync_folder(tmp)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        _fsync_folder(path.parent)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not path.exists():
            os.replace(old, path)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def c_library_path(path: str | os.PathLike, mode: str) -> Iterator[str]:
    """A name for ``path`` that a C library (OpenEXR, FFmpeg) can open: ``path`` itself when
    it is valid UTF-8; else a file in a private temporary folder, holding a copy of the file
    (``mode`` "r") or copied to ``path`` after the block (``mode`` "w"). A name that is not
    UTF-8 would reach the library as a broken string."""
    name = os.fspath(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        pass
    else:
        yield name
        return
    with tempfile.TemporaryDirectory(prefix="urhead-") as folder:
        proxy = Path(folder) / ("file" + Path(path).suffix)
        if mode == "r":
            shutil.copyfile(path, proxy)
        yield str(proxy)
        if mode == "w":
            shutil.copyfile(proxy, path)


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Removes the temporaries (``.NAME.tmp-PID``, and ``.NAME.old-PID`` once ``NAME``
    exists again) of processes that no longer run; returns what was removed. A previous
    folder kept while its replacement is missing is left: it is the newest complete copy
    (a checkpoint, say)."""
    removed = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = _TEMPORARY.match(entry.name)
        if match is None or _process_runs(int(match["pid"])):
            continue
        if match["kind"] == "old" and not (entry.parent / match["name"]).exists():
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed


@contextmanager
def folder_lock(folder: Path, option: str) -> Iterator[None]:
    """Holds an exclusive lock on ``folder`` (created if missing) for the block; another
    process holding it is an :class:`InvalidArgumentError` naming ``option`` and the
    folder. The lock goes with the process, so a killed run leaves none behind."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            raise InvalidArgumentError(
                f"{option} {folder}: another urhead process (pid {holder}) is writing there; "
                "wait for it or choose another folder"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)


def _process_runs(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _fsync_file(path: Path, target: Path) -> None:
    try:
        with open(path, "rb+") as f:
            os.fsync(f.fileno())
    except OSError as e:
        code = e.errno or errno.EIO
        raise OSError(code, f"{target}: cannot be written ({os.strerror(code)})") from None


def _fsync_folder(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
