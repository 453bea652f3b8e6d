"""One entry point for scenes: detect a folder's layout and load it. It reads files and writes none.

- `load_scene(path_or_name)`: a folder (layout detected by `detect_format`) or a built-in name
  ``synthetic/<name>``, read from its cache folder (`gsbench.data.cache.scene_dir`); a built-in scene not
  made yet is an error naming ``gsbench scene make``. A run and the commands make it first
  (`gsbench.data.synthetic.make.ensure_scene`).
- `check_scene(path, gt_root)`: what a folder holds and what is wrong with it (``gsbench scene check``).
"""

from __future__ import annotations

from pathlib import Path

from gsbench.data.cache import scene_dir
from gsbench.data.camera import Scene
from gsbench.data.dtu import dtu_ground_truth, dtu_gt_paths, load_dtu, load_dtu_colmap, scan_number
from gsbench.data.frame import scene_frame
from gsbench.data.meta import read_meta
from gsbench.data.synthetic.builtin import BUILTIN_SCENES, builtin_name
from gsbench.data.tnt import gt_files, load_tnt, scene_gt_name
from gsbench.errors import DataError, GsbenchError

__all__ = ["BUILTIN_SCENES", "check_scene", "detect_format", "load_scene"]

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


def _scene_folder(path_or_name) -> Path:
    """The folder of a scene: a built-in name's cache folder (a DataError naming ``gsbench scene make`` when it
    has not been made), else the path itself."""
    name = builtin_name(path_or_name)
    if name is None:
        return Path(path_or_name)
    if name not in BUILTIN_SCENES:
        raise _not_a_folder(Path(name))
    folder = scene_dir(name)
    if not folder.is_dir():
        raise DataError(f"{name}: built-in scene not made yet (no folder {folder}); fix: make it with "
                        f"`gsbench scene make {name}` (gsbench run makes it before loading it)")
    return folder


def _check_gt_root(gt_root) -> None:
    if gt_root and not Path(gt_root).is_dir():
        raise DataError(f"{gt_root}: ground-truth folder not found; fix: --gt must name the folder holding "
                        "DTU Points/ and ObsMask/, or a TnT scene's .ply/.json/_trans.txt/_COLMAP_SfM.log")


def load_scene(path_or_name, *, downscale: float = 1.0, max_size=(), load_images: bool = True, gt_root=None,
               holdout_every: int = 0, tnt_frame: str = "colmap") -> Scene:
    """Load a scene folder or built-in name; the images are divided by
    `gsbench.data.resolution.fit_downscale` of ``downscale`` (>= 1) and ``max_size`` ([long, short] px).

    ``load_images=False`` reads cameras and image headers only (``images`` is empty, ``masks`` None,
    ``mask_paths`` set). ``gt_root`` (``--gt``) is the folder holding the ground truth when it is not
    beside the scene: DTU ``Points/`` and ``ObsMask/`` (the official SampleSet), or a TnT scene's four
    GT files. ``holdout_every`` is the view split the scene carries (`Scene.train_views`, 0: train on all).
    ``tnt_frame``: the training frame of a TnT layout (``data.tnt_frame``, `gsbench.data.tnt`; the papers'
    ``colmap`` unless a run says otherwise); the DTU layouts have one.
    """
    if downscale < 1.0:
        raise DataError(f"downscale must be >= 1 (it divides the image size), got {downscale}")
    _check_gt_root(gt_root)
    root = _scene_folder(path_or_name)
    fmt = detect_format(root)
    kwargs = {"downscale": downscale, "max_size": tuple(max_size or ()), "load_images": load_images,
              "gt_root": Path(gt_root) if gt_root else None}
    if fmt == "tnt":
        scene = load_tnt(root, frame=tnt_frame, **kwargs)
    else:
        scene = (load_dtu if fmt == "dtu" else load_dtu_colmap)(root, **kwargs)
    scene.holdout_every = int(holdout_every)
    return scene


def has_ground_truth(path_or_name, gt_root=None) -> bool:
    """Whether a scene has its ground truth, from file checks only (built-in scenes always do)."""
    if builtin_name(path_or_name) is not None:
        return True
    root = Path(path_or_name)
    _check_gt_root(gt_root)
    if detect_format(root) == "tnt":
        folder = Path(gt_root) if gt_root else root
        return all(p.is_file() for p in gt_files(folder, scene_gt_name(root, read_meta(root))).values())
    return dtu_ground_truth(root, scan_number(root, read_meta(root)), Path(gt_root) if gt_root else None)[0] is not None


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
    scene loads and enough of its cameras see it (`Scene.check_cameras_face_scene`; ``warnings`` names those that
    do not): ground truth is optional (``ground_truth`` says what was found, or why not, and
    which evaluators a run will skip without it).
    """
    root = Path(path)
    report = {"path": str(root), "format": None, "ok": False, "errors": [], "warnings": []}
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
        report["frame"] = scene_frame(scene)
        try:
            away = scene.check_cameras_face_scene()
        except GsbenchError as exc:
            report["errors"].append(str(exc))
        else:
            report["warnings"] += [away] if away else []
    if report["format"]:
        report["ground_truth"] = {
            "found": scene is not None and scene.gt is not None,
            "files": _ground_truth_files(scene, root, report["format"], gt_root),
            "missing": "" if scene is None else scene.gt_missing,
        }
    report["ok"] = scene is not None and not report["errors"]
    return report
