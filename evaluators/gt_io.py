"""Readers for the official ground-truth files (DTU ``.mat``/``.ply``, TnT ``.log``/``_trans.txt``/``.ply``).

Every reader raises EvaluationError naming the file when it is missing, empty or malformed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.io import loadmat

from gsbench.data.filecheck.arrays import check_crop_json
from gsbench.data.filecheck.ply import check_ply
from gsbench.errors import EvaluationError, import_open3d

GT_FIX = "download the ground truth again (or pass --gt PATH, a folder with an intact copy)"


def read_points(path: Path, with_normals: bool = False):
    """Points (N,3) float64 of a point-cloud ``.ply`` (open3d reader, as the reference scripts use).

    With ``with_normals`` returns ``(points, normals or None)``.
    """
    o3d = import_open3d()
    if not path.is_file():
        raise EvaluationError(f"ground-truth point cloud not found: {path}")
    check_ply(path, GT_FIX)  # open3d reads a truncated binary PLY without an error, as garbage
    pcd = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pcd.points, dtype=np.float64)
    if len(pts) == 0:
        raise EvaluationError(f"ground-truth point cloud {path} is empty or unreadable")
    if not with_normals:
        return pts
    return pts, (np.asarray(pcd.normals, dtype=np.float64) if pcd.has_normals() else None)


def read_mat(path: Path, names: tuple[str, ...]) -> dict:
    """Variables ``names`` of a MATLAB ``.mat`` file (``scipy.io.loadmat``)."""
    if not path.is_file():
        raise EvaluationError(f"ground-truth file not found: {path}")
    try:
        data = loadmat(str(path))
    except Exception as exc:  # noqa: BLE001
        raise EvaluationError(f"cannot read {path} with scipy.io.loadmat: {exc}") from exc
    missing = [n for n in names if n not in data]
    if missing:
        raise EvaluationError(f"{path} lacks variable(s) {missing}; found {sorted(k for k in data if not k.startswith('__'))}")
    return {n: data[n] for n in names}


def read_matrix4(path: Path) -> np.ndarray:
    """A 4x4 matrix written as text (``np.loadtxt``; TnT ``{scene}_trans.txt``)."""
    if not path.is_file():
        raise EvaluationError(f"ground-truth file not found: {path}")
    try:
        m = np.loadtxt(path)
    except ValueError as exc:
        raise EvaluationError(f"cannot parse {path} as a 4x4 matrix: {exc}") from exc
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise EvaluationError(f"{path} must hold a finite 4x4 matrix, found shape {m.shape}")
    return m


def read_log(path: Path) -> np.ndarray:
    """Camera-to-world poses (N,4,4) of a trajectory ``.log``: per frame a line ``i i 0`` then 4 rows."""
    if not path.is_file():
        raise EvaluationError(f"trajectory file not found: {path}")
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    if len(rows) == 0 or len(rows) % 5:
        raise EvaluationError(f"{path}: expected blocks of 5 lines (a header 'i i 0' and 4 matrix rows), found {len(rows)} lines")
    try:
        mats = np.array([[[float(x) for x in rows[5 * f + 1 + r]] for r in range(4)] for f in range(len(rows) // 5)])
    except ValueError as exc:
        raise EvaluationError(f"{path}: malformed matrix row: {exc}") from exc
    if mats.shape[1:] != (4, 4):
        raise EvaluationError(f"{path}: every pose must be 4x4, found {mats.shape[1:]}")
    return mats


def write_log(path: Path, poses: np.ndarray) -> None:
    """Write camera-to-world poses (N,4,4) in the ``.log`` format read by `read_log`."""
    lines = []
    for i, pose in enumerate(poses):
        lines.append(f"{i} {i} 0")
        lines.extend(" ".join(f"{x:.12g}" for x in row) for row in pose)
    Path(path).write_text("\n".join(lines) + "\n")


def write_colored_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """Write a coloured point cloud (colours in [0, 1]) for visual inspection."""
    o3d = import_open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.colors = o3d.utility.Vector3dVector(colors)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    o3d.io.write_point_cloud(str(path), pcd)


def read_crop_volume(path: Path):
    """The TnT crop volume (open3d ``SelectionPolygonVolume``) of ``path``, checked first (open3d returns
    an empty volume for a file it cannot read)."""
    check_crop_json(path, GT_FIX)
    return import_open3d().visualization.read_selection_polygon_volume(str(path))
