"""Lazy plugin registries for methods and evaluators.

Built-ins are ``"module:Object"`` strings, so listing imports nothing heavy: each built-in method names its
class in its own file, ``configs/methods/<method>.yaml`` (``plugin:``), the evaluators are listed here; third-party plugins come
from the entry-point groups ``gsbench.methods`` and ``gsbench.evaluators``; `Registry.register` adds
an object or a path at run time (tests, notebooks). Unknown names fail with "did you mean".
"""

from __future__ import annotations

import importlib
from importlib import metadata

from gsbench.config.files import declared_methods, suggest
from gsbench.errors import RegistryError


class Registry:
    """Name -> ``"module:Object"`` string or object; objects are imported on first `get`."""

    def __init__(self, kind: str, builtins: dict[str, str], entry_point_group: str):
        self.kind = kind
        self.entry_point_group = entry_point_group
        self._entries: dict[str, object] = dict(builtins)
        self._entry_points_loaded = False

    def _load_entry_points(self) -> None:
        if self._entry_points_loaded:
            return
        self._entry_points_loaded = True
        for ep in metadata.entry_points(group=self.entry_point_group):
            self._entries.setdefault(ep.name, ep.value)

    def names(self) -> list[str]:
        """Every registered name, sorted; imports no plugin."""
        self._load_entry_points()
        return sorted(self._entries)

    def register(self, name: str, target) -> None:
        """Add (or replace) ``name`` -> an object or a ``"module:Object"`` string."""
        self._entries[name] = target

    def path(self, name: str) -> str:
        """The ``"module:Object"`` string (or the object's qualified name) behind ``name``."""
        target = self._lookup(name)
        if isinstance(target, str):
            return target
        return f"{target.__module__}:{target.__qualname__}"

    def _lookup(self, name: str):
        self._load_entry_points()
        if name not in self._entries:
            raise RegistryError(
                f"unknown {self.kind} '{name}'{suggest(name, self._entries)}; "
                f"known: {', '.join(sorted(self._entries)) or '(none)'}"
            )
        return self._entries[name]

    def get(self, name: str):
        """The registered object, importing its module on first use."""
        target = self._lookup(name)
        if not isinstance(target, str):
            return target
        module_name, _, attr = target.partition(":")
        try:
            obj = getattr(importlib.import_module(module_name), attr)
        except (ImportError, AttributeError) as exc:
            raise RegistryError(f"{self.kind} '{name}' points to '{target}', which cannot be imported: {exc}") from exc
        self._entries[name] = obj
        return obj


METHODS = Registry("method", declared_methods(), "gsbench.methods")  # configs/methods/<method>.yaml

EVALUATORS = Registry(
    "evaluator",
    {
        "dtu_chamfer": "gsbench.evaluators.dtu_chamfer:DTUChamfer",
        "tnt_f1": "gsbench.evaluators.tnt_f1:TnTF1",
        "normal_similarity": "gsbench.evaluators.normal_similarity:NormalSimilarity",
        "image": "gsbench.evaluators.image:ImageMetrics",
        "surface_offset": "gsbench.evaluators.surface_offset:SurfaceOffset",
        "silhouette": "gsbench.evaluators.silhouette:Silhouette",
        "mesh_stats": "gsbench.evaluators.mesh_stats:MeshStats",
    },
    "gsbench.evaluators",
)
