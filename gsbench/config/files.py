"""Where the shipped YAML lives and how any YAML file is read: the ``configs/`` folder, a checked YAML
mapping, the "did you mean" hint every unknown-name error carries, and what the files declare (the built-in
plugins, a method's paper numbers and claims)."""

from __future__ import annotations

import difflib
from importlib import resources
from pathlib import Path

import yaml

from gsbench.errors import ConfigError

CONFIG_ROOT = Path(__file__).resolve().parents[2] / "configs"
PLUGIN_KEY = "plugin"  # in configs/<kind>/<name>.yaml: "module:Object" of a built-in method, evaluator or loss term
REPORTED_KEY = "reported"  # in configs/methods/<method>.yaml: the paper's numbers on the real datasets
CLAIMS_KEY = "claims"  # in configs/methods/<method>.yaml: the papers' claims it holds (gsbench.report.claims)
PAPER_BENCHMARK_KEY = "paper_benchmark"  # in configs/methods/<method>.yaml: its place among the papers' methods
DECLARATION_KEYS = (PLUGIN_KEY, REPORTED_KEY, CLAIMS_KEY, PAPER_BENCHMARK_KEY)  # what a method file declares besides settings


def config_root() -> Path:
    """The configs folder: the repository's ``configs/`` or, when installed, ``gsbench.configs``."""
    if CONFIG_ROOT.is_dir():
        return CONFIG_ROOT
    return Path(str(resources.files("gsbench.configs")))


def suggest(name: str, choices) -> str:
    """' (did you mean 'x'?)' for the closest choice, or an empty string."""
    close = difflib.get_close_matches(str(name), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def load_yaml(path: Path) -> dict:
    """Read a YAML mapping; a missing file or a non-mapping is a ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist; check the path")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of keys, found {type(data).__name__}")
    return data


def method_declaration(method: str, key: str):
    """``key`` of ``configs/methods/<method>.yaml`` (not inherited through ``extends``: a variant is another method);
    None for a method without that file or key."""
    path = config_root() / "methods" / f"{method}.yaml"
    return load_yaml(path).get(key) if path.is_file() else None


def reported_numbers(method: str) -> dict:
    """The paper's numbers ``{dataset: {metric, mean, source, scenes?}}`` of ``method`` (``reported:``), or ``{}``."""
    return method_declaration(method, REPORTED_KEY) or {}


def declared_plugins(kind: str) -> dict[str, str]:
    """Name -> ``"module:Object"`` of every ``configs/<kind>/<name>.yaml`` that names its object (``plugin:``):
    ``kind`` is ``methods``, ``evaluators`` or ``loss_terms``; each built-in is declared by its own file."""
    declared = {}
    for path in sorted((config_root() / kind).glob("*.yaml")):
        if "." not in path.stem:  # <method>.<dataset>.yaml layers declare nothing
            plugin = load_yaml(path).get(PLUGIN_KEY)
            if plugin:
                declared[path.stem] = str(plugin)
    return declared


def paper_methods() -> tuple[str, ...]:
    """The papers' methods (``paper_benchmark: <place>`` in their file), in that order: the methods
    `gsbench.bench.train` times at the papers' size; variants (ibgs-2dgs) have none."""
    places = {}
    for method in declared_plugins("methods"):
        place = method_declaration(method, PAPER_BENCHMARK_KEY)
        if place is None:
            continue
        if isinstance(place, bool) or not isinstance(place, int) or place in places:
            raise ConfigError(f"configs/methods/{method}.yaml: {PAPER_BENCHMARK_KEY} must be a place (1, 2, ...) no other "
                              f"method has, got {place!r}; taken: {sorted(places)}")
        places[place] = method
    return tuple(places[place] for place in sorted(places))
