"""How to read a metric (direction, unit, display name), which metric ranks a dataset, and the
paper-reported numbers that methods declare.

Directions and units come from the evaluators (`MetricInfo` of each registered evaluator); `FALLBACK`
covers the built-in metrics when an evaluator cannot be imported. The ranking metric of a dataset is
the one its papers rank by: DTU Chamfer (mm, lower is better), TnT F1 (higher is better).

Measures that need no ground-truth geometry (`NO_GT`: held-out PSNR/SSIM of ``image``, the mask
agreement of ``silhouette``, the ``mesh_stats`` description) have their own table, per run. Of them only
PSNR/SSIM may rank a leaderboard (when no run of a dataset has its papers' metric); `UNRANKED` never
do: mask IoU and the outside-hull share compare with masks, not with the object, and the mesh
statistics describe a mesh (``area``, ``vertices``, ``faces`` are not scores at all).

Protocols: DTU's ranking metric is the official script's Chamfer and TnT's the official toolbox's F1
(mesh vertices); `COMPANIONS` are each dataset's further leaderboards (area samples; for TnT also
vertices plus face centroids, the convention of the 2DGS / GOF / RaDe-GS scripts with which those papers
computed their TnT numbers). Every label names its protocol (`DISPLAY`).

Reported numbers: a method's declaration ``configs/methods/<method>.yaml`` may hold ``reported:``
(not inherited through ``extends``, since a variant is a different method)::

    reported:
      dtu: {metric: chamfer, mean: 0.80, scenes: {scan24: 0.48, ...}, source: "2DGS paper, Table 1"}

These are numbers on the real datasets (GPU, the paper's schedule). The report shows them beside the
measured ones and labels them so; they are not comparable with synthetic scenes or CPU budgets.
"""

from __future__ import annotations

from dataclasses import dataclass

from gsbench.config.files import reported_numbers
from gsbench.registry import EVALUATORS

PRIMARY = {"dtu": "chamfer", "tnt": "f1"}
PRIMARY_ORDER = ("chamfer", "f1", "psnr")
DATASET_TITLES = {"dtu": "DTU protocol", "tnt": "Tanks and Temples protocol"}
REAL_DATASETS = {"dtu": "real DTU", "tnt": "real TnT"}
DISPLAY = {"chamfer": "Chamfer, official script", "chamfer_sampled": "Chamfer, area samples",
           "f1": "F1, official toolbox (vertices)", "f1_centroids": "F1, vertices + centroids (2DGS / GOF scripts)",
           "f1_sampled": "F1, area samples", "psnr": "PSNR", "ssim": "SSIM",
           "normal_consistency": "normal consistency", "normal_consistency_gated": "gated normal consistency",
           "mask_iou": "mask IoU", "mask_iou_min": "worst-view mask IoU",
           "outside_hull_area_share": "outside-hull area share"}
# Each dataset's other leaderboards, after its ranking one: the tessellation-independent protocol and,
# for TnT, the point set of the papers' own scripts (where their reported numbers are shown).
COMPANIONS = {"dtu": ("chamfer_sampled",), "tnt": ("f1_centroids", "f1_sampled")}
# The metric in which the papers report each dataset (their reported numbers and orderings): DTU the official
# script's Chamfer, TnT the F1 on vertices + centroids of the 2DGS / GOF / RaDe-GS scripts.
PAPERS_METRIC = {"dtu": "chamfer", "tnt": "f1_centroids"}
FALLBACK = {  # (higher_is_better, unit) of the built-in evaluators' metrics; None: descriptive, never ranked
    "chamfer": (False, "mm"), "accuracy": (False, "mm"), "completeness": (False, "mm"),
    "chamfer_sampled": (False, "mm"), "accuracy_sampled": (False, "mm"), "completeness_sampled": (False, "mm"),
    "f1": (True, ""), "precision": (True, ""), "recall": (True, ""),
    "f1_centroids": (True, ""), "precision_centroids": (True, ""), "recall_centroids": (True, ""),
    "f1_sampled": (True, ""), "precision_sampled": (True, ""), "recall_sampled": (True, ""),
    "normal_consistency": (True, ""), "normal_accuracy": (True, ""), "normal_completeness": (True, ""),
    "normal_consistency_gated": (True, ""), "normal_accuracy_gated": (True, ""),
    "normal_completeness_gated": (True, ""), "psnr": (True, "dB"), "ssim": (True, ""),
    "mask_iou": (True, ""), "mask_iou_min": (True, ""), "outside_hull_area_share": (False, ""),
    "components": (False, ""), "watertight": (True, ""), "area": (None, "units^2"), "vertices": (None, ""),
    "faces": (None, ""),
}
# The no-ground-truth table's metrics, in column order (names as in a record's ``metrics``).
NO_GT = ("psnr", "ssim", "mask_iou", "outside_hull_area_share", "components", "watertight", "area")
UNRANKED = frozenset({"mask_iou", "mask_iou_min", "outside_hull_area_share", "components", "watertight", "area",
                      "vertices", "faces"})


@dataclass(frozen=True)
class MetricSpec:
    name: str
    higher_is_better: bool | None  # None: describes a mesh, never ranked (in `UNRANKED`)
    unit: str
    evaluator: str = ""  # the evaluator that reports it ("" when only `FALLBACK` knows it)

    @property
    def label(self) -> str:
        """e.g. ``Chamfer (mm)``."""
        name = DISPLAY.get(self.name, self.name)
        return f"{name} ({self.unit})" if self.unit else name

    @property
    def direction(self) -> str:
        return {True: "higher is better", False: "lower is better"}.get(self.higher_is_better, "descriptive")


def metric_specs() -> dict[str, MetricSpec]:
    """Every known metric: the registered evaluators' declarations over `FALLBACK`."""
    specs = {name: MetricSpec(name, better, unit) for name, (better, unit) in FALLBACK.items()}
    for evaluator in EVALUATORS.names():
        try:
            declared = EVALUATORS.get(evaluator).metrics
        except Exception:  # noqa: BLE001  (a broken plugin must not stop the report; FALLBACK stands)
            continue
        for name, info in declared.items():
            better = None if info.higher_is_better is None else bool(info.higher_is_better)
            specs[name] = MetricSpec(name, better, str(info.unit), evaluator)
    return specs


def primary_metric(dataset: str, metrics_seen: set[str], specs: dict[str, MetricSpec]) -> MetricSpec | None:
    """The ranking metric of ``dataset``: `PRIMARY`, else the first of `PRIMARY_ORDER` its runs have,
    else the alphabetically first metric they have outside `UNRANKED`; None when no run has one (for a
    dataset of `PRIMARY`: its papers' metric, whether or not a run has it)."""
    candidates = [PRIMARY.get(dataset), *PRIMARY_ORDER, *sorted(set(metrics_seen) - UNRANKED)]
    for name in candidates:
        if name and name in metrics_seen:
            return specs.get(name) or MetricSpec(name, False, "")
    if dataset in PRIMARY:
        name = PRIMARY[dataset]
        return specs.get(name) or MetricSpec(name, False, "")
    return None


@dataclass(frozen=True)
class Reported:
    """A paper's number for one method on one real dataset."""

    metric: str
    mean: float | None
    scenes: dict
    source: str

    def scene_value(self, scene: str) -> float | None:
        """The paper's per-scene value when ``scene`` names a real scene (case-insensitive)."""
        lowered = {str(k).lower(): v for k, v in self.scenes.items()}
        return lowered.get(scene.lower())


def reported(method: str, dataset: str, warnings: list[str]) -> Reported | None:
    """The ``reported`` entry of ``method``'s declaration for ``dataset`` (module docstring); an unreadable
    declaration or a malformed entry adds a warning and gives None."""
    try:
        entry = reported_numbers(method).get(dataset)
    except Exception as exc:  # noqa: BLE001  (an unreadable declaration: no reference numbers)
        warnings.append(f"method '{method}': no reported numbers ({type(exc).__name__}: {exc})")
        return None
    if entry is None:
        return None
    try:
        mean = entry.get("mean")
        return Reported(metric=str(entry["metric"]), mean=None if mean is None else float(mean),
                        scenes={str(k): float(v) for k, v in (entry.get("scenes") or {}).items()},
                        source=str(entry.get("source", "")))
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        warnings.append(f"method '{method}': malformed reported['{dataset}'] ignored ({type(exc).__name__}: {exc})")
        return None
