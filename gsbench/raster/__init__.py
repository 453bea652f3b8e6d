"""The shared differentiable CPU rasterizer (see `gsbench.raster.types` for the contract).

``rasterize(gaussians, camera, kernel=..., outputs=...)`` projects the Gaussians
(`gsbench.raster.projection`: fused C++ with a hand-written backward for every kernel, or PyTorch with
``GSBENCH_PROJECTION=torch``, the reference), sorts the visible ones by depth and bins them into tiles in C++, and
composites them with the C++/OpenMP tile kernel (``csrc/raster.cpp``, compiled on first use by
`gsbench.raster.build`); a `torch.autograd.Function` connects projection and compositing. ``integrate(...)`` evaluates GOF's opacity field at 3D points (no gradient).

``GSBENCH_RASTER=reference`` switches to the slow dense reference (`gsbench.raster.reference`).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import time
import warnings
from collections.abc import Iterable, Sequence

import numpy as np
import torch

from gsbench.data.camera import Camera
from gsbench.errors import NumericalError
from gsbench.raster.build import omp_threads
from gsbench.raster.types import KERNELS, OUTPUTS, RasterGaussians, RasterSettings, RenderOutput

__all__ = [
    "KERNELS",
    "OUTPUTS",
    "RasterGaussians",
    "RasterSettings",
    "RenderOutput",
    "rasterize",
    "integrate",
    "validate_gaussians",
]

KERNEL_ID = {"ewa": 0, "rade": 1, "raymax": 2, "surfel": 3}
_EMPTY = {}

# Phase timings (seconds) of the most recent calls, filled when `profile` is enabled (used by bench.py),
# under ``profile_tag + phase`` (`profile_as`).
profile: dict | None = None
profile_tag = ""


@contextlib.contextmanager
def profile_as(tag: str):
    """Record the timers of the renders made inside (and of their backward) as ``tag + phase`` (PGSR's
    neighbour view: ``"neighbour."``), apart from the step's own render."""
    global profile_tag
    saved, profile_tag = profile_tag, tag
    try:
        yield
    finally:
        profile_tag = saved


def _prof(key: str, dt: float, tag: str | None = None) -> None:
    if profile is not None:
        key = (profile_tag if tag is None else tag) + key
        profile[key] = profile.get(key, 0.0) + dt


def _check_finite(name: str, x: torch.Tensor | None) -> None:
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
        _check_finite(f"gaussians.{name}", getattr(g, name))


def _check_kernel_outputs(kernel: str, outputs) -> tuple[str, ...]:
    if kernel not in KERNELS:
        raise ValueError(f"unknown rasterizer kernel '{kernel}'; valid kernels: {', '.join(KERNELS)}")
    if isinstance(outputs, str):
        outputs = (outputs,)
    outs = tuple(dict.fromkeys(outputs))
    bad = [o for o in outs if o not in OUTPUTS]
    if bad:
        raise ValueError(f"unknown render output(s) {bad}; valid outputs: {', '.join(OUTPUTS)}")
    return outs


def _ptr(t: torch.Tensor | None):
    return None if t is None else ctypes.c_void_p(t.data_ptr())


class _State:
    """Everything one render shares between the forward and the backward of the C++ kernel."""

    def __init__(self, lib, args, kernel, n, m2d_leaf, absgrad, height, width, dtype, proj_bufs):
        self.lib = lib
        self.args = args
        self.kernel = kernel
        self.n = n
        self.m2d_leaf = m2d_leaf
        self.absgrad = absgrad
        self.height = height
        self.width = width
        self.dtype = dtype
        self.bufs = proj_bufs  # keeps the tensors the args point to alive
        self.saved = {}
        self.pairs_fwd = 0
        self.pairs_bwd = 0
        self.profiled = profile is not None
        self.profile_tag = profile_tag  # the backward runs after `profile_as` has ended
        self.centre_z = None  # surfel: the centres' camera z, for the 2DGS densification shortcut


class _RasterFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, params, plane_d, state):  # noqa: D401
        a = state.args
        H, W, dt = state.height, state.width, state.dtype
        want = state.want
        e = torch.empty(0, dtype=dt)
        rgb = torch.empty(H, W, 3, dtype=dt) if want["rgb"] else e
        alpha = torch.empty(H, W, dtype=dt)
        depth = torch.empty(H, W, dtype=dt) if want["depth"] else e
        med = torch.empty(H, W, dtype=dt) if want["median_depth"] else e
        nrm = torch.empty(H, W, 3, dtype=dt) if want["normal"] else e
        dist = torch.empty(H, W, dtype=dt) if want["distortion"] else e
        plane = torch.empty(H, W, dtype=dt) if want["plane_distance"] else e
        plane_c = plane_d.detach().contiguous() if want["plane_distance"] else None
        T_final = torch.empty(H, W, dtype=dt)
        last = torch.empty(H, W, dtype=torch.int32)
        medi = torch.empty(H, W, dtype=torch.int32) if want["median_depth"] else None
        M1 = torch.empty(H, W, dtype=dt) if want["distortion"] else None
        M2 = torch.empty(H, W, dtype=dt) if want["distortion"] else None
        params_c = params.detach().contiguous()
        a.params = params_c.data_ptr()
        a.out_rgb = rgb.data_ptr() if want["rgb"] else None
        a.out_alpha = alpha.data_ptr()
        a.out_depth = depth.data_ptr() if want["depth"] else None
        a.out_median = med.data_ptr() if want["median_depth"] else None
        a.out_normal = nrm.data_ptr() if want["normal"] else None
        a.out_dist = dist.data_ptr() if want["distortion"] else None
        a.plane_d = None if plane_c is None else plane_c.data_ptr()
        a.out_plane = plane.data_ptr() if want["plane_distance"] else None
        a.T_final = T_final.data_ptr()
        a.last = last.data_ptr()
        a.median_idx = None if medi is None else medi.data_ptr()
        a.M1 = None if M1 is None else M1.data_ptr()
        a.M2 = None if M2 is None else M2.data_ptr()
        t0 = time.perf_counter()
        rc = state.lib.gs_forward(ctypes.byref(a))
        _prof("raster_fwd", time.perf_counter() - t0)
        if rc != 0:
            raise RuntimeError(f"gsbench rasterizer forward failed (code {rc})")
        state.pairs_fwd = int(a.pairs)
        state.saved = {"T": T_final, "last": last, "medi": medi, "M1": M1, "M2": M2, "params": params_c,
                       "plane_d": plane_c}
        ctx.state = state
        ctx.set_materialize_grads(False)
        return rgb, alpha, depth, med, nrm, dist, plane

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_med, g_nrm, g_dist, g_plane):
        state = ctx.state
        a = state.args
        dt = state.dtype
        want = state.want

        def prep(g, key):
            if g is None or not want[key] or g.numel() == 0:
                return None
            return g.to(dt).contiguous()

        grads = {
            "g_rgb": prep(g_rgb, "rgb"),
            "g_alpha": None if g_alpha is None else g_alpha.to(dt).contiguous(),
            "g_depth": prep(g_depth, "depth"),
            "g_median": prep(g_med, "median_depth"),
            "g_normal": prep(g_nrm, "normal"),
            "g_dist": prep(g_dist, "distortion"),
            "g_plane": prep(g_plane, "plane_distance"),
        }
        for k, v in grads.items():
            setattr(a, k, None if v is None else v.data_ptr())
        s = state.saved
        a.params = s["params"].data_ptr()
        a.T_final = s["T"].data_ptr()
        a.last = s["last"].data_ptr()
        a.median_idx = None if s["medi"] is None else s["medi"].data_ptr()
        a.M1 = None if s["M1"] is None else s["M1"].data_ptr()
        a.M2 = None if s["M2"] is None else s["M2"].data_ptr()
        a.plane_d = None if s["plane_d"] is None else s["plane_d"].data_ptr()
        n, npar = state.n, int(a.n_params)
        gp = torch.zeros(n, npar, dtype=dt)
        g_plane_d = torch.zeros(n, dtype=dt) if want["plane_distance"] else None
        a.grad_plane = None if g_plane_d is None else g_plane_d.data_ptr()
        absg = torch.zeros(n, dtype=dt)
        proxy = torch.zeros(n, 2, dtype=dt) if state.kernel == "raymax" else torch.zeros(1, 2, dtype=dt)  # raymax only
        a.grad_params = gp.data_ptr()
        a.absgrad = absg.data_ptr()
        a.proxy = proxy.data_ptr()
        t0 = time.perf_counter()
        if any(v is not None for v in grads.values()):
            rc = state.lib.gs_backward(ctypes.byref(a))
            if rc != 0:
                raise RuntimeError(f"gsbench rasterizer backward failed (code {rc})")
            state.pairs_bwd = int(a.pairs)
        if state.profiled:  # a render made while the timers were off stays out of them
            _prof("raster_bwd", time.perf_counter() - t0, state.profile_tag)
        # densification statistics
        if state.kernel == "raymax":
            m2g = proxy
        elif state.kernel == "surfel":
            m2g = surfel_shortcut_grad(gp, s["params"], state.centre_z.to(dt), a.fx, a.fy)
        else:
            m2g = gp[:, :2]
        leaf = state.m2d_leaf
        m2g = m2g.to(leaf.dtype)
        leaf.grad = m2g.clone() if leaf.grad is None else leaf.grad + m2g
        state.absgrad += absg.to(state.absgrad.dtype)
        return gp, g_plane_d, None


def surfel_shortcut_grad(grad_params: torch.Tensor, params: torch.Tensor, centre_z: torch.Tensor, fx: float,
                         fy: float) -> torch.Tensor:
    """2DGS's densification statistic for surfels, in pixels (N,2) (docs/methods/2dgs.md §3.6).

    2DGS takes ``(∂L/∂Tu.z·Tw.z, ∂L/∂Tv.z·Tw.z)`` (then × W/2, H/2 to NDC): the gradient of the loss for a
    screen-space move of the centre at fixed depth, through the ray-splat intersection only (the low-pass
    filter's ∂L/∂means2d is left out). Tu.z = fx·μx + cx·μz, so a move of δ pixels in x is μ += (δ·μz/fx) e_x
    with the frame fixed. The payload holds the plane n·x = d and the local offsets b_u = μ·a_u,
    b_v = μ·a_v (d = n·μ), so with g the gradient of those columns
    ``∂L/∂μ = g_d n + g_bu a_u + g_bv a_v`` and the statistic is ``(∂L/∂μx·μz/fx, ∂L/∂μy·μz/fy)``.
    """
    x = params[:, 9:21]  # n (3), d, a_u (3), b_u, a_v (3), b_v  (csrc/raster.cpp surfel payload)
    g = grad_params[:, 9:21]
    dmu = g[:, 3:4] * x[:, 0:3] + g[:, 7:8] * x[:, 4:7] + g[:, 11:12] * x[:, 8:11]
    return torch.stack([dmu[:, 0] * centre_z / fx, dmu[:, 1] * centre_z / fy], -1)


def _background(background, settings: RasterSettings, dtype) -> torch.Tensor:
    bg = settings.background if background is None else background
    if isinstance(bg, torch.Tensor):
        bgt = bg.to(dtype).reshape(3)
        _check_finite("background", bgt.reshape(1, 3))
        return bgt
    values = np.asarray(bg, dtype=np.float64).reshape(3)
    if not np.isfinite(values).all():  # three numbers: checked here, not by a tensor reduction
        _check_finite("background", torch.as_tensor(values).reshape(1, 3))
    return torch.tensor(values.tolist(), dtype=dtype)


# Binning of ewa/rade: True = exact ellipse/tile overlap, False = every tile of the bounding rectangle (the
# images and gradients are identical; only the tile pairs differ). None = the GSBENCH_EXACT_OVERLAP
# environment variable ("0"/"false"/"off" = rectangle), default on.
EXACT_OVERLAP: bool | None = None


def exact_overlap_enabled() -> bool:
    if EXACT_OVERLAP is not None:
        return bool(EXACT_OVERLAP)
    return os.environ.get("GSBENCH_EXACT_OVERLAP", "1").strip().lower() not in ("0", "false", "off", "no")


def _bind_exact_bin(lib) -> None:
    """ctypes signatures of gs_bin_exact_count / gs_bin_exact_fill (csrc/raster.cpp)."""
    if getattr(lib, "_gs_exact_bound", False):
        return
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    lib.gs_bin_exact_count.argtypes = [i64, ptr, ptr, i64, ptr, ptr, ptr, i64, i64, i64, i64, i64, i64, ptr, ptr, ptr,
                                       ptr, i64]
    lib.gs_bin_exact_count.restype = i64
    lib.gs_bin_exact_fill.argtypes = [i64, ptr, ptr, ptr, ptr, i64, i64, i64, i64, i64, i64, ptr, ptr, ptr, ptr, i64,
                                      i64]
    lib.gs_bin_exact_fill.restype = i64
    lib._gs_exact_bound = True


def _use_reference() -> bool:
    return os.environ.get("GSBENCH_RASTER", "").strip().lower() == "reference"


def rasterize(
    gaussians: RasterGaussians,
    camera: Camera,
    *,
    kernel: str,
    outputs: Iterable[str] = ("rgb",),
    background=None,
    settings: RasterSettings = RasterSettings(),
) -> RenderOutput:
    """Render ``outputs`` of ``gaussians`` seen by ``camera`` with ``kernel``; differentiable.

    See `gsbench.raster.types` for every definition. ``background`` (3,) overrides
    ``settings.background`` (a tensor may require grad). Only the requested outputs are returned
    (what the kernel accumulates alongside: `gsbench.raster.types`).
    """
    outs = _check_kernel_outputs(kernel, outputs)
    validate_gaussians(gaussians, kernel)
    if camera.width < 1 or camera.height < 1:
        raise ValueError(f"camera image size must be >= 1x1, got {camera.width}x{camera.height}")
    if _use_reference():
        from gsbench.raster import reference  # noqa: PLC0415

        warnings.warn("GSBENCH_RASTER=reference: using the slow dense PyTorch rasterizer", stacklevel=2)
        return reference.render(gaussians, camera, kernel=kernel, outputs=outs, settings=_with_bg(settings, background))

    from gsbench.raster.build import GsArgs, load_library  # noqa: PLC0415
    from gsbench.raster.projection import NUM_PARAMS, project  # noqa: PLC0415

    lib = load_library()
    dtype = gaussians.means.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"gaussians must be float32 or float64, got {dtype}")
    W, H = int(camera.width), int(camera.height)
    ts = int(settings.tile_size)
    if ts != 16:
        raise ValueError(f"the fast rasterizer uses 16x16 tiles; settings.tile_size={ts} is not supported")
    n = len(gaussians)
    bg = _background(background, settings, dtype)

    t0 = time.perf_counter()
    proj = project(gaussians, camera, kernel, settings)
    _prof("projection", time.perf_counter() - t0)

    t0 = time.perf_counter()
    tiles_x = (W + ts - 1) // ts
    tiles_y = (H + ts - 1) // ts
    # visible ids by (depth, id) (C++ radix sort) with their tile rectangles in that order, then per-tile lists
    rect = proj.rect.contiguous()
    depth_sort = proj.depth.to(dtype).contiguous()
    visible_u8 = proj.visible.contiguous().view(torch.uint8)
    order = torch.empty(n, dtype=torch.int32)
    rect_sorted = torch.empty(n, 4, dtype=torch.int32)
    cap = ctypes.c_int64(0)
    m_vis = lib.gs_depth_order(
        n, _ptr(visible_u8), _ptr(depth_sort), 0 if dtype == torch.float32 else 1, _ptr(rect), _ptr(order),
        _ptr(rect_sorted), ctypes.byref(cap),
    )
    capacity = int(cap.value)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int32)
    nthr = omp_threads()
    if kernel in ("ewa", "rade") and exact_overlap_enabled():
        # exact ellipse/tile overlap (csrc/raster.cpp): a Gaussian is listed only in the tiles of its rectangle
        # that its alpha >= 1/255 ellipse meets; the count pass sizes tile_list exactly
        _bind_exact_bin(lib)
        params_c = proj.params.detach().contiguous()
        keep_first = int("distortion" in outs)  # the distortion shift reads each tile's first rectangle Gaussian
        first = torch.empty(tiles_x * tiles_y if keep_first else 1, dtype=torch.int32)
        rec = torch.empty(max(n, 1) * 8, dtype=torch.int32)
        cursors = torch.empty(nthr * tiles_x * tiles_y, dtype=torch.int32)
        dt_id = 0 if dtype == torch.float32 else 1
        npar = int(params_c.shape[1])
        capacity = int(lib.gs_bin_exact_count(
            m_vis, _ptr(order), _ptr(rect_sorted), n, _ptr(visible_u8), _ptr(rect), _ptr(params_c), npar, dt_id, H,
            tiles_x, tiles_y, keep_first, _ptr(first), _ptr(rec), _ptr(offsets), _ptr(cursors), nthr,
        ))
        if capacity < 0:
            raise RuntimeError("gsbench rasterizer: tile list overflow")
        tile_list = torch.empty(max(capacity, 1), dtype=torch.int32)
        got = lib.gs_bin_exact_fill(
            m_vis, _ptr(order), _ptr(rect_sorted), _ptr(rec), _ptr(params_c), npar, dt_id, H, tiles_x, tiles_y,
            keep_first, _ptr(first), _ptr(offsets), _ptr(cursors), _ptr(tile_list), capacity, nthr,
        )
    else:
        tile_list = torch.empty(max(capacity, 1), dtype=torch.int32)
        got = lib.gs_bin_sorted(
            m_vis, _ptr(order), _ptr(rect_sorted), tiles_x, tiles_y, _ptr(offsets), _ptr(tile_list), capacity, nthr,
        )
    if got < 0:
        raise RuntimeError("gsbench rasterizer: tile list overflow")
    _prof("sort_bin", time.perf_counter() - t0)

    want = {o: (o in outs) for o in OUTPUTS}
    bounds = proj.bounds.contiguous()
    depth_key = depth_sort
    a = GsArgs()
    a.kernel = KERNEL_ID[kernel]
    a.dtype = 0 if dtype == torch.float32 else 1
    a.width, a.height, a.tiles_x, a.tiles_y = W, H, tiles_x, tiles_y
    a.n_gauss = n
    a.n_params = NUM_PARAMS[kernel]
    a.nthreads = omp_threads()
    a.want_rgb = int(want["rgb"])
    a.want_depth = int(want["depth"])
    a.want_median = int(want["median_depth"])
    a.want_normal = int(want["normal"])
    a.want_dist = int(want["distortion"])
    a.detach_dist = int(bool(settings.detach_distortion_weights))
    a.fx, a.fy, a.cx, a.cy = camera.fx, camera.fy, camera.cx, camera.cy
    a.near_z, a.far_z = settings.near, settings.far
    a.surfel_k = float(settings.surfel_filter)
    a.bounds = bounds.data_ptr()
    a.depth_key = depth_key.data_ptr()
    a.tile_offsets = offsets.data_ptr()
    a.tile_list = tile_list.data_ptr()

    m2d_leaf = proj.means2d.detach().clone().requires_grad_(True)
    absgrad = torch.zeros(n, dtype=dtype)
    # plane_distance = Σ w_i d_i (d_i = −n_i·μ_i), composited in the same pass as the colour, like a 4th channel
    plane_d = _plane_distances(proj.params, gaussians.means, camera, kernel) if want["plane_distance"] else None
    a.want_plane = int(want["plane_distance"])
    state = _State(lib, a, kernel, n, m2d_leaf, absgrad, H, W, dtype, (bounds, depth_key, offsets, tile_list, rect))
    state.want = want
    if kernel == "surfel":
        state.centre_z = proj.depth

    empty = torch.empty(0, dtype=dtype)
    plane_in = empty if plane_d is None else plane_d
    rgb, alpha, dacc, med, nrm, dist, plane = _RasterFn.apply(proj.params, plane_in, state)

    res = RenderOutput(width=W, height=H)
    if want["rgb"]:
        if bool((bg != 0).any()) or bg.requires_grad:
            rgb = rgb + (1.0 - alpha).unsqueeze(-1) * bg
        res.rgb = rgb
    if want["alpha"]:
        res.alpha = alpha
    if want["depth"]:
        res.depth = dacc / torch.clamp(alpha, min=1e-10)
    if want["median_depth"]:
        res.median_depth = med
    if want["normal"]:
        res.normal = nrm
    if want["distortion"]:
        res.distortion = dist
    if want["plane_distance"]:
        res.plane_distance = plane
    res.means2d = m2d_leaf
    res.radii = proj.radii
    res.visible = proj.visible
    res.extras = {"absgrad": absgrad, "pairs": state.pairs_fwd, "tile_pairs": capacity, "state": state}
    return res


# payload column of the first normal component per kernel (gsbench.raster.projection); raymax: b' = Σ⁻¹μ/c
_NORMAL_COLUMN = {"ewa": 10, "rade": 12, "surfel": 9, "raymax": 15}


def _plane_distances(params: torch.Tensor, means: torch.Tensor, camera: Camera, kernel: str) -> torch.Tensor:
    """d_i = −n_i·μ_i (N,), differentiable (contract ``plane_distance``, docs/methods/pgsr.md §3.1): n_i from
    the payload (raymax: −normalize(b'), its normal on the central ray), μ_i the camera-space centre.
    Culled rows are never binned, so their value is unused."""
    from gsbench.raster.projection import camera_tensors  # noqa: PLC0415

    R, t, _ = camera_tensors(camera, params.dtype)
    mu = means.to(params.dtype) @ R.T + t
    c = _NORMAL_COLUMN[kernel]
    normal = params[:, c:c + 3]
    if kernel == "raymax":
        normal = -torch.nn.functional.normalize(normal, dim=-1)
    return -(normal * mu).sum(-1)


def _with_bg(settings: RasterSettings, background) -> RasterSettings:
    if background is None:
        return settings
    from dataclasses import replace  # noqa: PLC0415

    bg = background.detach().cpu().tolist() if isinstance(background, torch.Tensor) else list(background)
    return replace(settings, background=tuple(float(x) for x in bg))


def integrate(
    gaussians: RasterGaussians,
    cameras: Sequence[Camera],
    points: torch.Tensor,
    *,
    kernel: str = "raymax",
    settings: RasterSettings = RasterSettings(),
) -> torch.Tensor:
    """GOF opacity (P,) of 3D ``points`` (P, 3): min over views of 1 − Π(1 − α_k) (no gradient), by
    `gsbench.raster.opacity_field.OpacityField` (which serves many queries from one binning)."""
    from gsbench.raster.opacity_field import OpacityField  # noqa: PLC0415

    with torch.no_grad():
        return OpacityField(gaussians, cameras, kernel=kernel, settings=settings).values(points)
