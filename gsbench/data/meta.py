"""The ``gsbench_scene.json`` meta file written into every generated scene and read by the loaders.

Keys: ``name`` (also the TnT GT file prefix), ``format`` (dtu | dtu-colmap | tnt), ``seed``,
``resolution`` [W, H], ``units`` (of the GT frame), ``scan`` (DTU) or ``tau`` (TnT, GT units),
``generator_version``, ``description``; ``builtin`` (the built-in name) or ``mesh`` (a scene of a mesh
file: its path, SHA-256, sizes, colours, albedo, axes and the repairs made); ``framing`` when the
cameras were placed for an object share (the share asked for, the distance in bounding radii, the share
measured). Real datasets have no meta file; the loaders then fall back to
the folder name (``scan24`` -> scan 24; TnT name -> the official tau table).
"""

from __future__ import annotations

import json
from pathlib import Path

from gsbench.errors import DataError

META_FILE = "gsbench_scene.json"


def read_meta(root: Path) -> dict:
    """The meta dict of a scene folder, or ``{}`` when there is none."""
    path = Path(root) / META_FILE
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: not a readable JSON meta file ({exc}); fix: delete it and re-generate the scene") from exc


def write_meta(root: Path, meta: dict) -> None:
    """Write the meta file (the caller's folder is moved into place atomically afterwards)."""
    (Path(root) / META_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


def optional_dir(path: Path) -> Path | None:
    """``path`` if it is a folder (e.g. the optional ``gt_depth/`` and ``gt_normal/`` maps), else None."""
    return path if path.is_dir() else None
