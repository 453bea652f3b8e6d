"""Checkpoints are data: read back with ``weights_only=True``, a file holding an object to unpickle is refused
before any of it runs, and the RNG states a resume needs survive as tensors and plain values."""

from __future__ import annotations

import pathlib
import random

import numpy as np
import pytest
import torch

from gsbench.errors import CheckpointError
from gsbench.training.trainer import load_checkpoint, rng_state, set_rng_state


class _RunsCodeWhenLoaded:
    """Unpickling this calls ``Path.touch(marker)``: what a checkpoint made to run code would do."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def test_a_checkpoint_carrying_a_pickled_object_is_refused_without_running_it(tmp_path):
    marker, path = tmp_path / "ran", tmp_path / "checkpoint.pt"
    torch.save({"step": 3, "payload": _RunsCodeWhenLoaded(marker)}, path)
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt is refused: it holds objects other than tensors"):
        load_checkpoint(path)
    assert not marker.exists()


def test_a_checkpoint_with_numpy_rng_objects_from_older_gsbench_is_refused_with_the_fix(tmp_path):
    path = tmp_path / "checkpoint.pt"
    torch.save({"step": 3, "rng": {"numpy": np.random.get_state()}}, path)
    with pytest.raises(CheckpointError, match="delete it, and the run trains again from the start"):
        load_checkpoint(path)


def test_a_damaged_checkpoint_is_one_clear_error(tmp_path):
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(b"PK\x03\x04 not a checkpoint")
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_checkpoint(path)


def test_rng_states_round_trip_through_a_weights_only_checkpoint(tmp_path):
    random.seed(1)
    np.random.seed(2)
    torch.manual_seed(3)
    np.random.normal()  # a cached Gaussian in numpy's state
    path = tmp_path / "checkpoint.pt"
    torch.save({"rng": rng_state()}, path)
    expected = (random.random(), np.random.normal(), float(torch.rand(1)))
    random.seed(9)
    np.random.seed(9)
    torch.manual_seed(9)
    set_rng_state(load_checkpoint(path)["rng"])
    assert (random.random(), np.random.normal(), float(torch.rand(1))) == expected
