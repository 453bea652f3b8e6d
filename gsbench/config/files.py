"""Where the shipped YAML lives and how any YAML file is read: the ``configs/`` folder, a checked YAML
mapping, and the "did you mean" hint every unknown-name error carries."""

from __future__ import annotations

import difflib
from importlib import resources
from pathlib import Path

import yaml

from gsbench.errors import ConfigError

CONFIG_ROOT = Path(__file__).resolve().parents[2] / "configs"
PLUGIN_KEY = "plugin"  # in configs/methods/<method>.yaml: "module:Class" of the method
REPORTED_KEY = "reported"  # in configs/methods/<method>.yaml: the paper's numbers on the real datasets
DECLARATION_KEYS = (PLUGIN_KEY, REPORTED_KEY)  # what a method file declares besides settings


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


def reported_numbers(method: str) -> dict:
    """The paper's numbers ``{dataset: {metric, mean, source, scenes?}}`` declared in
    ``configs/methods/<method>.yaml`` (``reported:``; not inherited through ``extends``, a variant is another
    method); ``{}`` for a method without that file or key."""
    path = config_root() / "methods" / f"{method}.yaml"
    return (load_yaml(path).get(REPORTED_KEY) or {}) if path.is_file() else {}


def declared_methods() -> dict[str, str]:
    """Method name -> ``"module:Class"`` of every method file ``configs/methods/<method>.yaml`` that names its
    class (``plugin:``); a method is declared by its own file, not in a central table."""
    folder = config_root() / "methods"
    declared = {}
    for path in sorted(folder.glob("*.yaml")):
        if "." not in path.stem:  # <method>.<dataset>.yaml layers declare nothing
            plugin = load_yaml(path).get(PLUGIN_KEY)
            if plugin:
                declared[path.stem] = str(plugin)
    return declared
