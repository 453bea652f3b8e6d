"""The built-in synthetic scenes: name -> format and description. Imports nothing heavy.

The generator (`gsbench.data.synthetic`) makes them on first use; this table is what `gsbench list`
and the config layering (`dataset_of`) read without importing open3d or torch.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BuiltinScene:
    """A built-in scene: ``format`` is ``dtu`` or ``tnt`` (the layout it is written in)."""

    name: str
    format: str
    description: str


BUILTIN_SCENES: dict[str, BuiltinScene] = {
    s.name: s
    for s in (
        BuiltinScene("synthetic/spot", "dtu", "Spot the cow, DTU layout, millimetres, 49 cameras on a cap"),
        BuiltinScene("synthetic/spot-tnt", "tnt", "Spot, Tanks-and-Temples layout, metres, cameras all around"),
        BuiltinScene("synthetic/thin-plate", "dtu", "a thin sheet seen at grazing angles (hard case)"),
        BuiltinScene("synthetic/textureless", "dtu", "a uniformly coloured object (hard case)"),
        BuiltinScene("synthetic/spot-far", "dtu", "Spot small in the image (hard case)"),
        BuiltinScene("synthetic/spot-km", "tnt", "Spot in kilometres (hard case: large coordinates)"),
    )
}
