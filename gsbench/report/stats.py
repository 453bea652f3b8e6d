"""The report's statistics: confidence intervals over seeds, ranks, and paired comparisons of rows.

**Interval of a cell** (`t_half_width`). A cell holds the values x_1..x_n of one configuration on one
scene, one per seed. With the sample mean m and the sample standard deviation
s = sqrt(Σ (x_i − m)² / (n − 1)), the 95% Student t-interval of the mean is

    m ± t_{0.975, n−1} · s / √n          (n ≥ 2; n = 1 has no interval)

where t_{0.975, n−1} is the 97.5% quantile of Student's t with n − 1 degrees of freedom
(scipy.stats.t.ppf; 12.71 for n = 2, 4.30 for n = 3, 2.78 for n = 5). It assumes the seeds' values
are independent draws from a normal distribution; it describes seed-to-seed variation only, not the
choice of scenes.

**Pairs** (`pair_values`). Two rows (configurations) are compared on what both measured under the
same conditions: the pairs (scene, seed) on which both have an ``ok`` run with the metric (several runs
of one row on one pair, which only a malformed runs folder holds, are averaged). The paired
difference is d_j = a_j − b_j, in the metric's own units; the row a is *better* on a pair when
d_j < 0 for a metric where lower is better (Chamfer) and d_j > 0 where higher is better (F1).

**Paired test** (`paired_test`), two-sided, of "the differences are symmetric about 0":

- Wilcoxon signed-rank (``scipy.stats.wilcoxon``, method "auto"): the zero differences are dropped
  (Wilcoxon's convention), the n' others ranked by |d_j| (ties: mid-ranks) and
  W+ = Σ_{d_j > 0} rank_j compared with its null distribution — exact for n' ≤ 50 without ties,
  an exact permutation distribution with ties for n' ≤ 13 (scipy ≥ 1.13), the normal approximation
  with tie and continuity corrections beyond;
- the sign test, when all differences are zero or fewer than `MIN_WILCOXON` = 6 are non-zero
  (n tiny): p = min(1, 2 · P[B ≤ min(k, n' − k)]) with B ~ Binomial(n', 1/2) and k the number of
  positive differences (exact; p = 1 when n' = 0). Below 6 non-zero differences neither test can
  reach p < 0.05 (the smallest two-sided p of both is 2 / 2^n' ≥ 0.0625), and the sign test's p is
  the simpler one to check by hand.

A difference is *significant* when p < `ALPHA` = 0.05 (no correction for the many comparisons of a
matrix: read a single significant cell among many with care), in the direction the statistic leans:
the sign of W+ − W− (sign test: of wins − losses), read in the metric's direction.

**Ranks** (`scene_ranks`, `mean_ranks`, `significance_ranks`). On each scene the rows with a value are
ranked by their cell means (1 = best, ties share the mean of their ranks); a row's mean rank is the
mean over the board's scenes, for rows with a value on every scene. The *significance rank* of such
a complete row is 1 + the number of complete rows that are significantly better than it in the paired
test: rows that no other row beats significantly share rank 1, and rows the test cannot separate
from the same rows share a rank.

**Interval of a paired difference** (`mean_interval`). The effect of a comparison is the mean paired difference
d̄ = Σ d_j / n over its n pairs, with the 95% Student t-interval d̄ ± t_{0.975, n−1} · s_d / √n (s_d the sample
standard deviation of the d_j; n ≥ 2), as for a cell. It assumes the pairs independent and normal; the pairs on one
scene share that scene's effect, so it speaks for these scenes, not for scenes in general. The verdicts rest on the
paired test above, not on it: at few pairs the two can disagree at the edge.

**Pairs to decide** (`pairs_to_decide`). How many pairs a comparison that is not separable would need,
if the true paired differences had the measured mean d̄ and standard deviation s_d: the
normal-approximation size of a two-sided test at level α with power 1 − β,

    n_t = ((z_{1−α/2} + z_{1−β}) · s_d / |d̄|)²          (α = 0.05, 1 − β = `POWER` = 0.8)

divided by 3/π ≈ 0.955, the asymptotic relative efficiency of the Wilcoxon signed-rank test to the
t-test for normal differences (Hodges and Lehmann 1956), and at least `MIN_WILCOXON`. It is a
projection, not a measurement: a measured |d̄| that happens to be large makes it too small, and pairs
from new scenes may spread more than the seeds of the scenes measured.
"""

from __future__ import annotations

import functools
import math
import statistics
from dataclasses import dataclass

import numpy as np
from scipy.stats import binomtest, norm, rankdata, t, wilcoxon

ALPHA = 0.05
CONFIDENCE = 0.95
POWER = 0.8
WILCOXON_ARE = 3 / math.pi  # Wilcoxon signed-rank vs t-test, normal differences (module docstring)
MIN_WILCOXON = 6  # non-zero differences below which the sign test is used (module docstring)


@functools.lru_cache(maxsize=None)
def _t_quantile(q: float, df: int) -> float:
    return float(t.ppf(q, df))


def t_half_width(values, confidence: float = CONFIDENCE) -> float | None:
    """Half-width t_{(1+confidence)/2, n−1} · s / √n of the Student t-interval of the mean; None for n < 2."""
    values = [float(v) for v in values]
    n = len(values)
    if n < 2:
        return None
    return _t_quantile(0.5 + confidence / 2, n - 1) * statistics.stdev(values) / math.sqrt(n)


@dataclass(frozen=True)
class PairedTest:
    """The paired comparison of row a against row b (module docstring).

    ``n``: pairs; ``mean_diff``: mean of a − b (None without pairs); ``wins``/``losses``: pairs where a
    is better / worse (ties are neither); ``p``: two-sided p-value (None without pairs); ``test``:
    ``wilcoxon``, ``sign`` or ``""`` (no pairs); ``direction``: +1 when the test's statistic leans
    towards a being better, −1 towards b, 0 neither (Wilcoxon: the sign of the signed-rank sum
    W+ − W− read in the metric's direction; sign test: wins − losses); ``sd_diff``: the sample
    standard deviation of a − b (None for fewer than 2 pairs)."""

    n: int
    mean_diff: float | None
    wins: int
    losses: int
    p: float | None
    test: str
    direction: int = 0
    sd_diff: float | None = None

    @property
    def significant(self) -> bool:
        return self.p is not None and self.p < ALPHA and self.direction != 0

    @property
    def a_better(self) -> bool:
        """Row a is significantly better than row b."""
        return self.significant and self.direction > 0

    @property
    def b_better(self) -> bool:
        """Row b is significantly better than row a."""
        return self.significant and self.direction < 0

    def swapped(self) -> PairedTest:
        """The same comparison read as b against a."""
        mean = None if self.mean_diff is None else -self.mean_diff
        return PairedTest(self.n, mean, self.losses, self.wins, self.p, self.test, -self.direction, self.sd_diff)


def sign_test_p(positive: int, negative: int) -> float:
    """Exact two-sided sign test, ``scipy.stats.binomtest(positive, n, 1/2)``: min(1, 2 · P[B ≤ min(k, n − k)]),
    B ~ Binomial(n, 1/2); 1 when n = 0."""
    n = positive + negative
    if n == 0:
        return 1.0
    return float(binomtest(positive, n, 0.5).pvalue)


def wilcoxon_p(differences) -> float:
    """Two-sided Wilcoxon signed-rank p-value of the non-zero ``differences`` (scipy, method "auto")."""
    return float(wilcoxon(differences, zero_method="wilcox", alternative="two-sided", method="auto").pvalue)


def paired_test(differences, higher_is_better: bool) -> PairedTest:
    """Test the paired differences a − b (module docstring): Wilcoxon signed-rank, or the sign test when
    fewer than `MIN_WILCOXON` are non-zero; wins/losses counted in the metric's direction."""
    d = [float(x) for x in differences]
    if not d:
        return PairedTest(0, None, 0, 0, None, "")
    sign = 1.0 if higher_is_better else -1.0
    wins = sum(1 for x in d if sign * x > 0)
    losses = sum(1 for x in d if sign * x < 0)
    nonzero = [x for x in d if x != 0]
    if len(nonzero) < MIN_WILCOXON:
        p, test = sign_test_p(sum(x > 0 for x in nonzero), sum(x < 0 for x in nonzero)), "sign"
        lean = wins - losses
    else:
        p, test = wilcoxon_p(nonzero), "wilcoxon"
        lean = sign * _signed_rank_sum(nonzero)
    direction = (lean > 0) - (lean < 0)
    sd = statistics.stdev(d) if len(d) >= 2 else None
    return PairedTest(len(d), statistics.fmean(d), wins, losses, p, test, direction, sd)


def mean_interval(test: PairedTest, confidence: float = CONFIDENCE) -> tuple[float, float] | None:
    """(low, high) of d̄ ± t_{(1+confidence)/2, n−1} · s_d / √n, the t-interval of the mean paired difference
    (module docstring); None for fewer than 2 pairs."""
    if test.sd_diff is None or test.mean_diff is None:
        return None
    half = _t_quantile(0.5 + confidence / 2, test.n - 1) * test.sd_diff / math.sqrt(test.n)
    return test.mean_diff - half, test.mean_diff + half


def pairs_to_decide(test: PairedTest, power: float = POWER) -> int | None:
    """Pairs at which the paired test would find the measured mean difference significant with probability
    ``power``, were it and the measured spread the true ones (module docstring):
    max(`MIN_WILCOXON`, ⌈((z_{1−α/2} + z_power) · s_d / |d̄|)² / (3/π)⌉); `MIN_WILCOXON` when s_d = 0.
    None for fewer than 2 pairs or d̄ = 0 (nothing to project from)."""
    if test.sd_diff is None or not test.mean_diff:
        return None
    z = float(norm.ppf(1 - ALPHA / 2) + norm.ppf(power))
    n_t = (z * test.sd_diff / abs(test.mean_diff)) ** 2
    return max(MIN_WILCOXON, math.ceil(n_t / WILCOXON_ARE))


def _signed_rank_sum(differences: list[float]) -> float:
    """W+ − W−: the ranks of |d| (ties: mid-ranks) summed with the signs of d."""
    d = np.asarray(differences, dtype=float)
    return float(np.sign(d) @ rankdata(np.abs(d)))


def pair_values(runs_a, runs_b, metric: str) -> list[tuple[tuple, float, float]]:
    """[((scene, seed), a, b)] over the pairs on which both run lists have an ok run with ``metric``,
    sorted; several runs of one list on one pair are averaged."""

    def by_pair(runs) -> dict[tuple, float]:
        values: dict[tuple, list[float]] = {}
        for run in runs:
            if run.ok and metric in run.metrics:
                values.setdefault((run.scene, -1 if run.seed is None else run.seed), []).append(run.metrics[metric])
        return {key: statistics.fmean(v) for key, v in values.items()}

    a, b = by_pair(runs_a), by_pair(runs_b)
    return [(key, a[key], b[key]) for key in sorted(set(a) & set(b))]


def compare_runs(runs_a, runs_b, metric: str, higher_is_better: bool) -> PairedTest:
    """`paired_test` of the runs of row a against those of row b on their shared (scene, seed) pairs."""
    return paired_test([x - y for _, x, y in pair_values(runs_a, runs_b, metric)], higher_is_better)


def compare_rows(board, a, b) -> PairedTest:
    """Row ``a`` against row ``b`` of ``board`` (a `gsbench.report.aggregate.Board`), on its scenes."""
    scenes = set(board.scenes)
    runs_a = [r for r in a.runs if r.scene in scenes]
    runs_b = [r for r in b.runs if r.scene in scenes]
    return compare_runs(runs_a, runs_b, board.spec.name, board.spec.higher_is_better)


def comparisons(board) -> dict[tuple[str, str], PairedTest]:
    """Every ordered pair of distinct rows (a, b) of ``board`` -> a against b."""
    out: dict[tuple[str, str], PairedTest] = {}
    rows = board.rows
    for i, a in enumerate(rows):
        for b in rows[i + 1:]:
            test = compare_rows(board, a, b)
            out[(a.name, b.name)] = test
            out[(b.name, a.name)] = test.swapped()
    return out


def _ranks(values: dict[str, float], higher_is_better: bool) -> dict[str, float]:
    """1 = best; ties share the mean of the ranks they span (``scipy.stats.rankdata``, method "average")."""
    sign = -1.0 if higher_is_better else 1.0
    return dict(zip(values, (float(r) for r in rankdata([sign * v for v in values.values()]))))


def scene_ranks(board) -> dict[str, dict[str, float]]:
    """Row name -> {scene: rank of its cell mean among the rows with a value on that scene}."""
    out: dict[str, dict[str, float]] = {row.name: {} for row in board.rows}
    for scene in board.scenes:
        values = {row.name: row.cells[scene].stat.mean for row in board.rows
                  if scene in row.cells and row.cells[scene].stat}
        for name, rank in _ranks(values, board.spec.higher_is_better).items():
            out[name][scene] = rank
    return out


def mean_ranks(board, ranks: dict[str, dict[str, float]] | None = None) -> dict[str, float | None]:
    """Row name -> its mean rank over the board's scenes; None for a row without a value on every scene."""
    ranks = scene_ranks(board) if ranks is None else ranks
    return {name: statistics.fmean(r.values()) if len(r) == len(board.scenes) and r else None
            for name, r in ranks.items()}


def significance_ranks(board, tests: dict[tuple[str, str], PairedTest]) -> dict[str, int]:
    """Row name -> 1 + the number of complete rows significantly better in the paired test (``tests``, the
    board's `comparisons`), for the rows with a value on every scene (module docstring)."""
    complete = [row.name for row in board.rows if board.mean(row)[1]]
    return {name: 1 + sum(1 for other in complete if other != name and tests[(other, name)].a_better)
            for name in complete}
