"""Run a call in a forked child with a time and memory bound, so a reader that hangs or allocates
without bound fails the test instead of hanging the suite (a C++ reader stuck in a loop cannot be
interrupted by a signal handler in the same process)."""

from __future__ import annotations

import multiprocessing as mp
import resource
from dataclasses import dataclass


@dataclass
class Outcome:
    """What the call did: ``kind`` is ``ok``, ``error`` or ``timeout``."""

    kind: str
    error_type: str = ""
    gsbench: bool = False  # the exception is a GsbenchError
    message: str = ""
    seconds: float = 0.0


def _address_space() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


def _child(conn, fn, args, kwargs, extra_memory):
    try:
        limit = _address_space() + extra_memory
        resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
        result = fn(*args, **kwargs)
        conn.send(("ok", "", False, repr(result)[:300]))
    except BaseException as exc:  # noqa: BLE001  everything goes back to the parent
        from gsbench.errors import GsbenchError

        conn.send(("error", type(exc).__name__, isinstance(exc, GsbenchError), str(exc)))
    finally:
        conn.close()


def bounded(fn, *args, timeout: float = 10.0, extra_memory: int = 2 << 30, **kwargs) -> Outcome:
    """``fn(*args, **kwargs)`` in a forked child with ``timeout`` seconds and ``extra_memory`` bytes of
    address space beyond what it starts with; the child is killed on timeout."""
    import time

    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child, fn, args, kwargs, extra_memory), daemon=True)
    start = time.perf_counter()
    proc.start()
    child.close()
    try:
        if not parent.poll(timeout):
            return Outcome("timeout", seconds=time.perf_counter() - start)
        try:
            kind, error_type, gsbench, message = parent.recv()
        except EOFError:  # the child died without a word (abort, segfault, OOM kill)
            proc.join(5)
            return Outcome("error", f"child exit code {proc.exitcode}", False, "", time.perf_counter() - start)
        return Outcome(kind, error_type, gsbench, message, time.perf_counter() - start)
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join(5)
        parent.close()
