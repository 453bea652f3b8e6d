"""Atomic file writes: nothing gsbench writes is ever seen half-written, even after a crash.

`atomic_path` yields a temporary path in the target's folder; when the block finishes the file is moved
into place with ``os.replace`` (atomic on POSIX), and when it raises the temporary file is removed and the
target is left as it was. A write that fails because its disk is full (``ENOSPC``, or ``EDQUOT``: the user's
quota) is a `DiskFullError`, one line naming the file, the space left and the fix.

`check_writable` and `check_writable_files` find, before any work, what would stop the writes: a file where a
folder is needed, a symbolic link that leads nowhere, a folder or file that cannot be written, a file system that
takes no folders (probed with one empty folder, removed at once).
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from gsbench.errors import ConfigError, GsbenchError

DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


class DiskFullError(GsbenchError):
    """A write failed for want of space on its disk; what was written before is intact."""


@contextmanager
def atomic_path(path, *, keep_suffix: bool = False) -> Iterator[Path]:
    """A temporary file ``.<name>.<random>.tmp`` beside ``path`` (its own suffix when ``keep_suffix``, for
    writers that choose the format by it), replacing ``path`` when the block succeeds; folders are made."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix if keep_suffix else ".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        full = disk_full_error(exc, path)
        if full is not None:
            raise full from exc
        raise


def disk_full_error(exc: BaseException, path) -> DiskFullError | None:
    """The `DiskFullError` of writing ``path`` when ``exc``, or an exception it was raised from or during, is an
    OSError saying the disk is full (`DISK_FULL_ERRNOS`; a C++ writer's own error, such as torch's ``basic_ios::clear:
    iostream error``, is raised during the OSError of its Python file object); else None."""
    seen = exc
    while seen is not None and not (isinstance(seen, OSError) and seen.errno in DISK_FULL_ERRNOS):
        seen = seen.__cause__ or seen.__context__
    if seen is None:
        return None
    path = Path(path)
    folder = next((p for p in (path, *path.parents) if p.is_dir()), Path("."))
    free = shutil.disk_usage(folder).free
    return DiskFullError(f"{path}: cannot write there: the disk is full ({os.strerror(seen.errno).lower()}; "
                         f"{_size(free)} free on the file system of {folder}); what was written before is intact; "
                         "fix: free some space there (or choose another output folder), then run the same command "
                         "again: a run resumes from its last checkpoint")


def _size(count: int) -> str:
    """``512 B``, ``3.2 MiB``, ``41.0 GiB``."""
    if count < 1024:
        return f"{count} B"
    for unit in ("KiB", "MiB", "GiB"):
        count /= 1024
        if count < 1024:
            break
    return f"{count:.1f} {unit}"


def check_writable(folder, option: str) -> Path:
    """A ConfigError naming ``folder``, what is in the way and the fix (``option``: the setting that chose the
    folder) unless files can be written there: every part of its path that exists must be a folder (a symbolic
    link must lead to one) and the deepest of them writable, with a folder made in it (and removed) to prove it.
    Checked before any work whose results go there; nothing is left behind."""
    folder = Path(folder)
    existing = folder
    while not os.path.lexists(existing) and existing != existing.parent:
        existing = existing.parent
    other = f"choose another folder with {option}"
    if existing.is_symlink() and not existing.exists():
        target = os.readlink(existing)
        problem = (f"{existing} is a symbolic link loop; fix: point it at a folder or remove it, or {other}"
                   if _is_link_loop(existing) else
                   f"{existing} is a symbolic link to {target}, which does not exist; fix: create that folder, or "
                   f"{other}")
    elif not existing.is_dir():
        problem = f"{existing} is a file, not a folder; fix: move that file away, or {other}"
    elif not os.access(existing, os.W_OK | os.X_OK):
        problem = f"{existing} is not writable (read-only folder or file system); fix: {other} or make it writable"
    elif (refused := _folder_refused(existing)) is not None:
        full = disk_full_error(refused, existing / "x")
        if full is not None:
            raise full from refused
        problem = (f"{existing} takes no new folders ({os.strerror(refused.errno).lower()}: a file system such as "
                   f"/proc, or one that refuses this user); fix: {other}")
    else:
        return folder
    raise ConfigError(f"{folder}: cannot write there: {problem}")


def _folder_refused(folder: Path) -> OSError | None:
    """The OSError of making (and at once removing) an empty folder in ``folder``, or None when it can be made:
    permission bits say nothing of a file system that refuses folders (procfs, sysfs) or of a server's own rules."""
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".gsbench-probe-", dir=folder))
    except OSError as exc:
        return exc
    return None


def _is_link_loop(path: Path) -> bool:
    try:
        os.stat(path)
    except OSError as exc:
        return exc.errno == errno.ELOOP
    return False


def check_writable_files(paths: Iterable, option: str) -> None:
    """`check_writable` of the folder of each of ``paths`` (the files a piece of work will write), and a
    ConfigError naming the file and the fix when one that exists is not a file or cannot be written."""
    checked = set()
    for path in map(Path, paths):
        if path.parent not in checked:
            check_writable(path.parent, option)
            checked.add(path.parent)
        if not os.path.lexists(path):
            continue
        if path.is_dir() or not path.exists():
            what = "a folder" if path.is_dir() else "a symbolic link that leads nowhere"
            raise ConfigError(f"{path}: cannot write there: it is {what}, where a file will be written; fix: move it "
                              f"away, or choose another folder with {option}")
        if not os.access(path, os.W_OK):
            raise ConfigError(f"{path}: cannot write there: the file is read-only; fix: make it writable "
                              f"(chmod u+w {path}), or choose another folder with {option}")
