"""Suites: named lists of scenes with default seeds, kept as data in ``configs/suites/<name>.yaml``
(docs/design.md §10.1)::

    description: Spot and the six DTU-like table scenes, three seeds   # optional
    scenes: [synthetic/spot, synthetic/dtu-spot, ...]                   # built-in names or folders
    seeds: [0, 1, 2]                                                    # optional; default [0]

A sweep file names one with ``suite: <name>`` instead of ``scenes``; its runs are then over the
suite's scenes and, unless the sweep gives its own ``seeds``, the suite's seeds. On the command line
``gsbench sweep FILE --suite <name>`` does the same for any sweep file. A suite is several runs, so
``--scene suite:<name>`` (`SUITE_PREFIX`) of ``gsbench run`` / ``config`` is an error that points
to the sweep. Unknown names are a `ConfigError` listing the suites.
"""

from __future__ import annotations

from dataclasses import dataclass

from gsbench.config.files import config_root, load_yaml, suggest
from gsbench.errors import ConfigError

SUITE_PREFIX = "suite:"
SUITE_KEYS = ("description", "scenes", "seeds")


@dataclass(frozen=True)
class Suite:
    """A named list of scenes and the seeds to run each with."""

    name: str
    description: str
    scenes: tuple[str, ...]
    seeds: tuple[int, ...]


def suite_names() -> list[str]:
    """The suites shipped in ``configs/suites/``, sorted."""
    folder = config_root() / "suites"
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def load_suite(name: str) -> Suite:
    """The suite ``name`` (with or without the ``suite:`` prefix), checked: ``scenes`` a non-empty list of
    names, ``seeds`` a non-empty list of integers, no other keys."""
    name = str(name).removeprefix(SUITE_PREFIX).strip()
    available = suite_names()
    if name not in available:
        raise ConfigError(f"unknown suite '{name}'{suggest(name, available)}; available suites: "
                          f"{', '.join(available) or '(none)'} (configs/suites/<name>.yaml)")
    path = config_root() / "suites" / f"{name}.yaml"
    data = load_yaml(path)
    unknown = set(data) - set(SUITE_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown suite keys {sorted(unknown)}; valid: {', '.join(SUITE_KEYS)}")
    scenes, seeds = data.get("scenes"), data.get("seeds", [0])
    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, str) and s for s in scenes):
        raise ConfigError(f"{path}: 'scenes' must be a non-empty list of scene names or folders")
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and not isinstance(s, bool)
                                                          for s in seeds):
        raise ConfigError(f"{path}: 'seeds' must be a non-empty list of integers")
    return Suite(name, str(data.get("description") or ""), tuple(dict.fromkeys(scenes)), tuple(dict.fromkeys(seeds)))


def reject_suite_scene(scene: str) -> None:
    """A ``suite:<name>`` given where one scene is expected: a ConfigError naming the sweep to use instead
    (unknown suite names fail with the list of suites first)."""
    if str(scene).startswith(SUITE_PREFIX):
        suite = load_suite(scene)
        raise ConfigError(f"--scene {scene}: a suite is {len(suite.scenes)} scenes × {len(suite.seeds)} seeds, "
                          f"several runs; run it as a sweep: `gsbench sweep FILE --suite {suite.name}` (any sweep "
                          f"file, e.g. configs/sweeps/all_methods.yaml) or `suite: {suite.name}` in a sweep file")
