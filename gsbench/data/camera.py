"""Camera and Scene containers shared by loaders, rasterizer, methods and evaluators.

Conventions (docs/design.md §2.1):
- OpenCV camera: x right, y down, z forward. ``R`` and ``t`` map world to camera: ``x_c = R x_w + t``.
- ``K`` is the 3x3 pinhole matrix in pixels. Pixel (i, j) (column i, row j) has its centre at
  ``(i + 0.5, j + 0.5)`` in the coordinates K maps to, so a principal point ``cx = W/2`` is the
  image centre. The ray through pixel (i, j) in camera space is ``((i+0.5-cx)/fx, (j+0.5-cy)/fy, 1)``.
- A Scene is in its training frame (DTU: IDR's sphere; TnT: the COLMAP frame, `gsbench.data.tnt`);
  ``normalisation`` holds the similarity back to the dataset's ground-truth frame (DTU: mm world; TnT:
  the COLMAP frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from gsbench.errors import DataError

MIN_TRAIN_VIEWS_SEEING = 0.5  # share of the training cameras that must see the scene (`Scene.check_cameras_face_scene`)
NAMES_SHOWN = 5  # names a message lists before "and N more" (`name_list`)


def name_list(names) -> str:
    """``a, b, c, d, e and 3 more``: the first `NAMES_SHOWN` of ``names`` and the count of the others."""
    names = [str(n) for n in names]
    shown = ", ".join(names[:NAMES_SHOWN])
    return shown + (f" and {len(names) - NAMES_SHOWN} more" if len(names) > NAMES_SHOWN else "")


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: ``K`` (3x3), world-to-camera ``R`` (3x3), ``t`` (3), image size, name."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    name: str = ""

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-Rᵀ t``."""
        return -self.R.T @ self.t

    @property
    def world_to_camera(self) -> np.ndarray:
        """4x4 matrix ``[[R, t], [0, 1]]``."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def camera_to_world(self) -> np.ndarray:
        """4x4 inverse of `world_to_camera` (the pose written in trajectory ``.log`` files)."""
        m = np.eye(4)
        m[:3, :3] = self.R.T
        m[:3, 3] = self.center
        return m

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N,3) world points; returns continuous pixel coordinates (N,2) and camera z (N,)."""
        pc = points_world @ self.R.T + self.t
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (pc @ self.K.T)[:, :2] / z[:, None]
        return uv, z

    def sees_sphere(self, centre, radius: float) -> bool:
        """Whether the sphere (``centre``, ``radius``; world) reaches into the view pyramid: its centre lies less than
        ``radius`` behind each of the five planes through the camera centre, ``z = 0`` and the four through the
        picture's edges (inward normals ``(1, 0, cx/fx)``, ``(-1, 0, (W-cx)/fx)``, ``(0, 1, cy/fy)``,
        ``(0, -1, (H-cy)/fy)`` in camera space). Conservative: near an edge of the pyramid a sphere just outside
        passes."""
        normals = np.array([[0.0, 0.0, 1.0],
                            [1.0, 0.0, self.cx / self.fx], [-1.0, 0.0, (self.width - self.cx) / self.fx],
                            [0.0, 1.0, self.cy / self.fy], [0.0, -1.0, (self.height - self.cy) / self.fy]])
        centre_camera = self.R @ np.asarray(centre, dtype=np.float64) + self.t
        return bool(np.all(normals @ centre_camera / np.linalg.norm(normals, axis=1) > -radius))

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 for half resolution)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        K = self.K.copy()
        K[0, :] *= w / self.width
        K[1, :] *= h / self.height
        return replace(self, K=K, width=w, height=h)


@dataclass(frozen=True)
class Normalisation:
    """Similarity from the normalised training frame to the dataset's GT frame: ``x_gt = s x + c``.

    ``s`` is a scalar scale, ``center`` the translation. ``radius`` is the unit the length-like
    hyper-parameters are multiplied by (near and far planes, TSDF lengths, neighbour distances), in
    training units: 1 in the papers' frames (IDR's sphere on DTU, COLMAP's units on TnT), so a setting
    acts as the paper's. ``sphere`` is the radius of the sphere about the training frame's origin that
    holds the scene (DTU: the object's, 1; TnT: every camera's, 3DGS's ``cameras_extent``): where
    random points start and what a camera must look at.
    """

    scale: float = 1.0
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 1.0
    sphere: float = 1.0

    @property
    def to_dataset(self) -> np.ndarray:
        """4x4 matrix mapping normalised coordinates to the dataset frame."""
        m = np.eye(4)
        m[:3, :3] *= self.scale
        m[:3, 3] = self.center
        return m

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map (N,3) normalised points to the dataset frame."""
        return points * self.scale + self.center

    def invert(self, points: np.ndarray) -> np.ndarray:
        """Map (N,3) dataset-frame points to the normalised frame."""
        return (points - self.center) / self.scale


@dataclass(frozen=True)
class GroundTruth:
    """Where a scene's ground truth lives, in the official layouts the evaluators read unchanged.

    kind ``dtu``: ``root/Points/stl/stl{scan:03d}_total.ply``, ``root/ObsMask/ObsMask{scan}_10.mat``,
    ``root/ObsMask/Plane{scan}.mat``; ``scan`` is the scan number.
    kind ``tnt``: ``root/{name}.ply``, ``root/{name}.json`` (crop), ``root/{name}_trans.txt``,
    ``root/{name}_COLMAP_SfM.log``; ``tau`` is the F-score threshold in GT units (metres).
    ``normal_maps`` (optional): folder of GT normal maps for synthetic scenes (``{image_stem}.npy``,
    HxWx3 float32, camera-space unit normals, zero outside the object).
    ``depth_maps`` (optional): likewise, ``{image_stem}.npy`` HxW camera z in the generator's normalised frame
    (DTU: the training frame; TnT: 3DGS's ``getNerfppNorm`` frame, the training frame of ``data.tnt_frame: extent``).
    """

    kind: str
    root: Path
    name: str
    scan: int | None = None
    tau: float | None = None
    normal_maps: Path | None = None
    depth_maps: Path | None = None


@dataclass
class Scene:
    """Everything a method and an evaluator need about one scene.

    ``images``: list of float32 HxWx3 arrays in [0, 1]; ``masks``: list of bool HxW arrays or None;
    ``gt_missing``: why ``gt`` is None (the files looked for), for messages and records.
    ``source_size``: (W, H) of the files on disk; ``downscale``: the factor they were divided by.
    ``mask_paths``: the mask files (set by the layouts that have masks, also when ``masks`` is not
    loaded), so what a scene offers is known before its images are decoded (`has_masks`).
    ``points``/``colors``: optional SfM initialisation (N,3) in the normalised frame, colours in [0,1].
    Cameras are in the normalised frame. ``fmt`` is ``dtu``, ``dtu-colmap`` or ``tnt``.
    ``holdout_every``: the run's view split (``data.holdout_every``, set when the scene is loaded): every
    k-th view (``i % k == 0``) is held out of training when k > 0 (3DGS ``--eval`` with k = 8,
    docs/methods/3dgs.md §1.4); `train_views` and `held_out_views` are the two parts.
    """

    name: str
    fmt: str
    root: Path
    cameras: list[Camera]
    images: list[np.ndarray]
    masks: list[np.ndarray] | None = None
    points: np.ndarray | None = None
    colors: np.ndarray | None = None
    normalisation: Normalisation = field(default_factory=Normalisation)
    gt: GroundTruth | None = None
    image_names: list[str] = field(default_factory=list)
    mask_paths: list[Path] | None = None
    gt_missing: str = ""
    source_size: tuple[int, int] | None = None
    downscale: float = 1.0
    holdout_every: int = 0

    @property
    def radius(self) -> float:
        return self.normalisation.radius

    @property
    def sphere(self) -> float:
        return self.normalisation.sphere

    @property
    def train_views(self) -> list[int]:
        """Indices of the views trained on (class docstring: all but every ``holdout_every``-th)."""
        return [i for i in range(len(self.cameras)) if not self._held_out(i)]

    @property
    def held_out_views(self) -> list[int]:
        """Indices of the views held out of training (``i % holdout_every == 0``; none when it is 0)."""
        return [i for i in range(len(self.cameras)) if self._held_out(i)]

    def _held_out(self, view: int) -> bool:
        return self.holdout_every > 0 and view % self.holdout_every == 0

    def views_facing_scene(self) -> list[int]:
        """Indices of the cameras that see the scene: the scene sphere (radius r = ``sphere`` about the origin of the
        training frame, where the object lies) reaches into the camera's view pyramid, i.e. its centre lies less than r behind
        each of the pyramid's five planes (the camera plane z = 0 and the four through the picture's edges). A camera
        inside the sphere passes all five (every camera of a layout normalised around its cameras, as TnT's is, so a
        turned camera there is not found); `Camera.sees_sphere`."""
        return [i for i, cam in enumerate(self.cameras) if cam.sees_sphere(np.zeros(3), self.sphere)]

    def check_cameras_face_scene(self) -> str:
        """DataError when fewer than `MIN_TRAIN_VIEWS_SEEING` of the training cameras see the scene
        (`views_facing_scene`): training would fit views of nothing and end in an empty or wrong model. Otherwise
        a warning naming the cameras that do not see it (held-out ones too), "" when every camera does."""
        facing = set(self.views_facing_scene())
        away = [i for i in range(len(self.cameras)) if i not in facing]
        train = self.train_views
        train_away = [i for i in train if i not in facing]
        seeing = len(train) - len(train_away)
        sphere = f"the sphere of radius {self.sphere:.4g} about the origin of the training frame"
        fix = ("fix: check the camera poses (world-to-camera versus camera-to-world, the sign of the viewing axis) and "
               "the normalisation")
        if seeing < MIN_TRAIN_VIEWS_SEEING * len(train):
            which = f"none of its {len(train)} training cameras looks" if not seeing else \
                f"only {seeing} of its {len(train)} training cameras look"
            raise DataError(f"scene '{self.name}': {which} at the scene ({sphere} is behind or outside the pictures "
                            f"of {self._camera_names(train_away)}; at least {MIN_TRAIN_VIEWS_SEEING:.0%} must see it); "
                            f"{fix}")
        if not away:
            return ""
        return (f"scene '{self.name}': {len(away)} of its {len(self.cameras)} cameras do not see the scene ({sphere} "
                f"is behind or outside their pictures): {self._camera_names(away)}; {fix}")

    def _camera_names(self, views: list[int]) -> str:
        """The names (else indices) of ``views``, the first few and the count of the others (`name_list`)."""
        return name_list([self.cameras[i].name or f"view {i}" for i in views])

    @property
    def has_masks(self) -> bool:
        """True when the scene has object masks, loaded or not."""
        return self.masks is not None or bool(self.mask_paths)

    def summary(self) -> dict:
        """A small JSON-able description: counts, image size, normalisation, GT files found."""
        cam = self.cameras[0]
        return {
            "name": self.name,
            "format": self.fmt,
            "root": str(self.root),
            "cameras": len(self.cameras),
            "image_size": [cam.width, cam.height],
            "masks": self.masks is not None,
            "init_points": 0 if self.points is None else int(len(self.points)),
            "scale_to_gt": self.normalisation.scale,
            "gt": None if self.gt is None else {"kind": self.gt.kind, "root": str(self.gt.root), "name": self.gt.name},
            "gt_missing": self.gt_missing,
        }
