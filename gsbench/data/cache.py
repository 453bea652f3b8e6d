"""The data cache: generated scenes and decoded images live under ``$GSBENCH_DATA`` or
``~/.cache/gsbench/scenes``."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """``$GSBENCH_DATA`` or ``~/.cache/gsbench/scenes``."""
    return Path(os.environ.get("GSBENCH_DATA") or Path.home() / ".cache" / "gsbench" / "scenes")
