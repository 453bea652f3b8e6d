"""`write_report`: run records -> ``leaderboard.md``, ``leaderboard.csv``, ``index.html`` and ``plots/*.png``
(``gsbench report SOURCE --out DIR``; docs/report.md says what each section shows).

The Markdown and CSV hold no time stamps or absolute paths, so they are byte-stable for the same records (golden
tests); the page adds the generation time (``generated``, injectable), the source, and the list of every run.
"""

from __future__ import annotations

import hashlib
from datetime import datetime, timezone
from pathlib import Path

from gsbench.atomic import atomic_path
from gsbench.errors import one_line
from gsbench.report import plots as figures
from gsbench.report import png
from gsbench.report.aggregate import Board, ablations, leaderboard
from gsbench.report.anytime import accuracy_to_reach, board_series, budget_results
from gsbench.report.anytime_tables import TIME_NOTE, budget_table, curves_table, front_table, joins_table
from gsbench.report.claims import evaluate_claims
from gsbench.report.collect import (
    Source,
    label_variants,
    load_manifests,
    load_runs,
    merge_resized_scenes,
    read_source,
    unfinished_folders,
)
from gsbench.report.html import document_html
from gsbench.report.joins import curves, joins
from gsbench.report.leaderboard_csv import leaderboard_csv
from gsbench.report.metrics import COMPANIONS, PAPERS_METRIC, metric_specs, primary_metric, reported
from gsbench.report.pareto import step_points
from gsbench.report.run_tables import (
    environment_table,
    failed_table,
    nogt_table,
    protocol_table,
    runs_table,
    skipped_table,
    unfinished_table,
)
from gsbench.report.stats import comparisons
from gsbench.report.surfaces import ERROR_SCALE_MM, surface_picture
from gsbench.report.tables import Plot, Section, document_markdown
from gsbench.report.twins import twin_tables
from gsbench.report.views import (
    PAIRED_NOTE,
    ablation_table,
    claims_tables,
    leaderboard_table,
    method_claims_tables,
    paired_table,
    ranks_table,
    slug,
    speed_table,
    unmeasured_groups,
)
from gsbench.run_folder import RunFolder

TITLE = "gsbench report"
# one line a section; what each shows is docs/report.md
ROWS_NOTE = ("Rows are configurations: a method, plus `key=value` for each config key that differs between its runs "
             "on a scene (docs/report.md §2).")
PROTOCOLS_NOTE = ("Each dataset is ranked by its official protocol (DTU: the DTUeval script's Chamfer; TnT: the "
                  "official toolbox's F1 on the mesh vertices), other point sets beside it (docs/report.md §3).")
SURFACES_NOTE = ("Each row's mesh (its ok run of the lowest seed whose mesh was there) from two training views, beside "
                 f"the ground truth and, on DTU, coloured by the distance to it, 0 to {ERROR_SCALE_MM:g} mm "
                 "(docs/report.md §4).")
RANKS_NOTE = "Which differences between rows the seeds and scenes can tell apart (docs/report.md §5)."
CLAIMS_NOTE = ("The papers' orderings, tested on these runs in the paper's metric; only the order is checked, at these "
               "runs' budgets; first, for each method with an ablation run, its paper's claims about its own parts "
               "(docs/report.md §6).")
TWINS_NOTE = "What one factor of a scene (glass, framing, relief) costs each method (docs/report.md §7)."
WITHOUT_GT_NOTE = "What can be measured without ground-truth geometry (docs/report.md §8)."
TIME_SECTION_NOTE = ("Each dataset's ranking metric against training time, from the points each run evaluated along "
                     "its training (a record without them: its final result), one curve per row or per rows joined; "
                     "the best curve at each time budget and the Pareto front over every step (docs/report.md §10).")


FILE_STEM_MAX = 100  # characters of a plot's file name stem; a longer one (a row label with many keys) is cut


def _file_stem(text: str) -> str:
    """``text`` as a file name stem (`slug`), cut to FILE_STEM_MAX characters with a
    hash of the whole so that cut names stay distinct (file systems refuse names over 255 bytes)."""
    stem = slug(text) or "x"
    if len(stem) <= FILE_STEM_MAX:
        return stem
    return f"{stem[:FILE_STEM_MAX - 9].rstrip('-')}-{hashlib.sha1(stem.encode()).hexdigest()[:8]}"


class _Plots:
    """Collects figures under unique file names; disabled -> draws nothing."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.made: list[Plot] = []

    def file_name(self, name: str) -> str:
        """The file the next figure called ``name`` gets."""
        taken = {p.name for p in self.made}
        stem, n = _file_stem(name), 1
        file = f"{stem}.png"
        while file in taken:
            n += 1
            file = f"{stem}-{n}.png"
        return file

    def add(self, name: str, alt: str, draw, board: Board) -> list[Plot]:
        if not self.enabled:
            return []
        data = draw(board)
        if data is None:
            return []
        plot = Plot(self.file_name(name), alt, data)
        self.made.append(plot)
        return [plot]

    def add_png(self, name: str, alt: str, data: bytes) -> list[Plot]:
        """A figure drawn elsewhere (the surfaces)."""
        return self.add(name, alt, lambda _board: data, None)


def _drawn_surface(source: Source, runs, title: str, warnings: list[str]) -> tuple[bytes, dict] | None:
    """The picture of the first of ``runs`` whose run folder holds its mesh, tagged with its run id and seed."""
    if source.runs_dir is None:
        return None
    for run in runs:
        folder = source.runs_dir / Path(run.path).parent
        if not RunFolder(folder).mesh.is_file():
            continue
        about = {"run_id": run.run_id, "seed": run.seed}
        try:
            picture = surface_picture(folder, title=f"{title}, seed {run.seed}")
        except Exception as exc:  # noqa: BLE001  (one missing scene must not stop the report)
            warnings.append(f"{folder.relative_to(source.runs_dir).as_posix()}: no surface picture "
                            f"({type(exc).__name__}: {one_line(exc, 200)})")
            return None
        return png.with_text(picture.png, about), about
    return None


def _kept_surface(file: str, runs, earlier: list[Path]) -> tuple[bytes, dict] | None:
    """An earlier report's picture ``file`` (`png.text` names its run) that shows one of ``runs``."""
    ids = {run.run_id for run in runs}
    for folder in earlier:
        path = folder / file
        if path.is_file():
            data = path.read_bytes()
            about = png.text(data, str(path))
            if about.get("run_id") in ids:
                return data, about
    return None


def _surfaces(source: Source, boards: list[Board], made: _Plots, earlier: list[Path],
              warnings: list[str]) -> Section | None:
    """Per dataset and scene, each row's surface (docs/report.md §4): drawn from the ok run of the lowest seed
    whose mesh is there, else an earlier report's picture of one of its ok runs (in ``earlier`` folders); None
    when no row has either."""
    if not made.enabled:
        return None
    blocks = []
    for board in boards:
        for scene in board.scenes:
            for row in board.rows:
                runs = sorted((r for r in row.runs if r.ok and r.scene == scene),
                              key=lambda r: (r.seed if r.seed is not None else 1 << 30, r.run_id))
                name = f"surface_{board.dataset}_{scene}_{row.name}"
                picture = (_drawn_surface(source, runs, f"{row.name} on {scene}", warnings)
                           or _kept_surface(made.file_name(name), runs, earlier))
                if picture is None:
                    continue
                data, about = picture
                width, height = png.size(data)
                blocks += made.add_png(name, f"{row.name} on {scene} (seed {about.get('seed')}), {width}x{height} px", data)
    if not blocks:
        return None
    return Section("surfaces", "Surfaces", [SURFACES_NOTE], blocks)


def _summary(runs) -> str:
    statuses: dict[str, int] = {}
    for run in runs:
        statuses[run.status] = statuses.get(run.status, 0) + 1
    counts = ", ".join(f"{n} {s}" for s, n in sorted(statuses.items(), key=lambda kv: (kv[0] != "ok", kv[0])))
    datasets = sorted({r.dataset for r in runs})
    return f"{len(runs)} runs ({counts}) on {len(datasets)} dataset(s): {', '.join(datasets)}."


def _leaderboards(runs, warnings: list[str]) -> tuple[dict, list[Board], list[Board]]:
    """(dataset -> ranking metric, one leaderboard per dataset, the companion leaderboards of `COMPANIONS`
    that some run has); a method's reported number sits on the board of the metric it reports."""
    specs = metric_specs()
    primary = {}
    for dataset in sorted({r.dataset for r in runs}):
        spec = primary_metric(dataset, {m for r in runs if r.dataset == dataset and r.ok for m in r.metrics}, specs)
        if spec is None:
            warnings.append(f"dataset '{dataset}': no run has a metric that ranks, so it has no leaderboard")
        else:
            primary[dataset] = spec
    boards, companions = [], []
    for dataset, spec in primary.items():
        methods = sorted({r.method for r in runs if r.dataset == dataset})
        refs = {m: reported(m, dataset, warnings) for m in methods}
        seen = {m for r in runs if r.dataset == dataset and r.ok for m in r.metrics}
        extra = [specs[name] for name in COMPANIONS.get(dataset, ()) if name in seen and name in specs]
        for board_spec in (spec, *extra):
            # a paper's number sits only beside the metric it reports (not beside a fallback such as PSNR)
            board = leaderboard(runs, dataset, board_spec,
                                {m: r for m, r in refs.items() if r is not None and r.metric == board_spec.name})
            if board.scenes:
                (boards if board_spec is spec else companions).append(board)
            elif board_spec is spec:
                warnings.append(f"dataset '{dataset}': no scene can be scored by {spec.label} (its evaluator was "
                                f"skipped on {', '.join(board.unscored)}), so it has no leaderboard; see Captures "
                                "without ground truth")
    return primary, boards, companions


def _against_time(boards: list[Board], made: _Plots) -> Section:
    """Per dataset: which rows share a curve, the curves, the time-budget tables and the front over every step."""
    section = Section("error-against-time", "Error against time", [TIME_SECTION_NOTE, TIME_NOTE], [])
    for board in boards:
        board_curves = curves(board)
        joined = joins_table(board, board_curves, joins(board, board_curves))
        section.blocks += [joined] if joined else []
        section.blocks += made.add(f"curves_{board.dataset}", f"{board.dataset}: {board.spec.label} against training "
                                   "CPU seconds", figures.curves_figure, board)
        front = step_points(board_series(board, board_curves)[None], bool(board.spec.higher_is_better))
        section.blocks += [budget_table(board, budget_results(board, board_curves)),
                           curves_table(board, board_curves, accuracy_to_reach(board, board_curves)),
                           front_table(board, front)]
    return section


def _without_gt(runs) -> Section | None:
    """The section of the measures that need no ground truth and of the skipped evaluators; None when
    no run has either."""
    table, skipped = nogt_table(runs, metric_specs()), skipped_table(runs)
    if not table.rows and not skipped.rows:
        return None
    return Section("without-ground-truth", "Captures without ground truth", [WITHOUT_GT_NOTE], [table, skipped])


def _sweeps(manifests, runs, primary: dict, made: _Plots) -> tuple[Section, dict[str, list[str]]]:
    """(the ablation section, run id -> its ``sweep: label`` names)."""
    section = Section("sweeps", "Sweeps (ablations)", [PAIRED_NOTE] if manifests else [], [])
    if not manifests:
        section.paragraphs.append("No sweep manifests (`<out>/sweeps/<name>.json`, written by `gsbench sweep`) found.")
    by_id = {r.run_id: r for r in runs}
    labels: dict[str, list[str]] = {}
    for manifest in manifests:
        for entry in manifest.runs:
            labels.setdefault(entry.run_id, []).append(f"{manifest.name}: {entry.label}")
        described = f": {manifest.description}" if manifest.description else ""
        source = f", from {manifest.file}" if manifest.file else ""
        about = f"Sweep {manifest.name} ({manifest.path}{source}){described}."
        boards = ablations(manifest, by_id, primary)
        if not boards:
            section.paragraphs.append(f"{about} None of its runs has a record or a known dataset.")
        for board in boards:
            table = ablation_table(board)
            table.notes.insert(0, about)
            section.blocks.append(table)
            draw = figures.grid_figure if board.grid_key else figures.variants_figure
            section.blocks += made.add(f"sweep_{manifest.name}_{board.dataset}", board.title, draw, board)
    return section, labels


def _failed_section(runs, unfinished: list[str]) -> Section:
    """The records that are not ok, then the run folders without a record; its one "(none)" only when there are
    neither (an empty records table above a listed unfinished run read as "nothing failed")."""
    failed = failed_table(runs)
    tables = [failed] if failed.rows or not unfinished else []
    tables += [unfinished_table(unfinished)] if unfinished else []
    return Section("failed", "Failed and unfinished runs", [], tables)


def write_report(source, out, *, plots: bool = True, self_contained: bool = False, generated: str | None = None,
                 warn=None) -> list[Path]:
    """Write the report of ``source`` (a runs folder, or a board's records file or folder) into ``out``; return
    the written files (docs/report.md §1). ``plots=False`` draws nothing; ``self_contained`` embeds the pictures
    in the page; ``generated`` is the page's time (default: now, UTC); ``warn(message)`` gets each warning."""
    source, out = read_source(source), Path(out)
    runs, warnings = load_runs(source)
    unfinished = unfinished_folders(source)
    warnings += [f"{folder}: a run folder without a record (unfinished, listed under Failed and unfinished runs)"
                 for folder in unfinished]
    runs = label_variants(merge_resized_scenes(runs))
    manifests, manifest_warnings = load_manifests(source)
    warnings += manifest_warnings
    primary, boards, companions = _leaderboards(runs, warnings)

    made = _Plots(plots)
    speed = Section("speed", "Speed and size against error", [], [])
    for board in boards:
        speed.blocks.append(speed_table(board))
        speed.blocks += made.add(f"speed_{board.dataset}", f"{board.dataset}: cost against {board.spec.label}",
                                 figures.speed_figure, board)
    sweeps, sweep_labels = _sweeps(manifests, runs, primary, made)
    without_gt = _without_gt(runs)
    ordered = sorted([*boards, *companions], key=lambda b: b.dataset)
    ranked = [leaderboard_table(b) for b in ordered]
    tests = {id(board): comparisons(board) for board in ordered}  # each board's paired tests, once (tables, CSV)
    significance = Section("ranks", "Ranks and paired comparisons", [RANKS_NOTE, PAIRED_NOTE], [])
    for board in ordered:
        if board.spec.name in (primary[board.dataset].name, PAPERS_METRIC.get(board.dataset)):
            significance.blocks += [ranks_table(board, tests[id(board)]), paired_table(board, tests[id(board)])]
    specs = metric_specs()
    outcomes = evaluate_claims(runs, manifests, specs)
    unmeasured = unmeasured_groups(outcomes)
    left_out = [f"Left out, no run of any of their methods here: {'; '.join(unmeasured)}."] if unmeasured else []
    claims = Section("papers-orderings", "The papers' orderings, tested", [CLAIMS_NOTE, PAIRED_NOTE, *left_out],
                     [*method_claims_tables(outcomes), *claims_tables(outcomes, specs)])
    earlier = list(dict.fromkeys(folder / "plots" for folder in (out, source.board_dir) if folder is not None))
    surfaces = _surfaces(source, boards, made, earlier, warnings)
    twins = twin_tables(runs, specs)
    sections = [Section("leaderboards", "Leaderboards", [ROWS_NOTE, PROTOCOLS_NOTE], ranked),
                *([surfaces] if surfaces else []), significance, claims,
                *([Section("twins", "Twin scenes: what one factor costs", [TWINS_NOTE], twins)] if twins else []),
                _against_time(boards, made), speed, *([without_gt] if without_gt else []), sweeps,
                _failed_section(runs, unfinished),
                Section("protocols", "Protocols", [], [protocol_table(runs)]),
                Section("environment", "Environment", [], [environment_table(runs)])]
    warnings = list(dict.fromkeys(warnings))
    for message in warnings if warn is not None else ():
        warn(message)
    intro = [_summary(runs)]

    csv_boards = [*boards, *companions]
    page_sections = sections + [Section("runs", "All runs", [], [runs_table(runs, primary, sweep_labels)])]
    page = document_html(TITLE, [*intro, f"Records: {source.name}"], page_sections, warnings,
                         generated or datetime.now(timezone.utc).isoformat(timespec="seconds"), embed=self_contained)
    files = {out / "leaderboard.md": document_markdown(TITLE, intro, sections, warnings).encode(),
             out / "leaderboard.csv": leaderboard_csv(csv_boards, [tests[id(b)] for b in csv_boards]).encode(),
             **{out / "plots" / plot.name: plot.png for plot in made.made},
             out / "index.html": page.encode()}
    for path, data in files.items():
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
    # plots/ is the report's own: figures of an earlier report into the same folder that this one did not
    # draw or keep (a sweep no longer there, plots=False) would sit there as if they belonged to it
    for stale in sorted(set((out / "plots").glob("*.png")) - set(files)):
        stale.unlink()
    return list(files)
