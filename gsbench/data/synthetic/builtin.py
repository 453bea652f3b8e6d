"""The built-in synthetic scenes: name -> format and description. Imports nothing heavy.

``format`` is the dataset (``dtu`` or ``tnt``: the evaluation protocol and dataset config); the
layout a scene is written in is its spec's (``synthetic.SPECS``): the ``dtu-*`` scenes are written in
the 2DGS ``dtu-colmap`` layout. Scan numbers of DTU-like scenes are 1001 + the position in this table,
so new scenes are appended at the end.

`gsbench.data.synthetic.make` makes them into the cache (``gsbench scene make``, and a run's step before
loading); this table is what `gsbench list`, the config layering (`dataset_of`) and the loader read without
importing open3d or torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class BuiltinScene:
    """A built-in scene: ``format`` is ``dtu`` or ``tnt`` (the layout it is written in); ``share`` is the
    mean fraction of each image its object covers (`gsbench.data.synthetic.framing.object_share` of
    the scene's own cameras, measured; a test checks it). ``twin_of``: the built-in scene this one is made
    from with one factor changed, ``factor`` that change (``transparent``: the glass scene is its opaque
    twin made of glass); the report's twin tables (`gsbench.report.twins`) measure what it costs each method."""

    name: str
    format: str
    share: float
    description: str
    twin_of: str = ""
    factor: str = ""


FAR = "framed at 12.6% of the image, not 34%"  # the framing of the first suite against DTU's (experiments/suite_vs_papers/README.md)
GLASS = "transparent"  # a glass scene against its opaque twin (issue 41)

BUILTIN_SCENES: dict[str, BuiltinScene] = {
    s.name: s
    for s in (
        BuiltinScene("synthetic/spot", "dtu", 0.126, "Spot the cow, DTU layout, millimetres, 49 cameras on a cap"),
        BuiltinScene("synthetic/spot-tnt", "tnt", 0.046, "Spot, Tanks-and-Temples layout, metres, cameras all around"),
        BuiltinScene("synthetic/thin-plate", "dtu", 0.054, "a thin sheet seen at grazing angles (hard case)"),
        BuiltinScene("synthetic/textureless", "dtu", 0.126, "a uniformly coloured object (hard case)"),
        BuiltinScene("synthetic/spot-far", "dtu", 0.010, "Spot small in the image (hard case)"),
        BuiltinScene("synthetic/spot-km", "tnt", 0.046, "Spot in kilometres (hard case: large coordinates)"),
        BuiltinScene("synthetic/dtu-spot", "dtu", 0.126, "DTU-like: Spot on a wooden table in a room, full images, dtu-colmap layout",
                     twin_of="synthetic/dtu-spot-near", factor=FAR),
        BuiltinScene("synthetic/dtu-stool", "dtu", 0.188, "DTU-like: a stool with thin legs and rungs on the table (thin parts)"),
        BuiltinScene("synthetic/dtu-bowl", "dtu", 0.220, "DTU-like: a deep glazed bowl with a loop handle on the table (concavity)"),
        BuiltinScene("synthetic/dtu-blocks", "dtu", 0.170, "DTU-like: painted stepped prisms with a star level on the table (sharp edges)"),
        BuiltinScene("synthetic/dtu-fine", "dtu", 0.180, "DTU-like: a vase with a 2 mm hatch pattern on the table (fine texture)"),
        BuiltinScene("synthetic/dtu-plain", "dtu", 0.257, "DTU-like: a smooth uniformly coloured pebble stack on the table (low texture)"),
        BuiltinScene("synthetic/tnt-spot", "tnt", 0.046, "TnT-like: Spot on cobbles among crates and barrels in a courtyard"),
        BuiltinScene("synthetic/tnt-yard", "tnt", 0.248, "TnT-like: building blocks in a yard, cameras around them, 20 m across"),
        BuiltinScene("synthetic/tnt-sky", "tnt", 0.046, "TnT-like: Spot on a meadow under a sky/mountain dome 100x its size"),
        BuiltinScene("synthetic/dtu-bunny", "dtu", 0.340, "DTU-like, scanned: the Stanford bunny (pymeshlab's copy) on the table, framed as DTU"),
        BuiltinScene("synthetic/dtu-face", "dtu", 0.340, "DTU-like, scanned: a range scan of a face (pymeshlab's face000: an open sheet with holes) lying face up, framed as DTU"),
        BuiltinScene("synthetic/dtu-spot-near", "dtu", 0.340, "DTU-like: dtu-spot framed as DTU (the object fills 34% of the image)"),
        BuiltinScene("synthetic/dtu-bunny-far", "dtu", 0.126, "experiment twin: dtu-bunny framed like dtu-spot (12.6% of the image)",
                     twin_of="synthetic/dtu-bunny", factor=FAR),
        BuiltinScene("synthetic/dtu-bunny-smooth", "dtu", 0.340, "experiment twin: dtu-bunny with its fine relief smoothed off (Taubin, 200 iterations)",
                     twin_of="synthetic/dtu-bunny", factor="fine relief smoothed off"),
        BuiltinScene("synthetic/dtu-glass-orb", "dtu", 0.340, "glass: a solid clear ball (index 1.5) on the table, framed as DTU (refraction, reflection)",
                     twin_of="synthetic/dtu-glass-orb-opaque", factor=GLASS),
        BuiltinScene("synthetic/dtu-glass-orb-opaque", "dtu", 0.340, "opaque twin of dtu-glass-orb: the same ball, glazed"),
        BuiltinScene("synthetic/dtu-glass-wine", "dtu", 0.340, "glass: a wine glass (index 1.5; 2% walls, solid stem) on the table, framed as DTU",
                     twin_of="synthetic/dtu-glass-wine-opaque", factor=GLASS),
        BuiltinScene("synthetic/dtu-glass-wine-opaque", "dtu", 0.340, "opaque twin of dtu-glass-wine: the same wine glass, glazed"),
        BuiltinScene("synthetic/dtu-glass-bottle", "dtu", 0.340, "glass: a thin-walled open bottle (index 1.5) on the table, framed as DTU",
                     twin_of="synthetic/dtu-glass-bottle-opaque", factor=GLASS),
        BuiltinScene("synthetic/dtu-glass-bottle-opaque", "dtu", 0.340, "opaque twin of dtu-glass-bottle: the same bottle, glazed"),
        BuiltinScene("synthetic/dtu-rig-bunny", "dtu", 0.340, "dtu-bunny in DTU's own rig (49 cameras, fx 1.81 W, IDR's frame of scan 65), framed as DTU by its size"),
        BuiltinScene("synthetic/dtu-rig-face", "dtu", 0.340, "dtu-face in DTU's own rig, framed as DTU by its size"),
        BuiltinScene("synthetic/dtu-rig-spot", "dtu", 0.340, "dtu-spot-near in DTU's own rig, framed as DTU by its size"),
        BuiltinScene("synthetic/tnt-rig-spot", "tnt", 0.266, "tnt-spot with Barn's lens and floor plan (TnT's camera-to-object distances)"),
        BuiltinScene("synthetic/tnt-rig-yard", "tnt", 0.409, "tnt-yard with Barn's lens and floor plan"),
        BuiltinScene("synthetic/tnt-rig-sky", "tnt", 0.266, "tnt-sky with Barn's lens and floor plan"),
    )
}


def builtin_name(path_or_name) -> str | None:
    """``path_or_name`` when it is a built-in name (a string ``synthetic/<name>`` that is not an existing
    folder), else None (a scene folder). The name may be unknown: the loader and the maker refuse it."""
    if isinstance(path_or_name, str) and path_or_name.startswith("synthetic/") and not Path(path_or_name).is_dir():
        return path_or_name
    return None
