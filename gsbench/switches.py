"""Every ``GSBENCH_*`` environment variable, stated once (docs/switches.md); the package reads them only here.

A switch's ``kind`` says what it can change:

- ``result``: which implementation computes a number (a fast kernel or its PyTorch reference: equal to
  rounding, not bit for bit). A run writes all of them into its record (``environment.switches``), warns
  when one is not at its default, and a run folder refuses to resume under other values
  (`gsbench.runs.records.check_folder_switches`).
- ``speed``: how fast only; tests/test_switches.py checks that a run's numbers stay bit-identical.
- ``path``: where a cache lives.
- ``tests``: read by the test suite only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from gsbench.errors import ConfigError

KINDS = ("result", "speed", "path", "tests")
ON_OFF = ("on", "off")
_ON_OFF_SPELLINGS = {"1": "on", "true": "on", "yes": "on", "0": "off", "false": "off", "no": "off"}


@dataclass(frozen=True)
class Switch:
    """``name``: the variable; ``selects``: what it chooses; ``values``: the allowed values, the default first
    (empty: any text, a folder); ``default``: the value when unset or empty; ``kind``: one of `KINDS`."""

    name: str
    selects: str
    values: tuple[str, ...]
    default: str
    kind: str

    def value(self) -> str:
        """The value this process has: the default when unset or empty; an on/off switch also takes 1/0,
        true/false, yes/no. Any other value is a `ConfigError` naming the variable and the allowed values."""
        raw = os.environ.get(self.name, "").strip()
        if not raw:
            return self.default
        if not self.values:
            return raw
        value = raw.lower()
        if self.values == ON_OFF:
            value = _ON_OFF_SPELLINGS.get(value, value)
        if value not in self.values:
            raise ConfigError(f"{self.name}='{raw}' is not one of {self.values}; unset it to use the default "
                              f"({self.default})")
        return value


RASTER = Switch("GSBENCH_RASTER", "the rasterizer: the tiled C++ one, or the slow dense PyTorch reference "
                "(gsbench.raster.reference)", ("fast", "reference"), "fast", "result")
PROJECTION = Switch("GSBENCH_PROJECTION", "the per-view projection of the Gaussians: the fused C++ pass, or its "
                    "vectorised PyTorch oracle", ("fused", "torch"), "fused", "result")
EXACT_OVERLAP = Switch("GSBENCH_EXACT_OVERLAP", "the tile binning of ewa, rade and surfel: only the tiles the "
                       "Gaussian's alpha >= 1/255 ellipse meets, or every tile of its bounding rectangle", ON_OFF, "on",
                       "speed")
EIGEN = Switch("GSBENCH_EIGEN", "IBGS's batched 3x3 symmetric eigen-solver: the C++ closed form, or "
               "torch.linalg.eigh", ("fast", "reference"), "fast", "result")
SSIM = Switch("GSBENCH_SSIM", "the SSIM loss: the fused C++ kernel, or PyTorch's separable convolutions",
              ("fused", "reference"), "fused", "result")
NORMAL_CONSISTENCY = Switch("GSBENCH_NORMAL_CONSISTENCY", "the depth-normal consistency loss: the fused C++ kernel, "
                            "or PyTorch", ("fused", "reference"), "fused", "result")
LOCAL_COVARIANCE = Switch("GSBENCH_LOCAL_COVARIANCE", "IBGS's neighbourhood covariance: the fused C++ kernel, or "
                          "PyTorch", ("fused", "reference"), "fused", "result")
SUGAR_FIELD = Switch("GSBENCH_SUGAR_FIELD", "SuGaR's density and normal field over the kNN: the fused C++ kernel, "
                     "or PyTorch", ("fused", "reference"), "fused", "result")
NEUSG_GRID = Switch("GSBENCH_NEUSG_GRID", "NeuSG's multi-resolution grid features, dense or hashed "
                    "(method.encoding): the fused C++ kernels, or PyTorch (grid_sample; the hash's gathers)",
                    ("fused", "reference"), "fused", "result")
IMAGE_CACHE = Switch("GSBENCH_IMAGE_CACHE", "the decoded-image cache (<GSBENCH_DATA>/decoded): the decoded, "
                     "downscaled images kept between runs", ON_OFF, "on", "speed")
DATA = Switch("GSBENCH_DATA", "the scene cache: generated scenes and decoded images", (), "~/.cache/gsbench/scenes",
              "path")
NODE_RUNS = Switch("GSBENCH_NODE_RUNS", "a Ray node's own run folder: where a Ray task runs its run and keeps its "
                   "checkpoints (docs/cluster.md §1)", (), "~/.cache/gsbench/node-runs", "path")
CACHE = Switch("GSBENCH_CACHE", "the build cache: the compiled C++ libraries go to <it>/native", (), "~/.cache/gsbench",
               "path")
UPDATE_GOLDEN = Switch("GSBENCH_UPDATE_GOLDEN", "set to anything: tests/test_report.py rewrites its golden files "
                       "instead of comparing with them", (), "", "tests")

SWITCHES = (RASTER, PROJECTION, EXACT_OVERLAP, EIGEN, SSIM, NORMAL_CONSISTENCY, LOCAL_COVARIANCE, SUGAR_FIELD,
            NEUSG_GRID, IMAGE_CACHE, DATA, NODE_RUNS, CACHE, UPDATE_GOLDEN)


def result_switches() -> dict[str, str]:
    """``{name: value}`` of every ``result`` switch as this process has them, the defaults included."""
    return {s.name: s.value() for s in SWITCHES if s.kind == "result"}


def departures() -> list[str]:
    """One warning per ``result`` switch not at its default."""
    return [f"{s.name}={s.value()} (default {s.default}): {s.selects}; this run's numbers may differ from those "
            "made at the defaults (its record states the switch)"
            for s in SWITCHES if s.kind == "result" and s.value() != s.default]
