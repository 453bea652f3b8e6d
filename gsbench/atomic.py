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
