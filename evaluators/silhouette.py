"""Agreement of a mesh with the scene's object masks, and its surface outside their visual hull, protocol v1,
as docs/evaluation.md §5 states it: measures that need masks, not ground truth.

``IoU_v = |S_v ∩ M_v| / |S_v ∪ M_v|`` per view, S_v the pixels whose centre ray hits the mesh (1 where both are
empty); ``mask_iou`` its mean, ``mask_iou_min`` the worst view. ``outside_hull_area_share = Σ_{t: c_t ∉ hull} A_t /
Σ_t A_t`` over triangle centroids c_t, the hull that of every view's mask dilated by one pixel: without the
dilation, the exact mesh of synthetic/spot at 96x72 has 56 % of its area outside (its silhouette projects half
the time into the first background pixel). Its floor is not exactly 0 (the same mesh: 0.009 %, one triangle).
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
    memory_per_face = 350
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
