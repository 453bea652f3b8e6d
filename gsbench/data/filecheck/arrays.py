"""The array files of the DTU and TnT layouts: NPZ archives, MATLAB files, 4x4 text matrices, crop volumes
and trajectories (`gsbench.data.filecheck`)."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
from scipy.io import whosmat

from gsbench.data.filecheck.common import damaged
from gsbench.errors import DataError


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


def check_mat(path: Path, names: tuple[str, ...], fix: str) -> None:
    """A MATLAB ``.mat`` file whose headers list the variables ``names`` (`scipy.io.whosmat`, no data read)."""
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
