"""Loading at scale and incomplete folders (issue 65, cases 10a and 10b): decoding that lasts shows its progress;
a COLMAP model whose images are missing names every one of them (the first few and the count)."""

from __future__ import annotations

import numpy as np
import pytest

import gsbench.data.images as images
from gsbench.data.camera import Camera
from gsbench.data.colmap import write_colmap_model
from gsbench.data.images import read_views, write_mask, write_rgb
from gsbench.data.loader import load_scene
from gsbench.data.synthetic.rigs import look_at
from gsbench.errors import DataError

W, H = 16, 12


def _views(folder, count):
    folder.mkdir(parents=True)
    for k in range(count):
        write_rgb(folder / f"{k:03d}.png", np.full((H, W, 3), 0.25))
        write_mask(folder / f"m{k:03d}.png", np.ones((H, W), bool))
    return [folder / f"{k:03d}.png" for k in range(count)], [folder / f"m{k:03d}.png" for k in range(count)]


def test_decoding_that_lasts_prints_progress_lines(tmp_path, monkeypatch, capsys):
    paths, masks = _views(tmp_path / "views", 3)
    read_views(paths, masks, [(W, H)] * 3, 1.0, True)
    assert capsys.readouterr().err == ""  # a quick load says nothing
    monkeypatch.setattr(images, "LOAD_PROGRESS_SECONDS", 0.0)  # every view "lasts"
    loaded, loaded_masks = read_views(paths, masks, [(W, H)] * 3, 1.0, True)
    assert len(loaded) == len(loaded_masks) == 3
    lines = capsys.readouterr().err.splitlines()  # stderr is no terminal here: lines, not a bar
    assert [line.split(" after ")[0] for line in lines] == [f"gsbench: decoding images: {k}/3 views" for k in (1, 2, 3)]
    assert lines[-1].endswith("about 0 s left")


def _colmap_scene(root, names, present):
    cameras = []
    for k, name in enumerate(names):
        R, t = look_at(np.array([3.0 * np.cos(k), 3.0 * np.sin(k), 1.0]), np.zeros(3))
        cameras.append(Camera(K=np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]]), R=R, t=t, width=W, height=H,
                              name=name))
    write_colmap_model(root / "sparse" / "0", cameras, np.zeros((1, 3)), np.full((1, 3), 0.5))
    (root / "images").mkdir()
    for name in present:
        write_rgb(root / "images" / name, np.full((H, W, 3), 0.5))
    return root


@pytest.mark.parametrize("missing,named", [
    ((3, 7), "2 of the 10 images named in the COLMAP model .* not found: 003.png, 007.png; fix: add them"),
    (tuple(range(2, 10)), "8 of the 10 images .* not found: 002.png, 003.png, 004.png, 005.png, 006.png and 3 more"),
])
def test_a_colmap_model_with_missing_images_names_them_all(tmp_path, missing, named):
    names = [f"{k:03d}.png" for k in range(10)]
    root = _colmap_scene(tmp_path / "Barn", names, [n for k, n in enumerate(names) if k not in missing])
    with pytest.raises(DataError, match=named):
        load_scene(root, load_images=False)


def test_images_the_colmap_model_does_not_name_are_named(tmp_path):
    names = [f"{k:03d}.png" for k in range(4)]
    root = _colmap_scene(tmp_path / "Barn", names, names + ["extra-a.png", "extra-b.png"])
    with pytest.raises(DataError, match=r"6 images but 4 cameras .* \(not in the model: extra-a.png, extra-b.png\)"):
        load_scene(root, load_images=False)
