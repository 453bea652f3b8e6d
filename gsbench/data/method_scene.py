"""The scene a method is given: a copy of the run's scene with its ground truth hidden (docs/design.md §3.1).

A method trains and meshes from what a capture offers: images, cameras, masks, SfM points, the normalisation.
The ground truth is the evaluators' alone. `scene_for_method` replaces the two ways to it, ``gt`` (the
`GroundTruth` handle: its folder, the GT depth and normal maps) and ``root`` (the scene's folder, which holds the
GT files of TnT and synthetic layouts), by `HiddenGroundTruth`, so a method that reads either stops with
`GroundTruthRead` naming it, instead of silently scoring itself with what the papers' methods never had.
"""

from __future__ import annotations

import dataclasses

from gsbench.data.camera import Scene
from gsbench.errors import GroundTruthRead

HIDDEN_FIELDS = ("gt", "root")  # the Scene fields a method is not given


class HiddenGroundTruth:
    """Stands for the Scene field ``field`` in the scene given to ``method``: reading an attribute of it, its
    truth value, its path (``os.fspath``) or a path below it (``/``) raises `GroundTruthRead`."""

    __slots__ = ("method", "field")

    def __init__(self, method: str, field: str):
        self.method, self.field = method, field

    def _refuse(self, what: str):
        raise GroundTruthRead(f"method '{self.method}' read scene.{self.field}{what}, which is hidden from methods: a "
                              "method trains and meshes from the capture alone (images, cameras, masks, SfM points, "
                              "the normalisation), the ground truth is the evaluators'; fix: derive it from those "
                              "(e.g. a bound from scene.points or the cameras) or leave it to an evaluator")

    def __getattr__(self, name: str):
        if name.startswith("__") or name in self.__slots__:  # protocols (copy, pickle); a slot not yet set
            raise AttributeError(name)
        self._refuse(f".{name}")

    def __bool__(self):
        self._refuse(" (its truth value)")

    def __fspath__(self):
        self._refuse(" (its path)")

    def __truediv__(self, other):
        self._refuse(f" / {other!r}")

    def __repr__(self) -> str:
        return f"<scene.{self.field} hidden from method '{self.method}'>"


def scene_for_method(scene: Scene, method: str) -> Scene:
    """A shallow copy of ``scene`` (images, cameras, masks and points shared) with `HIDDEN_FIELDS` hidden from the
    method named ``method`` (module docstring)."""
    return dataclasses.replace(scene, **{field: HiddenGroundTruth(method, field) for field in HIDDEN_FIELDS})
