"""`write_report`: a runs folder -> ``leaderboard.md``, ``leaderboard.csv``, ``index.html`` and
``plots/*.png`` in the output folder (``gsbench report RUNS_DIR --out DIR``).

Sections: the leaderboards (cells: mean ± 95% t-interval over seeds); ranks and paired comparisons per
leaderboard (`gsbench.report.stats`); the papers' orderings tested (`gsbench.report.claims`); twin scenes
(what one factor of a scene costs each method, `gsbench.report.twins`); speed against error; captures without
ground truth; sweeps (ablations, with paired tests against the first row); failed runs; protocols; environment.

Runs with measures that need no ground truth (held-out PSNR/SSIM, mask IoU, the surface outside the
masks' visual hull, mesh statistics) or with skipped evaluators get the section "Captures without
ground truth"; it is left out when no run has either. A scene that cannot feed a dataset's ranking
metric is left off that leaderboard (`gsbench.report.aggregate.unscored_scenes`) rather than shown
as runs without a metric.

The Markdown and CSV hold no timestamps or absolute paths, so they are byte-stable for the same
records (golden tests); the HTML adds the generation time (``generated``, injectable), the runs
folder, the warnings and the list of every run.
"""

from __future__ import annotations

import hashlib
from datetime import datetime, timezone
from pathlib import Path

from gsbench.errors import one_line
from gsbench.report import plots as figures
from gsbench.report.aggregate import Board, ablations, leaderboard
from gsbench.report.claims import evaluate_claims
from gsbench.report.collect import label_variants, load_manifests, load_runs, unfinished_folders
from gsbench.report.html import document_html
from gsbench.report.leaderboard_csv import leaderboard_csv
from gsbench.report.metrics import COMPANIONS, PAPERS_METRIC, metric_specs, primary_metric, reported
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
    paired_table,
    ranks_table,
    slug,
    speed_table,
)
from gsbench.run_folder import RunFolder

TITLE = "gsbench report"
SURFACES_NOTE = ("Each row's mesh (the ok run of the lowest seed whose folder still holds it) from two fixed "
                 "training views, beside the ground truth from the same views (the exact mesh of a synthetic scene, "
                 "else the ground-truth points; the photo with its mask outline for a capture without ground truth) "
                 f"and, on the DTU protocol, coloured by each vertex's distance to the ground truth, 0 to "
                 f"{ERROR_SCALE_MM:g} mm on every picture (`gsbench render RUN_DIR` draws one run's).")
PROTOCOLS_NOTE = ("Each dataset is ranked by its official protocol (DTU: the DTUeval script's Chamfer; TnT: the "
                  "official toolbox's F1 on the mesh vertices). Beside it: the same distances on area samples of "
                  "the mesh (independent of how the surface is triangulated) and, for TnT, F1 on vertices plus face "
                  "centroids, the point set of the 2DGS / GOF / RaDe-GS scripts that produced those papers' TnT "
                  "numbers, so their reported values sit beside that board.")
RANKS_NOTE = ("Which differences between rows the seeds and scenes can tell apart, for each dataset's ranking "
              "leaderboard and the one in the papers' own metric: the rank of each row on each scene and on "
              "average, a rank shared by rows whose paired differences are not significant, and every row "
              "against every other, paired on the same scene and seed (`gsbench.report.stats` states the "
              "formulas).")
CLAIMS_NOTES = [
    "The orderings the papers report (`gsbench.report.claims`, each with its source), split into claims between "
    "two methods, or two rows of the sweep that repeats an ablation, and tested on these runs in the metric "
    "the paper used: DTU the official script's Chamfer, TnT the F1 on vertices + face centroids (the 2DGS / "
    "GOF / RaDe-GS scripts). The papers' numbers are on the real datasets (GPU, full schedules); here only "
    "their order is checked, at these runs' budgets: the cost tables (Speed and size against error) say "
    "which rows the Gaussian budget cut, and a verdict between rows cut at different steps is a verdict at "
    "that budget, not on the methods as published.",
    "Verdict, from the paired test of the claimed better side against the other: agrees (the claimed side "
    "significantly better, p < 0.05); disagrees (the other side significantly better; for ≈ any significant "
    "difference); not separable (p ≥ 0.05; for ≥ and ≈ that agrees with the claim: 'agrees (not "
    "separable)'); not measured (a side has no runs with the metric, or the two share no (scene, seed) "
    "pair). Not separable with few pairs is no evidence of equality. A method with several configurations "
    "on a leaderboard is represented by the one with the most runs (named under rows compared).",
]
TWINS_NOTE = ("Scenes made from another scene with one factor changed (the glass scenes from their opaque twins, a "
              "scene framed smaller, its relief smoothed off): per method, each metric on the twin and on the changed "
              "scene and the paired change over seeds, so what the factor costs each method, and whether a method "
              "made for it recovers it, can be read side by side (`gsbench.report.twins`).")
ROWS_NOTE = ("Rows are configurations: a method, plus `key=value` for each config key whose value differs "
             "between its runs on one scene (so different configs are never averaged as if they were seeds); "
             "where presets differ, the keys a preset sets (one value per preset) are named by `preset=...` alone.")


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

    def add(self, name: str, alt: str, draw, board: Board) -> list[Plot]:
        if not self.enabled:
            return []
        png = draw(board)
        if png is None:
            return []
        taken = {p.name for p in self.made}
        stem, n = _file_stem(name), 1
        file = f"{stem}.png"
        while file in taken:
            n += 1
            file = f"{stem}-{n}.png"
        plot = Plot(file, alt, png)
        self.made.append(plot)
        return [plot]

    def add_png(self, name: str, alt: str, png: bytes) -> list[Plot]:
        """A figure drawn elsewhere (the surfaces)."""
        return self.add(name, alt, lambda _board: png, None)


def _surfaces(runs_dir: Path, boards: list[Board], made: _Plots, warnings: list[str]) -> Section | None:
    """Per dataset and scene, each row's surface (`gsbench.report.surfaces`): the ok run of the lowest seed whose
    folder below ``runs_dir`` still holds its mesh. None when no run folder has one (a report of records
    only); a picture that cannot be drawn (the scene not on this machine) is a warning."""
    if not made.enabled:
        return None
    blocks = []
    for board in boards:
        for scene in board.scenes:
            for row in board.rows:
                runs = sorted((r for r in row.runs if r.ok and r.scene == scene),
                              key=lambda r: (r.seed if r.seed is not None else 1 << 30, r.run_id))
                meshed = [(runs_dir / Path(r.path).parent, r.seed) for r in runs]
                folder, seed = next(((f, s) for f, s in meshed if RunFolder(f).mesh.is_file()), (None, None))
                if folder is None:
                    continue
                try:
                    picture = surface_picture(folder, title=f"{row.name} on {scene}, seed {seed}")
                except Exception as exc:  # noqa: BLE001  (one missing scene must not stop the report)
                    warnings.append(f"{folder.relative_to(runs_dir).as_posix()}: no surface picture "
                                    f"({type(exc).__name__}: {one_line(exc, 200)})")
                    continue
                blocks += made.add_png(f"surface_{board.dataset}_{scene}_{row.name}",
                                       f"{row.name} on {scene} (seed {seed}), {picture.width}x{picture.height} px",
                                       picture.png)
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


def _without_gt(runs) -> Section | None:
    """The section of the measures that need no ground truth and of the skipped evaluators; None when
    no run has either."""
    table, skipped = nogt_table(runs, metric_specs()), skipped_table(runs)
    if not table.rows and not skipped.rows:
        return None
    about = ("What can be measured without ground-truth geometry: renders of held-out views against their "
             "photos, the mesh against the object masks, and the mesh itself. A capture without ground truth "
             "is judged by these alone; runs with ground truth are listed too.")
    return Section("without-ground-truth", "Captures without ground truth", [about], [table, skipped])


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


def write_report(runs_dir, out, *, plots: bool = True, generated: str | None = None, warn=None) -> list[Path]:
    """Write the report of every record below ``runs_dir`` into ``out``; return the written files. PNGs in
    ``out/plots`` that this report did not draw (an earlier report's) are removed.

    ``plots=False`` skips matplotlib (no PNGs, no figures in the page); ``generated`` is the time shown
    in the HTML (default: now, UTC); ``warn(message)`` is called with each warning the report carries
    (damaged records left out, …), e.g. to print them on the console."""
    runs_dir, out = Path(runs_dir), Path(out)
    runs, warnings = load_runs(runs_dir)
    unfinished = unfinished_folders(runs_dir)
    warnings += [f"{folder}: a run folder without a record (unfinished, listed under Failed and unfinished runs)"
                 for folder in unfinished]
    runs = label_variants(runs)
    manifests, manifest_warnings = load_manifests(runs_dir)
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
    claims = Section("papers-orderings", "The papers' orderings, tested", [*CLAIMS_NOTES, PAIRED_NOTE],
                     claims_tables(evaluate_claims(runs, manifests, specs), specs))
    surfaces = _surfaces(runs_dir, boards, made, warnings)
    twins = twin_tables(runs, specs)
    sections = [Section("leaderboards", "Leaderboards", [ROWS_NOTE, PROTOCOLS_NOTE], ranked),
                *([surfaces] if surfaces else []), significance, claims,
                *([Section("twins", "Twin scenes: what one factor costs", [TWINS_NOTE], twins)] if twins else []),
                speed, *([without_gt] if without_gt else []), sweeps,
                Section("failed", "Failed and unfinished runs", [],
                        [failed_table(runs), *([unfinished_table(unfinished)] if unfinished else [])]),
                Section("protocols", "Protocols", [], [protocol_table(runs)]),
                Section("environment", "Environment", [], [environment_table(runs)])]
    warnings = list(dict.fromkeys(warnings))
    for message in warnings if warn is not None else ():
        warn(message)
    intro = [_summary(runs)]

    out.mkdir(parents=True, exist_ok=True)
    csv_boards = [*boards, *companions]
    written = []
    for name, text in (("leaderboard.md", document_markdown(TITLE, intro, sections, warnings)),
                       ("leaderboard.csv", leaderboard_csv(csv_boards, [tests[id(b)] for b in csv_boards]))):
        (out / name).write_text(text)
        written.append(out / name)
    if made.made:
        (out / "plots").mkdir(exist_ok=True)
    for plot in made.made:
        (out / "plots" / plot.name).write_bytes(plot.png)
        written.append(out / "plots" / plot.name)
    # plots/ is the report's own: figures of an earlier report into the same folder that this one did not
    # draw (a sweep no longer there, plots=False) would sit there as if they belonged to it
    for stale in sorted(set((out / "plots").glob("*.png")) - set(written)):
        stale.unlink()
    page_sections = sections + [Section("runs", "All runs", [], [runs_table(runs, primary, sweep_labels)])]
    generated = generated or datetime.now(timezone.utc).isoformat(timespec="seconds")
    page = document_html(TITLE, [*intro, f"Runs folder: {runs_dir}"], page_sections, warnings, generated)
    (out / "index.html").write_text(page)
    written.append(out / "index.html")
    return written
