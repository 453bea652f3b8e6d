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

Decoded-image cache (`read_views`): decoding and box-downscaling every photo is most of a scene's
load time (49 DTU photos at 1600x1200: ~30 s), paid again by every run and every resume, so the
decoded, resized views of a scene are kept in ``<cache>/decoded/<key>.npz`` (``<cache>``:
``$GSBENCH_DATA`` or ``~/.cache/gsbench/scenes``, `gsbench.data.cache.cache_dir`). The key is a
sha1 over each image's and mask's absolute path, size and mtime (ns), the downscale factor, whether
masks were read and `DECODED_CACHE_VERSION`, so editing, replacing or touching a file, or a new
downscale, is a miss. The file is an uncompressed ``np.savez`` of the uint8 images as PIL gives them
after the resize (``image00000``, ...) and the bool masks (``mask00000``, ...), written atomically
(temp file + ``os.replace``); the float32 conversion happens after loading, so a cached load is
bit-identical to a decoded one. A cache file that cannot be read or does not match (view count,
shapes, dtypes) is ignored and rewritten; a cache that cannot be written is skipped. The header
checks (image sizes vs cameras, mask sizes) always run first; ``load_images=False`` never touches
the cache. ``GSBENCH_IMAGE_CACHE=off`` (or ``0``/``false``/``no``) turns the cache off. Stale
entries are not removed: delete ``<cache>/decoded/`` to reclaim the space.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError
from tqdm import tqdm

from gsbench.atomic import atomic_path
from gsbench.data.cache import cache_dir
from gsbench.errors import DataError
from gsbench.switches import IMAGE_CACHE

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")
DECODED_CACHE_VERSION = 1
LOAD_PROGRESS_SECONDS = 10.0  # decoding that lasts longer shows its progress (`_decode_views`)


def list_images(folder: Path) -> list[Path]:
    """Image files in ``folder``, sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.suffix in IMAGE_SUFFIXES and p.is_file())


def scaled_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    """Image size after downscaling (matches `Camera.scaled(1 / downscale)`)."""
    return max(1, int(round(width / downscale))), max(1, int(round(height / downscale)))


PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk's type and CRC: the last 8 bytes of a complete PNG


def _unreadable(path: Path, exc) -> DataError:
    detail = " ".join(str(exc).split())
    return DataError(f"{path}: unreadable image ({detail}); fix: replace the file with a valid PNG/JPEG")


def _open(path: Path):
    try:
        img = Image.open(path)
        img.load()
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError, ValueError) as exc:
        raise _unreadable(path, exc) from exc
    return img


def _check_png_end(path: Path) -> None:
    """A PNG must end with its IEND chunk (checked from the last bytes, so a truncated file is caught
    by header-only loads too, which never decode the pixels)."""
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        f.seek(max(0, size - 1024))
        tail = f.read()
    if PNG_END not in tail:
        raise DataError(f"{path}: truncated PNG (no IEND chunk at the end of its {size} bytes); "
                        "fix: replace the file with a complete PNG")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding the pixels (PNGs: also that the file is
    complete, `_check_png_end`). An image larger than PIL's decompression-bomb limit is an error."""
    try:
        with Image.open(path) as img:
            size, fmt = img.size, img.format
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError, ValueError) as exc:
        raise _unreadable(path, exc) from exc
    if fmt == "PNG":
        _check_png_end(path)
    return size


def _resize(img, downscale: float):
    if downscale == 1.0:
        return img
    return img.resize(scaled_size(*img.size, downscale), Image.Resampling.BOX)


def _eight_bit(img):
    """``img`` with 8 bits per channel. 16-bit grayscale (Pillow modes ``I;16*``, and ``I`` as older Pillow reads a
    16-bit PNG) is scaled by 255/65535 and rounded; Pillow's own conversion would clip every value above 255 to
    white, leaving a 16-bit image black and white."""
    if img.mode.startswith("I;16") or img.mode == "I":
        wide = np.asarray(img, dtype=np.int64)
        return Image.fromarray(((np.clip(wide, 0, 65535) * 255 + 32767) // 65535).astype(np.uint8), mode="L")
    return img


def decode_rgb(path: Path, downscale: float = 1.0) -> np.ndarray:
    """uint8 HxWx3 after the box resize (what the decoded-image cache stores); 16-bit grayscale scaled to 8 bits."""
    return np.asarray(_resize(_eight_bit(_open(path)).convert("RGB"), downscale), dtype=np.uint8)


def to_float(rgb: np.ndarray) -> np.ndarray:
    """uint8 -> float32 in [0, 1] (``/ 255`` in float32, in place on the one new array)."""
    out = np.array(rgb, dtype=np.float32)
    out /= 255.0
    return out


def read_rgb(path: Path, downscale: float = 1.0) -> np.ndarray:
    """float32 HxWx3 in [0, 1]."""
    return to_float(decode_rgb(path, downscale))


def read_mask(path: Path, downscale: float = 1.0) -> np.ndarray:
    """bool HxW: max over channels > 127 (16-bit masks scaled to 8 bits first), then (if downscaled) box-filtered
    coverage > 0.5."""
    arr = np.asarray(_eight_bit(_open(path)))
    if arr.ndim == 3:
        arr = arr[..., :3].max(axis=2) if arr.shape[2] >= 3 else arr[..., 0]
    mask = arr > 127 if arr.dtype != bool else arr
    if downscale == 1.0:
        return mask
    small = _resize(Image.fromarray(mask.astype(np.float32)), downscale)
    return np.asarray(small) > 0.5


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    """Write float [0, 1] or uint8 HxWx3 as PNG."""
    if rgb.dtype != np.uint8:
        rgb = np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
    Image.fromarray(rgb).save(path)


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write a bool HxW mask as a 3-channel 0/255 PNG (the DTU/IDR mask layout)."""
    Image.fromarray(np.repeat((mask.astype(np.uint8) * 255)[..., None], 3, axis=2)).save(path)


# ---- decoded-image cache (module docstring) ----------------------------------------------------------


def image_cache_enabled() -> bool:
    """False when ``$GSBENCH_IMAGE_CACHE`` is ``off`` (`gsbench.switches`)."""
    return IMAGE_CACHE.value() == "on"


def decoded_cache_path(image_paths, mask_paths, downscale: float) -> Path:
    """``<cache>/decoded/<sha1>.npz`` for these files (their path, size, mtime), downscale and mask flag."""
    def ident(path):
        st = os.stat(path)
        return [str(Path(path).resolve()), st.st_size, st.st_mtime_ns]

    key = {"version": DECODED_CACHE_VERSION, "downscale": repr(float(downscale)), "masks": mask_paths is not None,
           "images": [ident(p) for p in image_paths],
           "mask_files": [ident(p) for p in mask_paths] if mask_paths is not None else []}
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()
    return Path(cache_dir()) / "decoded" / f"{digest}.npz"


def _expected_shapes(sizes, downscale: float) -> list[tuple[int, int]]:
    """(H, W) of each view after the resize."""
    out = []
    for w, h in sizes:
        w2, h2 = (w, h) if downscale == 1.0 else scaled_size(w, h, downscale)
        out.append((h2, w2))
    return out


def _load_cached(path: Path, shapes, with_masks: bool):
    """(uint8 images, bool masks or None) from ``path``, or None when it is missing, unreadable or does
    not match ``shapes`` (any error is a miss: the caller decodes and rewrites the file)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as npz:
            names = set(npz.files)
            n = len(shapes)
            want = {f"image{k:05d}" for k in range(n)} | ({f"mask{k:05d}" for k in range(n)} if with_masks else set())
            if names != want:
                return None
            images, masks = [], [] if with_masks else None
            for k, (h, w) in enumerate(shapes):
                img = npz[f"image{k:05d}"]
                if img.dtype != np.uint8 or img.shape != (h, w, 3):
                    return None
                images.append(img)
                if with_masks:
                    mask = npz[f"mask{k:05d}"]
                    if mask.dtype != bool or mask.shape != (h, w):
                        return None
                    masks.append(mask)
        return images, masks
    except Exception:  # noqa: BLE001  a corrupt cache file is a miss, never a failed load
        return None


def _write_cached(path: Path, images, masks) -> None:
    """Uncompressed ``np.savez`` to a temp file next to ``path``, then ``os.replace``; errors
    (read-only or full disk) leave the cache without the entry and the load unaffected."""
    arrays = {f"image{k:05d}": img for k, img in enumerate(images)}
    if masks is not None:
        arrays.update({f"mask{k:05d}": m for k, m in enumerate(masks)})
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)
    except OSError:
        pass


def _check_headers(image_paths, mask_paths, sizes) -> None:
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


def _decode_views(image_paths, mask_paths, downscale: float):
    """(uint8 images, bool masks or None), decoded; once that has lasted `LOAD_PROGRESS_SECONDS`, its progress on
    stderr: a tqdm bar on a terminal, else a line every `LOAD_PROGRESS_SECONDS` (49 photos of 8000x6000 take
    minutes to decode)."""
    raw, masks = [], [] if mask_paths is not None else None
    total = len(image_paths)
    start = last = time.perf_counter()
    with tqdm(total=total, desc="decoding images", unit="view", disable=None, delay=LOAD_PROGRESS_SECONDS) as bar:
        for k, path in enumerate(image_paths):
            raw.append(decode_rgb(path, downscale))
            if masks is not None:
                masks.append(read_mask(mask_paths[k], downscale))
            bar.update()
            now = time.perf_counter()
            if bar.disable and now - last >= LOAD_PROGRESS_SECONDS:
                last, done = now, k + 1
                sys.stderr.write(f"gsbench: decoding images: {done}/{total} views after {now - start:.0f} s, about "
                                 f"{(now - start) / done * (total - done):.0f} s left\n")
                sys.stderr.flush()
    return raw, masks


def read_views(image_paths, mask_paths, sizes, downscale: float, load_images: bool):
    """Read all images (and masks, when ``mask_paths`` is not None), checking each has its expected size.

    ``sizes`` is the (width, height) each image must have on disk. Returns ``(images, masks)``; both
    are empty/None when ``load_images`` is False (only the headers are checked then). Decoded views
    come from / go to the decoded-image cache (module docstring); decoding that lasts shows its progress
    (`_decode_views`).
    """
    sizes = list(sizes)
    image_paths = list(image_paths)[:len(sizes)]
    sizes = sizes[:len(image_paths)]
    mask_paths = list(mask_paths)[:len(image_paths)] if mask_paths is not None else None
    _check_headers(image_paths, mask_paths, sizes)
    if not load_images:
        return [], None
    with_masks = mask_paths is not None
    cache = None
    if image_cache_enabled():
        try:
            cache = decoded_cache_path(image_paths, mask_paths, downscale)
        except OSError:  # a file vanished since its header was read: decode (and fail) as without a cache
            cache = None
    cached = _load_cached(cache, _expected_shapes(sizes, downscale), with_masks) if cache else None
    if cached is not None:
        raw, masks = cached
    else:
        raw, masks = _decode_views(image_paths, mask_paths, downscale)
        if cache is not None:
            _write_cached(cache, raw, masks)
    images = []
    for k in range(len(raw)):
        images.append(to_float(raw[k]))
        raw[k] = None  # free each uint8 view once converted
    return images, masks
