"""A DTU-layout scene folder with its world in millimetres scaled by ``s``: the units switch of experiments/dtu_rig_units.

    python experiments/dtu_rig_units/scaled_world.py SCENE OUT --scale S
    gsbench eval --mesh RUN/mesh.ply --scene OUT --frame normalised --evaluator dtu_chamfer

Scaling the whole world (object, table, room, cameras) by ``s`` about DTU's origin leaves every image and the
normalised frame that a method trains in unchanged: IDR's normalisation ``x_norm = scale_mat⁻¹ x_mm`` absorbs it.
So a trained run's mesh (written in the normalised frame) is the same mesh, and only its evaluation in millimetres
changes. In OUT:

- ``cameras.npz``: ``scale_mat' = diag(s, s, s, 1) scale_mat`` and ``world_mat' = world_mat diag(1/s, 1/s, 1/s, 1)``,
  so ``world_mat' scale_mat' = world_mat scale_mat`` (the normalised projections) to rounding;
- ``Points/stl``, ``gt_mesh.ply``, ``gt_scene_mesh.ply``: points times ``s``;
- ``ObsMask``: the same voxels with ``BB`` and ``Res`` times ``s``; ``Plane``: ``P = (n, d)`` becomes ``(n, s d)``;
- every other file and folder (images, masks, the COLMAP model in the normalised frame, the metadata): a link.

The DTU protocol's own constants stay in millimetres (its 0.2 mm sampling of the mesh, its 20 mm outlier cap), as
they do on every DTU scan: those are what the switch measures.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import trimesh
from scipy.io import loadmat

from gsbench.data.dtu import dtu_gt_paths, scan_number
from gsbench.data.meta import read_meta
from gsbench.data.synthetic.generator import save_mat
from gsbench.errors import DataError

SCALED = {"cameras.npz", "Points", "ObsMask", "gt_mesh.ply", "gt_scene_mesh.ply"}  # written here; the rest linked


def scaled_cameras(npz: Path, s: float) -> dict[str, np.ndarray]:
    """The ``cameras.npz`` arrays of a world scaled by ``s`` (module docstring)."""
    down, up = np.diag([1 / s, 1 / s, 1 / s, 1.0]), np.diag([s, s, s, 1.0])
    with np.load(npz) as data:
        return {k: (v @ down if k.startswith("world_mat_") else up @ v if k.startswith("scale_mat_") else v)
                for k, v in data.items()}


def scale_ply(source: Path, target: Path, s: float) -> None:
    """A point cloud or mesh with its vertices times ``s``, faces unchanged."""
    geometry = trimesh.load(source, process=False)
    geometry.vertices = np.asarray(geometry.vertices) * s
    target.parent.mkdir(parents=True, exist_ok=True)
    geometry.export(target)


def write_scaled_scene(scene: Path, out: Path, s: float) -> None:
    """OUT as the module docstring says; refused when OUT exists or SCENE is no DTU layout with its ground truth."""
    if not s > 0:
        raise DataError(f"--scale {s}: must be positive")
    if out.exists():
        raise DataError(f"{out}: exists; fix: give a new folder")
    scan = scan_number(scene, read_meta(scene))
    paths = dtu_gt_paths(scene, scan)
    for path in (scene / "cameras.npz", paths["STL points"], paths["ObsMask"], paths["Plane"]):
        if not path.is_file():
            raise DataError(f"{path}: not found; fix: give a DTU-layout scene with its ground truth (a synthetic one)")
    out.mkdir(parents=True)
    for entry in scene.iterdir():
        if entry.name not in SCALED:
            os.symlink(entry.resolve(), out / entry.name)
    np.savez(out / "cameras.npz", **scaled_cameras(scene / "cameras.npz", s))
    for name in ("gt_mesh.ply", "gt_scene_mesh.ply"):
        if (scene / name).is_file():
            scale_ply(scene / name, out / name, s)
    target = dtu_gt_paths(out, scan)
    scale_ply(paths["STL points"], target["STL points"], s)
    obs = loadmat(paths["ObsMask"])
    target["ObsMask"].parent.mkdir()
    save_mat(target["ObsMask"], {"ObsMask": obs["ObsMask"], "BB": obs["BB"] * s, "Res": obs["Res"] * s},
             do_compression=True)
    plane = loadmat(paths["Plane"])["P"].astype(float)
    plane[3] *= s
    save_mat(target["Plane"], {"P": plane})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--scale", type=float, required=True, help="s: the new world's millimetres per old millimetre")
    args = parser.parse_args()
    write_scaled_scene(args.scene, args.out, args.scale)
    print(f"{args.out}: {args.scene} with its world scaled by {args.scale:g}")


if __name__ == "__main__":
    main()
