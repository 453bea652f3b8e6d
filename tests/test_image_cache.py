"""The decoded-image cache of gsbench.data.images.read_views: hits are bit-identical, any change to the
files or the downscale misses, corrupt entries are replaced, GSBENCH_IMAGE_CACHE=0 turns it off."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from gsbench.data import images as images_mod
from gsbench.data.images import decoded_cache_path, list_images, write_rgb
from gsbench.data.loader import load_scene
from gsbench.errors import DataError


@pytest.fixture
def scene_dir(tiny_spot, tmp_path, monkeypatch):
    """A private copy of the 64x48 spot scene (its files get touched) and a private cache root."""
    monkeypatch.setenv("GSBENCH_DATA", str(tmp_path / "cache"))
    monkeypatch.delenv("GSBENCH_IMAGE_CACHE", raising=False)
    dst = tmp_path / "spot"
    shutil.copytree(tiny_spot, dst)
    return dst


def cache_files(tmp_path):
    folder = tmp_path / "cache" / "decoded"
    return sorted(folder.glob("*.npz")) if folder.is_dir() else []


def all_files(tmp_path):
    folder = tmp_path / "cache" / "decoded"
    return sorted(folder.iterdir()) if folder.is_dir() else []


class Counter:
    """Wraps the decoders: counts the calls, or raises to prove a load did not decode."""

    def __init__(self, monkeypatch, fail=False):
        self.calls = 0
        self.fail = fail
        for name in ("decode_rgb", "read_mask"):
            real = getattr(images_mod, name)
            monkeypatch.setattr(images_mod, name, self.wrap(real))

    def wrap(self, real):
        def f(*args, **kwargs):
            self.calls += 1
            if self.fail:
                raise AssertionError("decoded although the cache should have been used")
            return real(*args, **kwargs)
        return f


def assert_same(a, b):
    assert len(a.images) == len(b.images) and len(a.masks) == len(b.masks)
    for x, y in zip(a.images, b.images):
        assert x.dtype == y.dtype == np.float32 and np.array_equal(x, y)
    for x, y in zip(a.masks, b.masks):
        assert x.dtype == y.dtype == bool and np.array_equal(x, y)


def test_second_load_reads_the_cache_and_is_bit_identical(scene_dir, tmp_path, monkeypatch):
    first = load_scene(scene_dir)
    files = cache_files(tmp_path)
    assert len(files) == 1 and not [p for p in all_files(tmp_path) if p.suffix != ".npz"], "no temp files left"
    with monkeypatch.context() as m:
        Counter(m, fail=True)
        second = load_scene(scene_dir)
    assert_same(first, second)
    monkeypatch.setenv("GSBENCH_IMAGE_CACHE", "0")
    assert_same(first, load_scene(scene_dir))  # and both equal a plain decode
    with np.load(files[0]) as npz:
        assert npz["image00000"].dtype == np.uint8 and npz["mask00000"].dtype == bool


def test_touching_an_image_or_changing_downscale_misses(scene_dir, tmp_path, monkeypatch):
    load_scene(scene_dir)
    count = Counter(monkeypatch)
    load_scene(scene_dir)
    assert count.calls == 0
    img = list_images(scene_dir / "image")[3]
    st = os.stat(img)
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    load_scene(scene_dir)
    assert count.calls > 0 and len(cache_files(tmp_path)) == 2
    count.calls = 0
    half = load_scene(scene_dir, downscale=2)
    assert count.calls > 0 and len(cache_files(tmp_path)) == 3
    assert half.images[0].shape == (24, 32, 3) and half.masks[0].shape == (24, 32)
    count.calls = 0
    again = load_scene(scene_dir, downscale=2)
    assert count.calls == 0
    assert_same(half, again)


def test_key_depends_on_masks_and_downscale(scene_dir):
    paths = list_images(scene_dir / "image")
    masks = list_images(scene_dir / "mask")
    keys = {decoded_cache_path(paths, masks, 1.0), decoded_cache_path(paths, None, 1.0),
            decoded_cache_path(paths, masks, 2.0), decoded_cache_path(paths[:-1], masks[:-1], 1.0)}
    assert len(keys) == 4
    assert decoded_cache_path(paths, masks, 1.0) == decoded_cache_path(list(paths), list(masks), 1)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "fewer_views", "wrong_shape"])
def test_a_corrupt_cache_file_is_ignored_and_replaced(scene_dir, tmp_path, monkeypatch, damage):
    first = load_scene(scene_dir)
    (path,) = cache_files(tmp_path)
    if damage == "garbage":
        path.write_bytes(b"not a zip file at all")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        with np.load(path) as npz:
            arrays = {k: npz[k] for k in npz.files}
        if damage == "fewer_views":
            arrays.pop(sorted(k for k in arrays if k.startswith("image"))[-1])
        else:
            arrays["image00002"] = arrays["image00002"][:-1]
        with open(path, "wb") as f:
            np.savez(f, **arrays)
    count = Counter(monkeypatch)
    second = load_scene(scene_dir)
    assert count.calls > 0
    assert_same(first, second)
    count.fail = True
    assert_same(first, load_scene(scene_dir))  # rewritten: read back without decoding
    assert cache_files(tmp_path) == [path]


def test_disabled_cache_writes_nothing(scene_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("GSBENCH_IMAGE_CACHE", "0")
    count = Counter(monkeypatch)
    load_scene(scene_dir)
    load_scene(scene_dir)
    assert count.calls > 0 and not (tmp_path / "cache" / "decoded").exists()


def test_headers_only_load_never_touches_the_cache(scene_dir, tmp_path, monkeypatch):
    Counter(monkeypatch, fail=True)
    scene = load_scene(scene_dir, load_images=False)
    assert scene.images == [] and not (tmp_path / "cache" / "decoded").exists()


def test_header_checks_still_run_with_a_cache(scene_dir, tmp_path):
    load_scene(scene_dir)
    img = list_images(scene_dir / "image")[0]
    write_rgb(img, np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(DataError, match="image is 12x10"):
        load_scene(scene_dir)


def test_an_unwritable_cache_does_not_fail_the_load(scene_dir, tmp_path, monkeypatch):
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "decoded").write_text("a file where the folder should be")
    scene = load_scene(scene_dir)
    assert len(scene.images) > 0
