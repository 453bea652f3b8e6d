"""The orderings the papers claim, as data, and what the runs measured for each.

Each `Claim` says that one method (or one sweep row) is better than another on one dataset's metric,
with the paper that says so and its numbers. The metric is the one the paper used: DTU the official
script's Chamfer (``chamfer``, mm, lower is better); Tanks and Temples the F1 on mesh vertices plus
face centroids (``f1_centroids``), the point set of the 2DGS / GOF / RaDe-GS evaluation scripts that
produced those papers' TnT numbers (`gsbench.report.metrics.COMPANIONS`). Claims between methods are
measured on the leaderboard of that dataset and metric (runs of a method with several configurations:
the row with the most runs with the metric, named in the table); claims about an ablation are
measured on the rows of the sweep that repeats it (its manifest, by sweep name and row label).

A claim is checked with the paired test of `gsbench.report.stats` over the (scene, seed) pairs both
sides share. Verdicts (`verdict`):

- relation ``>`` (strictly better): *agrees* when the claimed side is significantly better
  (p < 0.05), *disagrees* when the other side is, *not separable* otherwise;
- ``≥`` (at least as good): *agrees* when the claimed side is significantly better, *agrees (not
  separable)* when the test cannot separate them, *disagrees* when the other side is significantly
  better;
- ``≈`` (about equal): *agrees (not separable)* when the test cannot separate them, *disagrees* when
  it can;
- *not measured*: a side has no runs with the metric, or the two share no (scene, seed) pair.

"Not separable" with few pairs is no evidence of equality: the p-value and the number of pairs are
shown beside every verdict.

A claim the runs contradict gets a **cause** (`Outcome.cause`): the measured one from
``configs/findings.yaml`` (`load_findings`: claim text and dataset -> what an experiment showed, with
where it is written up), or ``unexplained``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from gsbench.config.files import config_root, load_yaml
from gsbench.errors import ConfigError
from gsbench.report.aggregate import Board, Row, ablations, leaderboard
from gsbench.report.stats import PairedTest, compare_rows
from gsbench.report.twins import changed_scenes

DTU_TABLES = "2DGS paper, Table 1"
RELATIONS = {">": "better than", "≥": "at least as good as", "≈": "as good as"}


@dataclass(frozen=True)
class Claim:
    """``better`` is claimed ``relation`` (``>``, ``≥``, ``≈``) ``worse`` on ``dataset``'s ``metric``.

    Sides are method names, or with ``sweep`` set, row labels of that sweep (its manifest). ``paper``: the
    paper's numbers of the two sides, as quoted; ``source``: where they are. ``factor``: the claim is about
    scenes of one kind, so only the scenes made with that factor changed (`gsbench.report.twins`, e.g.
    ``transparent``: the glass scenes) are paired."""

    group: str
    dataset: str
    metric: str
    better: str
    worse: str
    paper: str
    source: str
    relation: str = ">"
    sweep: str = ""
    factor: str = ""

    @property
    def text(self) -> str:
        """e.g. ``sugar better than 3dgs``."""
        return f"{self.better} {RELATIONS[self.relation]} {self.worse}"


def _ordering(group, dataset, metric, chain) -> list[Claim]:
    return [Claim(group, dataset, metric, better, worse, paper, source, relation)
            for better, relation, worse, paper, source in chain]


K_PAPER = {2: 0.701, 3: 0.709, 4: 0.684, 5: 0.674, 6: 0.678, 7: 0.686, 8: 0.684, 9: 0.688, 10: 0.692}
K_SOURCE = "IBGS OpenReview discussion, K table (docs/methods/ibgs.md §11.2)"
LOSS_SOURCE = "IBGS OpenReview discussion, screen-space loss table (docs/methods/ibgs.md §11.2)"
LS_SOURCE = "IBGS OpenReview discussion, L_s / L_eigval table (docs/methods/ibgs.md §11.2)"
KERNEL_SOURCE = "IBGS OpenReview discussion, other rasterizers (docs/methods/ibgs.md §11.2)"
GGGS_SOURCE = "GGGS paper (arXiv 2601.17835), DTU mean and TnT Table 2 (docs/methods/gggs.md §4)"
NEUSG_SOURCE = "NeuSG paper v2, ablation table (as summarised; docs/methods/neusg.md §7)"
RT2DGS_SOURCE = "RT2DGS paper, Table 2 (its own transparent captures, 30 000 steps; docs/methods/rt2dgs.md §1)"
RT2DGS_LIGHT_SOURCE = ("RT2DGS paper, Tables 2 and 3 ('Ours' 32.57, 'Ours (with RT)' 30.59, 2DGS 31.06; 'Ours' read as "
                       "not tracing; docs/methods/rt2dgs.md §1)")

CLAIMS: tuple[Claim, ...] = (
    # DTU mean Chamfer (mm): 3DGS 1.96 > SuGaR 1.33 > 2DGS 0.80 > GOF 0.74 > RaDe-GS 0.68 >= IBGS 0.67
    *_ordering("DTU Chamfer (mm) 3DGS > SuGaR > 2DGS > GOF > RaDe-GS ≥ IBGS: 3DGS worst, IBGS best", "dtu", "chamfer", (
        ("sugar", ">", "3dgs", "1.33 vs 1.96", f"{DTU_TABLES} (SuGaR and 3DGS rows)"),
        ("2dgs", ">", "sugar", "0.80 vs 1.33", f"{DTU_TABLES} (2DGS and SuGaR rows)"),
        ("gof", ">", "2dgs", "0.74 vs 0.80", "GOF paper, DTU table (as quoted by PGSR, MILo); 2DGS paper, Table 1"),
        ("radegs", ">", "gof", "0.68 vs 0.74", "RaDe-GS paper v1, DTU table (as quoted by MILo); GOF paper, DTU table (as quoted by PGSR, MILo)"),
        ("ibgs", "≥", "radegs", "0.67 vs 0.68", "IBGS OpenReview discussion; RaDe-GS paper v1, DTU table"),
    )),
    # TnT mean F1 (vertices + centroids): GOF 0.46 > RaDe-GS 0.40 ~ IBGS 0.40 > 2DGS 0.32 > SuGaR 0.19 > 3DGS 0.09
    *_ordering("TnT F1 GOF > RaDe-GS ≈ IBGS > 2DGS > SuGaR > 3DGS: GOF best, 3DGS worst", "tnt", "f1_centroids", (
        ("gof", ">", "radegs", "0.46 vs 0.40", "GOF paper, TnT table (as quoted by MILo); RaDe-GS as quoted by MILo and the IBGS discussion"),
        ("gof", ">", "ibgs", "0.46 vs 0.40", "GOF paper, TnT table (as quoted by MILo); IBGS OpenReview discussion, TnT table"),
        ("ibgs", "≈", "radegs", "0.40 vs 0.40", "IBGS OpenReview discussion, TnT table"),
        ("radegs", ">", "2dgs", "0.40 vs 0.32", "RaDe-GS as quoted in the IBGS discussion; 2DGS paper v3, Table 2"),
        ("ibgs", ">", "2dgs", "0.40 vs 0.32", "IBGS OpenReview discussion, TnT table; 2DGS paper v3, Table 2"),
        ("2dgs", ">", "sugar", "0.32 vs 0.19", "2DGS paper v3, Table 2 (2DGS and SuGaR rows)"),
        ("sugar", ">", "3dgs", "0.19 vs 0.09", "2DGS paper, Table 2 (SuGaR and 3DGS rows)"),
    )),
    # GGGS against the two methods its paper re-ran (DTU mean Chamfer 0.47 vs PGSR 0.53, RaDe-GS 0.68; TnT F1 0.60 vs
    # PGSR 0.50, RaDe-GS 0.40 as RaDe-GS reports it; GGGS's own re-run of RaDe-GS gives 0.45, docs/methods/gggs.md §4)
    *_ordering("GGGS > PGSR, RaDe-GS (DTU Chamfer, mm)", "dtu", "chamfer", (
        ("gggs", ">", "pgsr", "0.47 vs 0.53", f"{GGGS_SOURCE}; PGSR paper, Table II, PGSR(DS) row"),
        ("gggs", ">", "radegs", "0.47 vs 0.68", f"{GGGS_SOURCE}; RaDe-GS paper v1, DTU table (as quoted by MILo)"),
    )),
    *_ordering("GGGS > PGSR, RaDe-GS (TnT F1)", "tnt", "f1_centroids", (
        ("gggs", ">", "pgsr", "0.6 vs 0.5", f"{GGGS_SOURCE}; PGSR paper, Table III"),
        ("gggs", ">", "radegs", "0.6 vs 0.4", f"{GGGS_SOURCE}; RaDe-GS v1, TnT table (as quoted by MILo)"),
    )),
    # RT2DGS against the methods it compares with on transparent objects (PSNR only; the glass scenes alone)
    *(Claim("RT2DGS > 2DGS, 3DGS on transparent objects (PSNR)", "dtu", "psnr", "rt2dgs", worse, numbers,
            RT2DGS_SOURCE, factor="transparent") for worse, numbers in (("2dgs", "32.57 vs 31.06"),
                                                                     ("3dgs", "32.57 vs 30.21"))),
    # the same paper's ablation: its gain without the ray tracing, which its Table 3 puts below 2DGS
    *(Claim("RT2DGS: its ray tracing (the paper's 'Ours' read as not tracing)", "dtu", "psnr", "rt2dgs_untraced",
            worse, numbers, RT2DGS_LIGHT_SOURCE, sweep="rt2dgs_light", factor="transparent")
      for worse, numbers in (("rt2dgs", "32.57 vs 30.59"), ("2dgs", "32.57 vs 31.06"))),
    # IBGS K: best at K = 5 (DTU mean Chamfer for K = 2..10)
    *(Claim("IBGS: K = 5 best", "dtu", "chamfer", "method.knn_k=5", f"method.knn_k={k}",
            f"{K_PAPER[5]} vs {K_PAPER[k]}", K_SOURCE, sweep="ibgs_k") for k in K_PAPER if k != 5),
    # IBGS loss terms (DTU mean Chamfer)
    Claim("IBGS losses: each one's effect", "dtu", "chamfer", "ibgs", "ibgs_without_Ld_Ln", "0.67 vs 1.28",
          LOSS_SOURCE, sweep="ibgs_losses"),
    Claim("IBGS losses: each one's effect", "dtu", "chamfer", "radegs_v1", "radegs_v1_without_Ld_Ln", "0.69 vs 1.31",
          LOSS_SOURCE, sweep="ibgs_losses"),
    Claim("IBGS losses: each one's effect", "dtu", "chamfer", "ibgs", "radegs_v1", "0.67 vs 0.69",
          LOSS_SOURCE, sweep="ibgs_losses"),
    Claim("IBGS losses: each one's effect", "dtu", "chamfer", "ibgs_without_Ld_Ln", "radegs_v1_without_Ld_Ln",
          "1.28 vs 1.31", LOSS_SOURCE, sweep="ibgs_losses"),
    Claim("IBGS losses: each one's effect", "dtu", "chamfer", "ibgs", "ibgs_Ls_instead_of_eigval", "0.674 vs 0.689",
          LS_SOURCE, sweep="ibgs_losses"),
    Claim("IBGS losses: each one's effect", "dtu", "chamfer", "ibgs", "ibgs_Ls_and_eigval", "0.674 vs 0.685",
          LS_SOURCE, sweep="ibgs_losses"),
    # NeuSG's ablation (Tanks and Temples F1 on one scene, Barn by its full-model value): raw 3DGS centres as the
    # point prior 0.59, + L_s 0.69, + L_s + L_align 0.73 (docs/methods/neusg.md §7)
    Claim("NeuSG: the Gaussian regularisers", "tnt", "f1_centroids", "neusg", "without_sdf_align", "0.73 vs 0.69",
          NEUSG_SOURCE, sweep="neusg_ablation"),
    Claim("NeuSG: the Gaussian regularisers", "tnt", "f1_centroids", "without_sdf_align",
          "without_flatten_and_sdf_align", "0.69 vs 0.59", NEUSG_SOURCE, sweep="neusg_ablation"),
    # The IBGS additions on other kernels (DTU mean Chamfer)
    Claim("IBGS on other kernels", "dtu", "chamfer", "ibgs-2dgs", "2dgs", "0.72 vs 0.75", KERNEL_SOURCE,
          sweep="ibgs_rasterizers"),
    Claim("IBGS on other kernels", "dtu", "chamfer", "ibgs-gof", "gof", "0.70 vs 0.72", KERNEL_SOURCE,
          sweep="ibgs_rasterizers"),
    Claim("IBGS on other kernels", "dtu", "chamfer", "ibgs", "radegs_v1", "0.67 vs 0.69", KERNEL_SOURCE,
          sweep="ibgs_rasterizers"),
)


@dataclass(frozen=True)
class Outcome:
    """What the runs say about one claim: the rows compared (names as in the report), the test, the verdict."""

    claim: Claim
    better_row: str
    worse_row: str
    test: PairedTest | None
    verdict: str
    why: str = ""  # for "not measured": what is missing
    cause: str = ""  # for "disagrees": the measured cause, or "unexplained"


def verdict(relation: str, test: PairedTest | None) -> str:
    """The verdict of a claim from the paired test of its claimed-better side against the other (module
    docstring); "not measured" without a test or pairs."""
    if test is None or test.p is None:
        return "not measured"
    if relation == "≈":
        return "disagrees" if test.significant else "agrees (not separable)"
    if test.a_better:
        return "agrees"
    if test.b_better:
        return "disagrees"
    return "agrees (not separable)" if relation == "≥" else "not separable"


def _has_metric(row: Row) -> int:
    return sum(1 for cell in row.cells.values() for r in cell.runs if r.ok and cell.metric in r.metrics)


def method_row(board: Board, method: str) -> Row | None:
    """The row of ``method`` on ``board``: its only row, or of several configurations the one with the most
    runs with the metric (then the first by name); None when it has none."""
    rows = [row for row in board.rows if row.methods == [method] and _has_metric(row)]
    return max(rows, key=_has_metric) if rows else None


def sweep_row(boards: list[Board], label: str) -> Row | None:
    rows = [row for board in boards for row in board.rows if row.name == label and _has_metric(row)]
    return rows[0] if rows else None


def _measure(claim: Claim, board: Board | None, better: Row | None, worse: Row | None) -> Outcome:
    missing = [side for side, row in ((claim.better, better), (claim.worse, worse)) if row is None]
    if board is None or missing:
        where = f"sweep {claim.sweep}" if claim.sweep else f"the {claim.dataset} {claim.metric} leaderboard"
        where += f" on the scenes made {claim.factor}" if claim.factor else ""
        why = f"no runs of {' and '.join(missing) if missing else 'either side'} with {claim.metric} in {where}"
        return Outcome(claim, better.name if better else "", worse.name if worse else "", None, "not measured", why)
    if claim.factor:
        changed = changed_scenes(claim.factor)
        board = replace(board, scenes=[s for s in board.scenes if s in changed])
    test = compare_rows(board, better, worse)
    why = "" if test.p is not None else "no (scene, seed) pair in common"
    if claim.factor and test.p is None:
        why = f"no (scene, seed) pair in common on the scenes made {claim.factor}"
    return Outcome(claim, better.name, worse.name, test, verdict(claim.relation, test), why)


FINDINGS_FILE = "findings.yaml"
UNEXPLAINED = "unexplained"


def load_findings(path=None) -> dict[tuple[str, str], str]:
    """(dataset, claim text) -> the measured cause of the runs contradicting it, from ``configs/findings.yaml``
    (``causes: {dataset: {claim text: cause}}``); unknown claim texts are an error naming them."""
    path = path or config_root() / FINDINGS_FILE
    causes = load_yaml(path).get("causes") or {}
    known = {(c.dataset, c.text) for c in CLAIMS}
    found = {(dataset, text): str(cause) for dataset, entries in causes.items() for text, cause in (entries or {}).items()}
    unknown = sorted(f"{d}: {t}" for d, t in found if (d, t) not in known)
    if unknown:
        raise ConfigError(f"{path}: causes for claims that do not exist: {'; '.join(unknown)}; fix: use a claim's text "
                          "as the report shows it (e.g. '2dgs better than sugar') under its dataset")
    return found


def evaluate_claims(runs, manifests, specs, claims=CLAIMS, findings=None) -> list[Outcome]:
    """Every claim against the runs (`gsbench.report.collect.Run`, labelled) and sweep manifests;
    ``specs``: metric name -> `MetricSpec` (`gsbench.report.metrics.metric_specs`); ``findings``: the causes of
    contradicted claims (`load_findings`, read when None)."""
    findings = load_findings() if findings is None else findings
    boards: dict[tuple, Board] = {}
    sweep_boards: dict[tuple, list[Board]] = {}
    by_id = {r.run_id: r for r in runs}
    outcomes = []
    for claim in claims:
        spec = specs.get(claim.metric)
        if spec is None:
            outcomes.append(Outcome(claim, "", "", None, "not measured", f"metric {claim.metric} unknown"))
            continue
        if claim.sweep:
            key = (claim.sweep, claim.dataset, claim.metric)
            if key not in sweep_boards:
                sweep_boards[key] = [b for m in manifests if m.name == claim.sweep
                                     for b in ablations(m, by_id, {claim.dataset: spec})]
            found = sweep_boards[key]
            better, worse = sweep_row(found, claim.better), sweep_row(found, claim.worse)
            board = next((b for b in found if any(r is better for r in b.rows) and any(r is worse for r in b.rows)),
                         None)
        else:
            key = (claim.dataset, claim.metric)
            if key not in boards:
                boards[key] = leaderboard(runs, claim.dataset, spec, {})
            board = boards[key]
            better, worse = method_row(board, claim.better), method_row(board, claim.worse)
        outcome = _measure(claim, board if better is not None and worse is not None else None, better, worse)
        if outcome.verdict == "disagrees":
            outcome = replace(outcome, cause=findings.get((claim.dataset, claim.text), UNEXPLAINED))
        outcomes.append(outcome)
    return outcomes

