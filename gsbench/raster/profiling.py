"""The rasterizer's phase timers: `gsbench bench` sets `profile` to a dict and reads the seconds each phase
took (projection, sort_bin, raster_fwd, raster_bwd) after a step; None (the default) records nothing."""

from __future__ import annotations

import contextlib

# Phase timings (seconds) of the most recent calls, filled when `profile` is enabled (used by bench.py),
# under ``profile_tag + phase`` (`profile_as`).
profile: dict | None = None
profile_tag = ""


@contextlib.contextmanager
def profile_as(tag: str):
    """Record the timers of the renders made inside (and of their backward) as ``tag + phase`` (PGSR's
    neighbour view: ``"neighbour."``), apart from the step's own render."""
    global profile_tag
    saved, profile_tag = profile_tag, tag
    try:
        yield
    finally:
        profile_tag = saved


def record(key: str, dt: float, tag: str | None = None) -> None:
    if profile is not None:
        key = (profile_tag if tag is None else tag) + key
        profile[key] = profile.get(key, 0.0) + dt
