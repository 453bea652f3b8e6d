"""DTU scenes: the IDR/NeuS layout (``cameras.npz``) and the 2DGS DTU+COLMAP variant.

IDR layout (docs/design.md §2.2)::

    scan{id}/image/*.png            RGB, sorted by name = camera index i
    scan{id}/mask/*.png             object = 255, sorted by name
    scan{id}/cameras.npz            world_mat_i (4x4, rows 0-2 = P = K[R|t] in DTU mm world), scale_mat_i

2DGS variant (docs/design.md §2.3): ``images/``, ``mask/``, ``sparse/0`` (COLMAP, cameras already in the normalised
frame) and optionally ``cameras.npz`` for the way back to millimetres.

Cameras: ``P = (world_mat @ scale_mat)[:3]`` is decomposed into K, R, t as in IDR's
``load_K_Rt_from_P`` but with an RQ decomposition (scipy) instead of OpenCV, so cameras live in the
normalised frame ``x_norm = scale_mat⁻¹ x_mm``; ``Normalisation(scale=scale_mat[0,0],
center=scale_mat[:3,3], radius=1)`` maps back to DTU world (mm).

Pixel convention: IDR/DTU matrices put pixel centres at integer coordinates; gsbench puts them at
``i + 0.5``. Loading adds 0.5 to cx and cy (``K_gs = [[1,0,.5],[0,1,.5],[0,0,1]] K_dtu``); writing
subtracts it (`world_mat`).

Ground truth (kind ``dtu``) is looked up in ``gt_root`` (``--gt``) if given, else in the scene folder,
else in its parent: ``Points/stl/stl{scan:03d}_total.ply`` and ``ObsMask/``. The scan number comes from the
meta file or the folder name ``scan{id}``. The GT files found are checked at load
(`check_dtu_ground_truth`: PLY header against the file size, the .mat variables), so a damaged ground
truth fails before training rather than at evaluation.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from scipy.linalg import rq

from gsbench.data.camera import Camera, GroundTruth, Normalisation, Scene
from gsbench.data.colmap import colmap_image_paths, read_colmap_model
from gsbench.data.filecheck.arrays import check_mat, check_npz
from gsbench.data.filecheck.common import damaged
from gsbench.data.filecheck.ply import check_ply
from gsbench.data.images import image_size, list_images, read_views
from gsbench.data.meta import optional_dir, read_meta
from gsbench.data.resolution import fit_downscale
from gsbench.errors import DataError

PIXEL_SHIFT = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])


def decompose_projection(P: np.ndarray, source: str = "P") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split a 3x4 projection ``P ~ K [R | t]`` into K (upper triangular, positive diagonal,
    ``K[2,2] = 1``), a rotation R (det +1) and t.

    RQ decomposition of ``M = P[:, :3]`` (scipy.linalg.rq), then signs moved from K into R so K has
    a positive diagonal; P is defined up to scale, so when det(R) = -1 the whole of P is negated.
    ``source`` names the file/key in error messages.
    """
    P = np.asarray(P, dtype=np.float64)
    if P.shape != (3, 4) or not np.all(np.isfinite(P)):
        raise DataError(f"{source}: projection matrix must be a finite 3x4 array, got {P.tolist()}; fix: regenerate the cameras")
    M = P[:, :3]
    sv = np.linalg.svd(M, compute_uv=False)
    if sv[-1] <= 1e-12 * sv[0]:
        raise DataError(f"{source}: projection matrix has rank < 3 (singular values {sv.tolist()}); fix: regenerate the cameras")
    K, R = rq(M)
    signs = np.sign(np.diag(K))
    K, R = K * signs, signs[:, None] * R
    if np.linalg.det(R) < 0:
        P, R = -P, -R
    t = np.linalg.solve(K, P[:, 3])
    K = K / K[2, 2]
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataError(f"{source}: decomposed focal length is not positive (K={K.tolist()}); fix: regenerate the cameras")
    return K, R, t


def world_mat(camera: Camera) -> np.ndarray:
    """4x4 DTU ``world_mat``: rows 0-2 = ``K_dtu [R|t]`` with integer pixel centres, row 3 = [0,0,0,1]."""
    m = np.eye(4)
    m[:3, :] = np.linalg.solve(PIXEL_SHIFT, camera.K) @ np.hstack([camera.R, camera.t[:, None]])
    return m


def write_cameras_npz(path: Path, cameras_mm: list[Camera], scale_mat: np.ndarray) -> None:
    """Write ``cameras.npz`` with ``world_mat_i`` (cameras in DTU mm world) and ``scale_mat_i``."""
    arrays = {}
    for i, cam in enumerate(cameras_mm):
        arrays[f"world_mat_{i}"] = world_mat(cam)
        arrays[f"scale_mat_{i}"] = scale_mat
    np.savez(path, **arrays)


NPZ_FIX = "replace it with the IDR/VolSDF cameras.npz (world_mat_i and scale_mat_i, 4x4 each)"


def _matrix_problem(m: np.ndarray) -> str:
    """What is wrong with a camera matrix from cameras.npz, or ``""``."""
    if m.shape != (4, 4):
        return f"must be a 4x4 matrix, got shape {m.shape}"
    if not np.all(np.isfinite(m)):
        bad = np.argwhere(~np.isfinite(m))
        entries = ", ".join(f"{m[tuple(ij)]} at [{ij[0]}, {ij[1]}]" for ij in bad[:4])
        return f"contains non-finite values ({entries}{' ...' if len(bad) > 4 else ''})"
    return ""


def read_cameras_npz(path: Path, count: int, names=None) -> tuple[list[np.ndarray], np.ndarray]:
    """Normalised projections ``(world_mat_i @ scale_mat_i)[:3]`` for i < count, and ``scale_mat_0``.

    The archive is checked first (`gsbench.data.filecheck.arrays.check_npz`: a valid zip of plain ``.npy``
    arrays whose sizes match their headers); ``names`` (the image of each camera) go into messages.
    """
    if not path.is_file():
        raise DataError(f"{path}: cameras.npz not found; fix: add the IDR/VolSDF cameras.npz (world_mat_i, scale_mat_i)")
    keys = set(check_npz(path, NPZ_FIX))
    n_world = len([k for k in keys if re.fullmatch(r"world_mat_\d+", k)])
    if n_world != count:
        raise DataError(f"{path}: {n_world} cameras (world_mat_i) but {count} images; fix: one world_mat_i per image")
    projections = []
    try:
        with np.load(path, allow_pickle=False) as data:
            for i in range(count):
                for key in (f"world_mat_{i}", f"scale_mat_{i}"):
                    if key not in keys:
                        raise DataError(f"{path}: {key} missing; fix: add world_mat_i and scale_mat_i for every camera")
                wm, sm = np.asarray(data[f"world_mat_{i}"], float), np.asarray(data[f"scale_mat_{i}"], float)
                for key, m in ((f"world_mat_{i}", wm), (f"scale_mat_{i}", sm)):
                    problem = _matrix_problem(m)
                    if problem:
                        camera = f"camera {i}" + (f", image {names[i]}" if names is not None and i < len(names) else "")
                        raise DataError(f"{path}: {key} ({camera}) {problem}; fix: regenerate cameras.npz")
                projections.append((wm @ sm)[:3])
            scale_mat = np.asarray(data["scale_mat_0"], float)
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001  a member that passed the checks but still cannot be decoded
        raise damaged(path, f"{type(exc).__name__}: {exc}", NPZ_FIX) from exc
    if scale_mat[0, 0] <= 0:
        raise DataError(f"{path}: scale_mat_0 has non-positive scale {scale_mat[0, 0]}; fix: regenerate cameras.npz")
    return projections, scale_mat


def normalisation_from_scale_mat(scale_mat: np.ndarray) -> Normalisation:
    """``x_mm = s x_norm + c`` with ``s = scale_mat[0,0]``, ``c = scale_mat[:3,3]`` (IDR convention)."""
    return Normalisation(scale=float(scale_mat[0, 0]), center=scale_mat[:3, 3].copy(), radius=1.0)


def scan_number(root: Path, meta: dict) -> int | None:
    """The DTU scan number: meta ``scan``, else the folder name ``scan{id}`` / ``dtu_scan{id}``."""
    if meta.get("scan") is not None:
        return int(meta["scan"])
    match = re.search(r"scan(\d+)$", root.name)
    return int(match.group(1)) if match else None


def dtu_gt_paths(root: Path, scan: int) -> dict[str, Path]:
    """The three files of the DTU protocol for ``scan`` under a GT ``root`` (they may not exist)."""
    root = Path(root)
    return {
        "STL points": root / "Points" / "stl" / f"stl{scan:03d}_total.ply",
        "ObsMask": root / "ObsMask" / f"ObsMask{scan}_10.mat",
        "Plane": root / "ObsMask" / f"Plane{scan}.mat",
    }


def dtu_ground_truth(root: Path, scan: int | None, gt_root: Path | None = None) -> tuple[GroundTruth | None, str]:
    """The DTU GT handle if ``Points/stl/stl{scan:03d}_total.ply`` exists in a candidate folder
    (``gt_root``, else the scene folder and its parent), and otherwise None with the reason: the
    files looked for, or that the scan number is unknown."""
    candidates = [Path(gt_root)] if gt_root else [root, root.parent]
    if scan is None:
        return None, (f"no scan number for {root} (the folder is not named scan<N> and has no gsbench_scene.json "
                      "'scan'), so Points/stl/stl<scan>_total.ply cannot be looked up")
    stl = [dtu_gt_paths(cand, scan)["STL points"] for cand in candidates]
    for cand, path in zip(candidates, stl):
        if path.is_file():
            return GroundTruth(kind="dtu", root=cand, name=f"scan{scan}", scan=scan,
                               normal_maps=optional_dir(root / "gt_normal"),
                               depth_maps=optional_dir(root / "gt_depth")), ""
    return None, f"{' or '.join(map(str, stl))} not found"


def _view_key(path: Path):
    """The number in a view's file stem (``000012.png`` and ``012.png`` -> 12), else the stem."""
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else path.stem


def _unmatched(images: list[Path], masks: list[Path]) -> str:
    """Which images have no mask (and which masks no image), matched by the number in their names."""
    image_keys, mask_keys = [_view_key(p) for p in images], [_view_key(p) for p in masks]
    if len(set(image_keys)) != len(image_keys) or len(set(mask_keys)) != len(mask_keys):
        return ""
    def names(paths, keys, others):
        found = [p.name for p, k in zip(paths, keys) if k not in others]
        return ", ".join(found[:5]) + (f" and {len(found) - 5} more" if len(found) > 5 else "")
    lonely_images, lonely_masks = names(images, image_keys, set(mask_keys)), names(masks, mask_keys, set(image_keys))
    parts = ([f"no mask for image {lonely_images}"] if lonely_images else []) + \
            ([f"no image for mask {lonely_masks}"] if lonely_masks else [])
    return "; ".join(parts)


def _mask_paths(root: Path, images: list[Path]) -> list[Path]:
    folder = root / "mask"
    if not folder.is_dir():
        raise DataError(f"{folder}: mask folder not found; fix: add one object mask (PNG, object=255) per image")
    masks = list_images(folder)
    if len(masks) != len(images):
        which = _unmatched(images, masks)
        raise DataError(f"{folder}: {len(masks)} masks for {len(images)} images{f' ({which})' if which else ''}; "
                        "fix: one mask per image, same sort order")
    return masks


def check_dtu_ground_truth(gt: GroundTruth | None) -> None:
    """Header checks of the DTU protocol's files that exist (`gsbench.data.filecheck`), so a damaged
    ground truth fails when the scene is loaded, not after training."""
    if gt is None:
        return
    fix = "re-download the DTU SampleSet (Points/stl and ObsMask) or re-generate the scene"
    paths = dtu_gt_paths(gt.root, gt.scan)
    check_ply(paths["STL points"], fix)
    if paths["ObsMask"].is_file():
        check_mat(paths["ObsMask"], ("ObsMask", "BB", "Res"), fix)
    if paths["Plane"].is_file():
        check_mat(paths["Plane"], ("P",), fix)


def load_dtu(root: Path, *, downscale: float = 1.0, max_size=(), load_images: bool = True,
             gt_root: Path | None = None) -> Scene:
    """Load an IDR-layout DTU scene (see the module docstring); the images are divided by
    `fit_downscale` of ``downscale`` and ``max_size``."""
    root = Path(root)
    folder = root / "image"
    if not folder.is_dir():
        raise DataError(f"{folder}: image folder not found; fix: put the RGB views in image/ (IDR layout)")
    paths = list_images(folder)
    if not paths:
        raise DataError(f"{folder}: no images; fix: put the RGB views (PNG) in image/")
    masks = _mask_paths(root, paths)
    projections, scale_mat = read_cameras_npz(root / "cameras.npz", len(paths), [p.name for p in paths])
    size = image_size(paths[0])
    downscale = fit_downscale(*size, downscale, max_size)
    cameras = []
    for i, (P, path) in enumerate(zip(projections, paths)):
        K, R, t = decompose_projection(P, source=f"{root / 'cameras.npz'} world_mat_{i}")
        cam = Camera(K=PIXEL_SHIFT @ K, R=R, t=t, width=size[0], height=size[1], name=path.name)
        cameras.append(cam if downscale == 1.0 else cam.scaled(1.0 / downscale))
    images, mask_arrays = read_views(paths, masks, [size] * len(paths), downscale, load_images)
    meta = read_meta(root)
    gt, gt_missing = dtu_ground_truth(root, scan_number(root, meta), gt_root)
    check_dtu_ground_truth(gt)
    return Scene(
        name=meta.get("name", root.name), fmt="dtu", root=root, cameras=cameras, images=images, masks=mask_arrays,
        normalisation=normalisation_from_scale_mat(scale_mat), gt=gt, gt_missing=gt_missing,
        image_names=[p.name for p in paths], mask_paths=masks, source_size=tuple(size), downscale=downscale,
    )


def load_dtu_colmap(root: Path, *, downscale: float = 1.0, max_size=(), load_images: bool = True,
                    gt_root: Path | None = None) -> Scene:
    """Load the 2DGS DTU+COLMAP variant: ``images/``, ``mask/``, ``sparse/0``, optional ``cameras.npz``.

    The COLMAP cameras are already normalised; without ``cameras.npz`` the normalisation is the
    identity (metrics then stay in the normalised frame).
    """
    root = Path(root)
    model = read_colmap_model(root / "sparse" / "0")
    paths = colmap_image_paths(root, model.cameras)
    masks = _mask_paths(root, paths)
    npz = root / "cameras.npz"
    norm = (normalisation_from_scale_mat(read_cameras_npz(npz, len(paths), [p.name for p in paths])[1])
            if npz.exists() else Normalisation())
    size = (model.cameras[0].width, model.cameras[0].height)
    downscale = fit_downscale(*size, downscale, max_size)
    images, mask_arrays = read_views(paths, masks, [(c.width, c.height) for c in model.cameras], downscale, load_images)
    cameras = [c if downscale == 1.0 else c.scaled(1.0 / downscale) for c in model.cameras]
    meta = read_meta(root)
    gt, gt_missing = dtu_ground_truth(root, scan_number(root, meta), gt_root)
    check_dtu_ground_truth(gt)
    return Scene(
        name=meta.get("name", root.name), fmt="dtu-colmap", root=root, cameras=cameras, images=images,
        masks=mask_arrays, points=model.points if len(model.points) else None,
        colors=model.colors if len(model.points) else None, normalisation=norm, gt=gt, gt_missing=gt_missing,
        image_names=[p.name for p in paths], mask_paths=masks, source_size=size, downscale=downscale,
    )
