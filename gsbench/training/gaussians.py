"""The Gaussians container: stored parameters, their activations and initialisation.

Storage and activations follow 3DGS `scene/gaussian_model.py` (docs/methods/3dgs.md §2):
means raw (N,3); log-scales (N,3), or (N,2) for 2D surfels (docs/methods/2dgs.md §2); quaternions (w,x,y,z)
normalised on use; opacity logits, ``o = sigmoid``; SH DC (N,1,3) and rest (N,K-1,3).

Initialisation from SfM points: DC = (rgb − 0.5)/C0, rest 0; isotropic scale
``s = sqrt(mean of squared distances to the 3 nearest neighbours)`` (simple-knn ``distCUDA2``),
clamped so ``s² >= 1e-7`` — computed exactly here with a scipy KD-tree; opacity logit(0.1); rotation
identity (3D) or uniform random then normalised (2D, as 2DGS does).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from gsbench.errors import DataError, NumericalError
from gsbench.raster.sh import C0 as SH_C0
from gsbench.raster.types import RasterGaussians
from gsbench.signals import signals_deferred

PARAMETER_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def knn_initial_scale(points: np.ndarray, k: int = 3) -> np.ndarray:
    """sqrt(mean squared distance to the ``k`` nearest other points), with s² clamped at >= 1e-7.

    Coincident points give distance 0, so the clamp (simple-knn's) keeps every scale positive.
    """
    n = len(points)
    if n < 2:
        return np.full(n, math.sqrt(1e-7) if n else 0.0)
    kk = min(k, n - 1)
    with signals_deferred():
        dist, _ = cKDTree(points).query(points, k=kk + 1, workers=-1)
    mean_sq = np.mean(np.square(dist[:, 1:]), axis=1)
    return np.sqrt(np.maximum(mean_sq, 1e-7))


def check_finite_params(params) -> None:
    """Raise `NumericalError` naming the first of ``params`` (name -> tensor with rows first) that holds NaN or
    Inf. One reduction per group on the common path: a sum of finite values is finite unless it overflows,
    and only then (or when it is not finite) is every element tested."""
    for name, tensor in params.items():
        if bool(torch.isfinite(tensor.detach().sum())):
            continue
        bad = ~torch.isfinite(tensor.detach())
        if bad.any():
            rows = bad.reshape(len(tensor), -1).any(-1).nonzero().flatten()
            raise NumericalError(f"parameter '{name}' has {len(rows)} non-finite rows (first at index "
                                 f"{int(rows[0])}); lower the learning rate or resume from an earlier checkpoint")


class Gaussians(torch.nn.Module):
    """Learnable Gaussian parameters as an ``nn.ParameterDict``-like module (one tensor per group)."""

    def __init__(self, means, log_scales, quats, opacity_logits, sh_dc, sh_rest, max_sh_degree: int, **state):
        """The six learnable groups, plus optional per-Gaussian ``state`` tensors (N, ...) that are not
        learned (``requires_grad`` False, no optimizer group) but are densified, pruned and checkpointed
        with the rows (e.g. IBGS's reference frame, `gsbench.methods.ibgs`)."""
        super().__init__()
        self.max_sh_degree = int(max_sh_degree)
        self.params = torch.nn.ParameterDict(
            {
                "means": torch.nn.Parameter(means),
                "log_scales": torch.nn.Parameter(log_scales),
                "quats": torch.nn.Parameter(quats),
                "opacity_logits": torch.nn.Parameter(opacity_logits),
                "sh_dc": torch.nn.Parameter(sh_dc),
                "sh_rest": torch.nn.Parameter(sh_rest),
            }
        )
        for name, value in state.items():
            self.add_state(name, value)

    def add_state(self, name: str, value: torch.Tensor) -> None:
        """Attach a non-learned per-Gaussian tensor ``value`` (N, ...) under ``name`` (see `__init__`)."""
        if name in PARAMETER_NAMES:
            raise ValueError(f"'{name}' is a learnable parameter group, not a state tensor")
        if value.shape[0] != len(self):
            raise ValueError(f"state '{name}' has {value.shape[0]} rows for {len(self)} Gaussians")
        self.params[name] = torch.nn.Parameter(value, requires_grad=False)

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_points(cls, points: np.ndarray, colors: np.ndarray | None, *, dims: int = 3, max_sh_degree: int = 3,
                    init_opacity: float = 0.1, seed: int = 0) -> "Gaussians":
        """Gaussians at SfM ``points`` (N,3) with ``colors`` (N,3) in [0,1] (grey if None)."""
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise DataError(f"initial points must be a non-empty (N,3) array, got shape {points.shape}")
        if not np.isfinite(points).all():
            raise DataError(f"initial points contain {int((~np.isfinite(points)).any(1).sum())} non-finite rows; "
                            "clean the SfM point cloud (points3D) before training")
        n = len(points)
        colors = np.full((n, 3), 0.5) if colors is None else np.clip(np.asarray(colors, dtype=np.float64), 0, 1)
        scale = knn_initial_scale(points)
        log_scales = torch.log(torch.as_tensor(scale, dtype=torch.float32))[:, None].repeat(1, dims)
        if dims == 3:
            quats = torch.zeros(n, 4)
            quats[:, 0] = 1.0
        else:
            gen = torch.Generator().manual_seed(seed)
            quats = torch.nn.functional.normalize(torch.rand(n, 4, generator=gen), dim=-1)
        n_rest = (max_sh_degree + 1) ** 2 - 1
        return cls(
            means=torch.as_tensor(points, dtype=torch.float32),
            log_scales=log_scales,
            quats=quats,
            opacity_logits=torch.full((n,), math.log(init_opacity / (1 - init_opacity))),
            sh_dc=torch.as_tensor((colors - 0.5) / SH_C0, dtype=torch.float32)[:, None, :],
            sh_rest=torch.zeros(n, n_rest, 3),
            max_sh_degree=max_sh_degree,
        )

    @classmethod
    def random_in_sphere(cls, n: int, radius: float, *, dims: int = 3, max_sh_degree: int = 3, seed: int = 0):
        """``n`` Gaussians uniform in a ball of ``radius`` with random colours (scenes without SfM points)."""
        rng = np.random.default_rng(seed)
        direction = rng.normal(size=(n, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        points = direction * radius * rng.uniform(0, 1, size=(n, 1)) ** (1 / 3)
        return cls.from_points(points, rng.uniform(0, 1, size=(n, 3)), dims=dims, max_sh_degree=max_sh_degree,
                               seed=seed)

    # ---- activations ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def dims(self) -> int:
        return int(self.params["log_scales"].shape[1])

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.params["log_scales"])

    @property
    def quats(self) -> torch.Tensor:
        return torch.nn.functional.normalize(self.params["quats"], dim=-1)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    def check_finite(self) -> None:
        """Raise `NumericalError` naming the first parameter group that holds NaN or Inf (`check_finite_params`)."""
        check_finite_params(self.params)

    def raster_input(self, filter3d: torch.Tensor | None = None) -> RasterGaussians:
        """Activated parameters for `gsbench.raster.rasterize`; the SH as its two parameters (sh_dc, sh_rest), not
        concatenated: every row of sh_rest gets a gradient, zero past the render's SH degree (as in 3DGS). The
        quaternions go in raw: every projection normalises them itself (`gsbench.raster.types`), and q/|q| is
        idempotent, so normalising them here first (a PyTorch pass and its backward each step) changed nothing
        but the rounding."""
        rest = self.params["sh_rest"]
        return RasterGaussians(means=self.means, quats=self.params["quats"], scales=self.scales, opacities=self.opacities,
                               sh=self.params["sh_dc"], filter3d=filter3d, sh_rest=rest if rest.shape[1] else None)
