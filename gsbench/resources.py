"""The machine resources a run uses: its threads and its peak memory, and the memory there is.

`set_threads` is the one place the thread count is set: ``OMP_NUM_THREADS`` (read by torch's and the
native libraries' OpenMP runtimes when they load) and torch's intra-op threads when torch is loaded, which
every native call passes on (`gsbench.native.build.omp_threads`). ``OMP_WAIT_POLICY=PASSIVE`` is set when
gsbench is imported (`gsbench/__init__.py`). `keep_freed_memory` is the allocator's policy for training.
"""

from __future__ import annotations

import ctypes
import math
import os
import resource
import sys

# glibc's mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
TRIM_THRESHOLD_BYTES = 2**31 - 1  # mallopt takes an int: free memory at the heap's top beyond 2 GiB is returned


def set_threads(threads: int) -> int:
    """Use ``threads`` threads (0 = every core) from now on; returns the number set."""
    n = threads if threads > 0 else (os.cpu_count() or 1)
    os.environ["OMP_NUM_THREADS"] = str(n)
    torch = sys.modules.get("torch")  # a process that has not loaded torch reads OMP_NUM_THREADS when it does
    if torch is not None:
        torch.set_num_threads(n)
    return n


def keep_freed_memory() -> bool:
    """Make glibc's malloc keep the memory a process frees for its next allocations: no block is given its own
    ``mmap`` (``M_MMAP_MAX`` = 0) and the heap's free top is returned to the system only beyond 2 GiB
    (``M_TRIM_THRESHOLD``). Returns whether the policy is in force (False where the C library is not glibc).

    By default glibc gives each large block (above a threshold that grows to at most 32 MiB) its own ``mmap`` and
    unmaps it when freed, so every training step faults in and zeroes its large tensors (images, per-pixel buffers,
    the Gaussians' gradients) afresh: at the papers' size that cost 9% of a step
    (experiments/papers_size/README.md, "Memory the allocator gave back"). Kept memory is reused by the next step, so
    the peak resident size does not grow; the executors give every run its own process (`gsbench.runs.executors`),
    so nothing is kept from one run to the next.
    """
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018  (glibc only: other C libraries have other mallopt parameters)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))


def peak_rss_bytes() -> int:
    """Peak resident set size of this process and its waited-for children, in bytes (``ru_maxrss``, which never
    decreases: KiB on Linux, bytes on macOS)."""
    peak = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    return int(peak if sys.platform == "darwin" else peak * 1024)


def available_memory_bytes() -> int | None:
    """Memory the system can give a new process now (``MemAvailable`` of ``/proc/meminfo``), or None where
    that is not known (not Linux)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def gib(n_bytes: float) -> str:
    """``12.3 GiB``."""
    return f"{n_bytes / 2**30:.1f} GiB"


def memory_size(n_bytes: float) -> str:
    """``12.3 GiB``, or below a GiB ``312 MiB`` (rounded up: ``1 MiB`` at least)."""
    return gib(n_bytes) if n_bytes >= 2**30 else f"{max(1, math.ceil(n_bytes / 2**20))} MiB"
