"""Pictures of a run's surface, the way people judge reconstructions: by looking.

`surface_picture(run_dir)` draws one PNG of a finished run (``gsbench render RUN_DIR`` and the report's
"Surfaces" section use it). Its panels, from two fixed viewpoints (`picture_views`):

- the run's mesh, shaded (Lambertian, the light at the camera: ``0.25 + 0.75·|n·d|`` for the face normal n
  and the viewing ray d), white background;
- beside it, the ground truth from the same viewpoints: the exact mesh of a synthetic scene
  (``gt_mesh.ply``) shaded the same way, else the ground-truth points (DTU's STL points; TnT's points
  mapped by ``{scene}_trans.txt``, the evaluation's initial alignment) splatted front-most first; for a
  capture without ground truth, the photo of that view with the outline of its mask;
- for DTU-protocol scenes, the mesh coloured by each vertex's distance to the nearest ground-truth point
  in mm (the DTU script's accuracy of that point, without its masks) on one fixed scale, 0 to
  `ERROR_SCALE_MM`, with the colour bar (every run of every method on the same scale, so pictures
  compare).

Rays are cast with open3d's ``RaycastingScene`` in the normalised frame through the pixel centres of the
view's camera, rescaled to `PICTURE_WIDTH` pixels across. Nothing here changes a number of the run.
"""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import numpy as np
import trimesh
import yaml
from scipy.spatial import cKDTree

from gsbench.data.camera import Camera, Scene
from gsbench.data.synthetic.generator import GT_MESH_NAME
from gsbench.errors import GsbenchError, import_open3d, missing_dependency
from gsbench.evaluators.gt_io import read_matrix4, read_points
from gsbench.geometry.depth import world_rays
from gsbench.report import png
from gsbench.run_folder import RunFolder
from gsbench.runs.records import check_folder_identity
from gsbench.runs.runner import load_run_scene, make_run_scene, resolve_recorded
from gsbench.signals import signals_deferred

PICTURE_WIDTH = 320  # pixels across one panel, as drawn
STORED_SCALE = 0.75  # the stored PNG's size against the drawn figure's (with a palette: 10-75 KiB a picture)
SECOND_VIEW_ANGLE = 90.0  # degrees between the two views' directions from the scene centre, as near as there is
ERROR_SCALE_MM = 2.0  # the colour scale of the distance to the ground truth, 0 to this, in mm
MESH_GREY, GT_GREY = np.array([0.72, 0.74, 0.78]), np.array([0.80, 0.76, 0.68])
COLORMAP = "viridis"


@dataclasses.dataclass(frozen=True)
class Picture:
    """A PNG of ``width`` x ``height`` pixels."""

    png: bytes
    width: int
    height: int


def picture_camera(camera: Camera, width: int = PICTURE_WIDTH) -> Camera:
    """``camera`` with its intrinsics scaled to ``width`` pixels across (same view, same aspect)."""
    s = width / camera.width
    K = np.array(camera.K, dtype=np.float64)
    K[:2] *= s
    return dataclasses.replace(camera, K=K, width=width, height=max(1, round(camera.height * s)))


def picture_views(scene: Scene) -> list[int]:
    """Two training views, the same for every method of a scene: the first, and the one whose direction from
    the scene's centre is closest to a right angle from the first's (the other side of a ring or a cap)."""
    views = scene.train_views or list(range(len(scene.cameras)))
    directions = np.array([scene.cameras[i].center for i in views], dtype=np.float64)
    directions /= np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    angles = np.degrees(np.arccos(np.clip(directions @ directions[0], -1.0, 1.0)))
    return list(dict.fromkeys([views[0], views[int(np.argmin(np.abs(angles - SECOND_VIEW_ANGLE)))]]))


def _rays(camera: Camera) -> np.ndarray:
    """`gsbench.geometry.depth.world_rays` with unit directions (the shading's viewing ray d)."""
    rays = world_rays(camera)
    rays[:, 3:] /= np.linalg.norm(rays[:, 3:], axis=1, keepdims=True)
    return rays


def shade(vertices: np.ndarray, faces: np.ndarray, camera: Camera, face_colors: np.ndarray | None = None,
          grey=MESH_GREY) -> np.ndarray:
    """(H, W, 3) uint8: the mesh (normalised frame) seen by ``camera``, Lambertian with the light at the camera
    (module docstring), ``face_colors`` (F, 3) in [0, 1] or one ``grey``; white where no face is hit."""
    o3d = import_open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32)))
    rays = _rays(camera)
    hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    face = hit["primitive_ids"].numpy().astype(np.int64)
    inside = face != scene.INVALID_ID
    normals = hit["primitive_normals"].numpy()
    light = 0.25 + 0.75 * np.abs((normals * rays[:, 3:]).sum(1))
    base = np.broadcast_to(grey, (len(rays), 3)) if face_colors is None else face_colors[np.where(inside, face, 0)]
    image = np.ones((len(rays), 3))
    image[inside] = base[inside] * light[inside, None]
    return (np.clip(image, 0, 1) * 255).round().astype(np.uint8).reshape(camera.height, camera.width, 3)


def splat(points: np.ndarray, camera: Camera, grey=GT_GREY) -> np.ndarray:
    """(H, W, 3) uint8: points (normalised frame) as 2x2-pixel dots, the front-most kept, darker with depth."""
    pixel, z = camera.project(np.asarray(points, np.float64))
    keep = (z > 0) & np.isfinite(pixel).all(1)
    pixel, z = pixel[keep], z[keep]
    image = np.ones((camera.height, camera.width, 3))
    if len(z):
        near, far = np.percentile(z, 1), np.percentile(z, 99) + 1e-12
        light = 0.95 - 0.55 * np.clip((z - near) / (far - near), 0, 1)
        for dx in (0, 1):
            for dy in (0, 1):
                x, y = np.floor(pixel[:, 0]).astype(int) + dx, np.floor(pixel[:, 1]).astype(int) + dy
                ok = (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
                order = np.argsort(-z[ok])  # far to near: the nearest point is written last
                image[y[ok][order], x[ok][order]] = grey * light[ok][order, None]
    return (image * 255).round().astype(np.uint8)


def ground_truth(scene: Scene) -> tuple[str, object] | None:
    """What the ground truth is, in the normalised frame: ``("mesh", trimesh)`` for a synthetic scene's exact
    surface, ``("points", (N, 3))`` for DTU's STL points or TnT's points, None without ground truth."""
    if scene.gt is None:
        return None
    exact = Path(scene.root) / GT_MESH_NAME
    if exact.is_file():
        mesh = trimesh.load(exact, process=False, force="mesh")
        return "mesh", trimesh.Trimesh(scene.normalisation.invert(np.asarray(mesh.vertices)), mesh.faces, process=False)
    root = Path(scene.gt.root)
    if scene.gt.kind == "dtu":
        points = read_points(root / "Points" / "stl" / f"stl{scene.gt.scan:03d}_total.ply")
    else:
        trans = read_matrix4(root / f"{scene.gt.name}_trans.txt")
        gt = read_points(root / f"{scene.gt.name}.ply")
        points = (gt - trans[:3, 3]) @ np.linalg.inv(trans[:3, :3]).T  # GT frame -> the COLMAP (dataset) frame
    return "points", scene.normalisation.invert(points)


def vertex_errors_mm(vertices: np.ndarray, scene: Scene, gt) -> np.ndarray | None:
    """Distance (dataset units: mm on DTU) of each vertex (normalised frame) to the nearest ground-truth point,
    or None where the protocol is not DTU's."""
    if scene.gt is None or scene.gt.kind != "dtu":
        return None
    kind, value = gt
    reference = np.asarray(value.sample(200_000) if kind == "mesh" else value)
    tree = cKDTree(scene.normalisation.apply(reference))
    with signals_deferred():
        return tree.query(scene.normalisation.apply(np.asarray(vertices)), workers=-1)[0]


def _mask_outline(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The photo with the border pixels of its mask drawn in red."""
    edge = mask & ~(np.roll(mask, 1, 0) & np.roll(mask, -1, 0) & np.roll(mask, 1, 1) & np.roll(mask, -1, 1))
    out = (np.clip(image, 0, 1) * 255).round().astype(np.uint8)
    out[edge] = (230, 30, 30)
    return out


def surface_picture(run_dir, title: str | None = None) -> Picture:
    """The PNG of a finished run's mesh (module docstring); a GsbenchError naming the missing file otherwise."""
    files = RunFolder(run_dir)
    for path in (files.config, files.mesh):
        if not path.is_file():
            raise GsbenchError(f"{path} not found: the pictures show a finished run's mesh; fix: pass "
                               "<out>/<dataset>/<scene>/<method>/<run_id> of a run that wrote its mesh")
    check_folder_identity(files)
    resolved = yaml.safe_load(files.config.read_text())
    cfg = resolve_recorded(resolved)
    make_run_scene(cfg)
    scene = load_run_scene(cfg, load_images=False)
    mesh = trimesh.load(files.mesh, process=False, force="mesh")
    vertices = np.asarray(mesh.vertices, np.float64)  # a run's mesh is in the normalised (training) frame
    faces = np.asarray(mesh.faces, np.int64)
    if not len(faces):
        raise GsbenchError(f"{files.mesh} has no faces: nothing to picture")
    views = picture_views(scene)
    cameras = [picture_camera(scene.cameras[i]) for i in views]
    gt = ground_truth(scene)
    rows = [[shade(vertices, faces, cam) for cam in cameras]]
    labels = [[f"{cfg.method['name']}, view {i}" for i in views]]
    if gt is None:
        photos = load_run_scene(cfg)
        rows.append([_mask_outline(np.asarray(_resized(photos.images[i], cam)),
                                   _resized(photos.masks[i], cam) if photos.masks is not None else
                                   np.zeros((cam.height, cam.width), bool)) for i, cam in zip(views, cameras)])
        labels.append([f"photo, view {i} (mask outline)" for i in views])
    else:
        kind, value = gt
        rows.append([shade(value.vertices, value.faces, cam, grey=GT_GREY) if kind == "mesh" else splat(value, cam)
                     for cam in cameras])
        labels.append([f"ground truth ({'exact mesh' if kind == 'mesh' else 'points'}), view {i}" for i in views])
    errors = vertex_errors_mm(vertices, scene, gt) if gt is not None else None
    return _compose(rows, labels, errors, vertices, faces, cameras, views, title or f"{cfg.method['name']} on {cfg.scene}")


def _resized(array: np.ndarray, camera: Camera) -> np.ndarray:
    """An image or mask of a view brought to the picture camera's size (nearest pixel)."""
    h, w = array.shape[:2]
    ys = np.minimum((np.arange(camera.height) + 0.5) * h / camera.height, h - 1).astype(int)
    xs = np.minimum((np.arange(camera.width) + 0.5) * w / camera.width, w - 1).astype(int)
    return array[ys][:, xs]


def _cropped(rows: list[list[np.ndarray]], margin: int = 8) -> list[list[np.ndarray]]:
    """Every panel of a column cut to the box of what any panel of that column shows (non-white pixels), plus
    ``margin``, so the object fills the panel; the same box down a column keeps the panels comparable."""
    out = [list(row) for row in rows]
    for c in range(len(rows[0])):
        drawn = np.zeros(rows[0][c].shape[:2], bool)
        for row in rows:
            drawn |= (row[c] < 250).any(-1)
        if not drawn.any():
            continue
        ys, xs = np.nonzero(drawn)
        y0, y1 = max(ys.min() - margin, 0), min(ys.max() + margin + 1, drawn.shape[0])
        x0, x1 = max(xs.min() - margin, 0), min(xs.max() + margin + 1, drawn.shape[1])
        for r in range(len(rows)):
            out[r][c] = rows[r][c][y0:y1, x0:x1]
    return out


def _compose(rows, labels, errors, vertices, faces, cameras, views, title) -> Picture:
    """One figure: a row per kind of panel, the error-coloured row with its colour bar last."""
    try:
        from matplotlib import colormaps  # noqa: PLC0415  (the report's optional plotting dependency)
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
        from matplotlib.cm import ScalarMappable  # noqa: PLC0415
        from matplotlib.colors import Normalize  # noqa: PLC0415
        from matplotlib.figure import Figure  # noqa: PLC0415
    except ImportError as exc:
        raise missing_dependency("matplotlib", "pip install matplotlib, a dependency of gsbench") from exc
    norm, cmap = Normalize(0.0, ERROR_SCALE_MM), colormaps[COLORMAP]
    if errors is not None:
        face_error = errors[faces].mean(1)
        rows.append([shade(vertices, faces, cam, face_colors=cmap(norm(face_error))[:, :3]) for cam in cameras])
        labels.append([f"distance to the ground truth, view {i}" for i in views])
    rows = _cropped(rows)
    ncols = len(cameras)
    width_px, height_px = PICTURE_WIDTH * ncols + 120, (cameras[0].height + 40) * len(rows) + 40
    figure = Figure(figsize=(width_px / 100, height_px / 100), dpi=100)
    FigureCanvasAgg(figure)
    figure.suptitle(title, fontsize=10)
    axes = figure.subplots(len(rows), ncols, squeeze=False)
    for r, (images, names) in enumerate(zip(rows, labels)):
        for c, (image, name) in enumerate(zip(images, names)):
            axes[r][c].imshow(image, interpolation="nearest")
            axes[r][c].set_title(name, fontsize=8)
            axes[r][c].axis("off")
    if errors is not None:
        bar = figure.colorbar(ScalarMappable(norm, cmap), ax=list(axes[-1]), fraction=0.04, pad=0.02)
        bar.set_label(f"mm (0 to {ERROR_SCALE_MM:g}, clipped)", fontsize=8)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, metadata={"Software": None})
    stored = png.compact(buffer.getvalue(), STORED_SCALE)
    return Picture(stored, *png.size(stored))
