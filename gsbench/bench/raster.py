"""Rasterizer benchmark: the standard workloads of docs/rasterizer.md §12.1 for each kernel.

``run_raster_benchmark(kernels, workloads, repeats=5, threads=None) -> dict`` (JSON-able) and
``format_table(result) -> str``. Per kernel × workload: median fwd and fwd+bwd ms over ``repeats``
runs after a warm-up, threads, pairs evaluated (counted in C++: pixel lanes evaluated forward and
backward, and tile pairs × 256 without early termination), pairs/s as a fraction of the measured floor
(1.45 G pairs/s forward, 0.75 G pairs/s backward on 2 threads), a phase breakdown (projection,
sort/bin, raster fwd, raster bwd, projection bwd = the rest of the backward) and the peak extra RSS
during the cold first fwd+bwd (later runs reuse memory the allocator already holds).
Also the dense reference on a reduced case (it needs O(pixels × Gaussians) memory).
"""

from __future__ import annotations

import os
import statistics
import threading
import time

import numpy as np
import torch

import gsbench.raster as R
from gsbench.bench import roofline
from gsbench.data.camera import Camera
from gsbench.errors import ConfigError
from gsbench.raster import profiling, rasterize, reference
from gsbench.raster.abi import library
from gsbench.raster.sh import C0 as SH_C0
from gsbench.raster.types import KERNELS, RasterGaussians, RasterSettings

FLOOR_FWD = 1.45e9  # pairs/s, 2 threads (docs/rasterizer.md §12.1)
FLOOR_BWD = 0.75e9

STANDARD_WORKLOADS = {
    "50k-400x300": dict(n=50_000, width=400, height=300),
    "200k-800x600": dict(n=200_000, width=800, height=600),
    "50k-400x300-opacity0.1": dict(n=50_000, width=400, height=300, opacity=0.1),
    "200k-800x600-opacity0.1": dict(n=200_000, width=800, height=600, opacity=0.1),
}


def standard_scene(n: int, width: int, height: int, kernel: str = "ewa", opacity: float | None = None, seed: int = 0):
    """The docs/rasterizer.md §12.1 workload: N random anisotropic Gaussians in front of an identity camera."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=gen)
    means[:, :2] -= 0.5
    means[:, 2] += 1.5
    ncols = 2 if kernel == "surfel" else 3
    scales = torch.exp(-4.5 + 0.5 * torch.randn(n, ncols, generator=gen))
    q = torch.randn(n, 4, generator=gen)
    q = q / q.norm(dim=-1, keepdim=True)
    opac = 0.1 + 0.8 * torch.rand(n, generator=gen) if opacity is None else torch.full((n,), float(opacity))
    rgb = torch.rand(n, 3, generator=gen)
    sh = ((rgb - 0.5) / SH_C0).reshape(n, 1, 3)
    f = 1.2 * width
    cam = Camera(
        K=np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]]),
        R=np.eye(3), t=np.zeros(3), width=width, height=height, name="bench",
    )
    return RasterGaussians(means=means, quats=q, scales=scales, opacities=opac, sh=sh), cam


def _rss() -> int:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:  # pragma: no cover
        return 0


class _PeakRSS:
    """Samples the resident set size every millisecond in a thread; ``peak - start`` in bytes."""

    def __enter__(self):
        self.start = _rss()
        self.peak = self.start
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, _rss())
            time.sleep(0.001)

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, _rss())

    @property
    def delta(self) -> int:
        return max(0, self.peak - self.start)


def _leaves(g: RasterGaussians) -> RasterGaussians:
    f = lambda x: x.detach().clone().requires_grad_(True)  # noqa: E731
    return RasterGaussians(f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(g.sh))


def _bench_one(kernel: str, g: RasterGaussians, cam: Camera, repeats: int, settings: RasterSettings) -> dict:
    fwd_ms, tot_ms, phases = [], [], []
    pairs = (0, 0, 0)
    mem = _PeakRSS()
    for it in range(repeats + 1):  # first run = warm-up; its RSS growth is the peak extra memory
        gg = _leaves(g)
        profiling.profile = {}
        if it == 0:
            mem.__enter__()
        t0 = time.perf_counter()
        out = R.rasterize(gg, cam, kernel=kernel, outputs=("rgb",), settings=settings)
        t1 = time.perf_counter()
        loss = out.rgb.mean()
        loss.backward()
        t2 = time.perf_counter()
        if it == 0:
            mem.__exit__(None, None, None)
        prof = dict(profiling.profile)
        profiling.profile = None
        if it == 0:
            continue
        fwd_ms.append(1e3 * (t1 - t0))
        tot_ms.append(1e3 * (t2 - t0))
        prof["projection_bwd"] = max(0.0, (t2 - t1) - prof.get("raster_bwd", 0.0))
        phases.append(prof)
        st = out.extras["state"]
        pairs = (st.pairs_fwd, st.pairs_bwd, out.extras["tile_pairs"] * 256)
    phase_med = {k: 1e3 * statistics.median(p.get(k, 0.0) for p in phases)
                 for k in ("projection", "sort_bin", "raster_fwd", "raster_bwd", "projection_bwd")}
    pf, pb, tile_pairs = pairs
    rf = phase_med["raster_fwd"] / 1e3
    rb = phase_med["raster_bwd"] / 1e3
    return {
        "fwd_ms": statistics.median(fwd_ms),
        "fwd_bwd_ms": statistics.median(tot_ms),
        "fwd_ms_runs": fwd_ms,
        "fwd_bwd_ms_runs": tot_ms,
        "phases_ms": phase_med,
        "pairs_fwd": pf,
        "pairs_bwd": pb,
        "tile_pairs_x256": tile_pairs,
        "pairs_per_s_fwd": pf / rf if rf > 0 else None,
        "pairs_per_s_bwd": pb / rb if rb > 0 else None,
        "floor_fraction_fwd": (pf / rf) / FLOOR_FWD if rf > 0 else None,
        "floor_fraction_bwd": (pb / rb) / FLOOR_BWD if rb > 0 else None,
        "peak_extra_rss_mb": mem.delta / 2**20,
    }


def _bench_reference(kernel: str, n: int, width: int, height: int, repeats: int) -> dict:
    """Dense reference vs the fast path on a reduced case (the reference is O(pixels × N) in memory)."""
    g, cam = standard_scene(n, width, height, kernel)
    cam = Camera(K=cam.K, R=cam.R, t=cam.t, width=width, height=height)
    res = {"n": n, "width": width, "height": height}
    for name, fn in (
        ("reference", lambda gg: reference.render(gg, cam, kernel=kernel, outputs=("rgb",))),
        ("fast", lambda gg: rasterize(gg, cam, kernel=kernel, outputs=("rgb",))),
    ):
        times = []
        for it in range(repeats + 1):
            gg = _leaves(g)
            t0 = time.perf_counter()
            fn(gg).rgb.mean().backward()
            if it:
                times.append(1e3 * (time.perf_counter() - t0))
        res[f"{name}_fwd_bwd_ms"] = statistics.median(times)
    res["speedup"] = res["reference_fwd_bwd_ms"] / res["fast_fwd_bwd_ms"]
    return res


def run_raster_benchmark(
    kernels=("ewa", "rade", "raymax", "surfel"),
    workloads=("50k-400x300", "200k-800x600", "50k-400x300-opacity0.1", "200k-800x600-opacity0.1"),
    repeats: int = 5,
    threads: int | None = None,
    reference_case: tuple[int, int, int] | None = (1000, 80, 60),
    measure_machine: bool = True,
) -> dict:
    """Benchmark ``kernels`` × ``workloads`` (names of `STANDARD_WORKLOADS` or dicts n/width/height/opacity);
    with ``measure_machine``, also the machine's limits and each phase's fraction of its bound
    (`gsbench.bench.roofline`).

    ``None`` for ``kernels`` or ``workloads`` means all of them (the CLI passes None when a flag is omitted).
    """
    if kernels is None:
        kernels = KERNELS
    if workloads is None:
        workloads = tuple(STANDARD_WORKLOADS)
    unknown = [w for w in workloads if isinstance(w, str) and w not in STANDARD_WORKLOADS]
    if unknown:
        raise ConfigError(f"unknown raster workload(s) {unknown}; available: {', '.join(STANDARD_WORKLOADS)}")
    unknown = [k for k in kernels if k not in KERNELS]
    if unknown:
        raise ConfigError(f"unknown raster kernel(s) {unknown}; available: {', '.join(KERNELS)}")

    library()
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        nthreads = torch.get_num_threads()
        rows = []
        for wl in workloads:
            spec = STANDARD_WORKLOADS[wl] if isinstance(wl, str) else dict(wl)
            name = wl if isinstance(wl, str) else f"{spec['n']}-{spec['width']}x{spec['height']}"
            for kernel in kernels:
                g, cam = standard_scene(spec["n"], spec["width"], spec["height"], kernel, spec.get("opacity"))
                r = _bench_one(kernel, g, cam, repeats, RasterSettings())
                r.update(kernel=kernel, workload=name, n=spec["n"], width=spec["width"], height=spec["height"])
                rows.append(r)
        machine = roofline.machine_limits(nthreads) if measure_machine else None
        if machine is not None:
            for row in rows:
                row["roofline"] = roofline.annotate(row, machine)
        ref = None
        if reference_case is not None:
            n, w, h = reference_case
            ref = _bench_reference("ewa", n, w, h, max(1, min(repeats, 3)))
            ref["note"] = "dense reference is O(pixels × N) memory; timed on this reduced case instead of 50k/400x300"
        return {
            "threads": nthreads,
            "repeats": repeats,
            "floor_pairs_per_s": {"fwd": FLOOR_FWD, "bwd": FLOOR_BWD},
            "targets_ms": {"50k-400x300 ewa fwd+bwd": 150, "200k-800x600 ewa fwd+bwd": 300},
            "results": rows,
            "machine": machine,
            "reference": ref,
            "torch": torch.__version__,
        }
    finally:
        torch.set_num_threads(old_threads)


def format_table(result: dict) -> str:
    """A markdown table of `run_raster_benchmark`'s result."""
    lines = [
        f"threads: {result['threads']}, median of {result['repeats']} runs after a warm-up; "
        "pairs = pixel lanes evaluated (fwd/bwd), floor = 1.45/0.75 G pairs/s",
        "",
        "| kernel | workload | fwd ms | fwd+bwd ms | proj | sort/bin | raster fwd | raster bwd | proj bwd "
        "| pairs fwd (M) | pairs bwd (M) | tile pairs×256 (M) | fwd/floor | bwd/floor | peak MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["results"]:
        p = r["phases_ms"]
        ff = r["floor_fraction_fwd"]
        fb = r["floor_fraction_bwd"]
        lines.append(
            f"| {r['kernel']} | {r['workload']} | {r['fwd_ms']:.1f} | {r['fwd_bwd_ms']:.1f} | {p['projection']:.1f} | "
            f"{p['sort_bin']:.1f} | {p['raster_fwd']:.1f} | {p['raster_bwd']:.1f} | {p['projection_bwd']:.1f} | "
            f"{r['pairs_fwd'] / 1e6:.1f} | {r['pairs_bwd'] / 1e6:.1f} | {r['tile_pairs_x256'] / 1e6:.1f} | "
            f"{'-' if ff is None else f'{ff:.2f}'} | {'-' if fb is None else f'{fb:.2f}'} | {r['peak_extra_rss_mb']:.0f} |"
        )
    if result.get("machine"):
        lines += ["", roofline.format_roofline({"machine": result["machine"], "rows": result["results"]})]
    ref = result.get("reference")
    if ref:
        lines += [
            "",
            f"reference (dense PyTorch) vs fast, ewa rgb fwd+bwd at {ref['n']} Gaussians {ref['width']}x{ref['height']}: "
            f"{ref['reference_fwd_bwd_ms']:.0f} ms vs {ref['fast_fwd_bwd_ms']:.1f} ms ({ref['speedup']:.0f}x). {ref['note']}",
        ]
    return "\n".join(lines)
