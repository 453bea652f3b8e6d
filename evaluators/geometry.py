"""Reading the geometry to evaluate: a mesh or point cloud, checked, in a known frame.

Frames: gsbench methods write meshes in the scene's **normalised** frame; ``Normalisation.apply``
maps them to the dataset frame (DTU: mm world, TnT: the COLMAP frame). ``frame="dataset"`` declares that
the input is already in that dataset frame and skips the mapping.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError
from gsbench.mesh.files import read_mesh_file

FRAMES = ("normalised", "dataset")


@dataclass
class Geometry:
    """Vertices (N,3) float64, faces (M,3) int64 or None for a point cloud, and a label for messages."""

    vertices: np.ndarray
    faces: np.ndarray | None
    label: str

    @property
    def is_mesh(self) -> bool:
        return self.faces is not None and len(self.faces) > 0


def read_geometry(mesh) -> Geometry:
    """A `Geometry` of a path, trimesh, (N,3) array or Geometry, empty or not (`load_geometry` rejects
    empty ones)."""
    if isinstance(mesh, Geometry):
        return mesh
    if isinstance(mesh, np.ndarray):
        return Geometry(np.asarray(mesh, dtype=np.float64).reshape(-1, 3), None, "<points array>")
    if isinstance(mesh, (str, Path)):
        path = Path(mesh)
        if not path.is_file():
            raise EvaluationError(f"mesh file not found: {path} (fix: pass the path of an existing .ply/.obj)")
        try:
            # process=False keeps every vertex, as open3d's reader does in the reference scripts.
            loaded = read_mesh_file(path)
        except Exception as exc:  # noqa: BLE001 - any reader failure becomes a clear message
            raise EvaluationError(f"cannot read mesh file {path}: {exc}") from exc
        if isinstance(loaded, trimesh.Scene):
            loaded = loaded.to_mesh() if loaded.geometry else trimesh.PointCloud(np.zeros((0, 3)))
        label = str(path)
    else:
        loaded, label = mesh, f"<{type(mesh).__name__}>"
    if isinstance(loaded, trimesh.Trimesh):
        return Geometry(np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64), label)
    if isinstance(loaded, trimesh.PointCloud):
        return Geometry(np.asarray(loaded.vertices, np.float64), None, label)
    raise EvaluationError(f"cannot evaluate {label}: expected a mesh or point cloud, got {type(loaded).__name__}")


def load_geometry(mesh, need_faces: bool = False) -> Geometry:
    """Read ``mesh`` (path, trimesh object or (N,3) array) and check it; no frame mapping.

    Errors (EvaluationError, naming the input): empty geometry, no faces when ``need_faces``,
    non-finite vertices, face indices out of range.
    """
    geo = read_geometry(mesh)
    if len(geo.vertices) == 0:
        raise EvaluationError(f"{geo.label} is empty (0 vertices); nothing to evaluate (fix: check mesh extraction)")
    if need_faces and not geo.is_mesh:
        raise EvaluationError(
            f"{geo.label} has no faces, and this evaluator scores surfaces (fix: give a mesh with faces; a point "
            "cloud is scored by dtu_chamfer alone: gsbench eval --points --evaluator dtu_chamfer, or its option "
            "mode='pcd' from Python)"
        )
    bad = ~np.isfinite(geo.vertices).all(axis=1)
    if bad.any():
        raise EvaluationError(
            f"{geo.label} has {int(bad.sum())} of {len(bad)} vertices with NaN/inf coordinates "
            f"(fix: clean the mesh, e.g. trimesh remove_infinite_values, or fix the extractor)"
        )
    if geo.faces is not None and len(geo.faces) and (geo.faces.min() < 0 or geo.faces.max() >= len(geo.vertices)):
        raise EvaluationError(f"{geo.label} has face indices outside [0, {len(geo.vertices)})")
    return geo


def check_frame(frame: str) -> None:
    if frame not in FRAMES:
        raise EvaluationError(f"unknown frame '{frame}'; expected one of {FRAMES}")


def to_dataset_frame(vertices: np.ndarray, scene: Scene, frame: str) -> np.ndarray:
    """Vertices given in ``frame`` mapped to the dataset frame (``Normalisation.apply`` if normalised)."""
    check_frame(frame)
    return scene.normalisation.apply(vertices) if frame == "normalised" else vertices


def to_normalised_frame(vertices: np.ndarray, scene: Scene, frame: str) -> np.ndarray:
    """Vertices given in ``frame`` mapped to the normalised (training) frame."""
    check_frame(frame)
    return vertices if frame == "normalised" else scene.normalisation.invert(vertices)
