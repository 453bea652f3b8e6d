"""A board's records in one file, ``records.jsonl.gz``: a line per run record and per sweep manifest.

A line is ``{"path": P, "record": R}`` or ``{"path": P, "manifest": M}``: P is where the file lies in a runs
folder (``dtu/spot/2dgs/<run_id>/record.json``, ``sweeps/<name>.json``), R or M its JSON object unchanged.
Lines are sorted by path and the gzip header holds no time or name, so the same records give the same bytes.
"""

from __future__ import annotations

import gzip
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

from gsbench.atomic import atomic_path
from gsbench.errors import GsbenchError

RECORDS_FILE = "records.jsonl.gz"
KINDS = ("record", "manifest")


@dataclass
class BoardRecords:
    """path -> JSON object, for the records and for the sweep manifests; ``warnings`` name the unreadable lines."""

    records: dict[str, object] = field(default_factory=dict)
    manifests: dict[str, object] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def board_file(path) -> Path | None:
    """The records file that ``path`` names: itself when it is a file, ``path/records.jsonl.gz`` when that
    exists; None for a folder without one (a runs folder)."""
    path = Path(path)
    if path.is_file():
        return path
    return path / RECORDS_FILE if (path / RECORDS_FILE).is_file() else None


def read_board(path) -> BoardRecords:
    """The records and manifests of the file at ``path`` (gzip or plain JSON Lines); a damaged line is a warning
    naming the file and line, a file that cannot be read at all a GsbenchError."""
    path = Path(path)
    try:
        raw = path.read_bytes()
        text = (gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw).decode("utf-8")
    except (OSError, EOFError, gzip.BadGzipFile, UnicodeDecodeError) as exc:
        raise GsbenchError(f"{path}: cannot read the board's records ({type(exc).__name__}: {exc}); fix: restore "
                           f"it from git (git checkout -- {path})") from exc
    board = BoardRecords()
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
            kind = next(k for k in KINDS if k in entry)
            (board.records if kind == "record" else board.manifests)[str(entry["path"])] = entry[kind]
        except (ValueError, TypeError, KeyError, StopIteration) as exc:
            board.warnings.append(f"{path}:{number}: unreadable line skipped ({type(exc).__name__}: {exc}; "
                                  "expected {\"path\": ..., \"record\" or \"manifest\": ...})")
    return board


def write_board(path, board: BoardRecords) -> None:
    """Write ``board`` to ``path`` atomically (module docstring); its warnings are not written."""
    entries = [{"path": p, "record": r} for p, r in board.records.items()]
    entries += [{"path": p, "manifest": m} for p, m in board.manifests.items()]
    lines = "".join(json.dumps(entry, ensure_ascii=False, separators=(",", ":")) + "\n"
                    for entry in sorted(entries, key=lambda e: e["path"]))
    buffer = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buffer, mtime=0, compresslevel=9) as stream:
        stream.write(lines.encode("utf-8"))
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getvalue())
