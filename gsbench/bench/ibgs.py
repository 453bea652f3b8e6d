"""IBGS overhead benchmark (`gsbench bench ibgs`): what IBGS adds to a training step, per size N.

Workload: N means sampled on a unit sphere with 1% radial noise (a surface, as trained Gaussians are),
K = 5. Timed (median of ``repeats`` after a warm-up): the kNN refresh (`gsbench.geometry.neighbours`), the
neighbourhood covariance + eigen-decomposition forward (`gsbench.geometry.local_geometry`), forward + backward
of eigval + eigvec (`gsbench.methods.ibgs_terms`), the frame alignment, and for comparison
``torch.linalg.eigh`` on the same covariances, forward and forward + backward of the same losses.
"""

from __future__ import annotations

import statistics
import time

import torch

from gsbench.geometry.local_geometry import (
    LocalGeometry,
    apply_alignment,
    frame_alignment,
    local_covariance,
    local_geometry,
)
from gsbench.geometry.neighbours import NeighbourIndex
from gsbench.methods.ibgs_terms import eigval_term, eigvec_term

DEFAULT_SIZES = (10_000, 100_000)


def surface_points(n: int, seed: int = 0) -> torch.Tensor:
    """``n`` points on the unit sphere, radius jittered by 1% (N,3) float32."""
    gen = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
    return direction * (1 + 0.01 * torch.randn(n, 1, generator=gen))


def _median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        began = time.perf_counter()
        fn()
        times.append(time.perf_counter() - began)
    return 1e3 * statistics.median(times)


def _losses(geometry: LocalGeometry) -> torch.Tensor:
    state = {"local_geometry": geometry, "scene_radius": 1.0}
    return eigval_term(None, None, state) + eigvec_term(None, None, state)


def run_ibgs_benchmark(sizes=DEFAULT_SIZES, k: int = 5, repeats: int = 5) -> dict:
    """{N: {phase: median ms}} for the phases of the module docstring."""
    result = {}
    for n in sizes:
        means = surface_points(n).requires_grad_(True)
        neighbours = NeighbourIndex(k)
        index = lambda: neighbours.refresh(means)  # noqa: E731
        index()
        frame = local_geometry(means.detach(), neighbours.index, 1.0).eigenvectors

        def losses_backward(make_geometry):
            means.grad = None
            _losses(make_geometry()).backward()

        def eigh_geometry():
            lam, vec = torch.linalg.eigh(local_covariance(means, neighbours.index, 1.0))
            return LocalGeometry(lam.flip(-1), vec.flip(-1), torch.ones(n, dtype=torch.bool), neighbours.index)

        def align():
            vectors = local_geometry(means.detach(), neighbours.index, 1.0).eigenvectors
            apply_alignment(vectors, *frame_alignment(vectors, frame))

        with torch.no_grad():
            forward = _median_ms(lambda: local_geometry(means, neighbours.index, 1.0), repeats)
            eigh_forward = _median_ms(eigh_geometry, repeats)
        result[n] = {
            "knn refresh": _median_ms(index, repeats),
            "covariance + eigen fwd": forward,
            "covariance + eigen + losses fwd+bwd": _median_ms(
                lambda: losses_backward(lambda: local_geometry(means, neighbours.index, 1.0)), repeats),
            "frame alignment (incl. fwd)": _median_ms(align, repeats),
            "torch.linalg.eigh: covariance + eigen fwd": eigh_forward,
            "torch.linalg.eigh: + losses fwd+bwd": _median_ms(lambda: losses_backward(eigh_geometry), repeats),
        }
    return result


def format_table(result: dict) -> str:
    sizes = list(result)
    phases = list(next(iter(result.values())))
    lines = ["| phase (median ms) | " + " | ".join(f"N = {n:,}" for n in sizes) + " |",
             "|---|" + "---|" * len(sizes)]
    lines += [f"| {p} | " + " | ".join(f"{result[n][p]:.1f}" for n in sizes) + " |" for p in phases]
    return "\n".join(lines)
