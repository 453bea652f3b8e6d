"""Scenes: cameras, images, masks, initial points and a handle to the ground truth.

`load_scene(path_or_name)` detects the format (DTU IDR layout, DTU COLMAP variant, Tanks-and-Temples)
or generates a built-in synthetic scene (`synthetic/<name>`) on first use.
"""

from gsbench.data.camera import Camera, GroundTruth, Normalisation, Scene

__all__ = ["Camera", "GroundTruth", "Normalisation", "Scene", "load_scene"]


def load_scene(path_or_name, **kwargs):
    """Load a scene folder or a built-in synthetic scene name; see `gsbench.data.loader.load_scene`."""
    from gsbench.data.loader import load_scene as _load  # noqa: PLC0415  (heavy imports stay lazy)

    return _load(path_or_name, **kwargs)
