"""What every file check shares: the one-line damage error, memory-mapped reading and a vectorised
record test."""

from __future__ import annotations

import mmap
from pathlib import Path

import numpy as np

from gsbench.errors import DataError, one_line


def damaged(path, what: str, fix: str) -> DataError:
    """``<path> is damaged: <what>; fix: <fix>`` (one line)."""
    return DataError(f"{path} is damaged: {one_line(what)}; fix: {fix}")


class PastEnd(Exception):
    def __init__(self, record: int, detail: str = "runs past the end of the file"):
        super().__init__(record)
        self.record, self.detail = record, detail


def mapped(path: Path):
    """(buffer, size): a read-only mmap of the file (bytes for an empty file)."""
    size = path.stat().st_size
    if size == 0:
        return b"", 0
    with open(path, "rb") as f:
        return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ), size


def all_equal(buf, offset: int, count: int, record: int, at: int, dtype: str, value: int) -> bool:
    """Whether the field ``dtype`` at byte ``at`` of each of ``count`` records of ``record`` bytes from
    ``offset`` equals ``value`` (a strided view, released before returning so the mmap can close)."""
    view = np.ndarray((count,), dtype=np.dtype({"names": ["v"], "formats": [dtype], "offsets": [at], "itemsize": record}),
                      buffer=buf, offset=offset)["v"]
    return bool(np.all(view == value))


def close_buffer(buf) -> None:
    if isinstance(buf, mmap.mmap):
        try:
            buf.close()
        except BufferError:  # a view still referenced from a traceback: the garbage collector closes it
            pass
