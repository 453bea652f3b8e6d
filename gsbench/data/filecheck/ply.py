"""PLY files: the header, then each element's records against the bytes left (`gsbench.data.filecheck`);
`ply_element_counts` reads the header alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gsbench.data.filecheck.common import all_equal, close_buffer, damaged, mapped
from gsbench.errors import DataError

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


def ply_element_counts(path, fix: str) -> dict[str, int]:
    """``{element: count}`` as a PLY file's header states them (its first `PLY_HEADER_LIMIT` bytes alone, so a
    file of any size answers at once); a damaged header is a `DataError` naming ``fix``."""
    path = Path(path)
    with open(path, "rb") as f:
        _, elements, _ = _ply_header(path, f.read(PLY_HEADER_LIMIT), fix)
    return {name: count for name, count, _ in elements}


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
                same = same and all_equal(buf, offset, count, record, at, order + count_type, length)
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
    buf, size = mapped(path)
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
        close_buffer(buf)
