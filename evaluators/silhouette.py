"""Agreement of a mesh with the scene's object masks, and its surface outside their visual hull,
protocol v1: measures that need masks, not ground truth.

A capture without ground-truth geometry still has its object masks (DTU's ``mask/`` folder, one mask
per image). They say, for every pixel of every view, whether the object is there; a good mesh seen
from that camera covers the same pixels, and has no surface where every view that sees it says
"background" (floaters).

Definition (the cameras and masks of the scene, in its normalised frame; a mesh given in the dataset
frame, ``frame="dataset"``, is mapped to it by ``Normalisation.invert``, `gsbench.evaluators.geometry`):

- Resolution: the masks' own (H, W); a camera of another size is rescaled to it (``K`` rows scaled by
  W / width and H / height), so the masks are never resampled.
- Silhouette ``S_v`` of view v: the pixels (i, j) whose ray through the pixel centre
  ``(i + 0.5, j + 0.5)`` (`gsbench.data.camera`), from the camera centre, hits a triangle of the mesh
  (either side; open3d ``RaycastingScene.cast_rays``, float32, coordinates shifted to the mesh's
  vertex mean so that large coordinates keep their precision, as in `surface_offset`).
- ``IoU_v = |S_v ∩ M_v| / |S_v ∪ M_v|`` with ``M_v`` the mask of view v; a view where both are empty
  agrees fully (``IoU_v = 1``). ``mask_iou`` = the mean of ``IoU_v`` over the views scored (option
  ``views``: scene view indices, default every view), ``mask_iou_min`` = the worst view.
- Visual hull (`gsbench.data.visual_hull`): point X is inside when at least one camera sees it (in front
  of it, projected into its image) and every camera that sees it has it inside its mask dilated by
  one pixel. The hull is always that of **every** view's mask (more views carve a tighter hull);
  ``views`` selects the IoU views only. The one-pixel dilation: a surface lying exactly on the
  object's silhouette projects, through pixel discretisation, half the time into the first background
  pixel; it must not count as a floater for that (the exact mesh of the built-in ``synthetic/spot``
  scene at 96x72 has 56 % of its area outside the undilated hull). ``min_views = 1``: a point that no camera sees is
  outside (surface beyond every view is not the captured object).
- ``outside_hull_area_share = Σ_{t: c_t ∉ hull} A_t / Σ_t A_t`` over the mesh's triangles t, with
  ``c_t`` the triangle's centroid and ``A_t`` its area: the fraction of the surface area outside the
  hull (a ratio, the same in either frame). Its floor is not exactly 0: a part of the object thinner
  than a pixel may hit no pixel centre, so its mask misses it (the exact mesh of the built-in
  ``synthetic/spot`` scene at 96x72: 0.009 %, one triangle).

An empty mesh (no faces) scores ``mask_iou = mask_iou_min = 0`` and ``outside_hull_area_share = 0``
with a warning, never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from gsbench.data.camera import Camera, Scene
from gsbench.data.visual_hull import inside_visual_hull
from gsbench.errors import EvaluationError, import_open3d
from gsbench.evaluators.base import Diagnostics, Evaluator, MetricInfo
from gsbench.evaluators.geometry import check_frame, load_geometry, read_geometry, to_normalised_frame
from gsbench.geometry.depth import world_rays

HULL_DILATE_PX = 1  # masks grown by one pixel before carving (module docstring)
HULL_MIN_VIEWS = 1


@dataclass(frozen=True)
class SilhouetteOptions:
    views: tuple[int, ...] | None = None  # scene view indices scored by the IoU; None: every view
    frame: str = "normalised"


def camera_at(cam: Camera, width: int, height: int) -> Camera:
    """``cam`` for an image of ``width`` x ``height`` (K's rows scaled; unchanged at its own size)."""
    if (width, height) == (cam.width, cam.height):
        return cam
    K = np.array(cam.K, dtype=np.float64)
    K[0, :] *= width / cam.width
    K[1, :] *= height / cam.height
    return replace(cam, K=K, width=width, height=height)


def silhouettes(vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera]) -> list[np.ndarray]:
    """Bool (H, W) per camera: which pixel-centre rays hit the mesh (module docstring)."""
    o3d = import_open3d()
    origin = vertices.mean(axis=0)  # float32 scene: shift to the mesh so coordinates keep their precision
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((vertices - origin).astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    out = []
    for cam in cameras:
        rays = world_rays(cam)
        rays[:, :3] -= origin
        t_hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        out.append(np.isfinite(t_hit).reshape(cam.height, cam.width))
    return out


def iou(silhouette: np.ndarray, mask: np.ndarray) -> float:
    """``|S ∩ M| / |S ∪ M|``; 1.0 when both are empty."""
    union = int(np.count_nonzero(silhouette | mask))
    return 1.0 if union == 0 else int(np.count_nonzero(silhouette & mask)) / union


def outside_hull_area_share(vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera],
                            masks: list[np.ndarray]) -> tuple[float, int]:
    """(area share of the triangles whose centroid is outside the hull, how many triangles are outside)."""
    tri = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    inside = inside_visual_hull(tri.mean(axis=1), cameras, masks, dilate_px=HULL_DILATE_PX, min_views=HULL_MIN_VIEWS)
    total = float(areas.sum())
    share = float(areas[~inside].sum()) / total if total > 0 else 0.0
    return share, int(np.count_nonzero(~inside))


class Silhouette(Evaluator):
    """Mask IoU of the mesh's silhouettes and its surface area outside the masks' visual hull."""

    name = "silhouette"
    version = 1
    requires = ("mesh",)
    needs = ("masks",)
    metrics = {
        "mask_iou": MetricInfo(True, "", "mean over views of |silhouette ∩ mask| / |silhouette ∪ mask| "
                                         "(pixel-centre rays)"),
        "mask_iou_min": MetricInfo(True, "", "the worst view's mask IoU"),
        "outside_hull_area_share": MetricInfo(False, "", "fraction of the surface area whose triangle centroids "
                                                         "lie outside the masks' visual hull (floaters)"),
    }
    Options = SilhouetteOptions

    def validate(self, scene: Scene) -> None:
        if not scene.has_masks:
            raise EvaluationError(
                f"silhouette: scene '{scene.name}' has no object masks; fix: add a mask/ folder (one mask per "
                "image) or drop silhouette from eval.evaluators"
            )

    def _masks(self, scene: Scene) -> list[np.ndarray]:
        if scene.masks is None:
            raise EvaluationError(f"silhouette: scene '{scene.name}' has masks on disk but they are not loaded; "
                                  "fix: load the scene's images (load_images=True), which loads its masks")
        if len(scene.masks) != len(scene.cameras):
            raise EvaluationError(f"silhouette: scene '{scene.name}' has {len(scene.masks)} masks for "
                                  f"{len(scene.cameras)} cameras; fix: one mask per image")
        return [np.asarray(m, dtype=bool) for m in scene.masks]

    def evaluate(self, mesh, scene: Scene, **options) -> dict:
        opts = self.options(**options)
        check_frame(opts.frame)
        diag = Diagnostics()
        with diag.phase("load"):
            self.validate(scene)
            masks = self._masks(scene)
            n = len(scene.cameras)
            views = list(range(n)) if opts.views is None else [int(v) for v in opts.views]
            bad = [v for v in views if not 0 <= v < n]
            if bad or not views:
                raise EvaluationError(f"silhouette: views {bad or '[]'} are not view indices of scene "
                                      f"'{scene.name}' (0..{n - 1}); fix: pass views=None or valid indices")
            cameras = [camera_at(cam, m.shape[1], m.shape[0]) for cam, m in zip(scene.cameras, masks)]
            geo = read_geometry(mesh)  # not load_geometry: an empty mesh is a score here, not an error
            empty = len(geo.vertices) == 0 or not geo.is_mesh
            if not empty:
                geo = load_geometry(geo, need_faces=True)
                verts = to_normalised_frame(geo.vertices, scene, opts.frame)
        protocol = self.protocol(opts) | {"hull_dilate_px": HULL_DILATE_PX, "hull_min_views": HULL_MIN_VIEWS}
        diag.data.update(views=views, resolution=[cameras[views[0]].width, cameras[views[0]].height],
                         mask_pixels=[int(np.count_nonzero(masks[v])) for v in views])
        if empty:
            diag.warn(f"silhouette: {geo.label} has no faces; mask IoU 0 and outside-hull share 0 reported")
            diag.data.update(per_view_iou=[0.0] * len(views), silhouette_pixels=[0] * len(views),
                             intersection_pixels=[0] * len(views), faces=0, faces_outside_hull=0)
            return {"metrics": {"mask_iou": 0.0, "mask_iou_min": 0.0, "outside_hull_area_share": 0.0},
                    "protocol": protocol, "diagnostics": diag.finish()}
        with diag.phase("raycast"):
            sils = silhouettes(verts, geo.faces, [cameras[v] for v in views])
        per_view = [iou(s, masks[v]) for s, v in zip(sils, views)]
        with diag.phase("hull"):
            share, outside = outside_hull_area_share(verts, geo.faces, cameras, masks)
        diag.data.update(per_view_iou=per_view, silhouette_pixels=[int(np.count_nonzero(s)) for s in sils],
                         intersection_pixels=[int(np.count_nonzero(s & masks[v])) for s, v in zip(sils, views)],
                         faces=int(len(geo.faces)), faces_outside_hull=outside)
        return {
            "metrics": {"mask_iou": float(np.mean(per_view)), "mask_iou_min": float(np.min(per_view)),
                        "outside_hull_area_share": share},
            "protocol": protocol,
            "diagnostics": diag.finish(),
        }
