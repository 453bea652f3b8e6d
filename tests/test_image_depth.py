"""Images and masks of 16 bits per channel: decoded to their values, not clipped to black and white."""

from __future__ import annotations

import numpy as np
from PIL import Image

from gsbench.data.images import decode_rgb, read_mask, read_rgb

VALUES = np.array([[0, 257, 1000, 32768], [40000, 50000, 65280, 65535]], dtype=np.uint16)


def test_a_16_bit_grayscale_png_is_decoded_to_its_true_values(tmp_path):
    path = tmp_path / "gray16.png"
    Image.fromarray(VALUES).save(path)
    assert Image.open(path).mode == "I;16"  # what Pillow reads such a file as
    rgb = read_rgb(path)
    assert rgb.shape == (2, 4, 3) and np.array_equal(rgb[..., 0], rgb[..., 2])
    assert np.abs(rgb[..., 0] - VALUES / 65535.0).max() <= 0.5 / 255 + 1e-7  # within 8-bit rounding
    assert len(np.unique(decode_rgb(path))) == 8  # every level kept, not 0/255 only


def test_a_16_bit_mask_thresholds_at_half_range(tmp_path):
    path = tmp_path / "mask16.png"
    Image.fromarray(VALUES).save(path)
    assert read_mask(path).tolist() == [[False, False, False, True], [True, True, True, True]]
