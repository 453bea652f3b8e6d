"""The DTU ground truth of one scan and DTUeval-python's filters on it (``eval.py`` steps 4 and 6).

- STL points (``Points/stl/stl{scan:03d}_total.ply``), the observation mask ``ObsMask``, its box ``BB``
  and voxel size ``Res`` (``ObsMask/ObsMask{scan}_10.mat``), the ground plane ``P``
  (``ObsMask/Plane{scan}.mat``).
- Box (step 4): ``BB[0] - patch <= p < BB[1] + 2 * patch`` on every axis (asymmetric, as coded in the
  reference).
- Observation (step 4): grid cell ``g = round((p - BB[0]) / Res)`` (half to even, like ``np.around``);
  cells outside the ObsMask array are unobserved; ``ObsMask[g]`` selects the points that count for accuracy.
- Plane (step 6): the STL points with ``[x y z 1] . P > 0`` count for completeness.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsbench.evaluators import gt_io


@dataclass
class DTUGroundTruth:
    """STL points (N,3) mm, ObsMask (bool grid), BB (2,3) mm, Res (mm), plane P (4,)."""

    stl: np.ndarray
    obs_mask: np.ndarray
    bb: np.ndarray
    res: float
    plane: np.ndarray

    @classmethod
    def read(cls, files: dict[str, Path]) -> DTUGroundTruth:
        """From the three files of `gsbench.data.dtu.dtu_gt_paths` (``STL points``, ``ObsMask``, ``Plane``)."""
        obs = gt_io.read_mat(files["ObsMask"], ("ObsMask", "BB", "Res"))
        plane = gt_io.read_mat(files["Plane"], ("P",))["P"].reshape(4).astype(np.float64)
        return cls(stl=gt_io.read_points(files["STL points"]), obs_mask=obs["ObsMask"].astype(bool),
                   bb=obs["BB"].astype(np.float64), res=float(np.ravel(obs["Res"])[0]), plane=plane)

    def in_box(self, points: np.ndarray, patch: float) -> np.ndarray:
        """Step 4's box test per point."""
        return np.all(points >= self.bb[0] - patch, axis=1) & np.all(points < self.bb[1] + 2 * patch, axis=1)

    def observed(self, points: np.ndarray) -> np.ndarray:
        """Step 4's ObsMask test per point (points outside the grid are unobserved)."""
        grid = np.around((points - self.bb[0]) / self.res).astype(np.int64)
        inside = np.all((grid >= 0) & (grid < np.array(self.obs_mask.shape)), axis=1)
        out = np.zeros(len(points), bool)
        g = grid[inside]
        out[inside] = self.obs_mask[g[:, 0], g[:, 1], g[:, 2]]
        return out

    def above_plane(self, points: np.ndarray) -> np.ndarray:
        """Step 6's plane test ``[x y z 1] . P > 0`` per point."""
        p = self.plane
        return points[:, 0] * p[0] + points[:, 1] * p[1] + points[:, 2] * p[2] + p[3] > 0

    def completeness_points(self) -> np.ndarray:
        """The STL points the completeness is measured from (above the plane)."""
        return self.stl[self.above_plane(self.stl)]
