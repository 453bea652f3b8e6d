"""Mask culling before DTU evaluation, on CPU (2DGS ``scripts/eval_dtu/evaluate_single_scene.py``), as
docs/evaluation.md §2.3 states it: a vertex is kept if in every view it is outside the frame or on the dilated
mask, a face if its three vertices are; ``cull`` chooses the dilation, 2DGS's disk(24) at 1600 px (scaled with the
mask width) or GOF's disk(6) at the masks' resolution.

The reference projects with ``uv = (K X_cam)_xy / (z + 1e-6)`` and no z > 0 test (reproduced), in a pixel
convention with integer centres: with gsbench's i + 0.5 centres a point is valid iff 0.5 < u < W − 0.5 (likewise
v), and the sampled pixel is ``rint(u − 0.5)`` (half to even, as ``grid_sample``'s nearest). The dilation is
"distance to the mask <= radius" (``distance_transform_edt``), which equals a binary dilation by
``disk(radius)`` and is linear in the pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt
from tqdm.auto import tqdm

from gsbench.data.camera import Camera, Scene
from gsbench.errors import EvaluationError


@dataclass(frozen=True)
class CullConvention:
    """A disk of ``radius`` px at ``reference_width`` (None: at the masks' own width), and its source."""

    radius: float
    reference_width: int | None
    source: str


CULL_CONVENTIONS = {
    "2dgs": CullConvention(24, 1600, "2DGS scripts/eval_dtu/evaluate_single_scene.py: disk(24) on the 1600x1200 masks"),
    "gof": CullConvention(6, None, "GOF / RaDe-GS evaluate_dtu_mesh.py: disk(6) on the training-resolution masks"),
}
NO_CULLING = "none"


def check_cull(cull: str) -> str:
    """``cull`` if it names a convention or ``none``, else an EvaluationError listing them."""
    if cull != NO_CULLING and cull not in CULL_CONVENTIONS:
        raise EvaluationError(f"dtu culling must be one of {[*CULL_CONVENTIONS, NO_CULLING]} (eval.dtu_culling), "
                              f"got {cull!r}")
    return cull


def dilate_mask(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation of ``mask`` by ``skimage.morphology.disk(radius)``, via the distance transform."""
    mask = np.asarray(mask, dtype=bool)
    if radius <= 0 or not mask.any():
        return mask.copy()
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    r0, r1 = max(0, rows[0] - radius), min(mask.shape[0], rows[-1] + radius + 1)
    c0, c1 = max(0, cols[0] - radius), min(mask.shape[1], cols[-1] + radius + 1)
    out = np.zeros_like(mask)  # nothing farther than radius from the mask's bounding box is reached
    out[r0:r1, c0:c1] = distance_transform_edt(~mask[r0:r1, c0:c1]) <= radius
    return out


def dilation_radius(width: int, dilation: float, reference_width: int | None) -> int:
    """The disk radius for an image ``width`` px wide: ``round(dilation * width / reference_width)``, or
    ``round(dilation)`` when ``reference_width`` is None (a radius in the masks' own pixels)."""
    return int(round(dilation if reference_width is None else dilation * width / reference_width))


def keep_in_view(vertices: np.ndarray, camera: Camera, dilated: np.ndarray) -> np.ndarray:
    """Per-vertex keep flag for one view: outside the frame, or on the dilated mask (steps 4-5)."""
    P = camera.K @ np.c_[camera.R, camera.t]  # 3x4; explicit columns: (N,3)@(3,3) BLAS calls are slow here
    x, y, z = (vertices[:, 0] * P[i, 0] + vertices[:, 1] * P[i, 1] + vertices[:, 2] * P[i, 2] + P[i, 3] for i in range(3))
    z = z + 1e-6  # reference: xy / (z + 1e-6), no z > 0 test
    u, v = x / z, y / z
    w, h = camera.width, camera.height
    valid = (u > 0.5) & (u < w - 0.5) & (v > 0.5) & (v < h - 0.5)
    keep = ~valid
    col = np.rint(u[valid] - 0.5).astype(np.int64)
    row = np.rint(v[valid] - 0.5).astype(np.int64)
    keep[valid] = dilated[row, col]
    return keep


def cull_vertices(vertices: np.ndarray, scene: Scene, dilation: float = 24, reference_width: int | None = 1600,
                  ) -> np.ndarray:
    """Keep flag per vertex (normalised frame) over all of the scene's views (steps 1-5); the disk is
    ``dilation`` px at ``reference_width`` (`dilation_radius`)."""
    if scene.masks is None:
        raise EvaluationError(
            f"culling needs object masks but scene '{scene.name}' has none "
            f"(fix: provide mask/*.png in the scene folder, or evaluate without culling: --set eval.dtu_culling=none)"
        )
    if len(scene.masks) != len(scene.cameras):
        raise EvaluationError(
            f"scene '{scene.name}' has {len(scene.masks)} masks for {len(scene.cameras)} cameras; expected one per camera"
        )
    keep = np.ones(len(vertices), dtype=bool)
    views = tqdm(zip(scene.cameras, scene.masks), total=len(scene.cameras), desc="cull", disable=None, leave=False)
    for cam, mask in views:
        if mask.shape[:2] != (cam.height, cam.width):
            raise EvaluationError(
                f"mask of camera '{cam.name}' is {mask.shape[1]}x{mask.shape[0]}, camera is {cam.width}x{cam.height}"
            )
        dilated = dilate_mask(mask, dilation_radius(cam.width, dilation, reference_width))
        alive = np.flatnonzero(keep)  # vertices culled by an earlier view need no more tests
        keep[alive] = keep_in_view(vertices[alive], cam, dilated)
    return keep


def cull_mesh(vertices: np.ndarray, faces: np.ndarray | None, scene: Scene, cull: str, label: str, frame_hint: str):
    """(keep flag per vertex, kept faces re-indexed or None) of a mesh whose ``vertices`` are in the
    normalised frame, by convention ``cull`` (`CULL_CONVENTIONS`; ``none`` keeps everything);
    EvaluationError naming ``label`` when culling removes every vertex (``frame_hint``: the frame the
    mesh was read in, for the message)."""
    if check_cull(cull) == NO_CULLING:
        return np.ones(len(vertices), bool), faces
    convention = CULL_CONVENTIONS[cull]
    keep = cull_vertices(vertices, scene, convention.radius, convention.reference_width)
    if not keep.any():
        raise EvaluationError(f"culling removed every vertex of {label}: no vertex projects onto the masks (fix: "
                              f"check frame= — '{frame_hint}' — and the scene cameras)")
    return keep, None if faces is None else kept_faces(faces, keep)


def kept_faces(faces: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Faces whose three vertices are all kept, re-indexed to the kept vertices (step 5)."""
    new_index = np.cumsum(keep) - 1
    f = faces[keep[faces].all(axis=1)]
    return new_index[f]
