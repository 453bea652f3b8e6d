"""IBGS's ablation grids on the rebuilt scenes (docs/methods/ibgs.md §11.4): the K = 1 row's eigen terms are idle, as
documented, and each grid's baseline row is its board's ibgs runs (the same run ids, so the boards' runs serve)."""

from __future__ import annotations

import functools

import pytest
import torch

from gsbench.geometry.local_geometry import local_geometry
from gsbench.geometry.neighbours import nearest_other
from gsbench.methods.ibgs_terms import eigval_term, eigvec_term
from gsbench.runs.sweep import expand, load_sweep
from sweep_files import sweep_file


def test_at_k_1_the_eigen_terms_have_nothing_to_fit():
    """A neighbourhood of two points is a line: λ2 = λ3 = 0 up to the jitter, so L_eigval has no gradient and every
    row's planarity is below L_eigvec's mask; at K = 5 on the same points both work."""
    means = torch.randn(200, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for k, idle in ((1, True), (5, False)):
        points = means.clone().requires_grad_(True)
        geometry = local_geometry(points, torch.from_numpy(nearest_other(means.numpy(), k)), radius=1.0)
        state = {"local_geometry": geometry, "scene_radius": 1.0}
        eigval, eigvec = eigval_term(None, None, state), eigvec_term(None, None, state)
        eigval.backward()
        assert (float(eigval.detach()) < 1e-9 and float(points.grad.abs().max()) < 1e-9) is idle, k
        assert (float(eigvec.detach()) == 0.0) is idle, k


@functools.cache
def board_ibgs_runs(board: str) -> frozenset:
    return frozenset(r.run_id for r in expand(load_sweep(sweep_file(board))) if r.label == "ibgs")


@pytest.mark.parametrize(("ablation", "board", "row"), [("ibgs_k", "dtu_rig", "method.knn_k=5"),
                                                       ("ibgs_k_tnt", "tnt_rig", "method.knn_k=5"),
                                                       ("ibgs_losses", "dtu_rig", "ibgs"),
                                                       ("ibgs_losses_tnt", "tnt_rig", "ibgs"),
                                                       ("ibgs_losses_paper", "dtu_rig", "ibgs")])
def test_each_grids_baseline_row_is_its_boards_ibgs_runs(ablation, board, row):
    """Three seeds on two of the board's scenes; the baseline row's runs are the board's, the other rows' are not."""
    runs = expand(load_sweep(sweep_file(ablation)))
    board_ids = board_ibgs_runs(board)
    baseline = {r.run_id for r in runs if r.label == row}
    assert len(baseline) == 6 and baseline <= board_ids
    assert {r.config.seed for r in runs} == {0, 1, 2} and len({r.config.scene for r in runs}) == 2
    assert not {r.run_id for r in runs if r.label != row} & board_ids


def test_the_budget_switch_changes_only_sadc_beside_the_boards_runs():
    """experiments/gaussian_budget/ibgs_sadc_rig.yaml: its ibgs and radegs rows are the dtu_rig board's runs; its
    switched row is the board's ibgs configuration with SADC off and nothing else changed."""
    runs = expand(load_sweep(sweep_file("ibgs_sadc_rig")))
    board = {r.run_id: r for r in expand(load_sweep(sweep_file("dtu_rig"))) if r.label in ("ibgs", "radegs")}
    assert {r.run_id for r in runs if r.label in ("ibgs", "radegs")} == set(board)
    board_ibgs = {(r.config.scene, r.config.seed): r.config.to_dict() for r in board.values() if r.label == "ibgs"}
    switched = [r for r in runs if r.label == "ibgs-without-sadc"]
    assert len(switched) == len(board_ibgs) and not {r.run_id for r in switched} & set(board)
    for run in switched:
        config = run.config.to_dict()
        assert config["method"]["sadc"] is False
        config["method"]["sadc"] = True
        assert config == board_ibgs[(run.config.scene, run.config.seed)]
