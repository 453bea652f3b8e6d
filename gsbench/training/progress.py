"""Progress lines for runs whose stderr is not a terminal, where tqdm (``disable=None``) is silent
(docs/training.md §7); `stage` prints a run stage's line, terminal or not. Only the standard library is
imported here.
"""

from __future__ import annotations

import sys
import time

DEFAULT_INTERVAL = 30.0

__all__ = ["DEFAULT_INTERVAL", "ProgressLines", "format_duration", "is_terminal", "stage"]


def is_terminal(stream) -> bool:
    """``stream.isatty()``, False for streams without it or closed ones."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def format_duration(seconds: float) -> str:
    """``41s``, ``9m41s``, ``2h05m`` (rounded to whole seconds; ``?`` when unknown/infinite)."""
    if seconds is None or seconds != seconds or seconds == float("inf") or seconds < 0:
        return "?"
    s = int(round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{(s % 3600) // 60:02d}m"


def write_line(text: str, stream) -> None:
    """``text`` and its newline in one ``write`` call, then a flush: processes that share the stream (sweep
    workers) interleave whole lines, never the pieces of one (``print`` writes the text and the newline
    separately)."""
    stream.write(text + "\n")
    stream.flush()


def stage(message: str, stream=None) -> None:
    """``gsbench: <message>`` on its own line to stderr (or ``stream``), written whole (`write_line`)."""
    write_line(f"gsbench: {message}", sys.stderr if stream is None else stream)


class ProgressLines:
    """Periodic one-line progress reports on a non-terminal stream (docs/training.md §7).

    ``total``: the last step; ``initial``: the step training starts from (a resume); ``interval``:
    seconds between lines (0: a line every update); ``stream``: default ``sys.stderr`` (looked up
    when constructed); ``enabled``: default ``not is_terminal(stream)``; ``unit``: what is counted
    (``step``; a scene's rendering counts ``view``).
    """

    def __init__(self, desc: str, total: int, initial: int = 0, interval: float = DEFAULT_INTERVAL,
                 stream=None, enabled: bool | None = None, clock=time.perf_counter, unit: str = "step"):
        self.desc, self.total, self.initial, self.unit = desc, int(total), int(initial), unit
        self.interval = float(interval)
        self.stream = sys.stderr if stream is None else stream
        self.enabled = (not is_terminal(self.stream)) if enabled is None else bool(enabled)
        self.clock = clock
        self.start = self.last = clock()
        self.step = self.initial
        self.loss: float | None = None
        self.num_gaussians: int | None = None
        self.lines = 0
        self.closed = False

    def rate(self, now: float | None = None) -> float:
        """Units (steps) per second since construction (0 before the first)."""
        elapsed = (self.clock() if now is None else now) - self.start
        done = self.step - self.initial
        return done / elapsed if done > 0 and elapsed > 0 else 0.0

    def line(self, now: float | None = None, final: bool = False) -> str:
        now = self.clock() if now is None else now
        rate = self.rate(now)
        pct = 100.0 * self.step / self.total if self.total > 0 else 100.0
        parts = [f"{self.desc}: {self.unit} {self.step}/{self.total} ({pct:.0f}%)", f"{rate:.3g} it/s"]
        if self.loss is not None:
            parts.append(f"loss {self.loss:.4g}")
        if self.num_gaussians is not None:
            parts.append(f"N {self.num_gaussians}")
        if final:
            parts.append(f"done in {format_duration(now - self.start)}")
        else:
            remaining = max(self.total - self.step, 0)
            parts.append(f"ETA {format_duration(remaining / rate) if rate > 0 else '?'}")
        return " ".join(parts)

    def _emit(self, text: str) -> None:
        write_line(text, self.stream)
        self.lines += 1

    def update(self, step: int, loss: float | None = None, num_gaussians: int | None = None) -> None:
        """Record the state after ``step``; print a line if ``interval`` seconds passed since the last."""
        self.step = int(step)
        if loss is not None:
            self.loss = float(loss)
        if num_gaussians is not None:
            self.num_gaussians = int(num_gaussians)
        if not self.enabled:
            return
        now = self.clock()
        if now - self.last >= self.interval:
            self.last = now
            self._emit(self.line(now))

    def close(self) -> None:
        """Print the final line (once; only when enabled)."""
        if self.closed:
            return
        self.closed = True
        if self.enabled:
            self._emit(self.line(final=True))

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()
