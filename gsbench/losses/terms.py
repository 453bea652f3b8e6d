"""Loss terms: named, weighted, scheduled (docs/design.md §3.2).

A term is ``fn(render, batch, state, **params) -> scalar tensor`` wrapped in a module-level `TermSpec`
(`loss_term`) with the render outputs it reads (``requires``) and its parameters with their defaults
(``params``), and registered like a method: ``configs/loss_terms/<name>.yaml`` names it (``plugin:``,
`gsbench.registry.LOSS_TERMS`, imported on first use), a plugin package through the ``gsbench.loss_terms``
entry points.

- ``render``: the `gsbench.raster.RenderOutput` of this step.
- ``batch``: a `Batch` (GT image, optional mask, camera, step).
- ``state``: a dict the method owns; terms that need more than the render read it
  (``state["gaussians"]`` for ``flatten``).

Config (``losses.<name>: {weight, start, end}``, `gsbench.config.run_config.LossTerm`) decides *whether* and *how
much*; a term is active at ``step`` iff ``weight != 0`` and ``start <= step`` and (``end < 0`` or
``step < end``). A weight of 0 removes the term and its outputs from the step. Unknown names are
`ConfigError` with a "did you mean".

Term parameters (e.g. which depth ``normal_consistency`` differentiates) are method hyper-parameters,
not schedule: the method passes ``params={name: {key: value}}`` to `active_terms`, which binds them
(`TermSpec.bind`, unknown keys are errors) so ``requires`` follows them (``depth_ratio`` 1 needs
``median_depth``, 0 needs ``depth``). The bound spec is called as ``spec(render, batch, state)``.
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import NamedTuple

import torch
import torch.nn.functional as F

from gsbench.config.files import suggest
from gsbench.data.camera import Camera
from gsbench.errors import ConfigError
from gsbench.losses.normal_consistency import normal_consistency
from gsbench.losses.ssim import ssim
from gsbench.raster.types import ALL_OUTPUTS, RenderOutput
from gsbench.registry import LOSS_TERMS

ENTROPY_EPS = 1e-10  # SuGaR coarse_*.py log(x + 1e-10), docs/methods/sugar.md §3.2, §5


@dataclass
class Batch:
    """The ground truth of one training view: ``image`` (H,W,3) float in [0,1], ``mask`` (H,W) bool or
    None, the `Camera` it was taken with, the training ``step`` and ``view``, the camera's index in the
    scene (None when the camera is not one of the scene's)."""

    image: torch.Tensor
    mask: torch.Tensor | None
    camera: Camera
    step: int
    view: int | None = None


@dataclass(frozen=True)
class TermSpec:
    """A registered loss term: ``fn(render, batch, state, **params) -> scalar``.

    ``requires`` is the set of render outputs (`gsbench.raster.types.ALL_OUTPUTS`) the term reads with its
    current ``params``; ``requires_fn(params)``, when given, recomputes it on `bind`.
    """

    name: str
    fn: Callable[..., torch.Tensor]
    requires: frozenset
    doc: str = ""
    params: Mapping = field(default_factory=lambda: MappingProxyType({}))
    requires_fn: Callable[[Mapping], frozenset] | None = None

    def bind(self, **overrides) -> TermSpec:
        """The same term with ``overrides`` merged into its parameters (unknown keys are ConfigError)."""
        for key in overrides:
            if key not in self.params:
                raise ConfigError(f"loss term '{self.name}' has no parameter '{key}'{suggest(key, self.params)}; "
                                  f"parameters: {', '.join(self.params) or '(none)'}")
        params = MappingProxyType({**self.params, **overrides})
        requires = self.requires_fn(params) if self.requires_fn else self.requires
        return dataclasses.replace(self, params=params, requires=frozenset(requires))

    def __call__(self, render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
        return self.fn(render, batch, state, **self.params)


class ActiveTerm(NamedTuple):
    """One term in use at a step: its name, config weight and bound spec."""

    name: str
    weight: float
    spec: TermSpec


def loss_term(name: str, fn: Callable[..., torch.Tensor], requires=(), params: Mapping | None = None,
              requires_fn: Callable[[Mapping], frozenset] | None = None) -> TermSpec:
    """The `TermSpec` of ``fn`` (its doc: ``fn``'s docstring); ``requires`` must name render outputs."""
    requires = frozenset(requires)
    unknown = requires - set(ALL_OUTPUTS)
    if unknown:
        raise ConfigError(f"loss term '{name}' requires unknown render outputs {sorted(unknown)}; "
                          f"valid outputs: {', '.join(ALL_OUTPUTS)}")
    spec = TermSpec(name, fn, requires, (fn.__doc__ or "").strip(), MappingProxyType(dict(params or {})), requires_fn)
    return spec.bind() if requires_fn is not None else spec


def get_term(name: str) -> TermSpec:
    """The spec registered as ``name`` (`gsbench.registry.LOSS_TERMS`); unknown names are ConfigError."""
    known = LOSS_TERMS.names()
    if name not in known:
        raise ConfigError(f"unknown loss term '{name}'{suggest(name, known)}; known terms: {', '.join(known)}")
    spec = LOSS_TERMS.get(name)
    if not isinstance(spec, TermSpec) or spec.name != name:
        found = f"the TermSpec of '{spec.name}'" if isinstance(spec, TermSpec) else type(spec).__name__
        raise ConfigError(f"loss term '{name}' is registered as {found}, not a TermSpec named '{name}' "
                          f"(gsbench.losses.terms.loss_term)")
    return spec


def method_state(state: dict, key: str, term: str):
    """``state[key]``, which only the method that owns ``term`` provides; else a ConfigError naming the fix."""
    if key not in state:
        raise ConfigError(f"loss term '{term}' reads state['{key}'], which this method does not provide; "
                          f"remove losses.{term} for this method")
    return state[key]


def _schedule_value(cfg, key: str, default):
    return cfg.get(key, default) if isinstance(cfg, Mapping) else getattr(cfg, key, default)


def active_terms(loss_cfg: Mapping, step: int, params: Mapping[str, Mapping] | None = None) -> list[ActiveTerm]:
    """The terms in use at ``step``: ``loss_cfg`` maps name -> {weight, start, end} (dict or LossTerm).

    Every name and parameter is checked (also of inactive terms), so a typo fails at the first step. Weight 0 removes
    the term; active iff ``start <= step`` and (``end < 0`` or ``step < end``). ``params`` binds term
    parameters (see the module docstring); params for a name not in ``loss_cfg`` are an error too.
    """
    params = dict(params or {})
    for name in params:
        if name not in loss_cfg:
            raise ConfigError(f"parameters given for loss term '{name}', which is not in the loss config"
                              f"{suggest(name, loss_cfg)}; configured terms: {', '.join(loss_cfg) or '(none)'}")
    active = []
    for name, cfg in loss_cfg.items():
        spec = get_term(name).bind(**params.get(name, {}))
        weight = float(_schedule_value(cfg, "weight", 0.0))
        start = int(_schedule_value(cfg, "start", 0))
        end = int(_schedule_value(cfg, "end", -1))
        if weight == 0.0 or step < start or (end >= 0 and step >= end):
            continue
        active.append(ActiveTerm(name, weight, spec))
    return active


def required_outputs(active: list[ActiveTerm]) -> frozenset:
    """Union of the render outputs the active terms read."""
    out: frozenset = frozenset()
    for term in active:
        out |= term.spec.requires
    return out


def total_loss(active: list[ActiveTerm], render: RenderOutput, batch: Batch, state: dict
               ) -> tuple[torch.Tensor, dict[str, float]]:
    """(Σ weight·value, {name: unweighted value}); with no active term the loss is a constant 0."""
    total = torch.zeros(())
    values: dict[str, float] = {}
    for term in active:
        value = term.spec(render, batch, state)
        values[term.name] = float(value.detach())
        total = total + term.weight * value
    return total, values


# ---- built-in terms -----------------------------------------------------------------------------


def _masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of (H,W,...) ``x`` over the (H,W) ``mask`` (all pixels if None); 0 for an empty mask."""
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype).reshape(mask.shape + (1,) * (x.dim() - mask.dim()))
    count = m.sum() * (x.numel() // mask.numel())
    return (x * m).sum() / count.clamp(min=1)


class _MeanAbsDifference(torch.autograd.Function):
    """mean |x − y| with ∂/∂x = sign(x − y)/n (0 where x = y, as autograd's abs), y constant: one saved
    difference and one elementwise pass each way instead of autograd's chain of sub, abs and mean."""

    @staticmethod
    def forward(ctx, x, y):
        diff = x - y
        ctx.save_for_backward(diff)
        return diff.abs().mean()

    @staticmethod
    def backward(ctx, grad):
        (diff,) = ctx.saved_tensors
        return torch.sign(diff).mul_(grad / diff.numel()), None


def l1_term(render: RenderOutput, batch: Batch, state: dict, use_mask: bool = False) -> torch.Tensor:
    """L1 = mean |rgb − image| over H×W×3 (docs/methods/3dgs.md §4.1, ``l1_loss``).

    ``use_mask``: the mean over ``batch.mask`` pixels only (0 for an empty mask); off in 3DGS/2DGS.
    """
    image = batch.image.to(render.rgb.dtype)
    if not use_mask or batch.mask is None:
        return _MeanAbsDifference.apply(render.rgb, image)
    return _masked_mean((render.rgb - image).abs(), batch.mask)


def dssim_term(render: RenderOutput, batch: Batch, state: dict, use_mask: bool = False) -> torch.Tensor:
    """D-SSIM = 1 − SSIM(rgb, image), SSIM as `gsbench.losses.ssim` (docs/methods/3dgs.md §4.1, λ_dssim = 0.2 in configs).

    ``use_mask``: SSIM averaged over ``batch.mask`` pixels only (empty mask → 0).
    """
    return 1.0 - ssim(render.rgb, batch.image.to(render.rgb.dtype), batch.mask if use_mask else None)


DISTORTION_EPS = 1e-7  # GOF: distortion / ((1 − T_final)² + 1e-7), docs/methods/gof.md §4.3


def edge_weights(image: torch.Tensor) -> torch.Tensor:
    """exp(−g) (H,W) of an (H,W,3) image, 0 on the 1-pixel border (GOF/RaDe v1 edge-aware distortion,
    docs/methods/radegs.md §4.3): g = the largest of the 4 neighbour differences mean_c |I(p) − I(q)|."""
    centre = image[1:-1, 1:-1]
    diffs = [(centre - image[1:-1, :-2]), (centre - image[1:-1, 2:]), (centre - image[:-2, 1:-1]),
             (centre - image[2:, 1:-1])]
    g = torch.stack([d.abs().mean(-1) for d in diffs], -1).max(-1).values
    return F.pad(torch.exp(-g), (1, 1, 1, 1))


# maps computed from a GT image alone, by id of the image tensor (an entry leaves with its tensor), the map's
# function and the dtype: training never changes its GT images, so each view's map is computed once
_IMAGE_MAPS: dict[int, dict[tuple, torch.Tensor]] = {}


def image_map(fn: Callable[[torch.Tensor], torch.Tensor], image: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``fn(image.to(dtype))`` for a map ``fn`` that reads only the image (an edge weight), computed once per image
    tensor, ``fn`` and ``dtype``."""
    maps = _IMAGE_MAPS.get(id(image))
    if maps is None:
        maps = _IMAGE_MAPS[id(image)] = {}
        weakref.finalize(image, _IMAGE_MAPS.pop, id(image), None)
    if (fn, dtype) not in maps:
        maps[(fn, dtype)] = fn(image.to(dtype))
    return maps[(fn, dtype)]


def depth_distortion_term(render: RenderOutput, batch: Batch, state: dict, normalize: bool = False,
                          edge_aware: bool = False) -> torch.Tensor:
    """L_d = mean over pixels of the distortion map Σ_i Σ_{j<i} w_i w_j (m_i − m_j)² (docs/methods/2dgs.md §3.5, §4.2).

    ``normalize`` (docs/methods/gof.md §4.3, docs/methods/radegs.md §4.3): the map divided by stopgrad(alpha)² + 1e-7 (GOF divides by
    (1 − T_final)² + 1e-7 with detached weights). ``edge_aware`` (docs/methods/radegs.md §4.3): multiplied per pixel
    by `edge_weights` of the GT image. Both off in 2DGS.
    """
    distortion = render.distortion
    if normalize:
        distortion = distortion / (render.alpha.detach() ** 2 + DISTORTION_EPS)
    if edge_aware:
        distortion = distortion * image_map(edge_weights, batch.image, distortion.dtype)
    return distortion.mean()


def _depth_distortion_requires(params: Mapping) -> frozenset:
    return frozenset({"distortion", "alpha"} if params["normalize"] else {"distortion"})


def _check_depth_ratio(depth_ratio: float) -> float:
    if not 0.0 <= float(depth_ratio) <= 1.0:
        raise ConfigError(f"normal_consistency depth_ratio must be in [0, 1] (0 expected, 1 median depth), "
                          f"got {depth_ratio}")
    return float(depth_ratio)


def surface_depth(render: RenderOutput, depth_ratio: float) -> torch.Tensor:
    """2DGS surf_depth = (1 − r)·expected + r·median (docs/methods/2dgs.md §4.3); only the needed maps are read."""
    r = _check_depth_ratio(depth_ratio)
    if r == 1.0:
        return render.median_depth
    if r == 0.0:
        return render.depth
    return (1 - r) * render.depth + r * render.median_depth


NORMAL_MIXES = ("depth", "normal")


def _check_mix(mix: str) -> str:
    if mix not in NORMAL_MIXES:
        raise ConfigError(f"normal_consistency mix must be one of {NORMAL_MIXES} (2DGS: depth, RaDe-GS: normal), "
                          f"got {mix!r}")
    return mix


def _depth_maps(render: RenderOutput, depth_ratio: float, mix: str) -> tuple[list[torch.Tensor], list[float]]:
    """The depth maps of n_d and their weights (`normal_consistency_term`): one map (the mixed depth, or
    the one map r selects), or both maps with weights 1 − r and r."""
    r = _check_depth_ratio(depth_ratio)
    if _check_mix(mix) == "depth" or r in (0.0, 1.0):
        return [surface_depth(render, r)], [1.0]
    return [render.depth, render.median_depth], [1 - r, r]


def normal_consistency_term(render: RenderOutput, batch: Batch, state: dict, depth_ratio: float = 1.0,
                            normalize: bool = False, mix: str = "depth") -> torch.Tensor:
    """L_n = mean over all H×W pixels of 1 − n_r · n_d (docs/methods/2dgs.md §4.3; docs/methods/gof.md §4.2; docs/methods/radegs.md §4.2).

    n_d from ``mix`` and r = ``depth_ratio``:
    - ``depth`` (2DGS): `depth_to_normal` of the surface depth (1 − r)·expected + r·median (2DGS
      ``depth_ratio``; its code default is 0, its DTU/TnT scripts use 1; GOF: r = 1, median depth);
    - ``normal`` (RaDe-GS): (1 − r)·N(expected) + r·N(median), i.e.
      L_n = (1 − r)·mean(1 − n_r·N(expected)) + r·mean(1 − n_r·N(median)) (RaDe ``depth_ratio`` 0.6).

    n_r with ``normalize`` False (2DGS): the rendered normal (unnormalised, length ≈ alpha) against
    n_d·stopgrad(alpha); True (GOF, RaDe-GS): the rendered normal normalised, against n_d.
    Background and the 1-pixel border (n_d = 0) contribute a constant 1 each, which carries no gradient.
    Evaluated by `gsbench.losses.normal_consistency.normal_consistency` (a fused C++ kernel; PyTorch reference).
    """
    depths, weights = _depth_maps(render, depth_ratio, mix)
    return normal_consistency(render.normal, depths, weights, batch.camera, normalize,
                              alpha=None if normalize else render.alpha)


def _normal_consistency_requires(params: Mapping) -> frozenset:
    r = _check_depth_ratio(params["depth_ratio"])
    _check_mix(params["mix"])
    depths = {"depth"} if r == 0.0 else {"median_depth"} if r == 1.0 else {"depth", "median_depth"}
    return frozenset({"normal"} | depths | (set() if params["normalize"] else {"alpha"}))


def _gaussians(state: dict, term: str):
    if "gaussians" not in state:
        raise ConfigError(f"loss term '{term}' needs the Gaussians in state['gaussians']; this method does not "
                          f"provide them, so remove losses.{term} or set its weight to 0")
    return state["gaussians"]


def flatten_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """L_s = mean over Gaussians of min(s_1, s_2, s_3) (NeuSG / IBGS flattening loss); 0 if none."""
    scales = _gaussians(state, "flatten").scales
    if scales.shape[0] == 0:
        return scales.sum()
    return scales.min(dim=-1).values.mean()


def opacity_entropy_term(render: RenderOutput, batch: Batch, state: dict) -> torch.Tensor:
    """SuGaR entropy: mean over visible Gaussians of −o log(o + ε) − (1−o) log(1 − o + ε), ε = 1e-10
    (SuGaR coarse stage, docs/methods/sugar.md §3.2; "visible" = radii > 0 in this render); 0 if none is visible."""
    o = _gaussians(state, "opacity_entropy").opacities
    if render.visible is not None:
        o = o[render.visible]
    if o.numel() == 0:
        return o.sum()
    return (-o * torch.log(o + ENTROPY_EPS) - (1 - o) * torch.log(1 - o + ENTROPY_EPS)).mean()


L1 = loss_term("l1", l1_term, {"rgb"}, params={"use_mask": False})
DSSIM = loss_term("dssim", dssim_term, {"rgb"}, params={"use_mask": False})
DEPTH_DISTORTION = loss_term("depth_distortion", depth_distortion_term, params={"normalize": False, "edge_aware": False},
                             requires_fn=_depth_distortion_requires)
NORMAL_CONSISTENCY = loss_term("normal_consistency", normal_consistency_term,
                               params={"depth_ratio": 1.0, "normalize": False, "mix": "depth"},
                               requires_fn=_normal_consistency_requires)
FLATTEN = loss_term("flatten", flatten_term)
OPACITY_ENTROPY = loss_term("opacity_entropy", opacity_entropy_term)
