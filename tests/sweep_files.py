"""The repository's sweep files: the shipped ones (configs/sweeps/: the boards and the ablation grids a user runs)
and the experiments' (experiments/<name>/, not installed), and a sweep's file by its name."""

from __future__ import annotations

from pathlib import Path

from gsbench.config.files import config_root

REPO = Path(__file__).resolve().parent.parent
SHIPPED = sorted((config_root() / "sweeps").glob("*.yaml"))
EXPERIMENTS = sorted((REPO / "experiments").glob("*/*.yaml"))
ALL = SHIPPED + EXPERIMENTS


def sweep_file(name: str) -> Path:
    """The one sweep file whose stem is ``name`` (every sweep's ``name:`` key is its stem: tests/test_sweep.py)."""
    found = [path for path in ALL if path.stem == name]
    assert len(found) == 1, f"sweep {name!r}: {found or 'no file in configs/sweeps/ or experiments/*/'}"
    return found[0]
