"""The data cache: generated scenes and decoded images live under ``$GSBENCH_DATA`` or
``~/.cache/gsbench/scenes``."""

from __future__ import annotations

from pathlib import Path

from gsbench.switches import DATA


def cache_dir() -> Path:
    """``$GSBENCH_DATA`` or ``~/.cache/gsbench/scenes``."""
    return Path(DATA.value()).expanduser()


def scene_dir(name: str, choices=()) -> Path:
    """The cache folder of generated scene ``name`` (``synthetic/<name>`` or ``mesh/<file stem>``):
    ``<cache>/synthetic/<name>``, plus ``-<choice>`` for each choice it was made with other than the default."""
    kind, short = name.split("/", 1)
    return cache_dir() / kind / "-".join([short, *choices])
