"""The quantities of a scene's frame that a method feels, computed alike for a real capture and a
synthetic one (docs/scenes.md §4).

A scene's *object region* is a centre and a radius in the GT frame:

- DTU: IDR's normalisation sphere (``scale_mat``): centre its centre, radius its scale (the object lies
  inside it). The training frame is the sphere's (radius 1).
- Tanks and Temples: the crop volume, horizontally (its prism axis is the GT z): centre the middle of the
  crop polygon's bounding box, radius the largest distance of a polygon vertex from it; distances are
  measured in the horizontal plane, because the crop's z range bounds the scan, not the object (Barn's runs
  11 m below the ground). The training frame is the COLMAP frame (the papers'; ``data.tnt_frame: colmap``,
  `gsbench.data.tnt`): Barn's is the GT frame's metres / 4.139 (``Barn_trans.txt``), a synthetic scene's
  its GT frame times its ``colmap_scale``. A scene loaded in the older ``extent`` frame is measured in it.

From the cameras (in the GT frame) and that region:

- ``fx_over_width``: the focal length over the image width (median over views);
- ``camera_distance``: the median distance of a camera centre from the region's centre, in region radii;
- ``depth_focal``: the median camera-to-centre distance in training-frame units times fx/W: the object's
  depth × focal per pixel of image width (× W gives pixels); 2DGS's depth distortion weighs a one-pixel
  depth spread by (near / (depth · fx))²;
- ``scene_radius``: 3DGS's ``cameras_extent`` (1.1 × the largest distance of a camera centre from their
  mean), the length its densification and learning rates scale with, in region radii;
- ``near_over_depth``: the near plane 0.2 of 2DGS/GOF's rasterizers (training units, as their code has it)
  over the median camera-to-centre distance in that frame.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gsbench.data.camera import Camera, Scene
from gsbench.data.filecheck.arrays import read_matrix4_text
from gsbench.data.similarity import decompose, transform_camera
from gsbench.data.tnt import gt_files

NEAR_PLANE = 0.2  # training-frame units: the near plane of the 2DGS / GOF rasterizers (docs/methods/2dgs.md)


@dataclass(frozen=True)
class Region:
    """The object region: ``centre`` (GT frame), ``radius`` (GT units); ``horizontal``: distances in the
    xy plane (Tanks and Temples), else in 3D (DTU); ``training_scale``: GT units per training-frame unit."""

    centre: np.ndarray
    radius: float
    horizontal: bool
    training_scale: float


@dataclass(frozen=True)
class FrameQuantities:
    """The module docstring's five quantities."""

    fx_over_width: float
    camera_distance: float
    depth_focal: float
    scene_radius: float
    near_over_depth: float

    def as_dict(self) -> dict:
        return {k: round(v, 4) for k, v in asdict(self).items()}


def cameras_extent(centres: np.ndarray) -> float:
    """3DGS ``getNerfppNorm``'s radius: 1.1 × the largest distance of a camera centre from their mean."""
    centres = np.asarray(centres, dtype=np.float64)
    return 1.1 * float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))


def crop_region(polygon_xy: np.ndarray, z_range: tuple[float, float], training_scale: float) -> Region:
    """The Tanks-and-Temples object region of a crop polygon (module docstring)."""
    polygon_xy = np.asarray(polygon_xy, dtype=np.float64)[:, :2]
    centre_xy = 0.5 * (polygon_xy.min(axis=0) + polygon_xy.max(axis=0))
    radius = float(np.max(np.linalg.norm(polygon_xy - centre_xy, axis=1)))
    return Region(np.array([*centre_xy, 0.5 * (z_range[0] + z_range[1])]), radius, True, training_scale)


def crop_file_region(path: Path, training_scale: float) -> Region:
    """`crop_region` of a TnT crop volume file (open3d ``SelectionPolygonVolume`` JSON)."""
    crop = json.loads(Path(path).read_text())
    return crop_region(np.asarray(crop["bounding_polygon"]), (crop["axis_min"], crop["axis_max"]), training_scale)


def frame_quantities(cameras: list[Camera], region: Region) -> FrameQuantities:
    """The quantities of ``cameras`` (GT frame) about ``region`` (module docstring)."""
    centres = np.array([c.center for c in cameras])
    offsets = centres - region.centre
    if region.horizontal:
        offsets = offsets[:, :2]
    distance = float(np.median(np.linalg.norm(offsets, axis=1)))
    fx_w = float(np.median([c.fx / c.width for c in cameras]))
    depth = distance / region.training_scale
    return FrameQuantities(fx_over_width=fx_w, camera_distance=distance / region.radius,
                           depth_focal=depth * fx_w, scene_radius=cameras_extent(centres) / region.radius,
                           near_over_depth=NEAR_PLANE / depth)


def scene_frame(scene: Scene) -> dict:
    """A loaded scene's frame quantities (`FrameQuantities.as_dict`) and how they were measured. A DTU scene:
    about its normalisation sphere (the training frame's unit sphere). A TnT scene: about its crop volume,
    which is ground truth (read for this report only, never by a method); without it, ``{"missing": why}``."""
    if scene.fmt.startswith("dtu"):
        region = Region(np.zeros(3), 1.0, False, 1.0)
        return {"region": "the normalisation sphere", **frame_quantities(scene.cameras, region).as_dict()}
    if scene.gt is None or scene.gt.kind != "tnt":
        return {"missing": f"the object region of a TnT scene is its crop volume, in its ground truth: {scene.gt_missing}"}
    files = gt_files(scene.gt.root, scene.gt.name)
    fix = "restore the scene's TnT ground truth files"
    training_to_gt = read_matrix4_text(files["_trans.txt"], fix) @ scene.normalisation.to_dataset
    region = crop_file_region(files[".json"], decompose(training_to_gt)[0])
    cameras = [transform_camera(c, training_to_gt) for c in scene.cameras]
    return {"region": "the crop volume, horizontally", **frame_quantities(cameras, region).as_dict()}
