"""One neighbouring view per step for the multi-view loss terms and a per-image exposure: what PGSR
(docs/methods/pgsr.md §4.3–§4.5) and GGGS (docs/methods/gggs.md §3) share.

- `neighbour_views`: PGSR's neighbours of each training view (camera distance, then angle);
- `MultiViewContext`: one step's neighbour and warp, read by ``pgsr_geo`` / ``pgsr_ncc`` and ``gggs_geo`` /
  ``gggs_ncc`` (`gsbench.methods.pgsr_terms`, `gsbench.methods.gggs_terms`) through ``state["pgsr_multiview"]``;
- `NeighbourViews`: the mixin of a `Method` that builds it once per step (a neighbour drawn with Python's
  seeded RNG, rendered by the method, the forward–backward warp of each pixel's plane), holds the
  per-image exposure (a_v, b_v) and times the neighbour work (``multiview``). A method gives the planes
  (`NeighbourViews.planes`), the outputs they need (``NEIGHBOUR_OUTPUTS``), its patch spacing and how many
  warped pixels the NCC may sample.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass

import numpy as np
import torch

from gsbench.errors import ConfigError
from gsbench.losses.terms import Batch
from gsbench.methods import pgsr_terms
from gsbench.raster import profiling
from gsbench.raster.types import RenderOutput


def neighbour_views(cameras, views, k: int, max_angle: float, min_dis: float, max_dis: float) -> dict[int, list[int]]:
    """PGSR's neighbours of each training view: the others sorted by camera-centre distance (ties by the angle
    between viewing directions), kept when angle < ``max_angle`` degrees and ``min_dis`` < distance < ``max_dis``,
    the first ``k`` (docs/methods/pgsr.md §4.3). Returns {view index: [view indices]}."""
    views = list(views)
    centres = np.stack([np.asarray(cameras[i].center, np.float64) for i in views])
    axes = np.stack([np.asarray(cameras[i].R, np.float64)[2] for i in views])  # camera z in world
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    angle = np.degrees(np.arccos(np.clip(axes @ axes.T, -1.0, 1.0)))
    out = {}
    for a, view in enumerate(views):
        order = np.lexsort((angle[a], dist[a]))
        keep = [b for b in order if angle[a, b] < max_angle and min_dis < dist[a, b] < max_dis]
        out[view] = [views[b] for b in keep[:k]]
    return out


@dataclass
class MultiViewContext:
    """One step's neighbour and warp, shared by a method's two multi-view terms."""

    warp: pgsr_terms.Warp
    ncc_index: torch.Tensor
    ref_gray: torch.Tensor
    nb_gray: torch.Tensor
    patch_half: int
    patch_step: float = 1.0  # px between patch samples (PGSR 1; GGGS 0.5)


def check_multiview_params(p, document: str) -> None:
    """ConfigError naming the first multi-view or exposure setting out of range (``document`` says where they are)."""
    checks = [("multi_view_num", p.multi_view_num >= 1), ("multi_view_patch_half", p.multi_view_patch_half >= 1),
              ("multi_view_pixel_noise_th", p.multi_view_pixel_noise_th > 0),
              ("multi_view_max_angle", 0 < p.multi_view_max_angle <= 180),
              ("multi_view_max_dis", p.multi_view_max_dis > p.multi_view_min_dis >= 0),
              ("exposure_lr", p.exposure_lr > 0)]
    for key, ok in checks:
        if not ok:
            raise ConfigError(f"method.{key} is out of range (got {getattr(p, key)}); see {document}")


class NeighbourViews:
    """Mixin of a `Method` (module docstring); call `init_neighbours` in ``__init__`` and `setup_neighbours`
    in ``setup``, after the base setup."""

    NEIGHBOUR_OUTPUTS: tuple[str, ...] = ()

    def init_neighbours(self) -> None:
        self.exposure: torch.nn.Parameter | None = None
        self.multiview_seconds = 0.0
        self._cache: tuple | None = None

    def new_exposure(self, scene) -> None:
        """The per-image (a_v, b_v), zero (before the optimizer is made)."""
        self.exposure = torch.nn.Parameter(torch.zeros(len(scene.cameras), 2))

    def setup_neighbours(self, scene) -> None:
        p = self.params
        self.cameras = list(scene.cameras)
        self.neighbours = neighbour_views(self.cameras, scene.train_views, p.multi_view_num, p.multi_view_max_angle,
                                          p.multi_view_min_dis * scene.radius, p.multi_view_max_dis * scene.radius)
        self.gray = [pgsr_terms.gray(torch.as_tensor(np.asarray(img, dtype=np.float32))) for img in scene.images] \
            if scene.images is not None else []

    # ---- what a method gives ------------------------------------------------------------------
    def planes(self, render: RenderOutput, camera) -> tuple[torch.Tensor, torch.Tensor]:
        """(plane distance (H, W), normal (H, W, 3)) of each pixel's plane, PGSR's convention n·X = −d."""
        raise NotImplementedError

    def ncc_sample_cap(self) -> int:
        """At most this many warped pixels in the NCC (0: all)."""
        return 0

    def patch_step(self) -> float:
        """Pixels between the NCC patch's samples."""
        return 1.0

    # ---- the step's context -------------------------------------------------------------------
    def _multiview(self, render: RenderOutput, batch: Batch) -> MultiViewContext | None:
        """This step's neighbour render and warp, computed on first use and shared by the terms."""
        key = (batch.step, id(render))
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        t0 = time.perf_counter()
        # the neighbour's render is part of the terms' cost; `gsbench bench train` times its rasterizer phases
        # apart from the step's own render (gsbench/bench/train.py, ``neighbour_raster``)
        with profiling.profile_as("neighbour."):
            ctx = self._build_multiview(render, batch)
        self.multiview_seconds += time.perf_counter() - t0
        self._cache = (key, ctx)
        return ctx

    def _build_multiview(self, render: RenderOutput, batch: Batch) -> MultiViewContext | None:
        p = self.params
        view = batch.view
        candidates = self.neighbours.get(view, []) if view is not None else []
        if not candidates:
            return None
        nb = candidates[random.randrange(len(candidates))]  # PGSR, GGGS: random.sample(nearest_id, 1)
        nb_cam = self.cameras[nb]
        nb_render = self.render(nb_cam, set(self.NEIGHBOUR_OUTPUTS))
        warp = pgsr_terms.warp_to_neighbour(self.planes(render, batch.camera), batch.camera,
                                            self.planes(nb_render, nb_cam), nb_cam,
                                            near=self.raster_settings().near, threshold=p.multi_view_pixel_noise_th)
        index = torch.nonzero(warp.mask).flatten()
        cap = self.ncc_sample_cap()
        if 0 < cap < index.numel():
            index = index[torch.randperm(index.numel())[:cap]]
        ref_gray = pgsr_terms.gray(batch.image.to(torch.float32)) if view is None else self.gray[view]
        return MultiViewContext(warp=warp, ncc_index=index, ref_gray=ref_gray, nb_gray=self.gray[nb],
                                patch_half=p.multi_view_patch_half, patch_step=self.patch_step())

    def training_phases(self) -> dict[str, float]:
        return {"multiview": self.multiview_seconds}

    # ---- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The exposure and the neighbour work's seconds (so a resumed run's ``multiview`` covers all its steps,
        as the Trainer's phases do)."""
        return {**super().state_dict(), "exposure": self.exposure.detach().clone(),
                "multiview_seconds": self.multiview_seconds}

    def load_state_dict(self, state: dict) -> None:
        self.exposure = torch.nn.Parameter(state["exposure"].clone())
        # checkpoints written before the seconds were kept resume from zero, as the Trainer's phases do
        self.multiview_seconds = float(state.get("multiview_seconds", 0.0))
        super().load_state_dict(state)
