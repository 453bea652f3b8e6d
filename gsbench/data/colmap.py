"""COLMAP sparse models (``sparse/0``) read and written with pycolmap.

Conventions: COLMAP's image coordinates put the centre of the top-left pixel at (0.5, 0.5), the
same as gsbench, so K is used unchanged. ``cam_from_world`` is gsbench's world-to-camera (R, t).
Only undistorted pinhole cameras are accepted: PINHOLE, SIMPLE_PINHOLE, and the perspective models
with distortion (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) when all their distortion
parameters are zero. Anything else must be undistorted first (``colmap image_undistorter``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsbench.data.camera import Camera, name_list
from gsbench.data.filecheck.colmap import (
    COLMAP_FIX,
    check_colmap_model,
    colmap_text_count_problem,
    locate_colmap_text_error,
)
from gsbench.data.images import list_images
from gsbench.errors import DataError, one_line

PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


@dataclass
class ColmapModel:
    """Cameras sorted by image name (the trajectory order), and the 3D points with colours in [0, 1]."""

    cameras: list[Camera]
    points: np.ndarray
    colors: np.ndarray


def _model_file(sparse_dir: Path, stem: str) -> Path:
    binary = sparse_dir / f"{stem}.bin"
    return binary if binary.exists() or not (sparse_dir / f"{stem}.txt").exists() else sparse_dir / f"{stem}.txt"


def _intrinsics(cam, sparse_dir: Path) -> np.ndarray:
    model = cam.model.name
    distortion = np.asarray(cam.params)[list(cam.extra_params_idxs())] if model in PERSPECTIVE_MODELS else None
    if distortion is None or np.any(distortion != 0.0):
        raise DataError(
            f"{_model_file(sparse_dir, 'cameras')}: camera {cam.camera_id} has model {model} with parameters "
            f"{list(np.round(cam.params, 6))}; gsbench needs undistorted PINHOLE cameras; "
            "fix: run `colmap image_undistorter` and load its output folder"
        )
    K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
    if not np.all(np.isfinite(K)):
        raise DataError(
            f"{_model_file(sparse_dir, 'cameras')}: camera {cam.camera_id} has non-finite parameters "
            f"{list(np.asarray(cam.params).tolist())}; fix: re-run the COLMAP reconstruction"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataError(
            f"{_model_file(sparse_dir, 'cameras')}: camera {cam.camera_id} has a non-positive focal "
            f"length (K={K.tolist()}); fix: re-run the COLMAP reconstruction"
        )
    return K


def read_colmap_model(sparse_dir: Path) -> ColmapModel:
    """Read ``cameras``, ``images`` and ``points3D`` (.bin or .txt) from a COLMAP model folder.

    Binary files are checked against their sizes first (`gsbench.data.filecheck.colmap.check_colmap_model`):
    pycolmap's reader hangs, allocating without bound, on a truncated ``points3D.bin``. Whatever
    pycolmap still rejects becomes a one-line `DataError` naming the file (or the line of a text model).
    """
    import pycolmap  # noqa: PLC0415  (only COLMAP folders need it; its import loads a large native library)

    sparse_dir = Path(sparse_dir)
    kind = check_colmap_model(sparse_dir)
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:  # noqa: BLE001  pycolmap raises ValueError, IndexError, RuntimeError, ...
        where = locate_colmap_text_error(sparse_dir) if kind == "txt" else ""
        if where:
            raise DataError(f"{one_line(where)}; fix: {COLMAP_FIX}") from exc
        raise DataError(
            f"{sparse_dir}: pycolmap cannot read the COLMAP {kind} model ({type(exc).__name__}: {one_line(exc)}); "
            f"fix: {COLMAP_FIX}"
        ) from exc
    if kind == "txt" and (problem := colmap_text_count_problem(sparse_dir, len(rec.cameras), len(rec.points3D))):
        raise DataError(f"{problem}; fix: {COLMAP_FIX}")
    cameras = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            raise DataError(
                f"{_model_file(sparse_dir, 'images')}: image {image.name} has no pose; "
                "fix: remove unregistered images from the model"
            )
        cam = rec.cameras[image.camera_id]
        pose = image.cam_from_world()
        R = np.asarray(pose.rotation.matrix(), dtype=np.float64)
        t = np.asarray(pose.translation, dtype=np.float64)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            frames = sparse_dir / f"frames{_model_file(sparse_dir, 'images').suffix}"
            where = f"{frames} (the pose of its frame {image.frame_id})" if frames.is_file() else _model_file(sparse_dir, 'images')
            raise DataError(
                f"{where}: image {image.name} has a non-finite pose (R={np.round(R, 6).tolist()}, t={t.tolist()}); "
                "fix: re-run the COLMAP reconstruction"
            )
        cameras.append(Camera(K=_intrinsics(cam, sparse_dir), R=R, t=t, width=int(cam.width),
                              height=int(cam.height), name=image.name))
    if not cameras:
        raise DataError(f"{_model_file(sparse_dir, 'images')}: the model has no images; fix: re-run COLMAP")
    ids, pts = list(rec.points3D.keys()), list(rec.points3D.values())
    points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    colors = np.array([p.color for p in pts], dtype=np.float64).reshape(-1, 3) / 255.0
    finite = np.all(np.isfinite(points), axis=1)
    if not np.all(finite):
        k = int(np.flatnonzero(~finite)[0])
        raise DataError(
            f"{_model_file(sparse_dir, 'points3D')}: {int(np.sum(~finite))} of {len(pts)} points have non-finite "
            f"coordinates (point3D {ids[k]} at {points[k].tolist()}); fix: {COLMAP_FIX}"
        )
    return ColmapModel(cameras=cameras, points=points, colors=colors)


def write_colmap_model(sparse_dir: Path, cameras: list[Camera], points: np.ndarray, colors: np.ndarray) -> None:
    """Write a binary COLMAP model: PINHOLE cameras (shared when intrinsics are equal), poses, points.

    ``colors`` are in [0, 1]. Points have empty tracks (they are an initialisation, not matches).
    Skew in K is not representable in COLMAP and must be zero.
    """
    import pycolmap  # noqa: PLC0415  (only COLMAP folders need it; its import loads a large native library)

    rec = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for image_id, cam in enumerate(cameras, start=1):
        key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(
                model="PINHOLE", width=cam.width, height=cam.height,
                params=[cam.fx, cam.fy, cam.cx, cam.cy], camera_id=camera_ids[key]))
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=cam.name, camera_id=camera_ids[key], image_id=image_id), pose)
    rgb = np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)
    for xyz, c in zip(np.asarray(points, dtype=np.float64), rgb):
        rec.add_point3D(xyz, pycolmap.Track(), c)
    Path(sparse_dir).mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(sparse_dir))


def colmap_image_paths(root: Path, cameras: list[Camera]) -> list[Path]:
    """``images/<name>`` for every COLMAP image; the folder must hold exactly those images. The error names every
    image missing (or extra), the first few and the count of the others (`name_list`)."""
    folder = root / "images"
    model = root / "sparse" / "0"
    if not folder.is_dir():
        raise DataError(f"{folder}: images folder not found; fix: put the undistorted views in images/")
    paths = [folder / c.name for c in cameras]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise DataError(f"{folder}: {len(missing)} of the {len(cameras)} images named in the COLMAP model {model} not "
                        f"found: {name_list(missing)}; fix: add them or re-run COLMAP")
    found = list_images(folder)
    if len(found) != len(cameras):
        listed = set(paths)
        extra = [p.name for p in found if p not in listed]
        raise DataError(f"{folder}: {len(found)} images but {len(cameras)} cameras in {model}"
                        f"{f' (not in the model: {name_list(extra)})' if extra else ''}; fix: one image per registered "
                        "COLMAP image")
    return paths
