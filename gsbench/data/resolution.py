"""The trained image size: a factor from ``data.downscale`` and ``data.max_size`` and the size on disk."""

from __future__ import annotations

from gsbench.errors import DataError


def fit_downscale(width: int, height: int, downscale: float = 1.0, max_size=()) -> float:
    """The factor images of ``width`` x ``height`` are divided by: ``downscale``, raised so that the long
    side fits in ``max_size[0]`` and the short side in ``max_size[1]`` pixels (``data.max_size``):

        f = max(downscale, max(W, H) / long, min(W, H) / short)

    so a preset names one image size whatever the files on disk (1600x1200 DTU photos and 400x300
    synthetic views both train at 200x150 under ``max_size [240, 150]``). Empty ``max_size``: ``downscale``.
    """
    if downscale < 1.0:
        raise DataError(f"downscale must be >= 1 (it divides the image size), got {downscale}")
    if not max_size:
        return float(downscale)
    if len(max_size) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in max_size):
        raise DataError(f"data.max_size must be [long side, short side] in pixels (two positive numbers) or [], "
                        f"got {list(max_size)}; fix: e.g. data.max_size=[240,150]")
    long_side, short_side = max(max_size), min(max_size)
    return float(max(downscale, max(width, height) / long_side, min(width, height) / short_side))
