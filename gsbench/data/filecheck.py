"""Fast structural checks of input files, run before a third-party reader (pycolmap, open3d, numpy,
scipy) sees them, so that a damaged file gives a one-line `DataError` naming it instead of a hang, an
unbounded allocation or silently wrong data.

Every check compares what a file's header promises with the file's size, without decoding payloads:

- COLMAP binary models (`check_colmap_binary`): the uint64 record count, then each record's fixed
  part and its variable-length part (points3D tracks, images' names and points2D, cameras' params by
  model id, rigs' sensors, frames' data ids); a record that runs past the end of the file, or bytes
  left after the last record, is an error. pycolmap's reader loops over the count it reads and, on a
  truncated ``points3D.bin``, spins on a failed stream while allocating (observed: ~40 MB/s until
  killed). A points3D file is walked with one Python step per record (0.15-0.3 s for a million
  points with tracks of 2-10, a 99 MB file, on 2 cores), or with one vectorised step when all tracks
  have the same length (e.g. empty, as gsbench writes them: 0.01 s per million).
- COLMAP text models cannot hang pycolmap (it stops at the first line it cannot parse, in
  milliseconds), but its message names neither the file nor the line: `locate_colmap_text_error`
  finds them after pycolmap has failed. A text file cut at a line boundary reads without an error;
  `colmap_text_count_problem` compares the ``# Number of cameras/points`` comment with what was read.
- PLY (`check_ply`): the header (``ply``, ``format``, ``element``/``property`` lines, ``end_header``),
  then for binary formats each element's records against the bytes left (list properties are
  checked vectorised when every list of an element has the same length, else per record), for ASCII
  the number of lines. open3d reads a truncated binary PLY without an error (the missing points come
  back as garbage) and allocates whatever ``element vertex N`` asks for.
- NPZ (`check_npz`): a zip archive whose members are ``.npy`` arrays without pickled objects, each
  member's CRC and size matching the shape and dtype its header declares (so `np.load` neither
  allocates for a lying header nor fails later with an unhandled ``BadZipFile``/``EOFError``).
- MATLAB ``.mat`` (`check_mat`), a 4x4 text matrix (`read_matrix4_text`), an open3d crop volume
  ``.json`` (`check_crop_json`), a TnT ``.log`` (`check_log`): the variables/keys/values the
  evaluators need.

Messages read ``<file> is damaged: <what>; fix: <fix>``.
"""

from __future__ import annotations

import json
import mmap
import struct
import zipfile
from pathlib import Path

import numpy as np

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


def damaged(path, what: str, fix: str) -> DataError:
    """``<path> is damaged: <what>; fix: <fix>`` (one line)."""
    return DataError(f"{path} is damaged: {one_line(what)}; fix: {fix}")


def one_line(text, limit: int = 300) -> str:
    """``text`` with runs of whitespace (newlines included) collapsed, cut to ``limit`` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _PastEnd(Exception):
    def __init__(self, record: int, detail: str = "runs past the end of the file"):
        super().__init__(record)
        self.record, self.detail = record, detail


def _mapped(path: Path):
    """(buffer, size): a read-only mmap of the file (bytes for an empty file)."""
    size = path.stat().st_size
    if size == 0:
        return b"", 0
    with open(path, "rb") as f:
        return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ), size


# ---- COLMAP binary --------------------------------------------------------------------------------


def _walk_cameras(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + _CAMERA.size > size:
            raise _PastEnd(i)
        _, model_id, _, _ = _CAMERA.unpack_from(buf, off)
        params = COLMAP_MODEL_PARAMS.get(model_id)
        if params is None:
            raise _PastEnd(i, f"has unknown camera model id {model_id} (known: 0-{max(COLMAP_MODEL_PARAMS)})")
        off += _CAMERA.size + 8 * params
        if off > size:
            raise _PastEnd(i)
    return off


def _walk_images(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + 64 > size:  # image id u32, qvec 4 f64, tvec 3 f64, camera id u32
            raise _PastEnd(i)
        end = buf.find(b"\0", off + 64)
        if end < 0:
            raise _PastEnd(i, "has an image name without its terminating NUL byte before the end of the file")
        if end + 9 > size:
            raise _PastEnd(i)
        (count,) = _U64.unpack_from(buf, end + 1)
        off = end + 9 + 24 * count  # per point2D: x f64, y f64, point3D id u64
        if off > size:
            raise _PastEnd(i)
    return off


def _all_equal(buf, offset: int, count: int, record: int, at: int, dtype: str, value: int) -> bool:
    """Whether the field ``dtype`` at byte ``at`` of each of ``count`` records of ``record`` bytes from
    ``offset`` equals ``value`` (a strided view, released before returning so the mmap can close)."""
    view = np.ndarray((count,), dtype=np.dtype({"names": ["v"], "formats": [dtype], "offsets": [at], "itemsize": record}),
                      buffer=buf, offset=offset)["v"]
    return bool(np.all(view == value))


def _close(buf) -> None:
    if isinstance(buf, mmap.mmap):
        try:
            buf.close()
        except BufferError:  # a view still referenced from a traceback: the garbage collector closes it
            pass


def _walk_points3d(buf, n: int, size: int) -> int:
    # id u64, xyz 3 f64, rgb 3 u8, error f64 (43 bytes), track length u64, then length x (image id, point2D idx)
    if n == 0:
        return 8
    (first,) = _U64.unpack_from(buf, 8 + 43) if size >= 8 + 51 else (None,)
    if first is not None and size == 8 + n * (51 + 8 * first) and _all_equal(buf, 8, n, 51 + 8 * first, 43, "<u8", first):
        return size  # every track has the same length (e.g. none): one vectorised test
    off = 8
    unpack = _U64.unpack_from
    i = 0
    try:
        for i in range(n):
            off += 51 + 8 * unpack(buf, off + 43)[0]
            if off > size:
                raise _PastEnd(i)
    except struct.error:
        raise _PastEnd(i) from None
    return off


def _walk_rigs(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + 8 > size:
            raise _PastEnd(i)
        (sensors,) = _U32.unpack_from(buf, off + 4)
        off += 8 + (8 if sensors > 0 else 0)
        if sensors > 1 and off + 9 * (sensors - 1) > size:
            raise _PastEnd(i)
        for _ in range(max(0, sensors - 1)):  # sensor type i32, id u32, has_pose u8 [, 7 f64]
            if off + 9 > size:
                raise _PastEnd(i)
            off += 9 + (56 if buf[off + 8] else 0)
        if off > size:
            raise _PastEnd(i)
    return off


def _walk_frames(buf, n: int, size: int) -> int:
    off = 8
    for i in range(n):
        if off + 68 > size:  # frame id u32, rig id u32, 7 f64, data id count u32
            raise _PastEnd(i)
        (count,) = _U32.unpack_from(buf, off + 64)
        off += 68 + 16 * count  # per data id: sensor type i32, sensor id u32, id u64
        if off > size:
            raise _PastEnd(i)
    return off


_COLMAP_WALKERS = {"cameras": (_walk_cameras, 24 + 16), "images": (_walk_images, 73), "points3D": (_walk_points3d, 51),
                   "rigs": (_walk_rigs, 8), "frames": (_walk_frames, 68)}


def check_colmap_binary(path: Path) -> int:
    """Check a COLMAP ``cameras/images/points3D/rigs/frames.bin`` against its size (module docstring);
    returns its record count, raises `DataError` naming the file."""
    path = Path(path)
    stem = path.stem
    walk, min_record = _COLMAP_WALKERS[stem]
    buf, size = _mapped(path)
    try:
        if size < 8:
            raise damaged(path, f"the file has {size} bytes, fewer than the 8-byte record count (truncated?)", COLMAP_FIX)
        (n,) = _U64.unpack_from(buf, 0)
        if n * min_record > size - 8:
            raise damaged(path, f"its header says {n} records (at least {n * min_record} bytes) but only {size - 8} bytes "
                          f"follow (truncated, or not a COLMAP {path.name}?)", COLMAP_FIX)
        try:
            end = walk(buf, n, size)
        except _PastEnd as exc:
            raise damaged(path, f"record {exc.record + 1} of {n} {exc.detail}"
                          + (" (truncated?)" if "past the end" in exc.detail else ""), COLMAP_FIX) from None
        if end != size:
            raise damaged(path, f"{size - end} bytes are left after the last of its {n} records (wrong record count, "
                          f"or not a COLMAP {path.name}?)", COLMAP_FIX)
        return n
    finally:
        _close(buf)


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


# ---- COLMAP text (located after pycolmap failed) -----------------------------------------------------


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


# ---- PLY ------------------------------------------------------------------------------------------

PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
             "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4",
             "float32": "f4", "double": "f8", "float64": "f8"}
PLY_HEADER_LIMIT = 1 << 20


def _ply_header(path: Path, head: bytes, fix: str):
    """(format, [(element, count, [(name, type, list count type or None)])], body offset)."""
    if not head.startswith(b"ply"):
        raise damaged(path, f"it does not start with 'ply' (first bytes {head[:16]!r}: not a PLY file)", fix)
    marker = head.find(b"end_header")
    if marker < 0:
        raise damaged(path, f"no 'end_header' line in its first {len(head)} bytes (truncated header, or not a PLY file)", fix)
    body = marker + len(b"end_header")
    body += 2 if head[body:body + 2] == b"\r\n" else 1 if head[body:body + 1] in (b"\n", b"\r") else 0
    fmt, elements = None, []
    for number, raw in enumerate(head[:marker].decode("ascii", errors="replace").splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            if len(words) < 2 or words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise damaged(path, f"header line {number} {raw.strip()!r} names no known format", fix)
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise damaged(path, f"header line {number} {raw.strip()!r} is not 'element NAME COUNT'", fix)
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            ok = elements and ((len(words) == 3 and words[1] in PLY_TYPES)
                               or (len(words) == 5 and words[1] == "list" and words[2] in PLY_TYPES and words[3] in PLY_TYPES))
            if not ok:
                raise damaged(path, f"header line {number} {raw.strip()!r} is not a property of a known type "
                              "after an element", fix)
            elements[-1][2].append((words[-1], PLY_TYPES[words[-2]], PLY_TYPES[words[2]] if words[1] == "list" else None))
        else:
            raise damaged(path, f"header line {number} {raw.strip()!r} is not a PLY header line", fix)
    if fmt is None:
        raise damaged(path, "its header has no 'format' line", fix)
    return fmt, elements, body


def _list_element_size(buf, offset: int, count: int, props, order: str, left: int):
    """Bytes taken by ``count`` records with list properties starting at ``offset``, or None if they do
    not fit in ``left`` bytes. Vectorised when every list of the element has the length of the first
    record's; otherwise one step per record."""
    def record_layout(at):
        fields, size = [], 0
        for name, dtype, count_type in props:
            if count_type is None:
                fields.append((size, None, None))
                size += np.dtype(dtype).itemsize
                continue
            if at + size + np.dtype(count_type).itemsize > offset + left:
                return None, None
            length = int(np.frombuffer(buf[at + size:at + size + 8], dtype=order + count_type, count=1)[0])
            if length < 0:
                return None, None
            fields.append((size, count_type, length))
            size += np.dtype(count_type).itemsize + length * np.dtype(dtype).itemsize
        return fields, size

    if count == 0:
        return 0
    fields, record = record_layout(offset)
    if fields is None:
        return None
    if count * record <= left:
        same = True
        for at, count_type, length in fields:
            if count_type is not None:
                same = same and _all_equal(buf, offset, count, record, at, order + count_type, length)
        if same:
            return count * record
    at = offset
    for _ in range(count):
        fields, record = record_layout(at)
        if fields is None or at + record > offset + left:
            return None
        at += record
    return at - offset


def check_ply(path: Path, fix: str, need_vertices: bool = True) -> dict[str, int]:
    """Check a PLY file's header against its size (module docstring); returns ``{element: count}``.
    ``need_vertices``: a ``vertex`` element with x, y, z and at least one record is required."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found; fix: {fix}")
    buf, size = _mapped(path)
    try:
        if size == 0:
            raise damaged(path, "the file is empty (0 bytes)", fix)
        fmt, elements, body = _ply_header(path, bytes(buf[:min(size, PLY_HEADER_LIMIT)]), fix)
        counts = {name: count for name, count, _ in elements}
        if need_vertices:
            vertex = next((e for e in elements if e[0] == "vertex"), None)
            if vertex is None or not {"x", "y", "z"} <= {p[0] for p in vertex[2]}:
                raise damaged(path, "it has no 'vertex' element with x, y, z properties", fix)
            if vertex[1] == 0:
                raise damaged(path, "its header says 0 vertices (an empty point cloud)", fix)
        left = size - body
        if fmt == "ascii":
            chunk = 1 << 24  # count newlines 16 MB at a time (no copy of a whole large file)
            lines = sum(buf[at:min(at + chunk, size)].count(b"\n") for at in range(body, size, chunk))
            lines += 1 if left and buf[size - 1:size] != b"\n" else 0
            need = sum(counts.values())
            if lines < need:
                raise damaged(path, f"its header promises {need} records ({counts}) but only {lines} lines follow it "
                              "(truncated?)", fix)
            return counts
        order = "<" if fmt == "binary_little_endian" else ">"
        offset = body
        for name, count, props in elements:
            if all(count_type is None for _, _, count_type in props):
                record = sum(np.dtype(dtype).itemsize for _, dtype, _ in props)
                used = count * record if count * record <= left else None
                detail = f"{count} records of {record} bytes"
            else:
                used = _list_element_size(buf, offset, count, props, order, left)
                detail = f"{count} records"
            if used is None:
                raise damaged(path, f"element {name}: {detail} need more than the {left} bytes left after the header "
                              f"and the elements before it (truncated?)", fix)
            offset += used
            left -= used
        return counts
    finally:
        _close(buf)


# ---- NPZ ------------------------------------------------------------------------------------------


def check_npz(path: Path, fix: str) -> list[str]:
    """Check an ``.npz`` (module docstring); returns its array names."""
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise damaged(path, "the file is empty (0 bytes)", fix)
    if not zipfile.is_zipfile(path):
        raise damaged(path, "it is not an npz (zip) archive (truncated, or another kind of file)", fix)
    names = []
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
            if bad is not None:
                raise damaged(path, f"member {bad} fails its CRC check (corrupted)", fix)
            for info in archive.infolist():
                if not info.filename.endswith(".npy"):
                    raise damaged(path, f"member {info.filename} is not an .npy array", fix)
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read_header(member)
                    header = member.tell()
                if dtype.hasobject:
                    raise damaged(path, f"member {info.filename} holds pickled Python objects, not numbers", fix)
                expected = header + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
                if expected != info.file_size:
                    raise damaged(path, f"member {info.filename} declares shape {shape} {dtype} ({expected} bytes) but "
                                  f"holds {info.file_size} bytes", fix)
                names.append(info.filename[:-4])
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001  BadZipFile, EOFError, zlib.error, ValueError of a bad .npy header
        raise damaged(path, f"{type(exc).__name__}: {exc}", fix) from exc
    return names


# ---- MATLAB, text matrices, crop volumes, trajectories -------------------------------------------


def check_mat(path: Path, names: tuple[str, ...], fix: str) -> None:
    """A MATLAB ``.mat`` file whose headers list the variables ``names`` (`scipy.io.whosmat`, no data read)."""
    from scipy.io import whosmat  # noqa: PLC0415

    path = Path(path)
    if path.stat().st_size == 0:
        raise damaged(path, "the file is empty (0 bytes)", fix)
    try:
        found = {name for name, _, _ in whosmat(str(path))}
    except Exception as exc:  # noqa: BLE001  MatReadError, OSError, ValueError, IndexError of a damaged file
        raise damaged(path, f"scipy.io cannot read its headers ({type(exc).__name__}: {exc})", fix) from exc
    missing = [n for n in names if n not in found]
    if missing:
        raise damaged(path, f"it lacks variable(s) {missing} (found {sorted(found)}; truncated?)", fix)


def _non_finite(m: np.ndarray) -> str:
    bad = np.argwhere(~np.isfinite(m))
    first = tuple(int(v) for v in bad[0])
    return f"{len(bad)} non-finite entr{'y' if len(bad) == 1 else 'ies'} ({m[first]} at {list(first)})"


def read_matrix4_text(path: Path, fix: str) -> np.ndarray:
    """A finite 4x4 matrix written as text (TnT ``{scene}_trans.txt``)."""
    path = Path(path)
    try:
        with np.errstate(all="ignore"):
            m = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise damaged(path, f"it is not a 4x4 text matrix ({exc})", fix) from exc
    if m.shape != (4, 4):
        raise damaged(path, f"expected a 4x4 matrix, found shape {m.shape}", fix)
    if not np.all(np.isfinite(m)):
        raise damaged(path, f"the 4x4 matrix has {_non_finite(m)}", fix)
    return m


def check_log(path: Path, fix: str) -> int:
    """A trajectory ``.log``: blocks of 5 lines ('i i 0' and 4 finite matrix rows); returns the pose count."""
    path = Path(path)
    try:
        rows = [line.split() for line in path.read_text(errors="replace").splitlines() if line.strip()]
    except OSError as exc:
        raise damaged(path, f"unreadable ({exc})", fix) from exc
    if not rows or len(rows) % 5:
        raise damaged(path, f"expected blocks of 5 lines (a header 'i i 0' and 4 matrix rows), found {len(rows)} "
                      "non-empty lines (truncated?)", fix)
    for k in range(0, len(rows), 5):
        block = rows[k + 1:k + 5]
        try:
            pose = np.array([[float(v) for v in row] for row in block])
        except ValueError as exc:
            raise damaged(path, f"pose {k // 5} (lines after header {k + 1}): {exc}", fix) from exc
        if pose.shape != (4, 4):
            raise damaged(path, f"pose {k // 5} is not 4x4 (rows of {[len(r) for r in block]} values)", fix)
        if not np.all(np.isfinite(pose)):
            raise damaged(path, f"pose {k // 5} has {_non_finite(pose)}", fix)
    return len(rows) // 5


def check_crop_json(path: Path, fix: str) -> None:
    """An open3d ``SelectionPolygonVolume`` JSON (open3d returns an empty volume, with only a warning,
    for a file it cannot read)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(errors="replace"))
    except (OSError, ValueError) as exc:
        raise damaged(path, f"not valid JSON ({exc})", fix) from exc
    if not isinstance(data, dict) or data.get("class_name") != "SelectionPolygonVolume":
        raise damaged(path, "not an open3d SelectionPolygonVolume (class_name missing or different)", fix)
    if str(data.get("orthogonal_axis", "")).upper() not in ("X", "Y", "Z"):
        raise damaged(path, f"orthogonal_axis is {data.get('orthogonal_axis')!r}, expected X, Y or Z", fix)
    try:
        lo, hi = float(data["axis_min"]), float(data["axis_max"])
        polygon = np.asarray(data["bounding_polygon"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise damaged(path, f"axis_min, axis_max and bounding_polygon must be numbers ({type(exc).__name__}: {exc})",
                      fix) from exc
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
        raise damaged(path, f"axis range [{lo}, {hi}] is not a finite interval", fix)
    if polygon.ndim != 2 or polygon.shape[1] != 3 or len(polygon) < 3 or not np.all(np.isfinite(polygon)):
        raise damaged(path, f"bounding_polygon must hold at least 3 finite [x, y, z] points, found shape {polygon.shape}", fix)
