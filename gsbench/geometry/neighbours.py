"""The K-nearest-neighbour index of Gaussian means (IBGS, docs/methods/ibgs.md §2).

``N(i)`` = the K nearest *other* means of Gaussian i, by a scipy KD-tree (``cKDTree``, all cores),
held fixed (no gradient) between refreshes. IBGS refreshes it every 100 steps and after every
densification or pruning, because the rows change (`gsbench.methods.ibgs`, `gsbench.training.strategies.sparsity`).

Coincident means (clones at one position, a duplicated SfM point) make "self" tie with its twins at
distance 0, so the tree does not always return i first: the query asks for K + 1 and drops i where it
appears, else the farthest. With fewer than K + 1 Gaussians, K shrinks to N − 1 (0 for one Gaussian).
"""

from __future__ import annotations

import time

import numpy as np
import torch
from scipy.spatial import cKDTree

from gsbench.errors import ConfigError, NumericalError
from gsbench.signals import signals_deferred


def rows(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values[index]`` for an integer ``index`` of any shape, by ``index_select`` on the flattened index
    (its backward is an index_add, much cheaper on the CPU than the index_put of advanced indexing)."""
    return values.index_select(0, index.reshape(-1)).reshape(*index.shape, *values.shape[1:])


def nearest_other(points: np.ndarray, k: int) -> np.ndarray:
    """(N, min(k, N−1)) int64 indices of the ``k`` nearest other points of each of ``points`` (N,3)."""
    n = len(points)
    k = min(int(k), max(n - 1, 0))
    if k == 0:
        return np.zeros((n, 0), dtype=np.int64)
    with signals_deferred():
        _, idx = cKDTree(points).query(points, k=k + 1, workers=-1)
    idx = np.asarray(idx, dtype=np.int64).reshape(n, k + 1)
    is_self = idx == np.arange(n)[:, None]
    drop = np.where(is_self.any(1), is_self.argmax(1), k)  # i's own column, or the farthest
    keep = np.ones_like(idx, dtype=bool)
    keep[np.arange(n), drop] = False
    return idx[keep].reshape(n, k)


class NeighbourIndex:
    """K nearest other means of every Gaussian (module docstring); ``index`` (N, K) int64; ``seconds``
    the time spent in refreshes so far (checkpointed, for the run record)."""

    def __init__(self, k: int):
        if int(k) < 1:
            raise ConfigError(f"the kNN size K must be >= 1, got {k}")
        self.k = int(k)
        self.index = torch.zeros((0, self.k), dtype=torch.int64)
        self.seconds = 0.0

    @torch.no_grad()
    def refresh(self, means: torch.Tensor) -> None:
        """Recompute the index from the current ``means`` (N,3)."""
        began = time.perf_counter()
        points = means.detach().to(torch.float64).numpy()
        if not np.isfinite(points).all():
            raise NumericalError(f"kNN refresh: {int((~np.isfinite(points)).any(1).sum())} Gaussian means are "
                                 "not finite; lower the position learning rate or resume from an earlier checkpoint")
        self.index = torch.from_numpy(nearest_other(points, self.k))
        self.seconds += time.perf_counter() - began

    def check(self, n: int) -> torch.Tensor:
        """The index, after checking it was computed for ``n`` Gaussians (a stale index is a bug)."""
        if len(self.index) != n:
            raise NumericalError(f"the kNN index holds {len(self.index)} rows for {n} Gaussians; it must be "
                                 "refreshed after every densification or pruning")
        return self.index

    def state_dict(self) -> dict:
        return {"k": self.k, "index": self.index.clone(), "seconds": self.seconds}

    def load_state_dict(self, state: dict) -> None:
        self.k, self.index, self.seconds = int(state["k"]), state["index"].clone(), float(state["seconds"])
