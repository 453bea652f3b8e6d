"""The data cache: generated scenes and decoded images live under ``$GSBENCH_DATA`` or
``~/.cache/gsbench/scenes``."""

from __future__ import annotations

from pathlib import Path

from gsbench.switches import DATA


def cache_dir() -> Path:
    """``$GSBENCH_DATA`` or ``~/.cache/gsbench/scenes``."""
    return Path(DATA.value()).expanduser()
