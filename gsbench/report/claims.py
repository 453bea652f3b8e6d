"""The orderings the papers claim, and what the runs measured for each.

The claims are data: each stands in a method's file (``configs/methods/<method>.yaml``, ``claims:``) and names its
group in ``configs/claim_groups.yaml`` (the report's table: its heading, dataset, metric, and for an ablation the
sweep whose rows are the sides); a side's number is its method's ``reported:`` mean unless the entry's ``paper:``
gives it, so each paper number is written once. A row of an ablation the paper gives no number for (a removal it does
not tabulate, a suite it did not run; or ``null`` under ``paper:``, a row named after its method at a budget the paper
did not run) is quoted as ``–``: the claim is then the paper's direction only. The metric is the one the paper used:
DTU the official script's Chamfer (``chamfer``, mm, lower is better); Tanks and Temples the F1 on mesh vertices plus
face centroids (``f1_centroids``, `gsbench.report.metrics.COMPANIONS`). Claims between methods are measured on the
leaderboard of that dataset and metric (of a method's several configurations, the row with the most runs with the
metric); claims about an ablation on the rows of the sweep that repeats it (its manifest, by sweep name and row
label).

A claim is checked with the paired test of `gsbench.report.stats` over the (scene, seed) pairs both sides share,
its effect the mean paired difference with its 95% t-interval (`gsbench.report.stats.mean_interval`):

- ``>``: *agrees* when the claimed side is significantly better (p < 0.05), *disagrees* when the other side is,
  *not separable* otherwise;
- ``≥``: as ``>``, but *agrees (not separable)* when the test cannot separate them;
- ``≈``: *agrees (not separable)* when the test cannot separate them, *disagrees* when it can;
- *not measured*: a side has no runs with the metric, or the two share no (scene, seed) pair.

A claim the runs contradict gets a **cause** (`Outcome.cause`): the measured one from ``experiments/findings.yaml``
(`load_findings`), or ``unexplained``. Each claim keeps the method whose file declares it (`Claim.method`), so the
report can gather a paper's claims about its own parts, its ablations, into one table per method.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from gsbench.config.files import (
    CLAIMS_KEY,
    config_root,
    declared_plugins,
    load_yaml,
    method_declaration,
    reported_numbers,
    suggest,
)
from gsbench.errors import ConfigError
from gsbench.report.aggregate import Board, Row, ablations, leaderboard
from gsbench.report.stats import PairedTest, compare_rows
from gsbench.report.twins import changed_scenes

RELATIONS = {">": "better than", "≥": "at least as good as", "≈": "as good as"}
GROUPS_FILE = "claim_groups.yaml"
GROUP_KEYS = {"heading", "dataset", "metric", "sweep", "factor", "order"}
ENTRY_KEYS = {"group", "claim", "source", "paper", "digits"}
DIGITS = 2  # decimals of the paper's numbers as the report quotes them, unless an entry says otherwise
NO_NUMBER = "–"  # a side of an ablation the paper gives no number for


@dataclass(frozen=True)
class Claim:
    """``better`` is claimed ``relation`` (``>``, ``≥``, ``≈``) ``worse`` on ``dataset``'s ``metric``.

    Sides are method names, or with ``sweep`` set, row labels of that sweep (its manifest). ``paper``: the
    paper's numbers of the two sides, as quoted (`NO_NUMBER` for an ablation row it gives none for); ``source``: where
    they are. ``factor``: the claim is about scenes of one kind, so only the scenes made with that factor changed
    (`gsbench.report.twins`, e.g. ``transparent``: the glass scenes) are paired. ``method``: the method whose file
    declares it."""

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
    method: str = ""

    @property
    def text(self) -> str:
        """e.g. ``sugar better than 3dgs``."""
        return f"{self.better} {RELATIONS[self.relation]} {self.worse}"


def _parse(where: str, text) -> tuple[str, str, str]:
    parts = str(text).split()
    if len(parts) != 3 or parts[1] not in RELATIONS:
        raise ConfigError(f"{where}: claim {text!r} must read 'better RELATION worse' with RELATION one of "
                          f"{', '.join(RELATIONS)}, e.g. 'gof > 2dgs'")
    return parts[0], parts[1], parts[2]


def _number(where: str, side: str, paper: dict, group: dict) -> float | None:
    """The paper's number of ``side``: the entry's (None where it is ``null``: a row named after a method, at a budget
    the paper did not run), else its method's reported mean; None for a row of an ablation (a ``sweep`` group) that
    has neither."""
    dataset, metric = group["dataset"], group["metric"]
    if side in paper:
        return paper[side]
    entry = reported_numbers(side).get(dataset) or {}
    if entry.get("metric") != metric or entry.get("mean") is None:
        if group.get("sweep"):
            return None
        raise ConfigError(f"{where}: no paper number for '{side}': it has no reported {dataset} {metric} mean "
                          f"(configs/methods/{side}.yaml); give it under paper:")
    return float(entry["mean"])


def _quoted(value: float | None, digits: int) -> str:
    return NO_NUMBER if value is None else f"{value:.{digits}f}"


def quoted_numbers(entry: dict) -> dict[str, float | None]:
    """A claims entry's ``paper:``, side → the paper's number; None where it is ``null`` (no number for that side)."""
    return {str(label): None if value is None else float(value) for label, value in (entry.get("paper") or {}).items()}


def _entry_claims(where: str, method: str, entry, groups: dict) -> tuple[str, list[Claim]]:
    """(group name, the claims of one ``claims:`` entry of ``method``'s file)."""
    if not isinstance(entry, dict) or set(entry) - ENTRY_KEYS or not {"group", "claim", "source"} <= set(entry):
        raise ConfigError(f"{where}: a claims entry is a mapping with group, claim and source (optional: paper, "
                          f"digits), got {entry!r}")
    name = entry["group"]
    if name not in groups:
        raise ConfigError(f"{where}: unknown group {name!r}{suggest(name, groups)}; groups: configs/{GROUPS_FILE}")
    group = groups[name]
    texts = [entry["claim"]] if isinstance(entry["claim"], str) else entry["claim"]
    source = entry["source"] if isinstance(entry["source"], str) else "; ".join(entry["source"])
    try:
        paper = quoted_numbers(entry)
        digits = int(entry.get("digits", DIGITS))
    except (AttributeError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: paper must map sides to numbers (or null) and digits be an integer ({exc})") from exc
    claims = []
    for text in texts:
        better, relation, worse = _parse(where, text)
        a, b = (_number(where, side, paper, group) for side in (better, worse))
        claims.append(Claim(group["heading"], group["dataset"], group["metric"], better, worse,
                            f"{_quoted(a, digits)} vs {_quoted(b, digits)}", source, relation, group.get("sweep", ""),
                            group.get("factor", ""), method))
    return name, claims


def _in_order(where: str, order, claims: list[Claim]) -> list[Claim]:
    by_sides = {(c.better, c.relation, c.worse): c for c in claims}
    wanted = [_parse(where, text) for text in order]
    if len(by_sides) != len(claims) or sorted(by_sides) != sorted(wanted):
        declared = sorted(f"{b} {r} {w}" for b, r, w in by_sides)
        raise ConfigError(f"{where}: order must list each of the group's claims once; the method files declare "
                          f"{declared}, order lists {list(order)}")
    return [by_sides[sides] for sides in wanted]


def load_claims() -> tuple[Claim, ...]:
    """Every claim of the method files, group by group in the order of ``configs/claim_groups.yaml``; within a
    group in its ``order`` or, without one, as declared (method files by name). Errors name the file and key."""
    path = config_root() / GROUPS_FILE
    groups = load_yaml(path).get("groups") or {}
    for name, group in groups.items():
        if not isinstance(group, dict) or set(group) - GROUP_KEYS or not {"heading", "dataset", "metric"} <= set(group):
            raise ConfigError(f"{path}: groups.{name} must map heading, dataset, metric (optional: sweep, factor, "
                              f"order), got {group!r}")
    found: dict[str, list[Claim]] = {name: [] for name in groups}
    for method in declared_plugins("methods"):
        for i, entry in enumerate(method_declaration(method, CLAIMS_KEY) or []):
            name, claims = _entry_claims(f"configs/methods/{method}.yaml: claims[{i}]", method, entry, groups)
            found[name] += claims
    return tuple(claim for name, group in groups.items()
                 for claim in (_in_order(f"{path}: groups.{name}.order", group["order"], found[name])
                               if "order" in group else found[name]))


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


FINDINGS_FILE = Path("experiments") / "findings.yaml"  # the repository's, read from its root; not installed
UNEXPLAINED = "unexplained"


def load_findings(path=None) -> dict[tuple[str, str], str]:
    """(dataset, claim text) -> the measured cause of the runs contradicting it, from ``path`` (default
    ``experiments/findings.yaml`` under the working folder; none there: no causes, every contradiction
    "unexplained") as ``causes: {dataset: {claim text: cause}}``; unknown claim texts are an error naming them."""
    if path is None and not FINDINGS_FILE.is_file():
        return {}
    path = path or FINDINGS_FILE
    causes = load_yaml(path).get("causes") or {}
    known = {(c.dataset, c.text) for c in load_claims()}
    found = {(dataset, text): str(cause) for dataset, entries in causes.items() for text, cause in (entries or {}).items()}
    unknown = sorted(f"{d}: {t}" for d, t in found if (d, t) not in known)
    if unknown:
        raise ConfigError(f"{path}: causes for claims that do not exist: {'; '.join(unknown)}; fix: use a claim's text "
                          "as the report shows it (e.g. '2dgs better than sugar') under its dataset")
    return found


def evaluate_claims(runs, manifests, specs, claims=None, findings=None) -> list[Outcome]:
    """The claims (`load_claims` when None) against the runs (`gsbench.report.collect.Run`, labelled) and sweep
    manifests; ``specs``: metric name -> `MetricSpec` (`gsbench.report.metrics.metric_specs`); ``findings``: the
    causes of contradicted claims (`load_findings`, read when None)."""
    claims = load_claims() if claims is None else claims
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

