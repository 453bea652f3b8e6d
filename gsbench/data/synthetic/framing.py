"""How much of each image the object fills, and the camera distance that makes it fill a given share.

The **object share** of a view is the fraction of its pixels whose centre ray hits the object (the
object alone: on a table seen from above nothing stands in front of it, so this is the mask's share);
a scene's share is the mean over its views, measured on a ``PROBE_WIDTH``-pixel-wide copy of each
camera (the share of a fixed view hardly depends on the resolution).

Shares of reference (`FRAMINGS`):

- ``dtu`` = 0.34: a real DTU capture (scan 65, the skull; 49 views at 1600x1200) measured with its
  own masks in this project's issue 39: the object covers 34% of each image (its bounding box 83% of
  the image height);
- ``small`` = 0.126: the first DTU-layout synthetic scenes (``synthetic/spot``, ``synthetic/dtu-spot``:
  Spot on the cap rig at 3.5 bounding radii), measured by `object_share` on them (the other
  DTU-like table scenes of generator v7 fill 0.17 to 0.26; `gsbench list` gives each scene's share).

`framed_distance` finds the rig distance (in object bounding radii) whose views have a given share:
the share falls monotonically with the distance, so a bisection on log distance between
``MIN_DISTANCE`` and ``MAX_DISTANCE`` radii, ``BISECTIONS`` halvings (relative precision 2⁻¹⁶ of the
bracket's log width), each step casting ``views x PROBE_WIDTH x PROBE_WIDTH * H / W`` rays.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from gsbench.data.camera import Camera
from gsbench.data.synthetic.primitives import Surface
from gsbench.data.synthetic.render import Renderer
from gsbench.errors import DataError

FRAMINGS = {"dtu": 0.34, "small": 0.126}
PROBE_WIDTH = 96
MIN_DISTANCE, MAX_DISTANCE = 1.25, 40.0  # object bounding radii
BISECTIONS = 16


def parse_framing(value) -> float | None:
    """``dtu``, ``small`` or a share in (0, 1) -> the share; None stays None (the layout's distance)."""
    if value is None or isinstance(value, float):
        share = value
    elif value in FRAMINGS:
        share = FRAMINGS[value]
    else:
        try:
            share = float(value)
        except ValueError:
            share = -1.0
    if share is not None and not 0.0 < share < 1.0:
        raise DataError(f"framing {value!r}: expected {' or '.join(FRAMINGS)} or an object share of the image in (0, 1), "
                        "e.g. --framing 0.3")
    return share


def object_share(renderer: Renderer, cameras: list[Camera]) -> float:
    """Mean fraction of the pixels whose centre ray hits the renderer's surface (module docstring)."""
    shares = []
    for cam in cameras:
        probe = cam.scaled(PROBE_WIDTH / cam.width)
        shares.append(float(np.mean(renderer.depth(probe) > 0)))
    return float(np.mean(shares))


def framed_distance(surface: Surface, cameras_at: Callable[[float], list[Camera]], share: float) -> tuple[float, float]:
    """(distance in bounding radii, the share measured there) for which the views ``cameras_at(distance)``
    of the object ``surface`` have object share ``share`` (module docstring)."""
    renderer = Renderer(surface)
    lo, hi = np.log(MIN_DISTANCE), np.log(MAX_DISTANCE)
    nearest, farthest = object_share(renderer, cameras_at(MIN_DISTANCE)), object_share(renderer, cameras_at(MAX_DISTANCE))
    if not farthest <= share <= nearest:
        raise DataError(f"framing {share:g}: the object covers {farthest:.3g} to {nearest:.3g} of the image between "
                        f"{MIN_DISTANCE:g} and {MAX_DISTANCE:g} bounding radii; fix: a framing in that range")
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        if object_share(renderer, cameras_at(float(np.exp(mid)))) > share:
            lo = mid
        else:
            hi = mid
    distance = float(np.exp(0.5 * (lo + hi)))
    return distance, object_share(renderer, cameras_at(distance))
