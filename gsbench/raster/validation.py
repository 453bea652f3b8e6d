"""What the rasterizer checks before it renders: finite inputs (a `NumericalError` naming the tensor and the
first bad row), the Gaussians' shapes, the kernel and output names, and the background colour."""

from __future__ import annotations

import numpy as np
import torch

from gsbench.errors import NumericalError
from gsbench.raster.types import KERNEL_OUTPUTS, KERNELS, OUTPUTS, RasterGaussians, RasterSettings


def check_finite(name: str, x: torch.Tensor | None) -> None:
    if x is None:
        return
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.is_floating_point():
        if x.numel() and bool(torch.isfinite(x.detach().sum())):
            return  # one pass: a sum of finite values is finite unless it overflows (then the exact check runs)
        finite = torch.isfinite(x.detach())
        if not bool(finite.all()):
            bad = ~finite
            count = int(bad.sum())
            first = int(torch.nonzero(bad.reshape(x.shape[0], -1).any(-1))[0, 0]) if x.dim() > 0 else 0
            raise NumericalError(
                f"{name} has {count} non-finite value{'s' if count != 1 else ''} (first at index {first}); "
                "expected finite numbers — check the optimiser step or the loaded checkpoint"
            )


def validate_gaussians(g: RasterGaussians, kernel: str) -> None:
    """Shapes and finiteness of every parameter; raises NumericalError / ValueError naming it."""
    n = g.means.shape[0] if g.means.dim() == 2 else -1
    if g.means.dim() != 2 or g.means.shape[1] != 3:
        raise ValueError(f"gaussians.means must be (N, 3), got {tuple(g.means.shape)}")
    expect = {
        "quats": (n, 4),
        "opacities": (n,),
    }
    for name, shape in expect.items():
        t = getattr(g, name)
        if tuple(t.reshape(n, -1).shape[:1]) != (n,) or (name == "quats" and tuple(t.shape) != shape):
            raise ValueError(f"gaussians.{name} must be {shape}, got {tuple(t.shape)}")
    if g.opacities.numel() != n:
        raise ValueError(f"gaussians.opacities must be (N,) = ({n},), got {tuple(g.opacities.shape)}")
    need = 2 if kernel == "surfel" else 3
    if g.scales.dim() != 2 or g.scales.shape[0] != n or g.scales.shape[1] < need:
        raise ValueError(f"gaussians.scales must be (N, {need}) for kernel '{kernel}', got {tuple(g.scales.shape)}")
    for name in ("sh", "sh_rest"):
        t = getattr(g, name)
        if t is not None and (t.dim() != 3 or t.shape[0] != n or t.shape[2] != 3):
            raise ValueError(f"gaussians.{name} must be (N, K, 3), got {tuple(t.shape)}")
    if g.filter3d is not None and g.filter3d.numel() != n:
        raise ValueError(f"gaussians.filter3d must be (N,), got {tuple(g.filter3d.shape)}")
    for name in ("means", "quats", "scales", "opacities", "sh", "filter3d", "sh_rest"):
        check_finite(f"gaussians.{name}", getattr(g, name))


def check_kernel_outputs(kernel: str, outputs) -> tuple[str, ...]:
    if kernel not in KERNELS:
        raise ValueError(f"unknown rasterizer kernel '{kernel}'; valid kernels: {', '.join(KERNELS)}")
    if isinstance(outputs, str):
        outputs = (outputs,)
    outs = tuple(dict.fromkeys(outputs))
    valid = OUTPUTS + KERNEL_OUTPUTS.get(kernel, ())
    bad = [o for o in outs if o not in valid]
    if bad:
        owners = {o: k for k, extra in KERNEL_OUTPUTS.items() for o in extra}
        known = [f"{o} (the {owners[o]} kernel only)" for o in bad if o in owners]
        raise ValueError(f"render output(s) {bad} not defined for kernel '{kernel}'"
                         + (f": {', '.join(known)}" if known else "") + f"; valid outputs: {', '.join(valid)}")
    return outs


def background_color(background, settings: RasterSettings, dtype) -> torch.Tensor:
    bg = settings.background if background is None else background
    if isinstance(bg, torch.Tensor):
        bgt = bg.to(dtype).reshape(3)
        check_finite("background", bgt.reshape(1, 3))
        return bgt
    values = np.asarray(bg, dtype=np.float64).reshape(3)
    if not np.isfinite(values).all():  # three numbers: checked here, not by a tensor reduction
        check_finite("background", torch.as_tensor(values).reshape(1, 3))
    return torch.tensor(values.tolist(), dtype=dtype)
