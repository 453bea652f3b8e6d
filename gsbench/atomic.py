"""Atomic file writes: nothing gsbench writes is ever seen half-written, even after a crash.

`atomic_path` yields a temporary path in the target's folder; when the block finishes the file is moved
into place with ``os.replace`` (atomic on POSIX), and when it raises the temporary file is removed and the
target is left as it was.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from gsbench.errors import ConfigError


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
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def check_writable(folder, option: str) -> Path:
    """A ConfigError naming ``folder`` and ``option`` (the setting that chose it) unless files can be written
    there: its nearest existing ancestor must be a writable folder. Checked before any work whose results go
    there; nothing is created."""
    folder = Path(folder)
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        problem = f"{existing} is a file, not a folder"
    elif not os.access(existing, os.W_OK | os.X_OK):
        problem = f"{existing} is not writable (read-only folder or file system)"
    else:
        return folder
    raise ConfigError(f"{folder}: cannot write there: {problem}; fix: choose another folder with {option} or make "
                      "it writable")
