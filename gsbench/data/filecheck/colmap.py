"""COLMAP models: binary files walked record by record against their size, and the file and line of a
text model's first error (`gsbench.data.filecheck`)."""

from __future__ import annotations

import struct
from pathlib import Path

from gsbench.data.filecheck.common import PastEnd, all_equal, close_buffer, damaged, mapped
from gsbench.errors import DataError

COLMAP_FIX = "re-export the COLMAP model (e.g. colmap model_converter, or re-run the reconstruction)"


# Parameter count of each COLMAP camera model id (colmap/sensor/models.h; pycolmap 4.x).
COLMAP_MODEL_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16, 12: 4, 13: 5,
                       14: 3, 15: 4, 16: 6, 17: 2}


COLMAP_MODEL_NAMES = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
                      "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6, "FOV": 7, "SIMPLE_RADIAL_FISHEYE": 8,
                      "RADIAL_FISHEYE": 9, "THIN_PRISM_FISHEYE": 10, "RAD_TAN_THIN_PRISM_FISHEYE": 11,
                      "SIMPLE_DIVISION": 12, "DIVISION": 13, "SIMPLE_FISHEYE": 14, "FISHEYE": 15, "EUCM": 16,
                      "EQUIRECTANGULAR": 17}


COLMAP_FILES = ("cameras", "images", "points3D")


COLMAP_OPTIONAL = ("rigs", "frames")  # pycolmap >= 3.12 writes and reads them when present


_U32 = struct.Struct("<I")


_U64 = struct.Struct("<Q")


_CAMERA = struct.Struct("<IiQQ")


def _walk_cameras(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + _CAMERA.size > size:
            raise PastEnd(i)
        _, model_id, _, _ = _CAMERA.unpack_from(buf, off)
        params = COLMAP_MODEL_PARAMS.get(model_id)
        if params is None:
            raise PastEnd(i, f"has unknown camera model id {model_id} (known: 0-{max(COLMAP_MODEL_PARAMS)})")
        off += _CAMERA.size + 8 * params
        if off > size:
            raise PastEnd(i)
    return off


def _walk_images(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + 64 > size:  # image id u32, qvec 4 f64, tvec 3 f64, camera id u32
            raise PastEnd(i)
        end = buf.find(b"\0", off + 64)
        if end < 0:
            raise PastEnd(i, "has an image name without its terminating NUL byte before the end of the file")
        if end + 9 > size:
            raise PastEnd(i)
        (count,) = _U64.unpack_from(buf, end + 1)
        off = end + 9 + 24 * count  # per point2D: x f64, y f64, point3D id u64
        if off > size:
            raise PastEnd(i)
    return off


def _walk_points3d(buf, n: int, size: int) -> int:
    # id u64, xyz 3 f64, rgb 3 u8, error f64 (43 bytes), track length u64, then length x (image id, point2D idx)
    if n == 0:
        return 8
    (first,) = _U64.unpack_from(buf, 8 + 43) if size >= 8 + 51 else (None,)
    if first is not None and size == 8 + n * (51 + 8 * first) and all_equal(buf, 8, n, 51 + 8 * first, 43, "<u8", first):
        return size  # every track has the same length (e.g. none): one vectorised test
    off = 8
    unpack = _U64.unpack_from
    i = 0
    try:
        for i in range(n):
            off += 51 + 8 * unpack(buf, off + 43)[0]
            if off > size:
                raise PastEnd(i)
    except struct.error:
        raise PastEnd(i) from None
    return off


def _walk_rigs(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + 8 > size:
            raise PastEnd(i)
        (sensors,) = _U32.unpack_from(buf, off + 4)
        off += 8 + (8 if sensors > 0 else 0)
        if sensors > 1 and off + 9 * (sensors - 1) > size:
            raise PastEnd(i)
        for _ in range(max(0, sensors - 1)):  # sensor type i32, id u32, has_pose u8 [, 7 f64]
            if off + 9 > size:
                raise PastEnd(i)
            off += 9 + (56 if buf[off + 8] else 0)
        if off > size:
            raise PastEnd(i)
    return off


def _walk_frames(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + 68 > size:  # frame id u32, rig id u32, 7 f64, data id count u32
            raise PastEnd(i)
        (count,) = _U32.unpack_from(buf, off + 64)
        off += 68 + 16 * count  # per data id: sensor type i32, sensor id u32, id u64
        if off > size:
            raise PastEnd(i)
    return off


_COLMAP_WALKERS = {"cameras": (_walk_cameras, 24 + 16), "images": (_walk_images, 73), "points3D": (_walk_points3d, 51),
                   "rigs": (_walk_rigs, 8), "frames": (_walk_frames, 68)}


def check_colmap_binary(path: Path) -> int:
    """Check a COLMAP ``cameras/images/points3D/rigs/frames.bin`` against its size (module docstring);
    returns its record count, raises `DataError` naming the file."""
    path = Path(path)
    stem = path.stem
    walk, min_record = _COLMAP_WALKERS[stem]
    buf, size = mapped(path)
    try:
        if size < 8:
            raise damaged(path, f"the file has {size} bytes, fewer than the 8-byte record count (truncated?)", COLMAP_FIX)
        (n,) = _U64.unpack_from(buf, 0)
        if n * min_record > size - 8:
            raise damaged(path, f"its header says {n} records (at least {n * min_record} bytes) but only {size - 8} bytes "
                          f"follow (truncated, or not a COLMAP {path.name}?)", COLMAP_FIX)
        try:
            end = walk(buf, n, size)
        except PastEnd as exc:
            raise damaged(path, f"record {exc.record + 1} of {n} {exc.detail}"
                          + (" (truncated?)" if "past the end" in exc.detail else ""), COLMAP_FIX) from None
        if end != size:
            raise damaged(path, f"{size - end} bytes are left after the last of its {n} records (wrong record count, "
                          f"or not a COLMAP {path.name}?)", COLMAP_FIX)
        return n
    finally:
        close_buffer(buf)


def colmap_model_files(sparse_dir: Path) -> tuple[str, list[Path]]:
    """``("bin" | "txt", files)``: the model files pycolmap will read (all three ``.bin`` if present,
    else all three ``.txt``; plus rigs/frames of that kind when present). Raises when neither is complete."""
    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        raise DataError(f"{sparse_dir}: COLMAP model folder not found; fix: put the COLMAP model (cameras, images, "
                        "points3D .bin or .txt) in sparse/0")
    for ext in ("bin", "txt"):
        if all((sparse_dir / f"{stem}.{ext}").is_file() for stem in COLMAP_FILES):
            files = [sparse_dir / f"{stem}.{ext}" for stem in COLMAP_FILES + COLMAP_OPTIONAL]
            return ext, [p for p in files if p.is_file()]
    found = sorted(p.name for p in sparse_dir.iterdir())
    raise DataError(f"{sparse_dir}: not a COLMAP model: it needs cameras, images and points3D all .bin or all .txt, "
                    f"found {found[:10]}{' ...' if len(found) > 10 else ''}; fix: re-export the COLMAP model into it")


def check_colmap_model(sparse_dir: Path) -> str:
    """Check every binary file pycolmap will read (`check_colmap_binary`); returns ``bin`` or ``txt``."""
    kind, files = colmap_model_files(sparse_dir)
    if kind == "bin":
        for path in files:
            check_colmap_binary(path)
    return kind


def _floats(tokens) -> bool:
    try:
        [float(t) for t in tokens]
    except ValueError:
        return False
    return True


def _ints(tokens) -> bool:
    return all(t.lstrip("-").isdigit() for t in tokens)


def _text_lines(path: Path):
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, line in enumerate(f, start=1):
            yield number, line.strip()


def _camera_line(tokens) -> str:
    if len(tokens) < 4 or not _ints([tokens[0], tokens[2], tokens[3]]):
        return "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"
    count = COLMAP_MODEL_PARAMS.get(COLMAP_MODEL_NAMES.get(tokens[1], -1))
    if count is None:
        return f"unknown camera model {tokens[1]!r}"
    if len(tokens) - 4 != count or not _floats(tokens[4:]):
        return f"model {tokens[1]} needs {count} numeric parameters, found {tokens[4:]}"
    return ""


def locate_colmap_text_error(sparse_dir: Path) -> str:
    """``<file>:<line>: <problem>`` for the first malformed line of a text model's cameras, images or
    points3D file (what pycolmap could not parse), or ``""`` when none is found there."""
    sparse_dir = Path(sparse_dir)
    path = sparse_dir / "cameras.txt"
    records = 0
    for number, line in _text_lines(path):
        if line and not line.startswith("#"):
            records += 1
            if problem := _camera_line(line.split()):
                return f"{path}:{number}: {problem}"
    if not records:
        return f"{path}: no camera lines (empty or truncated?)"
    path = sparse_dir / "images.txt"
    lines = _text_lines(path)
    records = 0
    for number, line in lines:
        if not line or line.startswith("#"):
            continue
        records += 1
        tokens = line.split()
        if len(tokens) < 10 or not (_ints([tokens[0], tokens[8]]) and _floats(tokens[1:8])):
            return f"{path}:{number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"
        second = next(lines, None)
        if second is None:
            return f"{path}:{number}: image {tokens[0]} has no POINTS2D line after it (truncated?)"
        points = second[1].split()
        if len(points) % 3 or not _floats(points):
            return f"{path}:{second[0]}: expected POINTS2D[] as (X, Y, POINT3D_ID) triples"
    if not records:
        return f"{path}: no image lines (empty or truncated?)"
    path = sparse_dir / "points3D.txt"
    for number, line in _text_lines(path):
        if not line or line.startswith("#"):
            continue
        tokens = line.split()
        if len(tokens) < 8 or (len(tokens) - 8) % 2 or not _floats(tokens):
            return f"{path}:{number}: expected POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX) pairs"
    return ""


def colmap_text_count_problem(sparse_dir: Path, cameras: int, points: int) -> str:
    """``<file>: ...`` when the ``# Number of cameras/points: N`` comment COLMAP writes at the top of
    cameras.txt / points3D.txt disagrees with what pycolmap read (a text file cut at a line boundary
    reads without an error), else ``""``."""
    for stem, label, found in (("cameras", "cameras", cameras), ("points3D", "points", points)):
        path = Path(sparse_dir) / f"{stem}.txt"
        for _, line in _text_lines(path):
            if not line.startswith("#"):
                break
            words = line.replace(",", " ").split()
            if words[1:3] == ["Number", "of"] and len(words) > 4 and words[3] == f"{label}:" and words[4].isdigit():
                if int(words[4]) != found:
                    return f"{path}: its header says {words[4]} {label} but {found} were read (truncated?)"
                break
    return ""
