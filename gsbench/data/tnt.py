"""Tanks-and-Temples scenes: COLMAP ``sparse/0`` + ``images/`` with the official GT files beside them.

Layout (one folder per scene; GT files live in the scene folder itself, prefixed by the scene name)::

    {scene}/images/*                      undistorted views; sorted by name = trajectory order
    {scene}/sparse/0/                     COLMAP model (PINHOLE / SIMPLE_PINHOLE / zero distortion)
    {scene}/{scene}.ply                   GT points (GT frame, metres)
    {scene}/{scene}.json                  crop volume (open3d SelectionPolygonVolume, GT frame)
    {scene}/{scene}_trans.txt             4x4 similarity COLMAP frame -> GT frame
    {scene}/{scene}_COLMAP_SfM.log        reference trajectory (camera-to-world, COLMAP frame)

When all four GT files are there, their headers are checked at load (`check_tnt_ground_truth`), so a
damaged ground truth fails before training rather than at evaluation.

``{scene}`` is the meta file's ``name``, else the prefix of the ``*_COLMAP_SfM.log`` found, else the
folder name. tau is the meta file's ``tau``, else the official value for the scene name (config.py of
the TnT toolbox), else None.

The training frame (``frame``, the run's ``data.tnt_frame``; `TNT_FRAMES`), with centre = the mean of the
camera centres and extent E = 1.1 x the largest distance of a centre from it (3DGS ``getNerfppNorm``):

- ``colmap``: the papers' frame. 2DGS, GOF, RaDe-GS, PGSR and GGGS train a TnT scene in its COLMAP frame
  and units; ``getNerfppNorm`` only gives ``cameras_extent`` for the learning rates and densification.
  ``x = x_colmap - centre`` (the translation changes no setting): ``Normalisation(scale=1, center=centre,
  radius=1, sphere=E)``, so an absolute length (near plane 0.2, TSDF voxel, neighbour distances) is the
  papers' number of COLMAP units.
- ``extent``: ``x = (x_colmap - centre) / E``, every camera inside the unit sphere:
  ``Normalisation(scale=E, center=centre, radius=1, sphere=1)``; the frame of the records made before
  ``data.tnt_frame`` existed (docs/design.md §12.1), in which those lengths act E times the papers'.

Either way the dataset frame is the COLMAP frame.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gsbench.data.camera import Camera, GroundTruth, Normalisation, Scene
from gsbench.data.colmap import colmap_image_paths, read_colmap_model
from gsbench.data.filecheck.arrays import check_crop_json, check_log, read_matrix4_text
from gsbench.data.filecheck.ply import check_ply
from gsbench.data.images import read_views
from gsbench.data.meta import optional_dir, read_meta
from gsbench.data.resolution import fit_downscale
from gsbench.data.similarity import similarity, transform_camera
from gsbench.errors import DataError

TNT_TAU = {"Barn": 0.01, "Caterpillar": 0.005, "Church": 0.025, "Courthouse": 0.025, "Ignatius": 0.003,
           "Meetingroom": 0.01, "Truck": 0.005}
GT_SUFFIXES = (".ply", ".json", "_trans.txt", "_COLMAP_SfM.log")
TNT_FRAMES = ("colmap", "extent")  # data.tnt_frame (module docstring)


def nerfpp_normalisation(centers: np.ndarray) -> Normalisation:
    """3DGS ``getNerfppNorm``: centre = mean camera centre, scale = 1.1 x max distance to it (the ``extent`` frame)."""
    centers = np.asarray(centers, dtype=np.float64)
    center = centers.mean(axis=0)
    extent = 1.1 * float(np.max(np.linalg.norm(centers - center, axis=1)))
    if not np.isfinite(extent) or extent <= 0:
        raise DataError(f"camera centres span no volume (extent {extent}); fix: a scene needs cameras at distinct positions")
    return Normalisation(scale=extent, center=center, radius=1.0)


def tnt_normalisation(centers: np.ndarray, frame: str) -> Normalisation:
    """The training frame ``frame`` of `TNT_FRAMES` for cameras at ``centers`` (COLMAP frame; module docstring)."""
    norm = nerfpp_normalisation(centers)
    if frame == "extent":
        return norm
    if frame != "colmap":
        raise DataError(f"unknown TnT training frame {frame!r}; fix: data.tnt_frame must be one of "
                        f"{', '.join(TNT_FRAMES)}")
    return Normalisation(scale=1.0, center=norm.center, radius=1.0, sphere=norm.scale)


def normalise_cameras(cameras: list[Camera], norm: Normalisation) -> list[Camera]:
    """Cameras in the dataset frame -> the training frame ``(x - center) / scale``."""
    to_norm = similarity(1.0 / norm.scale, None, -norm.center / norm.scale)
    return [transform_camera(c, to_norm) for c in cameras]


def write_log(path: Path, camera_to_world: list[np.ndarray]) -> None:
    """TnT trajectory ``.log``: per frame a line ``i i 0`` then the 4x4 camera-to-world matrix."""
    lines = []
    for i, pose in enumerate(camera_to_world):
        lines.append(f"{i} {i} 0")
        lines.extend(" ".join(f"{v:.12g}" for v in row) for row in np.asarray(pose))
    Path(path).write_text("\n".join(lines) + "\n")


def read_log(path: Path) -> np.ndarray:
    """(N,4,4) camera-to-world poses of a TnT ``.log`` file (5 lines per frame)."""
    try:
        lines = [ln.split() for ln in Path(path).read_text().splitlines() if ln.strip()]
        if len(lines) % 5:
            raise ValueError(f"{len(lines)} non-empty lines is not a multiple of 5")
        poses = np.array([[[float(v) for v in row] for row in lines[k + 1:k + 5]] for k in range(0, len(lines), 5)])
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError("each frame needs a 4x4 matrix")
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable trajectory ({exc}); fix: 5 lines per frame ('i i 0' and a 4x4 matrix)") from exc
    return poses


def write_crop_json(path: Path, polygon_xy: np.ndarray, z_min: float, z_max: float) -> None:
    """open3d ``SelectionPolygonVolume`` (orthogonal axis Z) as read by ``read_selection_polygon_volume``."""
    volume = {
        "class_name": "SelectionPolygonVolume",
        "orthogonal_axis": "Z",
        "axis_min": float(z_min),
        "axis_max": float(z_max),
        "bounding_polygon": [[float(x), float(y), 0.0] for x, y in polygon_xy],
        "version_major": 1,
        "version_minor": 0,
    }
    Path(path).write_text(json.dumps(volume, indent=1) + "\n")


def scene_gt_name(root: Path, meta: dict) -> str:
    """The GT file prefix (see the module docstring)."""
    if meta.get("name"):
        return str(meta["name"])
    logs = sorted(root.glob("*_COLMAP_SfM.log"))
    return logs[0].name[: -len("_COLMAP_SfM.log")] if logs else root.name


def gt_files(root: Path, name: str) -> dict[str, Path]:
    """The four official GT paths of a scene (they may not exist)."""
    return {suffix: root / f"{name}{suffix}" for suffix in GT_SUFFIXES}


def check_tnt_ground_truth(files: dict[str, Path]) -> None:
    """Header checks of the four TnT GT files (`gsbench.data.filecheck`), so a damaged ground truth
    fails when the scene is loaded, not after training: the point cloud's PLY header against its size,
    the crop volume's JSON, the 4x4 alignment and the trajectory's poses."""
    fix = (f"re-download the Tanks and Temples ground truth of the scene (GT/{files['.ply'].stem}/) "
           "or re-generate the scene")
    check_ply(files[".ply"], fix)
    check_crop_json(files[".json"], fix)
    read_matrix4_text(files["_trans.txt"], fix)
    check_log(files["_COLMAP_SfM.log"], fix)


def load_tnt(root: Path, *, downscale: float = 1.0, max_size=(), load_images: bool = True,
             gt_root: Path | None = None, frame: str = "colmap") -> Scene:
    """Load a TnT-layout scene (see the module docstring); cameras and SfM points are in the training frame
    ``frame`` (`TNT_FRAMES`).

    ``gt_root`` (``--gt``): the folder holding the four GT files when it is not the scene folder (the
    official ``GT/{scene}/`` download); the images are divided by `fit_downscale` of ``downscale``
    and ``max_size``."""
    root = Path(root)
    model = read_colmap_model(root / "sparse" / "0")
    paths = colmap_image_paths(root, model.cameras)
    size = (model.cameras[0].width, model.cameras[0].height)
    downscale = fit_downscale(*size, downscale, max_size)
    images, _ = read_views(paths, None, [(c.width, c.height) for c in model.cameras], downscale, load_images)
    norm = tnt_normalisation(np.array([c.center for c in model.cameras]), frame)
    cameras = normalise_cameras(model.cameras, norm)
    if downscale != 1.0:
        cameras = [c.scaled(1.0 / downscale) for c in cameras]
    meta = read_meta(root)
    name = scene_gt_name(root, meta)
    gt_folder = Path(gt_root) if gt_root else root
    missing = [str(p) for p in gt_files(gt_folder, name).values() if not p.is_file()]
    gt = None
    if not missing:
        check_tnt_ground_truth(gt_files(gt_folder, name))
        gt = GroundTruth(kind="tnt", root=gt_folder, name=name, tau=meta.get("tau", TNT_TAU.get(name)),
                         normal_maps=optional_dir(root / "gt_normal"), depth_maps=optional_dir(root / "gt_depth"))
    has_points = len(model.points) > 0
    return Scene(
        name=meta.get("name", root.name), fmt="tnt", root=root, cameras=cameras, images=images, masks=None,
        points=norm.invert(model.points) if has_points else None, colors=model.colors if has_points else None,
        normalisation=norm, gt=gt, gt_missing=f"{', '.join(missing)} not found" if missing else "",
        image_names=[p.name for p in paths], source_size=size, downscale=downscale,
    )

