"""IBGS: the kNN index, neighbourhood eigen-structure, frame continuity, the eigval/eigvec terms, SADC,
the config ``extends`` layer, resume, and quick end-to-end runs of the three kernel variants."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import gsbench.config.run_config as config
from gsbench.errors import ConfigError, NumericalError
from gsbench.geometry.local_geometry import (
    PERMUTATIONS_3D,
    LocalGeometry,
    apply_alignment,
    frame_alignment,
    local_geometry,
)
from gsbench.geometry.neighbours import NeighbourIndex, nearest_other
from gsbench.geometry.rotations import quat_multiply, rotmat_to_quat
from gsbench.methods.ibgs_terms import eigval_term, eigvec_term
from gsbench.raster.reference_projection import quat_to_rotmat
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run
from gsbench.training.gaussians import Gaussians
from gsbench.training.strategies.base import append_params
from gsbench.training.strategies.sparsity import SparsityAwareStrategy
from gsbench.training.trainer import Trainer
from tests.method_setup import quick_run, setup_method, straight_and_resumed


def random_rotations(n, seed=0):
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=torch.Generator().manual_seed(seed),
                                                  dtype=torch.float64), dim=-1)
    return quat_to_rotmat(q)


# ---- kNN index -----------------------------------------------------------------------------------


def test_nearest_other_drops_self_even_among_coincident_points():
    points = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [3, 0, 0]], dtype=float)
    idx = nearest_other(points, 2)
    assert idx.shape == (5, 2)
    assert not (idx == np.arange(5)[:, None]).any()
    assert set(idx[0]) == {1, 2} and set(idx[3]) <= {0, 1, 2}
    assert nearest_other(points[:2], 5).shape == (2, 1)  # K shrinks to N − 1
    assert nearest_other(points[:1], 5).shape == (1, 0)


def test_stale_index_and_non_finite_means_are_errors():
    index = NeighbourIndex(3)
    index.refresh(torch.rand(10, 3))
    with pytest.raises(NumericalError, match="refreshed after every densification"):
        index.check(11)
    with pytest.raises(NumericalError, match="not finite"):
        index.refresh(torch.tensor([[0.0, 0, 0], [float("nan"), 0, 0]]))
    with pytest.raises(ConfigError, match="K must be >= 1"):
        NeighbourIndex(0)


# ---- rotations and frames ------------------------------------------------------------------------


def test_rotmat_to_quat_inverts_quat_to_rotmat_with_finite_gradients():
    R = random_rotations(500)
    half_turns = quat_to_rotmat(torch.tensor([[0.0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1e-9, 1, 1, 0]],
                                             dtype=torch.float64))
    R = torch.cat([R, half_turns]).requires_grad_(True)
    q = rotmat_to_quat(R)
    assert torch.allclose(quat_to_rotmat(q), R, atol=1e-12) and (q[:, 0] >= 0).all()
    q.sum().backward()
    assert torch.isfinite(R.grad).all()
    a, b = torch.randn(50, 4, dtype=torch.float64), torch.randn(50, 4, dtype=torch.float64)
    assert torch.allclose(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-12)


@pytest.mark.parametrize("surfel", [False, True])
def test_frame_alignment_undoes_permutations_and_sign_flips(surfel):
    previous = random_rotations(len(PERMUTATIONS_3D) * 8, seed=1)
    perms = [p for p in PERMUTATIONS_3D if not surfel or p[2] == 2]
    scrambled = torch.stack([previous[i][:, list(perms[i % len(perms)])] for i in range(len(previous))])
    scrambled = scrambled * torch.where(torch.rand(len(previous), 1, 3) < 0.5, -1.0, 1.0).double()
    perm, signs = frame_alignment(scrambled, previous, surfel=surfel)
    aligned = apply_alignment(scrambled, perm, signs)
    assert torch.allclose(aligned, previous, atol=1e-12)
    # a frame far from every candidate still gets det +1 (and surfels keep v3 in column 3)
    perm, signs = frame_alignment(scrambled, random_rotations(len(previous), seed=2), surfel=surfel)
    aligned = apply_alignment(scrambled, perm, signs)
    assert torch.allclose(torch.linalg.det(aligned), torch.ones(len(aligned), dtype=torch.float64))
    if surfel:
        assert torch.equal(perm[:, 2], torch.full((len(perm),), 2))


# ---- neighbourhood eigen-structure and the two terms ---------------------------------------------


def plane_points(n=60, noise=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g, dtype=torch.float64)
    z = noise * torch.randn(n, generator=g, dtype=torch.float64)
    return torch.stack([xy[:, 0], xy[:, 1], 0.3 * xy[:, 0] + z], -1)


def test_coplanar_neighbourhoods_have_the_plane_normal_and_tiny_lambda3():
    means = plane_points()
    index = torch.from_numpy(nearest_other(means.numpy(), 5))
    geometry = local_geometry(means, index, radius=1.0)
    normal = torch.tensor([-0.3, 0.0, 1.0], dtype=torch.float64) / math.hypot(0.3, 1.0)
    assert geometry.valid.all()
    assert torch.allclose(geometry.normals.abs() @ normal.abs(), torch.ones(len(means), dtype=torch.float64),
                          atol=1e-6)
    assert (geometry.eigenvalues[:, 2] < 1e-9).all()
    assert torch.allclose(torch.linalg.det(geometry.eigenvectors), torch.ones(len(means), dtype=torch.float64))


def test_eigval_gradient_is_the_analytic_plane_pull():
    """∂λ3/∂p = (2/n)(v3·(p − μ̄))v3 for each of the n points of one neighbourhood (docs/methods/ibgs.md §5.2)."""
    means = plane_points(n=7, noise=0.05).requires_grad_(True)
    index = torch.tensor([[j for j in range(7) if j != i] for i in range(7)])  # each with the other six
    geometry = local_geometry(means, index, radius=1.0)
    geometry.eigenvalues[0, 2].backward()
    p = means.detach()
    v3 = geometry.normals[0].detach()
    expected = (2 / 7) * ((p - p.mean(0)) @ v3)[:, None] * v3
    assert torch.allclose(means.grad, expected, atol=1e-10)


def test_eigvec_term_is_invariant_to_eigenvector_signs_and_masks_flat_or_degenerate_rows():
    means = plane_points(n=40, noise=0.02)
    index = torch.from_numpy(nearest_other(means.numpy(), 5))
    geometry = local_geometry(means, index, radius=1.0)
    state = {"local_geometry": geometry, "scene_radius": 1.0}
    flips = torch.where(torch.rand(len(means), 1, 3, generator=torch.Generator().manual_seed(3)) < 0.5, -1.0, 1.0)
    flipped = LocalGeometry(geometry.eigenvalues, geometry.eigenvectors * flips.double(), geometry.valid, index)
    value = eigvec_term(None, None, state)
    assert value > 0
    assert torch.allclose(eigvec_term(None, None, {**state, "local_geometry": flipped}), value, atol=1e-7)
    isotropic = LocalGeometry(torch.ones_like(geometry.eigenvalues), geometry.eigenvectors, geometry.valid, index)
    assert float(eigvec_term(None, None, {**state, "local_geometry": isotropic})) == 0.0  # γ = 0: masked
    assert torch.allclose(eigval_term(None, None, {**state, "scene_radius": 2.0}),
                          geometry.eigenvalues[:, 2].mean().float() / 4)
    with pytest.raises(ConfigError, match="only the IBGS"):
        eigval_term(None, None, {"gaussians": None})


def test_eigvec_term_is_the_double_sum_of_its_formula_in_value_and_gradient():
    """L = mean over (i, j ∈ N(i)) of γ_i·[γ_i >= 1e-3]·valid_i·valid_j·(1 − |v3,i·v3,j|), written as a plain loop."""
    gen = torch.Generator().manual_seed(5)
    n, k = 12, 4
    vectors = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))[0].requires_grad_(True)
    lam = torch.sort(torch.rand(n, 3, generator=gen, dtype=torch.float64), dim=1, descending=True).values
    valid = torch.rand(n, generator=gen) > 0.2
    index = torch.stack([torch.randperm(n, generator=gen)[:k] for _ in range(n)])
    geometry = LocalGeometry(lam, vectors, valid, index)
    value = eigvec_term(None, None, {"local_geometry": geometry, "scene_radius": 1.0})
    gamma = (lam[:, 1] - lam[:, 2]) / lam[:, 0]
    terms = [gamma[i] * (gamma[i] >= 1e-3) * valid[i] * valid[j] * (1 - (vectors[i, :, 2] @ vectors[j, :, 2]).abs())
             for i in range(n) for j in index[i].tolist()]
    expected = torch.stack(terms).mean()
    assert torch.allclose(value.double(), expected, atol=1e-7)
    (grad,) = torch.autograd.grad(value, vectors)
    (grad_expected,) = torch.autograd.grad(expected.float(), vectors)
    assert torch.allclose(grad, grad_expected, atol=1e-7)


def test_coincident_and_collinear_neighbourhoods_give_finite_values_and_gradients():
    coincident = torch.zeros(6, 3, dtype=torch.float64)
    line = torch.linspace(0, 1, 6, dtype=torch.float64)[:, None] * torch.tensor([[1.0, 2.0, 0.5]], dtype=torch.float64)
    for points in (coincident, line, torch.cat([coincident[:3], line[:3]])):
        for k in (2, 5):
            means = (points * 1e3).requires_grad_(True)  # a scene in millimetres
            index = torch.from_numpy(nearest_other(points.numpy(), k))
            geometry = local_geometry(means, index, radius=1e3)
            state = {"local_geometry": geometry, "scene_radius": 1e3}
            loss = eigval_term(None, None, state) + eigvec_term(None, None, state)
            loss.backward()
            assert torch.isfinite(loss) and torch.isfinite(means.grad).all()
            assert torch.isfinite(geometry.eigenvectors).all()
    assert not local_geometry(coincident, torch.from_numpy(nearest_other(coincident.numpy(), 5)), 1.0).valid.any()


# ---- the method ----------------------------------------------------------------------------------


def test_setup_orients_gaussians_by_their_neighbourhood(tiny_spot):
    m, _, _ = setup_method("ibgs", tiny_spot)
    g = m.gaussians
    assert torch.equal(g.params["quats"], torch.tensor([[1.0, 0, 0, 0]]).expand(len(g), 4))  # ΔR = I
    assert m.neighbours.index.shape == (len(g), 5) and "frame" not in {grp["name"] for grp in m.optimizer.param_groups}
    rotation = quat_to_rotmat(m.raster_input().quats.detach().double())
    assert torch.allclose(rotation, g.params["frame"].double(), atol=1e-5)
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(len(g), dtype=torch.float64), atol=1e-5)
    state = m.loss_state()
    assert state["local_geometry"].eigenvalues.shape == (len(g), 3) and state["scene_radius"] == m.scene_radius


def test_densification_and_sadc_keep_the_knn_index_valid(tiny_spot):
    m, scene, _ = setup_method("ibgs", tiny_spot, "method.refine_every=1", "method.refine_start=0")
    strategy = m.strategy()
    assert isinstance(strategy, SparsityAwareStrategy) and strategy.neighbours is m.neighbours
    state = strategy.init_state(len(m.gaussians))
    state["grad2d"][:] = 1.0
    state["absgrad"][:] = 1.0
    state["count"][:] = 1.0
    n = len(m.gaussians)
    info = strategy._refine(m.gaussians, m.optimizer, state, step=2)
    index = m.neighbours.check(len(m.gaussians))
    assert len(m.gaussians) > n and info["sadc"] > 0
    assert int(index.max()) < len(m.gaussians) and not (index == torch.arange(len(index))[:, None]).any()
    assert len(m.filter3d()) == len(m.gaussians) == len(state["grad2d"])
    assert m.gaussians.params["frame"].shape == (len(m.gaussians), 3, 3)
    loss = m.render(scene.cameras[0], {"rgb"}).rgb.sum()
    loss.backward()
    assert torch.isfinite(m.gaussians.params["quats"].grad).all()


def grid_and_sparse_cluster(height, cluster_scale=None):
    """A 6x6 grid of Gaussians 0.1 apart and a far cluster of 4 (the higher indices) at z = height(x),
    optionally with the cluster's own scale; returns (Gaussians with IBGS frames, optimizer, SADC strategy)."""
    xy = torch.cartesian_prod(torch.arange(6.0), torch.arange(6.0)) * 0.1
    xy = torch.cat([xy, xy[:4] + torch.tensor([1.5, 0.0])])
    g = Gaussians.from_points(torch.cat([xy, height(xy[:, :1])], 1).numpy(), None)
    if cluster_scale is not None:
        with torch.no_grad():
            g.params["log_scales"][:] = math.log(0.01)
            g.params["log_scales"][36:] = math.log(cluster_scale)
    neighbours = NeighbourIndex(5)
    neighbours.refresh(g.means)
    g.add_state("frame", local_geometry(g.means, neighbours.index, 1.0).eigenvectors.float())
    optimizer = torch.optim.Adam([{"params": [p], "name": k} for k, p in g.params.items() if p.requires_grad])
    return g, optimizer, SparsityAwareStrategy(neighbours=neighbours, percent_dense=1.0, scene_extent=1.0)


def test_sadc_places_new_gaussians_on_the_local_plane_between_sparse_neighbours():
    g, optimizer, strategy = grid_and_sparse_cluster(lambda x: 0.2 * x + 0.1)  # the plane z = 0.2x + 0.1
    added, cut = strategy._densify_sparse(g, optimizer)
    new = g.means[-added:].detach()
    assert added > 0 and cut == 0  # no budget
    assert torch.allclose(new[:, 2], 0.2 * new[:, 0] + 0.1, atol=1e-5)  # on the plane
    assert (new[:, 0] > 0.5).all()  # between the sparse cluster and the grid
    assert torch.equal(g.params["quats"][-added:], torch.tensor([[1.0, 0, 0, 0]]).expand(added, 4))
    before = len(g)
    append_params(g, optimizer, {k: v.detach()[:1] for k, v in g.params.items()})
    assert len(g) == before + 1 and g.params["frame"].shape[0] == before + 1


def test_sadc_takes_the_sparse_gaussian_of_a_pair_even_when_its_neighbour_comes_first():
    g, optimizer, strategy = grid_and_sparse_cluster(torch.zeros_like, cluster_scale=0.3)
    added, _ = strategy._densify_sparse(g, optimizer)
    assert added > 0
    assert (g.scales[-added:].detach().max(-1).values > 0.1).all()  # the sparse parent's scales, not the grid's


def test_sadc_under_the_budget_keeps_the_widest_gaps_and_counts_the_pairs_left_out():
    g, optimizer, strategy = grid_and_sparse_cluster(torch.zeros_like)
    unbounded, _ = strategy._densify_sparse(*grid_and_sparse_cluster(torch.zeros_like)[:2])
    n = len(g)
    added, cut = dataclasses.replace(strategy, max_gaussians=n + 2)._densify_sparse(g, optimizer)
    assert unbounded > 2 and added == 2 and cut == unbounded - 2 and len(g) == n + 2


def test_resume_is_bit_identical(tiny_spot, tmp_path, monkeypatch, restore_threads):
    """24 steps straight vs 12 + crash + resume + 12, densifying and refreshing the kNN every 4 steps."""
    overrides = ("train.iterations=24", "train.checkpoint_every=12", "method.refine_every=4",
                 "method.refine_stop=30000", "method.reset_every=30000", "method.knn_refresh_every=5",
                 "losses.eigval.start=0", "losses.eigvec.start=0")
    straight, resumed = straight_and_resumed("ibgs", tiny_spot, tmp_path, monkeypatch, *overrides, crash_after=12)
    assert len(resumed.method.gaussians) == len(straight.method.gaussians) != 400
    for k, v in straight.method.gaussians.params.items():
        assert torch.equal(v, resumed.method.gaussians.params[k]), k
    assert torch.equal(straight.method.neighbours.index, resumed.method.neighbours.index)


def test_a_binding_budget_is_recorded_from_its_first_cut_and_survives_a_resume(tiny_spot, tmp_path, monkeypatch,
                                                                               restore_threads):
    """With 450 Gaussians allowed from 400, clone/split and SADC are cut before the crash at step 12; the
    resumed run counts the cuts from the checkpoint on, so its `DensifyBudget` equals the straight run's."""
    overrides = ("train.iterations=24", "train.checkpoint_every=12", "method.refine_every=4",
                 "method.refine_stop=30000", "method.reset_every=30000", "train.max_gaussians=450")
    straight, resumed = straight_and_resumed("ibgs", tiny_spot, tmp_path, monkeypatch, *overrides, crash_after=12)
    budget = straight.result().budget
    assert budget.max_gaussians == 450 and budget.first_cut_step <= 12 and budget.candidates_cut > 0
    assert resumed.result().budget == budget and len(straight.method.gaussians) <= 450


@pytest.mark.parametrize("attach", [False, True])
def test_duplicated_points_and_attached_eigenvectors_train_without_nan(tiny_spot, tmp_path, attach, restore_threads):
    m, scene, cfg = setup_method("ibgs", tiny_spot, "train.iterations=8", f"method.attach_eigenvectors={attach}",
                                 "losses.eigval.start=0", "losses.eigvec.start=0")
    with torch.no_grad():
        m.gaussians.params["means"][1::2] = m.gaussians.params["means"][::2]  # every point twice
    m.neighbours.refresh(m.gaussians.means)
    result = Trainer(m, scene, cfg, tmp_path).fit()
    assert result.steps == 8
    assert all(torch.isfinite(p).all() for p in m.gaussians.params.values())


# ---- configs -------------------------------------------------------------------------------------


def test_variants_extend_their_base_method_configs():
    ibgs, rade = resolve_run("ibgs", "synthetic/spot", preset="paper"), resolve_run("radegs", "synthetic/spot",
                                                                                     preset="paper")
    assert ibgs.losses["depth_distortion"]["weight"] == 100.0  # v1
    assert {k: v for k, v in ibgs.losses.items() if k not in ("eigval", "eigvec", "depth_distortion")} == \
        {k: v for k, v in rade.losses.items() if k != "depth_distortion"}
    assert ibgs.mesh == rade.mesh  # radegs.dtu.yaml reaches the variant
    assert resolve_run("ibgs-gof", "synthetic/spot", preset="paper").losses["depth_distortion"]["weight"] == 1000.0
    assert resolve_run("ibgs-gof", "synthetic/spot-tnt", preset="paper").mesh.extractor == "tets"
    assert resolve_run("ibgs-2dgs", "synthetic/spot", preset="paper").losses["depth_distortion"]["start"] == 3000
    for name, base in (("ibgs", "radegs"), ("ibgs-gof", "gof"), ("ibgs-2dgs", "2dgs")):
        cls = METHODS.get(name)
        assert cls.info() == METHODS.get(base).info()  # the base method's kernel and outputs
        base_terms = set(resolve_run(base, "synthetic/spot", preset="paper").losses)
        assert set(resolve_run(name, "synthetic/spot", preset="paper").losses) == base_terms | {"eigval", "eigvec"}
        assert cls.Config().knn_k == 5 and cls.Config().knn_refresh_every == 100 and not cls.Config().attach_eigenvectors


def test_extends_cycles_and_missing_bases_are_errors(tmp_path, monkeypatch):
    (tmp_path / "methods").mkdir()
    (tmp_path / "presets").mkdir()
    (tmp_path / "presets" / "cpu.yaml").write_text("{}\n")
    (tmp_path / "methods" / "a.yaml").write_text("extends: b\n")
    (tmp_path / "methods" / "b.yaml").write_text("extends: a\n")
    (tmp_path / "methods" / "c.yaml").write_text("extends: nowhere\n")
    monkeypatch.setattr(config, "config_root", lambda: tmp_path)
    with pytest.raises(ConfigError, match="loops through a -> b -> a"):
        config.resolve("a", "synthetic/spot")
    with pytest.raises(ConfigError, match="extends 'nowhere'"):
        config.resolve("c", "synthetic/spot")


# ---- quick end-to-end runs -----------------------------------------------------------------------

QUICK = ["data.downscale=1", "method.random_init_points=2000", "train.iterations=60", "train.checkpoint_every=0",
         "train.log_every=10", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08", "eval.evaluators=[dtu_chamfer]",
         "threads=1"]


@pytest.mark.parametrize("name", ["ibgs", "ibgs-gof", "ibgs-2dgs"])
def test_quick_run_trains_meshes_evaluates_and_records(name, tiny_spot, tmp_path, restore_threads):
    record = quick_run(name, tiny_spot, tmp_path)
    assert record.losses["schedule"]["eigval"]["start"] == 14  # 7000 · 60/30000
    assert 0 < record.timings["train.knn"] < record.timings["train"]
    assert 0 < record.timings["train.local_geometry"] < record.timings["train"]


def test_overhead_benchmark_times_every_phase(capsys):
    from gsbench.cli import main

    assert main(["bench", "ibgs", "--sizes", "300", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    assert "| knn refresh |" in out and "torch.linalg.eigh: + losses fwd+bwd" in out and "N = 300" in out
