"""One entry point for scenes: detect a folder's layout and load it, or generate a built-in scene.

- `load_scene(path_or_name)`: a folder (layout detected by `detect_format`) or a built-in name
  ``synthetic/<name>`` (generated into the cache on first use).
- `make_scene(name, ...)`: generate a built-in scene (``gsbench scene make``); skipped when the folder
  already holds the same scene (same ``gsbench_scene.json``); `make_mesh_scene(file, ...)` the same for
  a scene made of any mesh file (``gsbench scene make --mesh FILE``).
- `check_scene(path, gt_root)`: what a folder holds and what is wrong with it (``gsbench scene check``).

Cache: ``$GSBENCH_DATA`` or ``~/.cache/gsbench/scenes``; built-in scenes go to
``<cache>/synthetic/<name>`` (plus ``-<format>``, ``-framing<share>``, ``-<W>x<H>``, ``-s<seed>`` for
non-default choices), mesh-file scenes to ``<cache>/mesh/<file stem>`` (plus ``-<W>x<H>``, ``-s<seed>``).
Generation is atomic: the scene is written into a temporary sibling folder which is then renamed.
It imports the loaders and the generator (about 1 s: trimesh, scipy); `gsbench.data.synthetic.builtin` is the
table of built-in scenes without them.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from gsbench.data.cache import cache_dir
from gsbench.data.camera import Scene
from gsbench.data.dtu import dtu_ground_truth, dtu_gt_paths, load_dtu, load_dtu_colmap, scan_number
from gsbench.data.meta import read_meta
from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.data.synthetic.generator import (
    DEFAULT_SUPERSAMPLE,
    SPECS,
    plan_mesh_scene,
    plan_meta,
    plan_scene,
    write_scene,
)
from gsbench.data.tnt import gt_files, load_tnt, scene_gt_name
from gsbench.errors import DataError, GsbenchError

__all__ = ["BUILTIN_SCENES", "check_scene", "detect_format", "load_scene", "make_mesh_scene", "make_scene"]

LAYOUTS = ("dtu: cameras.npz + image/ + mask/; tnt: sparse/0 + images/ (+ {scene}.ply, .json, _trans.txt, "
           "_COLMAP_SfM.log); dtu-colmap: sparse/0 + images/ + mask/")


def detect_format(root: Path) -> str:
    """``dtu-colmap`` (sparse/0 + mask/), ``tnt`` (sparse/0) or ``dtu`` (cameras.npz or image/)."""
    root = Path(root)
    if not root.is_dir():
        raise _not_a_folder(root)
    if (root / "sparse" / "0").is_dir():
        return "dtu-colmap" if (root / "mask").is_dir() else "tnt"
    if (root / "cameras.npz").exists() or (root / "image").is_dir():
        return "dtu"
    raise DataError(f"{root}: not a recognised scene layout; expected {LAYOUTS}; fix: arrange the folder in one of these layouts")


def _not_a_folder(root: Path) -> DataError:
    """Why ``root`` is not a scene folder: it is a file, an unknown built-in name, or it does not exist."""
    builtin = ", ".join(BUILTIN_SCENES)
    if root.is_file():
        return DataError(f"{root} is a file; expected a scene folder ({LAYOUTS}) or a built-in name; "
                         f"fix: give a scene folder (e.g. {root.parent})")
    name = str(root)
    if name.startswith("synthetic/"):
        if name in BUILTIN_SCENES:
            return DataError(f"{name} is a built-in scene name, not a folder; fix: generate it with "
                             f"`gsbench scene make {name}` (it prints the folder) and give that folder")
        return DataError(f"{name}: no built-in scene of that name and no such folder; built-in scenes: {builtin}; "
                         "fix: use one of them (gsbench list) or give a scene folder")
    return DataError(f"{root}: scene folder not found; fix: give a scene folder or a built-in name ({builtin})")


def _is_builtin_name(name) -> bool:
    return isinstance(name, str) and (name in BUILTIN_SCENES or name.startswith("synthetic/")) and not Path(name).is_dir()


def _check_gt_root(gt_root) -> None:
    if gt_root and not Path(gt_root).is_dir():
        raise DataError(f"{gt_root}: ground-truth folder not found; fix: --gt must name the folder holding "
                        "DTU Points/ and ObsMask/, or a TnT scene's .ply/.json/_trans.txt/_COLMAP_SfM.log")


def load_scene(path_or_name, *, downscale: float = 1.0, max_size=(), load_images: bool = True, gt_root=None,
               holdout_every: int = 0) -> Scene:
    """Load a scene folder or built-in name; the images are divided by
    `gsbench.data.resolution.fit_downscale` of ``downscale`` (>= 1) and ``max_size`` ([long, short] px).

    ``load_images=False`` reads cameras and image headers only (``images`` is empty, ``masks`` None,
    ``mask_paths`` set). ``gt_root`` (``--gt``) is the folder holding the ground truth when it is not
    beside the scene: DTU ``Points/`` and ``ObsMask/`` (the official SampleSet), or a TnT scene's four
    GT files. ``holdout_every`` is the view split the scene carries (`Scene.train_views`, 0: train on all).
    """
    if downscale < 1.0:
        raise DataError(f"downscale must be >= 1 (it divides the image size), got {downscale}")
    _check_gt_root(gt_root)
    root = make_scene(path_or_name) if _is_builtin_name(path_or_name) else Path(path_or_name)
    fmt = detect_format(root)
    kwargs = {"downscale": downscale, "max_size": tuple(max_size or ()), "load_images": load_images,
              "gt_root": Path(gt_root) if gt_root else None}
    scene = (load_tnt if fmt == "tnt" else load_dtu if fmt == "dtu" else load_dtu_colmap)(root, **kwargs)
    scene.holdout_every = int(holdout_every)
    return scene


def has_ground_truth(path_or_name, gt_root=None) -> bool:
    """Whether a scene has its ground truth, from file checks only (built-in scenes always do)."""
    if _is_builtin_name(path_or_name):
        return True
    root = Path(path_or_name)
    _check_gt_root(gt_root)
    if detect_format(root) == "tnt":
        folder = Path(gt_root) if gt_root else root
        return all(p.is_file() for p in gt_files(folder, scene_gt_name(root, read_meta(root))).values())
    return dtu_ground_truth(root, scan_number(root, read_meta(root)), Path(gt_root) if gt_root else None)[0] is not None


def _default_folder(plan, custom_size: bool) -> Path:
    cam = plan.cameras[0]
    parts = [plan.short_name]
    if plan.builtin and plan.fmt != plan.spec.fmt:
        parts.append(plan.fmt)
    if plan.builtin and plan.spec.framing != SPECS[plan.name].framing:
        parts.append(f"framing{plan.spec.framing:g}")
    if custom_size:
        parts.append(f"{cam.width}x{cam.height}")
    if plan.seed != 0:
        parts.append(f"s{plan.seed}")
    if plan.supersample != DEFAULT_SUPERSAMPLE:
        parts.append(f"ss{plan.supersample}")
    return cache_dir() / plan.name.split("/", 1)[0] / "-".join(parts)


def make_scene(name: str, fmt: str | None = None, out=None, res=None, seed: int = 0, supersample: int | None = None,
               framing=None) -> Path:
    """Generate built-in scene ``name`` (``synthetic/spot`` or ``spot``) and return its folder.

    ``fmt``: ``dtu``, ``dtu-colmap`` or ``tnt`` (default: the scene's own). ``res``: None (0.25 of the
    full size), a float factor of the full size, or ``(W, H)``. ``out``: the folder (default: the cache).
    ``supersample``: rays per pixel side of the images (None: the default 2, area-sampled; 1: one ray
    through each pixel centre, as the rasterizer samples). ``framing``: ``dtu``, ``small`` or an object
    share (`gsbench.data.synthetic.framing`; None: the scene's own). Nothing is written when ``out``
    already holds this exact scene.
    """
    return write_plan(plan_scene(name, fmt, res, seed, framing=framing), out, res is not None, supersample)


def make_mesh_scene(mesh, *, out=None, fmt: str = "dtu-colmap", res=None, seed: int = 0, supersample: int | None = None,
                    framing="dtu", up: str = "y", yaw: float = 0.0, albedo: str = "auto", largest_part: bool = False,
                    smooth: int = 0) -> Path:
    """Generate a scene of the mesh file ``mesh`` (`gsbench.data.synthetic.generator.plan_mesh_scene`) and
    return its folder (default: ``<cache>/mesh/<file stem>``...); the other arguments as `make_scene`'s."""
    plan = plan_mesh_scene(mesh, fmt=fmt, res=res, seed=seed, framing=framing, up=up, yaw=yaw, albedo=albedo,
                           largest_part=largest_part, smooth=smooth)
    return write_plan(plan, out, res is not None, supersample)


def write_plan(plan, out, custom_size: bool, supersample: int | None) -> Path:
    """Write a planned scene into ``out`` (default: the cache) atomically, unless it already holds it."""
    if supersample is not None:
        if supersample < 1:
            raise DataError(f"supersample must be >= 1 (rays per pixel side), got {supersample}; fix: e.g. --supersample 1")
        plan.supersample = int(supersample)
    meta = plan_meta(plan)
    out = Path(out) if out else _default_folder(plan, custom_size)
    if out.exists():
        found = read_meta(out)
        if found == meta:
            return out
        if not found and any(out.iterdir()):
            raise DataError(f"{out}: folder exists and is not a gsbench-generated scene; fix: choose a new or empty --out")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        write_scene(plan, tmp)
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            out.rename(old / out.name)
            shutil.rmtree(old)
        tmp.rename(out)
    except OSError:
        if read_meta(out) != meta:  # not a concurrent generator that won the race
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _ground_truth_files(scene: Scene | None, root: Path, fmt: str, gt_root) -> dict[str, bool]:
    """Every ground-truth file the scene's protocol reads, with the paths filled in: found or not."""
    if fmt == "tnt":
        folder = Path(gt_root) if gt_root else root
        return {str(p): p.is_file() for p in gt_files(folder, scene_gt_name(root, read_meta(root))).values()}
    scan = scan_number(root, read_meta(root))
    if scan is None:
        return {}
    folder = scene.gt.root if scene is not None and scene.gt is not None else Path(gt_root) if gt_root else root
    return {str(p): p.is_file() for p in dtu_gt_paths(folder, scan).values()}


def check_scene(path, gt_root=None) -> dict:
    """What a folder holds and what is wrong with it: format, counts, image size, ground truth.

    Reads cameras, points and image/mask headers only (no pixel is decoded). ``ok`` is True when the
    scene loads: ground truth is optional (``ground_truth`` says what was found, or why not, and
    which evaluators a run will skip without it).
    """
    root = Path(path)
    report = {"path": str(root), "format": None, "ok": False, "errors": []}
    try:
        report["format"] = detect_format(root)
        scene = load_scene(root, load_images=False, gt_root=gt_root)
    except GsbenchError as exc:
        report["errors"].append(str(exc))
        scene = None
    if scene is not None:
        report.update(scene.summary())
        report["images"] = len(scene.cameras)
        report["masks"] = len(scene.mask_paths or ())
        report["gt_depth_maps"] = scene.gt is not None and scene.gt.depth_maps is not None
        report["gt_normal_maps"] = scene.gt is not None and scene.gt.normal_maps is not None
        facing = scene.views_facing_scene()
        report["cameras_facing_scene"] = len(facing)
        try:
            scene.check_cameras_face_scene()
        except GsbenchError as exc:
            report["errors"].append(str(exc))
    if report["format"]:
        report["ground_truth"] = {
            "found": scene is not None and scene.gt is not None,
            "files": _ground_truth_files(scene, root, report["format"], gt_root),
            "missing": "" if scene is None else scene.gt_missing,
        }
    report["ok"] = scene is not None and not report["errors"]
    return report
