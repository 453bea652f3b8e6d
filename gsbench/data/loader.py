"""One entry point for scenes: detect a folder's layout and load it, or generate a built-in scene.

- `load_scene(path_or_name)`: a folder (layout detected by `detect_format`) or a built-in name
  ``synthetic/<name>`` (generated into the cache on first use).
- `make_scene(name, ...)`: generate a built-in scene (``gsbench scene make``); skipped when the folder
  already holds the same scene (same ``gsbench_scene.json``).
- `check_scene(path)`: what a folder holds and what is wrong with it (``gsbench scene check``).

Cache: ``$GSBENCH_DATA`` or ``~/.cache/gsbench/scenes``; built-in scenes go to
``<cache>/synthetic/<name>`` (plus ``-<format>``, ``-<W>x<H>``, ``-s<seed>`` for non-default choices).
Generation is atomic: the scene is written into a temporary sibling folder which is then renamed.
This module imports nothing heavy, so `BUILTIN_SCENES` is cheap to import from here too.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from gsbench.data.builtin import BUILTIN_SCENES
from gsbench.data.camera import Scene
from gsbench.data.meta import read_meta
from gsbench.errors import DataError, GsbenchError

__all__ = ["BUILTIN_SCENES", "cache_dir", "check_scene", "detect_format", "load_scene", "make_scene"]

LAYOUTS = ("dtu: cameras.npz + image/ + mask/; tnt: sparse/0 + images/ (+ {scene}.ply, .json, _trans.txt, "
           "_COLMAP_SfM.log); dtu-colmap: sparse/0 + images/ + mask/")


def cache_dir() -> Path:
    """``$GSBENCH_DATA`` or ``~/.cache/gsbench/scenes``."""
    return Path(os.environ.get("GSBENCH_DATA") or Path.home() / ".cache" / "gsbench" / "scenes")


def detect_format(root: Path) -> str:
    """``dtu-colmap`` (sparse/0 + mask/), ``tnt`` (sparse/0) or ``dtu`` (cameras.npz or image/)."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: scene folder not found; fix: give a scene folder or a built-in name (gsbench list)")
    if (root / "sparse" / "0").is_dir():
        return "dtu-colmap" if (root / "mask").is_dir() else "tnt"
    if (root / "cameras.npz").exists() or (root / "image").is_dir():
        return "dtu"
    raise DataError(f"{root}: not a recognised scene layout; expected {LAYOUTS}; fix: arrange the folder in one of these layouts")


def _is_builtin_name(name) -> bool:
    return isinstance(name, str) and (name in BUILTIN_SCENES or name.startswith("synthetic/")) and not Path(name).is_dir()


def load_scene(path_or_name, *, downscale: float = 1.0, load_images: bool = True, gt_root=None) -> Scene:
    """Load a scene folder or built-in name; ``downscale`` >= 1 divides the image size.

    ``load_images=False`` reads cameras and image headers only (``images`` is empty, ``masks`` None).
    ``gt_root`` (DTU only) is the folder holding ``Points/`` and ``ObsMask/`` when it is not the scene
    folder or its parent.
    """
    if downscale < 1.0:
        raise DataError(f"downscale must be >= 1 (it divides the image size), got {downscale}")
    root = make_scene(path_or_name) if _is_builtin_name(path_or_name) else Path(path_or_name)
    fmt = detect_format(root)
    if fmt == "tnt":
        from gsbench.data.tnt import load_tnt  # noqa: PLC0415

        return load_tnt(root, downscale=downscale, load_images=load_images)
    from gsbench.data.dtu import load_dtu, load_dtu_colmap  # noqa: PLC0415

    loader = load_dtu if fmt == "dtu" else load_dtu_colmap
    return loader(root, downscale=downscale, load_images=load_images, gt_root=Path(gt_root) if gt_root else None)


def _default_folder(plan, custom_size: bool) -> Path:
    from gsbench.data.synthetic import DEFAULT_SUPERSAMPLE  # noqa: PLC0415

    cam = plan.cameras[0]
    parts = [plan.short_name]
    if plan.fmt != plan.spec.fmt:
        parts.append(plan.fmt)
    if custom_size:
        parts.append(f"{cam.width}x{cam.height}")
    if plan.seed != 0:
        parts.append(f"s{plan.seed}")
    if plan.supersample != DEFAULT_SUPERSAMPLE:
        parts.append(f"ss{plan.supersample}")
    return cache_dir() / "synthetic" / "-".join(parts)


def make_scene(name: str, fmt: str | None = None, out=None, res=None, seed: int = 0, supersample: int | None = None) -> Path:
    """Generate built-in scene ``name`` (``synthetic/spot`` or ``spot``) and return its folder.

    ``fmt``: ``dtu``, ``dtu-colmap`` or ``tnt`` (default: the scene's own). ``res``: None (0.25 of the
    full size), a float factor of the full size, or ``(W, H)``. ``out``: the folder (default: the cache).
    ``supersample``: rays per pixel side of the images (None: the default 2, area-sampled; 1: one ray
    through each pixel centre, as the rasterizer samples). Nothing is written when ``out`` already holds this exact scene.
    """
    from gsbench.data.synthetic import plan_meta, plan_scene, write_scene  # noqa: PLC0415

    plan = plan_scene(name, fmt, res, seed)
    if supersample is not None:
        if supersample < 1:
            raise DataError(f"supersample must be >= 1 (rays per pixel side), got {supersample}; fix: e.g. --supersample 1")
        plan.supersample = int(supersample)
    meta = plan_meta(plan)
    out = Path(out) if out else _default_folder(plan, custom_size=res is not None)
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


def _expected_gt(scene: Scene | None, root: Path, fmt: str) -> dict[str, bool]:
    if fmt == "tnt":
        from gsbench.data.tnt import gt_files, scene_gt_name  # noqa: PLC0415

        return {p.name: p.is_file() for p in gt_files(root, scene_gt_name(root, read_meta(root))).values()}
    gt = scene.gt if scene is not None else None
    if gt is None:
        return {"Points/stl/stl{scan:03d}_total.ply": False}
    return {rel: (gt.root / rel).is_file() for rel in (f"Points/stl/stl{gt.scan:03d}_total.ply",
                                                       f"ObsMask/ObsMask{gt.scan}_10.mat", f"ObsMask/Plane{gt.scan}.mat")}


def check_scene(path) -> dict:
    """Load a folder fully and report: format, counts, image size, GT files found/missing, errors."""
    root = Path(path)
    report = {"path": str(root), "format": None, "ok": False, "errors": []}
    try:
        report["format"] = detect_format(root)
        scene = load_scene(root)
    except GsbenchError as exc:
        report["errors"].append(str(exc))
        scene = None
    if scene is not None:
        report.update(scene.summary())
        report["images"] = len(scene.images)
        report["masks"] = 0 if scene.masks is None else len(scene.masks)
        report["gt_depth_maps"] = scene.gt is not None and scene.gt.depth_maps is not None
        report["gt_normal_maps"] = scene.gt is not None and scene.gt.normal_maps is not None
    if report["format"]:
        report["gt_files"] = _expected_gt(scene, root, report["format"])
        report["ok"] = not report["errors"] and all(report["gt_files"].values())
    return report
