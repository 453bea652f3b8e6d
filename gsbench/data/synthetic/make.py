"""Make generated scene folders: the one step that writes a scene, before anything loads it.

- `make_scene(name, ...)`: a built-in scene (``gsbench scene make NAME``); `make_mesh_scene(file, ...)` a
  scene of any mesh file (``gsbench scene make --mesh FILE``).
- `ensure_scene(path_or_name)`: the step before loading that a run and every command taking a scene run:
  a built-in name is made (`make_scene` with its defaults), a folder is left as it is.

Cache folders (`gsbench.data.cache.scene_dir`): ``<cache>/synthetic/<name>`` (plus ``-<format>``,
``-framing<share>``, ``-<W>x<H>``, ``-s<seed>``, ``-ss<n>`` for non-default choices), ``<cache>/mesh/<file
stem>`` (plus ``-<W>x<H>``, ``-s<seed>``, ``-ss<n>``). A folder already holding the same scene (the same
``gsbench_scene.json``) is left as it is. Writing is atomic: the scene is written into a temporary sibling
folder which is then renamed, so two makers of one scene (two sweep workers) each write their own, and the
one that finishes second discards its copy and keeps the first one's folder untouched (the first maker may
already be reading it).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from gsbench.data.cache import scene_dir
from gsbench.data.meta import read_meta
from gsbench.data.synthetic.builtin import builtin_name
from gsbench.data.synthetic.generator import (
    DEFAULT_SUPERSAMPLE,
    SPECS,
    ScenePlan,
    plan_mesh_scene,
    plan_meta,
    plan_scene,
    write_scene,
)
from gsbench.errors import DataError


def ensure_scene(path_or_name) -> Path:
    """The folder of a scene, made first when ``path_or_name`` is a built-in name (`make_scene` with the
    defaults: written when its cache folder is missing or holds another version of it); a folder as given."""
    name = builtin_name(path_or_name)
    return make_scene(name) if name is not None else Path(path_or_name)


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
    return _write_plan(plan_scene(name, fmt, res, seed, framing=framing), out, res is not None, supersample)


def make_mesh_scene(mesh, *, out=None, fmt: str = "dtu-colmap", res=None, seed: int = 0, supersample: int | None = None,
                    framing="dtu", up: str = "y", yaw: float = 0.0, albedo: str = "auto", largest_part: bool = False,
                    smooth: int = 0, rig: str | None = None) -> Path:
    """Generate a scene of the mesh file ``mesh`` (`gsbench.data.synthetic.generator.plan_mesh_scene`) and
    return its folder (default: ``<cache>/mesh/<file stem>``...); the other arguments as `make_scene`'s."""
    plan = plan_mesh_scene(mesh, fmt=fmt, res=res, seed=seed, framing=framing, up=up, yaw=yaw, albedo=albedo,
                           largest_part=largest_part, smooth=smooth, rig=rig)
    return _write_plan(plan, out, res is not None, supersample)


def _default_folder(plan: ScenePlan, custom_size: bool) -> Path:
    cam = plan.cameras[0]
    choices = []
    if plan.builtin and plan.fmt != plan.spec.fmt:
        choices.append(plan.fmt)
    if plan.builtin and plan.spec.framing != SPECS[plan.name].framing:
        choices.append(f"framing{plan.spec.framing:g}")
    if custom_size:
        choices.append(f"{cam.width}x{cam.height}")
    if plan.seed != 0:
        choices.append(f"s{plan.seed}")
    if plan.supersample != DEFAULT_SUPERSAMPLE:
        choices.append(f"ss{plan.supersample}")
    return scene_dir(plan.name, choices)


def _write_plan(plan: ScenePlan, out, custom_size: bool, supersample: int | None) -> Path:
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
        if read_meta(out) == meta:  # a concurrent maker finished first: its folder may be open in its reader
            return out
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            out.rename(old / out.name)
            shutil.rmtree(old)
        tmp.rename(out)
    except OSError:
        if read_meta(out) != meta:  # not a concurrent maker that won the race
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out
