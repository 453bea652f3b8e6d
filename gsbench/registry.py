"""Lazy plugin registries: methods, evaluators and loss terms, all three declared alike.

A built-in is declared by its own file ``configs/<kind>/<name>.yaml`` (``plugin: "module:Object"``), so listing
imports nothing heavy; third-party plugins come from the entry-point groups ``gsbench.<kind>``; `Registry.register`
adds an object or a path at run time (tests, notebooks). Unknown names fail with "did you mean".
"""

from __future__ import annotations

import importlib
from importlib import metadata

from gsbench.config.files import declared_plugins, suggest
from gsbench.errors import RegistryError


class Registry:
    """Name -> ``"module:Object"`` string or object; a string's object is imported on first `get`."""

    def __init__(self, kind: str, builtins: dict[str, str], entry_point_group: str):
        self.kind = kind
        self.entry_point_group = entry_point_group
        self._entries: dict[str, object] = dict(builtins)
        self._imported: dict[str, object] = {}
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
        self._imported.pop(name, None)

    def path(self, name: str) -> str:
        """The ``"module:Object"`` string behind ``name`` (for an object registered as such: its qualified name,
        its class's for an instance)."""
        target = self._lookup(name)
        if isinstance(target, str):
            return target
        return f"{target.__module__}:{getattr(target, '__qualname__', type(target).__qualname__)}"

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
        if name not in self._imported:
            module_name, _, attr = target.partition(":")
            try:
                self._imported[name] = getattr(importlib.import_module(module_name), attr)
            except (ImportError, AttributeError) as exc:
                raise RegistryError(f"{self.kind} '{name}' points to '{target}', which cannot be imported: {exc}") from exc
        return self._imported[name]


METHODS = Registry("method", declared_plugins("methods"), "gsbench.methods")
EVALUATORS = Registry("evaluator", declared_plugins("evaluators"), "gsbench.evaluators")
LOSS_TERMS = Registry("loss term", declared_plugins("loss_terms"), "gsbench.loss_terms")  # objects: TermSpec
