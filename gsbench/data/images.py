"""Reading and writing images and masks (PIL), with optional downscaling.

Conventions:
- RGB images load as float32 HxWx3 in [0, 1]; an alpha channel is ignored (2DGS's DTU images carry
  the mask in alpha; gsbench reads masks from ``mask/`` only).
- Masks load as bool HxW: the maximum over the colour channels > 127 (channel 0 for DTU's
  3-channel 0/255 masks, the same thing).
- ``downscale`` >= 1 divides the image size: the new size is ``round(W / downscale)`` x
  ``round(H / downscale)``, the same rounding as `Camera.scaled(1 / downscale)`. Resampling is PIL's
  box (area) filter, which maps the image extent [0, W] onto [0, W']; with pixel centres at
  ``i + 0.5`` that is exactly a scaling of the rows of K, so `Camera.scaled` is exact.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gsbench.errors import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")


def list_images(folder: Path) -> list[Path]:
    """Image files in ``folder``, sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.suffix in IMAGE_SUFFIXES and p.is_file())


def scaled_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    """Image size after downscaling (matches `Camera.scaled(1 / downscale)`)."""
    return max(1, int(round(width / downscale))), max(1, int(round(height / downscale)))


def _open(path: Path):
    from PIL import Image, UnidentifiedImageError  # noqa: PLC0415

    try:
        img = Image.open(path)
        img.load()
    except (OSError, UnidentifiedImageError) as exc:
        raise DataError(f"{path}: unreadable image ({exc}); fix: replace the file with a valid PNG/JPEG") from exc
    return img


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding the pixels."""
    from PIL import Image, UnidentifiedImageError  # noqa: PLC0415

    try:
        with Image.open(path) as img:
            return img.size
    except (OSError, UnidentifiedImageError) as exc:
        raise DataError(f"{path}: unreadable image ({exc}); fix: replace the file with a valid PNG/JPEG") from exc


def _resize(img, downscale: float):
    from PIL import Image  # noqa: PLC0415

    if downscale == 1.0:
        return img
    return img.resize(scaled_size(*img.size, downscale), Image.Resampling.BOX)


def read_rgb(path: Path, downscale: float = 1.0) -> np.ndarray:
    """float32 HxWx3 in [0, 1]."""
    img = _resize(_open(path).convert("RGB"), downscale)
    return np.asarray(img, dtype=np.float32) / 255.0


def read_mask(path: Path, downscale: float = 1.0) -> np.ndarray:
    """bool HxW: max over channels > 127, then (if downscaled) box-filtered coverage > 0.5."""
    from PIL import Image  # noqa: PLC0415

    arr = np.asarray(_open(path))
    if arr.ndim == 3:
        arr = arr[..., :3].max(axis=2) if arr.shape[2] >= 3 else arr[..., 0]
    mask = arr > 127 if arr.dtype != bool else arr
    if downscale == 1.0:
        return mask
    small = _resize(Image.fromarray(mask.astype(np.float32)), downscale)
    return np.asarray(small) > 0.5


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    """Write float [0, 1] or uint8 HxWx3 as PNG."""
    from PIL import Image  # noqa: PLC0415

    if rgb.dtype != np.uint8:
        rgb = np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
    Image.fromarray(rgb).save(path)


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write a bool HxW mask as a 3-channel 0/255 PNG (the DTU/IDR mask layout)."""
    from PIL import Image  # noqa: PLC0415

    Image.fromarray(np.repeat((mask.astype(np.uint8) * 255)[..., None], 3, axis=2)).save(path)


def read_views(image_paths, mask_paths, sizes, downscale: float, load_images: bool):
    """Read all images (and masks, when ``mask_paths`` is not None), checking each has its expected size.

    ``sizes`` is the (width, height) each image must have on disk. Returns ``(images, masks)``; both
    are empty/None when ``load_images`` is False (only the headers are checked then).
    """
    images, masks = [], [] if mask_paths is not None else None
    for k, (path, size) in enumerate(zip(image_paths, sizes)):
        found = image_size(path)
        if tuple(found) != tuple(size):
            raise DataError(
                f"{path}: image is {found[0]}x{found[1]} but {size[0]}x{size[1]} was expected (camera/other images); "
                "fix: give every view the same resolution as its camera"
            )
        if mask_paths is not None:
            mfound = image_size(mask_paths[k])
            if tuple(mfound) != tuple(size):
                raise DataError(
                    f"{mask_paths[k]}: mask is {mfound[0]}x{mfound[1]} but its image is {size[0]}x{size[1]}; "
                    "fix: give masks the resolution of their images"
                )
        if load_images:
            images.append(read_rgb(path, downscale))
            if mask_paths is not None:
                masks.append(read_mask(mask_paths[k], downscale))
    if not load_images:
        masks = None
    return images, masks
