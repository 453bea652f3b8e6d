"""Merge finished runs' records into a board's records file, machine paths made relative; or write them back out.

    python tools/commit_records.py RUNS_DIR BOARD [--sweep FILE ...] [--suite NAME] [--seeds SEED ...]
    python tools/commit_records.py --extract BOARD RUNS_DIR

BOARD is ``docs/results/<board>`` (its ``records.jsonl.gz``, `gsbench.report.records_file`) or the file itself.
Every ``record.json`` under ``RUNS_DIR`` (with ``--sweep``: only the runs of those sweep files, expanded as
``gsbench sweep FILE --dry-run [--suite NAME] [--seeds SEED ...]`` lists them) enters the file at its path in
the runs folder, replacing the record of the same run id, with one change (docs/results/README.md): the runs folder
becomes ``.``, the data cache (``$GSBENCH_DATA``) the text ``$GSBENCH_DATA``, and a failed run's traceback names
its files from the checkout (``gsbench/...``) or the installed packages (``site-packages/...``). Unfinished runs
(no record, or status ``interrupted``: it resumes) are left out. The sweeps' manifests (``RUNS_DIR/sweeps/``: of
the given sweep files, else all) enter it the same way, a committed one keeping its entries for runs the new one
lacks (a sweep run a seed at a time). The file is rewritten atomically.

``--extract`` writes each record and manifest of BOARD to its path under RUNS_DIR, leaving files already there
(``cp -n``), so a sweep run into RUNS_DIR skips the board's finished runs.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from gsbench.atomic import atomic_path
from gsbench.data.cache import cache_dir
from gsbench.report.records_file import RECORDS_FILE, BoardRecords, read_board, write_board
from gsbench.runs.sweep import expand, load_sweep, merge_manifest_runs, with_suite

TRACEBACK_FOLDER = re.compile(r'File "[^"]*?/(gsbench|site-packages)/')  # the machine's part of a traceback's path


def relative(value, runs: str, cache: str):
    """``value`` with the runs folder and the data cache in every string made relative (module docstring)."""
    if isinstance(value, dict):
        return {k: relative(v, runs, cache) for k, v in value.items()}
    if isinstance(value, list):
        return [relative(v, runs, cache) for v in value]
    if isinstance(value, str):
        if value == runs:
            return "."
        return TRACEBACK_FOLDER.sub(r'File "\1/', value.replace(runs + "/", "").replace(cache, "$GSBENCH_DATA"))
    return value


def sweep_runs(files: list[Path], suite: str | None = None, seeds=None) -> set[str] | None:
    """Run ids of every run of the sweep ``files``, each on ``suite`` and ``seeds`` when given, as `gsbench sweep`
    overrides them (None: every run)."""
    if not files:
        return None
    return {run.run_id for file in files for run in expand(with_suite(load_sweep(file), suite, seeds))}


def records_path(board: Path) -> Path:
    """The records file of ``board``: a board folder's ``records.jsonl.gz``, or ``board`` when it names a ``.gz``."""
    return board if board.name.endswith(".gz") else board / RECORDS_FILE


def commit(runs_dir: Path, board: Path, sweeps: list[Path], suite: str | None, seeds) -> tuple[int, int]:
    """Merge the finished records and the manifests of ``runs_dir`` into ``board``'s file; (records, manifests)."""
    target = records_path(board)
    committed = read_board(target) if target.is_file() else None
    if committed is not None and committed.warnings:
        raise SystemExit(f"{target}: {len(committed.warnings)} unreadable lines ({committed.warnings[0]}); fix: "
                         "restore it from git before committing more records")
    merged = committed or BoardRecords()
    runs, cache = str(runs_dir.resolve()), str(cache_dir().resolve())
    wanted = sweep_runs(sweeps, suite, seeds)
    copied = 0
    for path in sorted(runs_dir.resolve().rglob("record.json")):
        record = json.loads(path.read_text())
        if record.get("status") == "interrupted" or (wanted is not None and record.get("run_id") not in wanted):
            continue
        merged.records = {p: r for p, r in merged.records.items()
                          if not isinstance(r, dict) or r.get("run_id") != record.get("run_id")}
        merged.records[path.relative_to(runs).as_posix()] = relative(record, runs, cache)
        copied += 1
    names = [load_sweep(file)["name"] for file in sweeps]
    manifests = [runs_dir / "sweeps" / f"{name}.json" for name in names] if names else \
        sorted((runs_dir / "sweeps").glob("*.json"))
    manifests = [path for path in manifests if path.is_file()]
    for path in manifests:
        key = f"sweeps/{path.name}"
        manifest = relative(json.loads(path.read_text()), runs, cache)
        manifest["runs"] = merge_manifest_runs(list((merged.manifests.get(key) or {}).get("runs", [])),
                                               manifest["runs"])
        merged.manifests[key] = manifest
    write_board(target, merged)
    return copied, len(manifests)


def extract(board: Path, runs_dir: Path) -> int:
    """Write ``board``'s records and manifests under ``runs_dir`` where no file is; the number written."""
    contents = read_board(records_path(board))
    written = 0
    for rel, data in [*contents.records.items(), *contents.manifests.items()]:
        target = runs_dir / rel
        if target.exists():
            continue
        with atomic_path(target) as tmp:
            tmp.write_text(json.dumps(data, indent=2) + "\n")
        written += 1
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="RUNS_DIR (or with --extract, BOARD)")
    parser.add_argument("target", type=Path, help="BOARD (or with --extract, RUNS_DIR)")
    parser.add_argument("--extract", action="store_true", help="write the board's records under RUNS_DIR")
    parser.add_argument("--sweep", action="append", default=[], type=Path, help="a sweep file (repeatable)")
    parser.add_argument("--suite", default=None, help="run every sweep file on this suite (as gsbench sweep --suite)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="and with these seeds (gsbench sweep --seeds)")
    args = parser.parse_args()
    if args.extract:
        print(f"{extract(args.source, args.target)} files written under {args.target}")
        return
    copied, manifests = commit(args.source, args.target, args.sweep, args.suite, args.seeds)
    print(f"{copied} records and {manifests} sweep manifests merged into {records_path(args.target)}")


if __name__ == "__main__":
    main()
