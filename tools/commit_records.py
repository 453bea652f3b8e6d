"""Copy finished runs' records into a committed records folder, machine paths made relative.

    python tools/commit_records.py RUNS_DIR RECORDS_DIR [--sweep FILE ...] [--suite NAME] [--seeds SEED ...]

Every ``record.json`` under ``RUNS_DIR`` (only the runs of the given sweep files, expanded as
``gsbench sweep FILE --dry-run [--suite NAME] [--seeds SEED ...]`` lists them, when ``--sweep`` is given)
is written to the same relative place under ``RECORDS_DIR`` with one change (docs/results/README.md): the
runs folder becomes ``.`` (so the run's files are relative to the records folder) and the data cache
(``$GSBENCH_DATA``, default ``~/.cache/gsbench/scenes``) becomes the text ``$GSBENCH_DATA``, and a failed run's
traceback names its files from the checkout (``gsbench/...``) or the installed packages (``site-packages/...``)
instead of the machine's folders; every other field is as the run wrote it. Unfinished runs (no record, or one
with status ``interrupted``: it resumes) are skipped; records already there are replaced. The sweeps' manifests
(``RUNS_DIR/sweeps/<name>.json``: of the given sweep files, else all) go to ``RECORDS_DIR/sweeps`` the same way:
`gsbench report` finds a sweep's rows (its ablation tables and claims) through them. A manifest already there
keeps its entries for runs the new one lacks, as a sweep's own manifest does (a sweep run a seed at a time).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from gsbench.atomic import atomic_path
from gsbench.data.cache import cache_dir
from gsbench.runs.sweep import expand, load_sweep, merge_manifest_runs, read_manifest_runs, with_suite

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path)
    parser.add_argument("records", type=Path)
    parser.add_argument("--sweep", action="append", default=[], type=Path, help="a sweep file (repeatable)")
    parser.add_argument("--suite", default=None, help="run every sweep file on this suite (as gsbench sweep --suite)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="and with these seeds (gsbench sweep --seeds)")
    args = parser.parse_args()
    runs, cache = str(args.runs.resolve()), str(cache_dir().resolve())
    wanted = sweep_runs(args.sweep, args.suite, args.seeds)
    copied = 0
    for path in sorted(args.runs.resolve().rglob("record.json")):
        record = json.loads(path.read_text())
        if record.get("status") == "interrupted" or (wanted is not None and record.get("run_id") not in wanted):
            continue
        target = args.records / path.relative_to(runs)
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            tmp.write_text(json.dumps(relative(record, runs, cache), indent=2, sort_keys=True) + "\n")
        copied += 1
    names = [load_sweep(file)["name"] for file in args.sweep]
    manifests = [args.runs / "sweeps" / f"{name}.json" for name in names] if names else \
        sorted((args.runs / "sweeps").glob("*.json"))
    manifests = [path for path in manifests if path.is_file()]
    for path in manifests:
        target = args.records / "sweeps" / path.name
        target.parent.mkdir(parents=True, exist_ok=True)
        manifest = relative(json.loads(path.read_text()), runs, cache)
        manifest["runs"] = merge_manifest_runs(read_manifest_runs(target), manifest["runs"])
        with atomic_path(target) as tmp:
            tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"{copied} records and {len(manifests)} sweep manifests written under {args.records}")


if __name__ == "__main__":
    main()
