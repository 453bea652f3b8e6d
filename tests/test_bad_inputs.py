"""Damaged input files: every loader fails within seconds, with a one-line GsbenchError naming the file.

Each case damages a copy of a generated scene (hard links, so a damaged file is always written anew)
and loads it in a forked child with a time and memory bound (`bounded_call.bounded`), so a reader that
hangs (pycolmap on a truncated points3D.bin did) fails the test instead of hanging the suite.
Scenes: synthetic/spot (IDR DTU layout, the session's ``tiny_spot``) and synthetic/spot-tnt (TnT
layout, COLMAP binary model), both at 64x48.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from bounded_call import bounded

from gsbench.data.loader import check_scene, load_scene
from gsbench.data.synthetic.make import make_scene

TIMEOUT = 10.0  # seconds a load may take before it counts as a hang
SCAN = 1001


@pytest.fixture(scope="module")
def tnt_src(tmp_path_factory):
    return make_scene("synthetic/spot-tnt", out=tmp_path_factory.mktemp("bad") / "spot-tnt", res=(64, 48))


@pytest.fixture
def dtu(tiny_spot, tmp_path):
    return _copy(tiny_spot, tmp_path / "spot")


@pytest.fixture
def tnt(tnt_src, tmp_path):
    return _copy(tnt_src, tmp_path / "spot-tnt")


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=os.link)
    return dst


def _write(path: Path, data: bytes) -> None:
    """Replace a (hard-linked) file with ``data``."""
    path.unlink()
    path.write_bytes(data)


def _damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "half":
        data = data[: len(data) // 2]
    elif how == "empty":
        data = b""
    elif how == "garbage":
        data = np.random.default_rng(len(data)).integers(0, 256, max(len(data), 64), dtype=np.uint8).tobytes()
    elif how == "trailing":
        data = data + b"\0" * 7
    else:
        raise ValueError(how)
    _write(path, data)


def _expect(fn, *args, named: Path, fragments=(), **kwargs) -> str:
    """``fn(*args)`` fails within TIMEOUT with a one-line GsbenchError naming ``named``."""
    out = bounded(fn, *args, timeout=TIMEOUT, **kwargs)
    assert out.kind != "timeout", f"{fn.__name__} on {named} did not finish within {TIMEOUT} s"
    assert out.kind == "error" and out.gsbench, f"expected a GsbenchError naming {named}, got {out}"
    assert "\n" not in out.message, out.message
    assert str(named) in out.message, out.message
    for fragment in fragments:
        assert fragment in out.message, out.message
    return out.message


def _check_scene_error(root: Path) -> None:
    """`check_scene` reports (does not raise) errors: raise the first so `_expect` sees it."""
    from gsbench.errors import DataError

    report = check_scene(root)
    if report["errors"]:
        raise DataError(report["errors"][0])
    return report["ok"]


def _header_only(root: Path):
    return load_scene(root, load_images=False)


# ---- COLMAP ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("how", ["half", "empty", "garbage", "trailing"])
@pytest.mark.parametrize("stem", ["cameras", "images", "points3D", "rigs", "frames"])
def test_colmap_binary_damaged(tnt, stem, how):
    path = tnt / "sparse" / "0" / f"{stem}.bin"
    _damage(path, how)
    _expect(_header_only, tnt, named=path, fragments=("is damaged", "fix:"))


def test_colmap_points_with_tracks_walked(tmp_path):
    """Variable-length tracks: a valid file passes, a cut one names the record, a long count fails fast."""
    from gsbench.data.filecheck.colmap import check_colmap_binary
    from gsbench.errors import DataError

    rng = np.random.default_rng(0)
    records = []
    for k in range(1, 2001):
        track = int(rng.integers(0, 6))
        records.append(struct.pack("<Q3d3BdQ", k, 0.0, 1.0, 2.0, 1, 2, 3, 0.5, track)
                       + np.arange(2 * track, dtype="<i4").tobytes())
    path = tmp_path / "points3D.bin"
    path.write_bytes(struct.pack("<Q", len(records)) + b"".join(records))
    assert check_colmap_binary(path) == 2000
    _write(path, path.read_bytes()[:-4])
    with pytest.raises(DataError, match="record 2000 of 2000 runs past the end"):
        check_colmap_binary(path)
    _write(path, struct.pack("<Q", 2000) + records[0][:43] + struct.pack("<Q", 2**60) + b"\0" * 200_000)
    with pytest.raises(DataError, match="record 1 of 2000 runs past the end"):
        check_colmap_binary(path)


def _patch(path: Path, offset: int, fmt: str, *values) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    _write(path, bytes(data))


def test_colmap_nan_point(tnt):
    sparse = tnt / "sparse" / "0"
    _patch(sparse / "points3D.bin", 8 + 8, "<d", np.nan)
    _expect(_header_only, tnt, named=sparse / "points3D.bin", fragments=("non-finite", "point3D 1"))


@pytest.mark.parametrize("case", ["nan_focal", "nan_pose", "model_id"])
def test_colmap_camera_and_pose_values(tnt, case):
    sparse = tnt / "sparse" / "0"
    if case == "nan_focal":
        _patch(sparse / "cameras.bin", 8 + 24, "<d", np.nan)
        _expect(_header_only, tnt, named=sparse / "cameras.bin", fragments=("non-finite parameters",))
    elif case == "nan_pose":
        _patch(sparse / "frames.bin", 8 + 8 + 8, "<d", np.inf)  # pycolmap >= 3.12: poses live in frames.bin
        _expect(_header_only, tnt, named=sparse / "frames.bin", fragments=("image 000000.png has a non-finite pose",))
    else:
        _patch(sparse / "cameras.bin", 8 + 4, "<i", 99)
        _expect(_header_only, tnt, named=sparse / "cameras.bin", fragments=("unknown camera model id 99",))


def _to_text(tnt: Path) -> Path:
    import pycolmap

    sparse = tnt / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    for p in sparse.glob("*.bin"):
        p.unlink()
    rec.write_text(str(sparse))
    return sparse


@pytest.mark.parametrize("stem,how", [("cameras", "garbage"), ("cameras", "empty"), ("images", "half"),
                                      ("points3D", "half"), ("points3D", "lines")])
def test_colmap_text_damaged(tnt, stem, how):
    path = _to_text(tnt) / f"{stem}.txt"
    if how == "lines":  # cut at a line boundary: pycolmap reads it without an error
        lines = path.read_text().splitlines(keepends=True)
        _write(path, "".join(lines[: len(lines) // 2]).encode())
    else:
        _damage(path, how)
    _expect(_header_only, tnt, named=path, fragments=("fix:",))


def test_colmap_model_incomplete(tnt):
    sparse = tnt / "sparse" / "0"
    (sparse / "images.bin").unlink()
    _expect(_header_only, tnt, named=sparse, fragments=("cameras, images and points3D",))


# ---- DTU: cameras.npz, images, masks --------------------------------------------------------------


@pytest.mark.parametrize("how", ["half", "empty", "garbage", "crc"])
def test_cameras_npz_damaged(dtu, how):
    path = dtu / "cameras.npz"
    if how == "crc":
        data = bytearray(path.read_bytes())
        data[len(data) // 2: len(data) // 2 + 16] = b"\xff" * 16  # inside a stored member's data
        _write(path, bytes(data))
    else:
        _damage(path, how)
    _expect(_header_only, dtu, named=path, fragments=("fix:",))


def _rewrite_npz(path: Path, **changes) -> None:
    data = dict(np.load(path))
    data.update(changes)
    path.unlink()
    np.savez(path, **data)


def test_cameras_npz_nan_is_named(dtu):
    path = dtu / "cameras.npz"
    world = np.load(path)["world_mat_3"].copy()
    world[0, 1] = np.nan
    _rewrite_npz(path, world_mat_3=world)
    _expect(_header_only, dtu, named=path, fragments=("world_mat_3", "camera 3, image 000003.png",
                                                      "non-finite", "nan at [0, 1]"))


def test_cameras_npz_wrong_shape(dtu):
    path = dtu / "cameras.npz"
    _rewrite_npz(path, world_mat_2=np.load(path)["world_mat_2"][:3])
    _expect(_header_only, dtu, named=path, fragments=("world_mat_2", "got shape (3, 4)"))


def test_cameras_npz_lying_header_and_pickle(dtu):
    """A member whose header declares 1e9 doubles (np.load would allocate 8 GB), and a pickled member."""
    path = dtu / "cameras.npz"
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1))
    header["shape"] = (10**9,)
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    members["world_mat_0.npy"] = buf.getvalue() + b"\0" * 128
    path.unlink()
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    _expect(_header_only, dtu, named=path, fragments=("world_mat_0.npy", "declares shape (1000000000,)"))
    path.unlink()
    np.savez(path, **{f"world_mat_{k}": np.eye(4) for k in range(49)}, scale_mat_0=np.array([{"a": 1}], dtype=object))
    _expect(_header_only, dtu, named=path, fragments=("pickled",))


@pytest.mark.parametrize("how", ["half", "empty", "garbage"])
def test_image_damaged(dtu, how):
    path = dtu / "image" / "000005.png"
    _damage(path, how)
    _expect(_header_only, dtu, named=path, fragments=("fix:",))
    _expect(_check_scene_error, dtu, named=path)


def test_truncated_image_fails_full_load_too(dtu):
    path = dtu / "image" / "000007.png"
    _damage(path, "half")
    _expect(load_scene, dtu, named=path)


def test_mask_damaged_and_missing(dtu):
    path = dtu / "mask" / "004.png"
    _damage(path, "half")
    _expect(_header_only, dtu, named=path)
    path.unlink()
    _expect(_header_only, dtu, named=dtu / "mask", fragments=("48 masks for 49 images", "no mask for image 000004.png"))


def _png(width: int, height: int) -> bytes:
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)) + chunk(b"IEND", b"")


def test_image_header_of_a_decompression_bomb(dtu):
    path = dtu / "image" / "000000.png"
    _write(path, _png(100_000, 100_000))
    _expect(_header_only, dtu, named=path, fragments=("unreadable image",))


# ---- ground truth: DTU .ply / .mat, TnT .ply / .json / _trans.txt / .log ------------------------------


def _ply_variants(path: Path, how: str) -> None:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    if how == "header_only":
        _write(path, data[:end])
    elif how == "huge_count":
        header = data[:end].decode()
        count = header.split("element vertex ")[1].split()[0]
        _write(path, header.replace(f"element vertex {count}", "element vertex 100000000000").encode() + data[end:])
    elif how == "no_end_header":
        _write(path, data[: end - 12])
    else:
        _damage(path, how)


@pytest.mark.parametrize("how", ["half", "header_only", "huge_count", "no_end_header", "empty", "garbage"])
def test_dtu_gt_points_damaged(dtu, how):
    path = dtu / "Points" / "stl" / f"stl{SCAN}_total.ply"
    _ply_variants(path, how)
    _expect(_header_only, dtu, named=path, fragments=("is damaged",))


@pytest.mark.parametrize("name,how", [(f"ObsMask{SCAN}_10.mat", "half"), (f"ObsMask{SCAN}_10.mat", "empty"),
                                      (f"Plane{SCAN}.mat", "garbage")])
def test_dtu_obsmask_damaged(dtu, name, how):
    path = dtu / "ObsMask" / name
    _damage(path, how)
    _expect(_header_only, dtu, named=path, fragments=("is damaged",))


@pytest.mark.parametrize("suffix,how", [(".ply", "half"), (".ply", "huge_count"), (".json", "half"), (".json", "class"),
                                        ("_trans.txt", "half"), ("_trans.txt", "nan"), ("_trans.txt", "garbage"),
                                        ("_COLMAP_SfM.log", "half"), ("_COLMAP_SfM.log", "nan"),
                                        ("_COLMAP_SfM.log", "garbage")])
def test_tnt_gt_damaged(tnt, suffix, how):
    path = tnt / f"spot-tnt{suffix}"
    if suffix == ".ply":
        _ply_variants(path, how)
    elif how == "class":
        data = json.loads(path.read_text())
        del data["class_name"]
        _write(path, json.dumps(data).encode())
    elif how == "nan":
        lines = path.read_text().splitlines()
        lines[2] = " ".join(["nan"] + lines[2].split()[1:])
        _write(path, ("\n".join(lines) + "\n").encode())
    else:
        _damage(path, how)
    _expect(_header_only, tnt, named=path, fragments=("is damaged",))


def test_meta_file_damaged(dtu):
    path = dtu / "gsbench_scene.json"
    _damage(path, "half")
    _expect(_header_only, dtu, named=path)


# ---- a mesh given to evaluation ---------------------------------------------------------------------


@pytest.mark.parametrize("how", ["half", "header_only", "huge_count", "empty", "garbage"])
def test_mesh_for_eval_damaged(tiny_spot, tmp_path, how):
    from gsbench.evaluators.geometry import load_geometry

    path = tmp_path / "mesh.ply"
    shutil.copy(tiny_spot / "gt_mesh.ply", path)
    _ply_variants(path, how)
    _expect(load_geometry, path, named=path)


# ---- messages that misled -------------------------------------------------------------------------


def test_scene_given_as_a_file(dtu):
    _expect(_header_only, dtu / "cameras.npz", named=dtu / "cameras.npz", fragments=("is a file; expected a scene folder",))


def test_unknown_builtin_lists_the_builtins():
    message = _expect(_check_scene_error, Path("synthetic/nope"), named="synthetic/nope")
    assert "synthetic/spot" in message and "synthetic/tnt-sky" in message


def test_check_ply_ascii_and_faces(tiny_spot, tmp_path):
    """ASCII records are counted by lines; faces (list properties) are walked, vectorised when every
    face has the same number of corners and one record at a time otherwise."""
    import open3d as o3d

    from gsbench.data.filecheck.ply import check_ply
    from gsbench.errors import DataError

    mesh = o3d.io.read_triangle_mesh(str(tiny_spot / "gt_mesh.ply"))
    for ascii_ in (True, False):
        path = tmp_path / f"mesh-{ascii_}.ply"
        o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=ascii_)
        counts = check_ply(path, "fix it")
        assert counts["vertex"] == len(mesh.vertices) and counts["face"] == len(mesh.triangles)
        _write(path, path.read_bytes()[:-40])
        with pytest.raises(DataError, match="is damaged: .*(lines follow|element face)"):
            check_ply(path, "fix it")
    mixed = tmp_path / "mixed.ply"
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n" \
             "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    faces = struct.pack("<B3i", 3, 0, 1, 2) + struct.pack("<B4i", 4, 0, 1, 2, 3)
    mixed.write_bytes(header.encode() + np.zeros((4, 3), "<f4").tobytes() + faces)
    assert check_ply(mixed, "fix it") == {"vertex": 4, "face": 2}
    _write(mixed, mixed.read_bytes()[:-1])
    with pytest.raises(DataError, match="element face: 2 records need more"):
        check_ply(mixed, "fix it")
