"""A preset names one image size whatever the files on disk (`gsbench.data.resolution.fit_downscale`)."""

from __future__ import annotations

import numpy as np
import pytest

from gsbench.data.images import scaled_size
from gsbench.data.loader import load_scene
from gsbench.data.resolution import fit_downscale
from gsbench.errors import DataError

CPU, QUICK = (240, 150), (64, 48)


@pytest.mark.parametrize("size, box, trained", [
    ((400, 300), CPU, (200, 150)),    # the DTU-like synthetic views: the DTU scripts' -r 2
    ((1600, 1200), CPU, (200, 150)),  # real DTU photos: the same size, not 800x600
    ((480, 270), CPU, (240, 135)),    # TnT-like synthetic views: -r 2
    ((1920, 1080), CPU, (240, 135)),  # real TnT frames
    ((1200, 1600), CPU, (150, 200)),  # portrait: the long side is the long side
    ((160, 120), CPU, (160, 120)),    # never enlarged
    ((64, 48), QUICK, (64, 48)),
    ((400, 300), QUICK, (64, 48)),
    ((480, 270), QUICK, (64, 36)),
])
def test_max_size_fits_every_capture_to_one_size(size, box, trained):
    assert scaled_size(*size, fit_downscale(*size, 1.0, box)) == trained


def test_downscale_is_a_floor_and_an_empty_box_keeps_it():
    assert fit_downscale(1600, 1200, 2.0, ()) == 2.0
    assert fit_downscale(400, 300, 4.0, CPU) == 4.0
    for bad in ([240], [0, 150], [240, -1], ["a", 3]):
        with pytest.raises(DataError, match="data.max_size"):
            fit_downscale(400, 300, 1.0, bad)
    with pytest.raises(DataError, match="downscale must be >= 1"):
        fit_downscale(400, 300, 0.5, ())


def test_loaded_scene_states_its_source_size_and_scales_cameras_with_images(tiny_spot):
    full = load_scene(tiny_spot, load_images=False)
    half = load_scene(tiny_spot, max_size=(32, 24))
    assert half.source_size == (64, 48) and half.downscale == 2.0 and full.downscale == 1.0
    assert half.images[0].shape == (24, 32, 3) and half.masks[0].shape == (24, 32)
    assert (half.cameras[0].width, half.cameras[0].height) == (32, 24)
    np.testing.assert_allclose(half.cameras[0].K[:2], full.cameras[0].K[:2] / 2)
