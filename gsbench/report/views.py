"""The report's tables of boards: leaderboard, ranks, paired tests, the papers' claims, speed against error
and sweep ablations (the tables of single runs are `gsbench.report.run_tables`, the CSV
`gsbench.report.leaderboard_csv`).

Every table is sorted deterministically and formats numbers with fixed digits (`gsbench.report.tables`).
"""

from __future__ import annotations

from collections import Counter

from gsbench.report.aggregate import Board, Row, Stat, natural_key
from gsbench.report.budget import BUDGET_NOTE, budget_text
from gsbench.report.collect import Run
from gsbench.report.metrics import COMPANIONS, REAL_DATASETS, MetricSpec
from gsbench.report.pareto import COSTS, cost_points
from gsbench.report.stats import (
    ALPHA,
    POWER,
    PairedTest,
    compare_rows,
    comparisons,
    mean_interval,
    mean_ranks,
    pairs_to_decide,
    scene_ranks,
    significance_ranks,
)
from gsbench.report.tables import MISSING, Table, TCell, count, join_text, metric_cell, mib, number, plain, status_text
from gsbench.runs.records import code_version

TIMES_NOTE = ("Times are wall-clock seconds (means over a row's ok runs), comparable only between runs at "
              "the same thread count on an equally loaded machine of the same kind (see Environment). train CPU: "
              "the training's process CPU time, every thread's (records from 2026-11-28 on); other processes on "
              "the machine do not stretch it, so at one thread it compares runs made side by side.")
INTERVAL_NOTE = ("± h: the 95% Student t-interval of the mean over a cell's ok runs (seeds), mean ± h with "
                 "h = t(0.975, n−1)·s/√n (s the sample standard deviation), for n ≥ 2; a cell of one run shows "
                 "no interval.")
PAIRED_NOTE = (f"Paired test: over the (scene, seed) pairs on which both rows have an ok run with the metric; "
               f"two-sided Wilcoxon signed-rank test of the differences (scipy.stats.wilcoxon: zero differences "
               f"dropped, exact for up to 50 pairs without ties), or the exact sign test when all differences "
               f"are zero or fewer than 6 are non-zero (then no test can reach p < {ALPHA}); significant: "
               f"p < {ALPHA}, no correction for multiple comparisons.")
MEMORY_NOTE = ("Memory: the process's peak RSS through training (the record's train stage); mesh extraction and "
               "evaluation are left out, they are the same protocol for every method.")


def slug(text: str) -> str:
    """``text`` for an anchor or a file name: alphanumerics kept (lower case), everything else "-"."""
    return "".join(c if c.isalnum() else "-" for c in text.lower()).strip("-")


def cpu_note(runs: list[Run]) -> str:
    """A warning when the runs' times come from more than one CPU model (the record's ``environment.cpu``),
    with the number of runs on each; empty when they come from one. A row's mean time then mixes machines
    in its own proportions, so two rows compare only as far as their runs share a CPU model."""
    models = Counter(str(run.environment.get("cpu") or MISSING) for run in runs)
    if len(models) < 2:
        return ""
    listed = "; ".join(f"{model}: {n} run{'s' if n > 1 else ''}" for model, n in sorted(models.items()))
    return (f"CPU models differ between runs ({listed}): a row's mean time mixes them, so compare times only "
            f"between runs on one CPU model (the page's list of runs and Environment say which).")


def short_code_version(run: Run) -> str:
    """A run's code version (`gsbench.runs.records.code_version`) with the commit cut to 12 hex digits;
    ``unknown`` when its record names none."""
    version = code_version(run.environment)
    return "unknown" if version is None else version[:12] + version[40:]


def code_version_note(board: Board) -> str:
    """A warning when the board's ok runs come from more than one code version (the records' commits), with
    the rows of each: their numbers need not be comparable (a change of code can move them). Empty when one."""
    rows_of: dict[str, set[str]] = {}
    for row in board.rows:
        for run in row.runs:
            if run.ok:
                rows_of.setdefault(short_code_version(run), set()).add(row.name)
    if len(rows_of) < 2:
        return ""
    listed = "; ".join(f"{version}: {join_text(sorted(rows, key=natural_key))}"
                       for version, rows in sorted(rows_of.items()))
    return (f"**Code versions differ** between this board's runs ({listed}): numbers made by different code need not "
            f"compare; re-run the rows of the other versions at one commit (gsbench sweep --other-code rerun).")


def protocol_note(board: Board) -> str:
    """Which evaluator version(s) produced the board's numbers, with run counts."""
    evaluator = board.spec.evaluator
    versions: dict[str, int] = {}
    for row in board.rows:
        for run in row.runs:
            if run.ok and board.spec.name in run.metrics:
                proto = run.eval_protocol.get(evaluator) if evaluator else None
                version = f"{evaluator}@{proto.get('version')}" if isinstance(proto, dict) else "unrecorded protocol"
                versions[version] = versions.get(version, 0) + 1
    text = ", ".join(f"{v} ({n} run{'s' if n > 1 else ''})" for v, n in sorted(versions.items())) or MISSING
    mixed = " — MIXED versions: numbers of different versions are not comparable" if len(versions) > 1 else ""
    return f"{board.spec.label} from {text}{mixed}."


def leaderboard_table(board: Board) -> Table:
    """Method × scene in the papers' shape, mean over scenes, the paper's number on the real dataset."""
    real = REAL_DATASETS.get(board.dataset, f"real {board.dataset}")
    header = ["method", *board.scenes, "mean", f"reported ({real})", "runs"]
    best = {column: board.best(column) for column in [*board.scenes, "mean"]}
    rows = []
    for row in board.rows:
        cells = [plain(row.name)]
        cells += [metric_cell(row.cells.get(scene), row.name in best[scene]) for scene in board.scenes]
        value, complete = board.mean(row)
        if value is None:
            cells.append(TCell(MISSING, None, "bad"))
        elif complete:
            cells.append(TCell(number(value), value, "best" if row.name in best["mean"] else ""))
        else:
            _, n = row.scene_mean(board.scenes)
            cells.append(TCell(f"{number(value)} ({n}/{len(board.scenes)} scenes)", value, "bad"))
        ref = board.reported.get(row.methods[0]) if len(row.methods) == 1 else None
        has_ref = ref is not None and ref.mean is not None
        cells.append(TCell(number(ref.mean, 2), ref.mean, "reported") if has_ref else plain(MISSING))
        cells.append(plain(status_text(row.counts)))
        rows.append(cells)
    notes = [
        f"{board.spec.label}, {board.spec.direction}; a cell: mean over its ok runs (seeds); **bold**: best in "
        f"its column; the mean is over scenes and ranked only for rows with every scene ('k/n scenes' "
        f"otherwise). Ranks and paired comparisons: the next section.",
        INTERVAL_NOTE,
        "Runs: ok, failed and other statuses, and missing (scene, seed) pairs among the seeds a row has.",
        protocol_note(board),
    ]
    versions = code_version_note(board)
    if versions:
        notes.insert(0, versions)
    resized = sorted({(run.scene_folder, run.scene) for row in board.rows for run in row.runs if run.scene_folder})
    if resized:
        notes.append("Shown on the scene it was rendered from, at another image size (docs/report.md §2): "
                     + "; ".join(f"{folder} on {scene}" for folder, scene in resized) + ".")
    if board.unscored:
        notes.append(f"Not on this board: {join_text(board.unscored)} — no run there has {board.spec.label}, its "
                     f"evaluator was skipped (see Captures without ground truth).")
    sources = sorted((m, r) for m, r in board.reported.items() if r.mean is not None)
    if sources:
        notes.append(
            f"Reported: the papers' numbers on the {real} data (GPU, the papers' full schedules). They are "
            f"NOT comparable with synthetic scenes or CPU budgets; they show the scale only. Sources: "
            + "; ".join(f"{m}: {r.source}" for m, r in sources) + "."
        )
    return Table(_board_anchor(board, "leaderboard"), board.title, header, rows, notes)


def p_text(p: float) -> str:
    """A p-value to 3 decimals; ``<0.001`` below that."""
    return "<0.001" if p < 0.001 else f"{p:.3f}"


def star(test: PairedTest | None) -> str:
    """`` *`` after a significant paired test's text, else nothing."""
    return " *" if test is not None and test.significant else ""


def _rank_text(rank: float | None) -> str:
    return MISSING if rank is None else (str(int(rank)) if rank == int(rank) else f"{rank:.1f}")


def _board_anchor(board: Board, kind: str) -> str:
    companion = board.spec.name in COMPANIONS.get(board.dataset, ())
    return f"{kind}-{slug(board.dataset)}" + (f"-{slug(board.spec.name)}" if companion else "")


def ranks_table(board: Board, tests: dict[tuple[str, str], PairedTest] | None = None) -> Table:
    """Per-scene ranks of the rows' cell means, the mean rank, and the significance rank (shared when the
    paired tests cannot separate the rows), with the mean over scenes for reference."""
    tests = comparisons(board) if tests is None else tests
    per_scene = scene_ranks(board)
    mean = mean_ranks(board, per_scene)
    shared = significance_ranks(board, tests)
    header = ["method", *board.scenes, "mean rank", "rank (paired tests)", f"mean {board.spec.label}"]
    best_mean = min((v for v in mean.values() if v is not None), default=None)
    rows = []
    for row in sorted(board.rows, key=lambda r: (shared.get(r.name, len(board.rows) + 1),
                                                 mean[r.name] if mean[r.name] is not None else float("inf"))):
        cells = [plain(row.name)]
        cells += [TCell(_rank_text(per_scene[row.name].get(scene)), per_scene[row.name].get(scene),
                        "best" if per_scene[row.name].get(scene) == 1 else "") for scene in board.scenes]
        value = mean[row.name]
        cells.append(TCell(number(value, 2) if value is not None else MISSING, value,
                           "best" if value is not None and value == best_mean else ""))
        rank = shared.get(row.name)
        cells.append(TCell(str(rank) if rank is not None else MISSING, rank, "best" if rank == 1 else ""))
        row_mean, complete = board.mean(row)
        cells.append(TCell(number(row_mean) if complete else MISSING, row_mean if complete else None))
        rows.append(cells)
    notes = [
        f"Rank on a scene: of the row's cell mean among the rows with a value there (1 = best in "
        f"{board.spec.label}, {board.spec.direction}; ties share the mean of their ranks). Mean rank: over the "
        f"board's scenes, for rows with a value on every scene.",
        f"Rank (paired tests): 1 + the number of rows (with every scene) significantly better than the row (p < "
        f"{ALPHA} in this section's paired test; matrix below), so rows whose differences are not significant "
        f"share a rank; rows are listed in this order.",
    ]
    return Table(_board_anchor(board, "ranks"), f"Ranks: {board.title}", header, rows, notes)


def paired_table(board: Board, tests: dict[tuple[str, str], PairedTest] | None = None) -> Table:
    """Every row against every other: mean paired difference (row − column), the pairs where the row is
    better, and the p-value; starred when significant, bold when the row is significantly better."""
    tests = comparisons(board) if tests is None else tests
    names = [row.name for row in board.rows]
    header = ["row − column", *names]
    rows = []
    for a in names:
        cells = [plain(a)]
        for b in names:
            if a == b:
                cells.append(TCell(MISSING))
                continue
            test = tests[(a, b)]
            if test.p is None:
                cells.append(TCell("no pairs"))
                continue
            text = f"{test.mean_diff:+.3f}, {test.wins}/{test.n} better, p={p_text(test.p)}{star(test)}"
            cells.append(TCell(text, test.mean_diff, "best" if test.a_better else ("bad" if test.b_better else "")))
        rows.append(cells)
    notes = [
        f"A cell compares its row with its column on {board.spec.label} ({board.spec.direction}): the mean over "
        f"their (scene, seed) pairs of row − column, how many of the pairs the row is better on, and the p-value "
        f"of the paired test of this section; * : p < {ALPHA}; **bold**: the row is significantly better, "
        f"'*' alone: worse.",
    ]
    return Table(_board_anchor(board, "paired"), f"Paired comparisons: {board.title}", header, rows, notes)


PAIRS_NOTE = (
    f"Pairs to decide: where the test did not separate the rows, the (scene, seed) pairs at which it would with "
    f"{POWER:.0%} probability if the measured mean difference and its spread were the true ones "
    f"(((1.96 + 0.84) · s_d / |Δ|)² / (3/π), at least 6); a projection: a Δ that is large by chance makes it too "
    f"small.")


def claim_groups(outcomes) -> dict[str, list]:
    """The outcomes by claim group, in order."""
    groups: dict[str, list] = {}
    for outcome in outcomes:
        groups.setdefault(outcome.claim.group, []).append(outcome)
    return groups


def _has_a_side(members) -> bool:
    """Whether some claim of a group found a row of the board for either of its sides."""
    return any(o.better_row or o.worse_row for o in members)


def unmeasured_groups(outcomes) -> list[str]:
    """The claim groups none of whose claims has a row on the board for either side: `claims_tables` leaves them
    out (a board of a few methods would otherwise print every paper's ordering as "not measured")."""
    return [group for group, members in claim_groups(outcomes).items() if not _has_a_side(members)]


def claims_tables(outcomes, specs: dict[str, MetricSpec]) -> list[Table]:
    """One table per group of claims (`gsbench.report.claims`) with a row on the board for a side of one of its
    claims (`unmeasured_groups`), one line per claim: the ordering, the
    paper's numbers and source, the rows compared, the mean paired difference and its 95% interval
    (`gsbench.report.stats.mean_interval`), the pairs won, the p-value, the verdict, where the test did not separate
    the rows, the pairs it would take (`gsbench.report.stats.pairs_to_decide`), and where the runs contradict the claim
    its measured cause or "unexplained" (`gsbench.report.claims.load_findings`)."""
    groups = {group: members for group, members in claim_groups(outcomes).items() if _has_a_side(members)}
    header = ["claim", "paper", "source", "rows compared", "Δ (claimed better − other)", "95% interval of Δ",
              "better on", "p (test)", "verdict", f"pairs to decide ({POWER:.0%} power at this Δ)",
              "cause, where it disagrees"]
    tables = []
    for group, members in groups.items():
        rows = []
        for o in members:
            c, t = o.claim, o.test
            where = f"sweep {c.sweep}: " if c.sweep else ""
            compared = f"{where}{o.better_row} vs {o.worse_row}" if not o.why else o.why
            measured = t is not None and t.p is not None
            rows.append([
                plain(c.text), plain(c.paper), plain(c.source), plain(compared), *_effect_cells(t),
                plain(f"{t.wins}/{t.n} pairs" if measured else MISSING),
                TCell(f"{p_text(t.p)} ({t.test})" if measured else MISSING, t.p if measured else None),
                _verdict_cell(o),
                _pairs_to_decide_cell(t) if measured and not t.significant else plain(MISSING),
                plain(o.cause or MISSING),
            ])
        first = members[0].claim
        anchor = f"claims-{slug(first.sweep or f'{first.dataset}-{first.metric}')}"
        tables.append(Table(anchor, f"{group} ({first.dataset}: {_metric_label(first, specs)})", header, rows,
                            [PAIRS_NOTE]))
    return tables


EFFECT_NOTE = ("Δ: the mean over the pairs of the claimed-better row's value minus the other's, in the metric's units "
               "(a better claimed side: Δ < 0 for an error, > 0 for F1 or PSNR), with its 95% t-interval over the "
               "(scene, seed) pairs; the verdict is the paired test's (docs/report.md §6).")


def method_claims_tables(outcomes) -> list[Table]:
    """One table per method whose paper's claims about its own parts (its ablations: the claims on a sweep's rows,
    `gsbench.report.claims.Claim.sweep`) have at least one measured: each such claim of its file, the sweep, dataset
    and metric it is tested on, the paper's numbers, the effect Δ with its 95% interval, the pairs and the verdict."""
    by_method: dict[str, list] = {}
    for outcome in outcomes:
        if outcome.claim.sweep:
            by_method.setdefault(outcome.claim.method, []).append(outcome)
    header = ["claim", "tested on", "paper", "Δ (claimed better − other)", "95% interval of Δ", "pairs", "verdict"]
    tables = []
    for method, members in by_method.items():
        if all(o.test is None or o.test.p is None for o in members):
            continue
        rows = [[plain(o.claim.text),
                 plain(f"sweep {o.claim.sweep}, {o.claim.dataset} {o.claim.metric}"),
                 plain(o.claim.paper), *_effect_cells(o.test),
                 plain(str(o.test.n) if o.test is not None and o.test.p is not None else MISSING), _verdict_cell(o)]
                for o in members]
        tables.append(Table(f"own-claims-{slug(method)}", f"{method}: the paper's claims about its own parts", header,
                            rows, [EFFECT_NOTE]))
    return tables


def _metric_label(claim, specs: dict[str, MetricSpec]) -> str:
    spec = specs.get(claim.metric)
    return spec.label + f", {spec.direction}" if spec else claim.metric


def _effect_cells(test) -> list[TCell]:
    """[Δ, its 95% interval] of a paired test (`MISSING` without pairs; the interval needs two)."""
    if test is None or test.p is None:
        return [plain(MISSING), plain(MISSING)]
    interval = mean_interval(test)
    return [TCell(f"{test.mean_diff:+.3f}", test.mean_diff),
            plain(MISSING) if interval is None else TCell(f"[{interval[0]:+.3f}, {interval[1]:+.3f}]", interval[0])]


def _verdict_cell(outcome) -> TCell:
    return TCell(outcome.verdict, None, {"agrees": "best", "disagrees": "bad"}.get(outcome.verdict, ""))


def _pairs_to_decide_cell(test) -> TCell:
    n = pairs_to_decide(test)
    return TCell(MISSING if n is None else f"{n} (have {test.n})", n)


def fronts(board: Board) -> dict[str, set[str]]:
    """Row name -> the costs (`COSTS` keys) on whose Pareto front it lies."""
    on: dict[str, set[str]] = {}
    for cost in COSTS:
        for point in cost_points(board, cost):
            if point.front:
                on.setdefault(point.row, set()).add(cost)
    return on


SPEED_COLUMNS = (  # Row.speed key -> format of its mean
    ("train", lambda v: number(v, 1)), ("train_cpu", lambda v: number(v, 1)), ("total", lambda v: number(v, 1)),
    ("it_per_s", lambda v: number(v, 2)),
    ("train_rss", mib), ("gaussians", count),
)


def _stat_cell(value: Stat | None, show) -> TCell:
    return TCell(show(value.mean), value.mean) if value else TCell(MISSING)


def speed_table(board: Board) -> Table:
    """Per row: iterations, threads, times, memory, size and the Gaussian budget, mean metric, and the
    Pareto fronts it is on."""
    header = ["method", "iterations", "threads", "train (s)", "train CPU (s)", "total (s)", "it/s", "train peak RSS (MiB)",
              "Gaussians",
              "Gaussian budget", f"mean {board.spec.label}", "Pareto front"]
    on = fronts(board)
    rows = []
    for row in board.rows:
        value, complete = board.mean(row)
        shown = number(value) if complete or value is None else f"{number(value)} (incomplete)"
        front = [short for key, (short, _) in COSTS.items() if key in on.get(row.name, ())]
        rows.append([
            plain(row.name), plain(join_text(row.iterations)), plain(join_text(row.threads)),
            *(_stat_cell(row.speed[key], show) for key, show in SPEED_COLUMNS), plain(budget_text(row.runs)),
            TCell(shown, value, "" if complete else "bad"),
            TCell(", ".join(front) or MISSING, len(front), "front" if front else ""),
        ])
    threads = sorted({t for row in board.rows for t in row.threads})
    notes = [TIMES_NOTE, MEMORY_NOTE, BUDGET_NOTE,
             f"Pareto front: no other row (with a value on every scene) is at most as costly and at least as good "
             f"in mean {board.spec.label}; costs: {', '.join(short for short, _ in COSTS.values())}."]
    if len(threads) > 1:
        notes.append(f"Thread counts differ between runs ({join_text(threads)}): compare times only at one thread count.")
    cpus = cpu_note([run for row in board.rows for run in row.runs])
    if cpus:
        notes.append(cpus)
    title = f"{board.dataset}: cost against {board.spec.label}"
    return Table(f"speed-{slug(board.dataset)}", title, header, rows, notes)


def _row_speed_cells(row: Row) -> list[TCell]:
    """Training time and Gaussian count of a sweep row."""
    return [_stat_cell(row.speed["train"], lambda v: number(v, 1)), _stat_cell(row.speed["gaussians"], count)]


def _paired_text(test: PairedTest) -> TCell:
    """``p (n pairs)``, starred when significant; ``–`` without pairs."""
    if test.p is None:
        return TCell(MISSING)
    return TCell(f"{p_text(test.p)} ({test.n}){star(test)}", test.p, "best" if test.a_better else "")


def ablation_table(board: Board) -> Table:
    """A sweep: transposed (``key | v1 | v2 ...``) for a one-key numeric grid, else one row per label
    with the change of the mean against the first label and the paired test against it (over scene ×
    seed; starred when significant)."""
    anchor = f"sweep-{slug(board.title)}"
    baseline = board.rows[0] if board.rows else None
    notes = [protocol_note(board), INTERVAL_NOTE]
    if baseline is not None and len(board.rows) > 1:
        notes.append(f"Against the first row ({baseline.name}): p (pairs) of the paired test over scene × seed "
                     f"(this section's introduction); *, also on the Δ: p < {ALPHA}; **bold**: significantly "
                     f"better than {baseline.name}.")
    notes.append(TIMES_NOTE)
    if board.grid_key:
        return _grid_table(board, anchor, notes)
    several = len(board.scenes) > 1
    header = ["label", "method", *board.scenes, *(["mean"] if several else []),
              f"Δ vs {board.rows[0].name}" if board.rows else "Δ",
              f"p vs {board.rows[0].name} (pairs)" if board.rows else "p", "train (s)", "Gaussians", "runs"]
    best = {column: board.best(column) for column in [*board.scenes, "mean"]}
    first, first_complete = board.mean(board.rows[0]) if board.rows else (None, False)
    rows = []
    for row in board.rows:
        value, complete = board.mean(row)
        cells = [plain(row.name), plain(join_text(row.methods))]
        cells += [metric_cell(row.cells.get(scene), row.name in best[scene]) for scene in board.scenes]
        if several:
            cells.append(TCell(number(value) if complete else MISSING, value if complete else None,
                               "best" if row.name in best["mean"] else ""))
        delta = value - first if complete and first_complete and value is not None and first is not None else None
        test = compare_rows(board, row, baseline) if row is not baseline else None
        cells.append(TCell(MISSING if delta is None else f"{delta:+.3f}{star(test)}", delta))
        cells.append(_paired_text(test) if test is not None else TCell(MISSING))
        cells += _row_speed_cells(row)
        cells.append(plain(status_text(row.counts)))
        rows.append(cells)
    return Table(anchor, board.title, header, rows, notes)


def _value_text(value: float) -> str:
    return str(int(value)) if value == int(value) else f"{value:g}"


def _grid_table(board: Board, anchor: str, notes: list[str]) -> Table:
    header = [board.grid_key, *(_value_text(v) for v in board.grid_values)]
    rows = []
    for scene in board.scenes:
        best = board.best(scene)
        label = board.spec.label if len(board.scenes) == 1 else f"{board.spec.label}, {scene}"
        rows.append([plain(label)] + [metric_cell(row.cells.get(scene), row.name in best) for row in board.rows])
    if len(board.scenes) > 1:
        best = board.best("mean")
        means = [board.mean(row) for row in board.rows]
        rows.append([plain(f"{board.spec.label}, mean")] +
                    [TCell(number(v) if c else MISSING, v if c else None, "best" if row.name in best else "")
                     for row, (v, c) in zip(board.rows, means)])
    if len(board.rows) > 1:
        baseline = board.rows[0]
        tests = [compare_rows(board, row, baseline) for row in board.rows[1:]]
        rows.append([plain(f"paired vs {_value_text(board.grid_values[0])}: Δ, p (pairs)")] + [TCell(MISSING)] +
                    [TCell(MISSING if t.p is None else
                           f"{t.mean_diff:+.3f}, {p_text(t.p)} ({t.n}){star(t)}",
                           t.p, "best" if t.a_better else "") for t in tests])
    speed = [_row_speed_cells(row) for row in board.rows]
    rows.append([plain("train (s)")] + [cells[0] for cells in speed])
    rows.append([plain("Gaussians")] + [cells[1] for cells in speed])
    rows.append([plain("runs")] + [plain(status_text(row.counts)) for row in board.rows])
    return Table(anchor, board.title, header, rows, notes)
