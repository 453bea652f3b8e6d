"""The Evaluator interface shared by every metric family, and the result dictionary it returns.

An evaluator is a versioned protocol: ``name``, ``version`` (bumped whenever a number it reports can
change), ``requires`` (``"mesh"`` and/or ``"renders"``), ``needs`` (what it needs from the scene:
``"gt"`` ground truth, ``"masks"`` object masks, ``"held_out"`` views not trained on; the runner
resolves the evaluator list against these before loading images, `gsbench.evaluators.resolve`), and
``metrics`` (each with its direction and unit). ``evaluate`` returns::

    {"metrics": {metric: float},
     "protocol": {"name": ..., "version": ..., <every option that can change a number>},
     "diagnostics": {counts, per-phase seconds, peak RSS, warnings, ...}}

Options are a frozen dataclass per evaluator (``Options``); ``evaluate(mesh, scene, **options)``
rejects unknown option names with the list of valid ones. ``memory_per_face`` (bytes) is what an
evaluator of a mesh file needs at its peak per face, measured on large meshes (`gsbench.evaluators.api`
checks a mesh against the memory available before scoring it).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from abc import ABC, abstractmethod
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, ClassVar

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError
from gsbench.resources import peak_rss_bytes


@dataclass(frozen=True)
class MetricInfo:
    """How to read one metric: ``higher_is_better`` (None: a description of the mesh, shown and never ranked)
    and its ``unit`` (``""`` when unitless)."""

    higher_is_better: bool | None
    unit: str
    description: str = ""


class Diagnostics:
    """Collects per-phase wall times, the peak RSS after each phase, counts and warnings."""

    def __init__(self) -> None:
        self.data: dict[str, Any] = {"seconds": {}, "peak_rss_bytes": {}, "warnings": []}

    @contextmanager
    def phase(self, name: str):
        """Time a block; records ``seconds[name]`` and ``peak_rss_bytes[name]`` (process peak so far)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.data["seconds"][name] = round(time.perf_counter() - start, 4)
            self.data["peak_rss_bytes"][name] = peak_rss_bytes()

    def warn(self, message: str) -> None:
        """Issue a Python warning and keep the message in the diagnostics."""
        warnings.warn(message, stacklevel=3)
        self.data["warnings"].append(message)

    def __setitem__(self, key: str, value: Any) -> None:
        self.data[key] = value

    def finish(self) -> dict:
        self.data["total_seconds"] = round(sum(self.data["seconds"].values()), 4)
        self.data["peak_rss_bytes_total"] = peak_rss_bytes()
        return self.data


class Evaluator(ABC):
    """Base class: subclasses set the class attributes and implement `validate` and `evaluate`."""

    name: ClassVar[str]
    version: ClassVar[int] = 1
    requires: ClassVar[tuple[str, ...]] = ("mesh",)
    needs: ClassVar[tuple[str, ...]] = ("gt",)
    metrics: ClassVar[dict[str, MetricInfo]]
    Options: ClassVar[type]
    memory_per_face: ClassVar[int] = 0  # 0: not known (a plugin), not checked

    @property
    def protocol_id(self) -> str:
        """``name@version``, e.g. ``dtu_chamfer@1``."""
        return f"{self.name}@{self.version}"

    def options(self, **overrides: Any):
        """The protocol options with ``overrides`` applied; unknown names are an EvaluationError."""
        known = {f.name for f in dataclasses.fields(self.Options)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise EvaluationError(
                f"{self.name}: unknown option(s) {unknown}; valid options are {sorted(known)}"
            )
        return self.Options(**overrides)

    def protocol(self, opts) -> dict:
        """The protocol block of a result: name, version and every option value."""
        return {"name": self.name, "version": self.version, **dataclasses.asdict(opts)}

    @abstractmethod
    def validate(self, scene: Scene) -> None:
        """Raise EvaluationError naming every missing ground-truth file and how to get it."""

    @abstractmethod
    def evaluate(self, mesh, scene: Scene, **options: Any) -> dict:
        """Score ``mesh`` (path or trimesh.Trimesh, normalised frame unless ``frame="dataset"``)."""


def require_gt(scene: Scene, kind: str, evaluator: str):
    """The scene's GroundTruth, checked to be of ``kind``; EvaluationError otherwise."""
    gt = scene.gt
    if gt is None:
        raise EvaluationError(
            f"{evaluator}: scene '{scene.name}' has no ground truth ({scene.gt_missing or 'none found'}); "
            f"fix: --gt PATH, the folder holding the '{kind}' ground truth"
        )
    if gt.kind != kind:
        raise EvaluationError(
            f"{evaluator}: scene '{scene.name}' has '{gt.kind}' ground truth, expected '{kind}' "
            f"(fix: choose an evaluator for '{gt.kind}' scenes)"
        )
    return gt


def check_files(evaluator: str, files: dict, fix: str) -> None:
    """Raise one EvaluationError listing every missing file of ``files`` (label -> Path)."""
    missing = [f"{label} ({path})" for label, path in files.items() if not path.is_file()]
    if missing:
        raise EvaluationError(f"{evaluator}: missing ground-truth file(s): {'; '.join(missing)}; fix: {fix}")
