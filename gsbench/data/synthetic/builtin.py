"""The built-in synthetic scenes: name -> format and description. Imports nothing heavy.

``format`` is the dataset (``dtu`` or ``tnt``: the evaluation protocol and dataset config); the
layout a scene is written in is its spec's (``synthetic.SPECS``): the ``dtu-*`` scenes are written in
the 2DGS ``dtu-colmap`` layout. Scan numbers of DTU-like scenes are 1001 + the position in this table,
so new scenes are appended at the end.

The generator (`gsbench.data.synthetic.generator`) makes them on first use; this table is what `gsbench list`
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
        BuiltinScene("synthetic/dtu-spot", "dtu", "DTU-like: Spot on a wooden table in a room, full images, dtu-colmap layout"),
        BuiltinScene("synthetic/dtu-stool", "dtu", "DTU-like: a stool with thin legs and rungs on the table (thin parts)"),
        BuiltinScene("synthetic/dtu-bowl", "dtu", "DTU-like: a deep glazed bowl with a loop handle on the table (concavity)"),
        BuiltinScene("synthetic/dtu-blocks", "dtu", "DTU-like: painted stepped prisms with a star level on the table (sharp edges)"),
        BuiltinScene("synthetic/dtu-fine", "dtu", "DTU-like: a vase with a 2 mm hatch pattern on the table (fine texture)"),
        BuiltinScene("synthetic/dtu-plain", "dtu", "DTU-like: a smooth uniformly coloured pebble stack on the table (low texture)"),
        BuiltinScene("synthetic/tnt-spot", "tnt", "TnT-like: Spot on cobbles among crates and barrels in a courtyard"),
        BuiltinScene("synthetic/tnt-yard", "tnt", "TnT-like: building blocks in a yard, cameras around them, 20 m across"),
        BuiltinScene("synthetic/tnt-sky", "tnt", "TnT-like: Spot on a meadow under a sky/mountain dome 100x its size"),
    )
}
