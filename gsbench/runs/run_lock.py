"""One process at a time in a run folder: an advisory lock on ``<run>/.lock`` (``fcntl.flock``).

The lock file holds the holder's pid, host and start time, so a second ``gsbench run`` of the same
configuration says who works there and exits (`RunLockedError`) instead of training the same run twice.
The operating system releases the lock when the holder exits, however it exits (a crash, a kill), so a
stale lock file never blocks a resume.
"""

from __future__ import annotations

import fcntl
import os
import socket
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

from gsbench.errors import GsbenchError
from gsbench.run_folder import RunFolder


class RunLockedError(GsbenchError):
    """Another process holds the run folder's lock."""


@contextmanager
def run_lock(folder: Path):
    """Hold ``folder``'s lock for the ``with`` block (the folder is created if needed); RunLockedError,
    naming the holder, when another process has it."""
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(RunFolder(folder).lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "another process"
            raise RunLockedError(f"run folder {folder} is in use by {holder}; wait for that run to finish or stop it "
                                 "(a stopped run resumes from its last checkpoint)") from None
        since = datetime.now(timezone.utc).isoformat(timespec="seconds")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since {since}\n".encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the flock
