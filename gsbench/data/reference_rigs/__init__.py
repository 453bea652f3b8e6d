"""The cameras of two real captures, kept as data and read with the project's own loaders.

- ``dtu_scan65_cameras.npz``: DTU scan 65's ``cameras.npz`` in IDR's preprocessing (49 ``world_mat_i``
  in DTU's world, millimetres; ``scale_mat_i``: IDR's normalisation sphere). The 49 robot-arm positions
  and the intrinsics are the same for every DTU scan (the raw ``world_mat`` are bit-identical in the
  public copies of scans 24 and 65); only ``scale_mat`` is the scan's. DTU's 15 further positions (64 in
  all) are in no public copy found, so the rig has 49.
- ``Barn_COLMAP_SfM.log``, ``Barn_trans.txt``, ``Barn.json``: Tanks-and-Temples Barn's 410-frame
  trajectory (camera-to-world, COLMAP frame), its alignment to the GT frame (metres, z up) and its crop
  volume. TnT publishes no intrinsics; the frames' EXIF gives a 21 mm (35 mm-equivalent) lens on 1920x1080
  frames, fx = 21/36 × 1920 = 1120 px (``BARN_FOCAL_35MM``), principal point at the centre.

Sources, commits and blob hashes: README.md in this folder. The files are the public ones, unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsbench.data.camera import Camera
from gsbench.data.dtu import PIXEL_SHIFT, decompose_projection, read_cameras_npz
from gsbench.data.frame import Region, crop_file_region
from gsbench.data.similarity import decompose, similarity, transform_camera, transform_points
from gsbench.data.tnt import read_log

FOLDER = Path(__file__).parent
DTU_CAMERAS = FOLDER / "dtu_scan65_cameras.npz"
DTU_VIEWS, DTU_SIZE = 49, (1600, 1200)
BARN_LOG, BARN_TRANS, BARN_CROP = FOLDER / "Barn_COLMAP_SfM.log", FOLDER / "Barn_trans.txt", FOLDER / "Barn.json"
BARN_SIZE = (1920, 1080)
BARN_FOCAL_35MM = 21.0  # mm, EXIF FocalLengthIn35mmFilm of Barn's frames (Sony A7S II)


@dataclass(frozen=True)
class ReferenceRig:
    """A real capture's cameras in its GT frame (full-resolution intrinsics, gsbench's pixel-centre
    convention), its object region (`gsbench.data.frame.Region`) and its training frame's similarity
    ``to_training`` (4x4, GT frame -> training frame)."""

    name: str
    cameras: list[Camera]
    region: Region
    to_training: np.ndarray

    @property
    def training_cameras(self) -> list[Camera]:
        return [transform_camera(c, self.to_training) for c in self.cameras]


def dtu_rig() -> ReferenceRig:
    """DTU's 49 cameras in DTU's world (mm); the region and training frame are scan 65's IDR sphere."""
    projections, scale_mat = read_cameras_npz(DTU_CAMERAS, DTU_VIEWS)
    cameras = []
    for i, projection in enumerate(projections):  # normalised frame, as `gsbench.data.dtu` loads them
        K, R, t = decompose_projection(projection, f"{DTU_CAMERAS.name}:world_mat_{i}")
        cam = Camera(K=PIXEL_SHIFT @ K, R=R, t=t, width=DTU_SIZE[0], height=DTU_SIZE[1], name=f"{i:06d}.png")
        cameras.append(transform_camera(cam, scale_mat))
    scale = float(scale_mat[0, 0])
    region = Region(scale_mat[:3, 3].copy(), scale, False, scale)
    return ReferenceRig("DTU scan 65", cameras, region, np.linalg.inv(scale_mat))


def barn_rig() -> ReferenceRig:
    """Tanks-and-Temples Barn's 410 cameras in its GT frame (metres, z up), its crop region, and the papers'
    training frame, which gsbench gives a TnT scene (``data.tnt_frame: colmap``, `gsbench.data.tnt`): the
    COLMAP frame (GT metres / ``Barn_trans.txt``'s scale, 4.139) about the cameras' centroid."""
    colmap_to_gt = np.loadtxt(BARN_TRANS)
    width, height = BARN_SIZE
    f = BARN_FOCAL_35MM / 36.0 * width
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    cameras = []
    for i, c2w in enumerate(read_log(BARN_LOG)):
        w2c = np.linalg.inv(c2w)
        cam = Camera(K=K, R=w2c[:3, :3], t=w2c[:3, 3], width=width, height=height, name=f"{i:06d}.jpg")
        cameras.append(transform_camera(cam, colmap_to_gt))
    region = crop_file_region(BARN_CROP, decompose(colmap_to_gt)[0])
    gt_to_colmap = np.linalg.inv(colmap_to_gt)
    centroid = transform_points(gt_to_colmap, np.array([c.center for c in cameras])).mean(axis=0)
    return ReferenceRig("Tanks and Temples Barn", cameras, region, similarity(1.0, None, -centroid) @ gt_to_colmap)
