"""`train.optimizer` (gsbench/training/optim.py): the papers' Adam by default, and the opt-in visible-only Adam,
which leaves the rows of unseen Gaussians untouched and is Adam when every row is visible."""

from __future__ import annotations

import pytest
import torch

from gsbench.errors import ConfigError
from gsbench.training.optim import FusedAdam, VisibleAdam, make_adam
from gsbench.training.trainer import Trainer
from tests.method_setup import setup_method, straight_and_resumed


def _params(seed=0, n=50):
    gen = torch.Generator().manual_seed(seed)
    return [torch.randn(n, 3, generator=gen).requires_grad_(True), torch.randn(n, 1, 3, generator=gen).requires_grad_(True)]


def _run(optimizer, params, visible=None, steps=6):
    gen = torch.Generator().manual_seed(1)
    for _ in range(steps):
        for p in params:
            p.grad = torch.randn(p.shape, generator=gen)
        if visible is not None:
            optimizer.visible = visible
        optimizer.step()
    return [p.detach().clone() for p in params]


def test_every_row_visible_is_adam_and_none_is_adam_bit_for_bit():
    groups = lambda ps: [{"params": [p], "lr": 1e-2 * (i + 1)} for i, p in enumerate(ps)]  # noqa: E731
    reference = _run(torch.optim.Adam(groups(a := _params()), lr=0.0, eps=1e-15, foreach=False), a)
    all_rows = _run(VisibleAdam(groups(b := _params()), lr=0.0, eps=1e-15), b, torch.ones(50, dtype=torch.bool))
    unset = _run(VisibleAdam(groups(c := _params()), lr=0.0, eps=1e-15), c)
    assert all(torch.allclose(x, y, rtol=1e-6, atol=1e-7) for x, y in zip(reference, all_rows))
    assert all(torch.equal(x, y) for x, y in zip(reference, unset))


def test_fused_adam_is_torchs_fused_step_bit_for_bit():
    """The lean step (one fused call per group) against torch's own fused step: same parameters and moments
    over steps with a group that has no gradient, rows added to the state between steps (as densification
    does) and a float64 group beside float32 ones."""
    def make(cls, **kw):
        ps = _params() + [torch.randn(7, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(2)).requires_grad_(True)]
        groups = [{"params": [p], "lr": 1e-2 * (i + 1)} for i, p in enumerate(ps)]
        return cls(groups, lr=0.0, eps=1e-15, **kw), ps

    (ours, a), (torchs, b) = make(FusedAdam), make(torch.optim.Adam, fused=True)
    gen = torch.Generator().manual_seed(1)
    for step in range(6):
        for x, y in zip(a, b):
            g = None if step == 2 and x.dim() == 3 else torch.randn(x.shape, generator=gen, dtype=x.dtype)
            x.grad, y.grad = g, None if g is None else g.clone()
        if step == 3:  # grow the first parameter and its moments by 5 rows (densification's surgery)
            for opt, ps in ((ours, a), (torchs, b)):
                old = ps[0]
                state = opt.state.pop(old)
                new = torch.cat([old.detach(), old.detach()[:5]]).requires_grad_(True)
                new.grad = torch.cat([old.grad, old.grad[:5]])
                opt.param_groups[0]["params"] = [new]
                opt.state[new] = {k: v if k == "step" else torch.cat([v, v[:5]]) for k, v in state.items()}
                ps[0] = new
        ours.step()
        torchs.step()
    for x, y in zip(a, b):
        assert torch.equal(x, y)
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(ours.state[x][key], torchs.state[y][key])


def test_unseen_rows_keep_their_parameters_and_moments():
    params = _params()
    before = [p.detach().clone() for p in params]
    optimizer = VisibleAdam([{"params": [p], "lr": 0.1} for p in params], lr=0.0, eps=1e-15)
    visible = torch.zeros(50, dtype=torch.bool)
    visible[::3] = True
    after = _run(optimizer, params, visible)
    for p, old, new in zip(params, before, after):
        assert torch.equal(new[~visible], old[~visible]) and not torch.equal(new[visible], old[visible])
        state = optimizer.state[p]
        assert torch.all(state["exp_avg"][~visible] == 0) and torch.all(state["exp_avg_sq"][visible] > 0)


def test_unknown_optimizer_is_a_config_error():
    with pytest.raises(ConfigError, match="adam, visible_adam"):
        make_adam([{"params": _params()}], "sgd", 1e-15)


def test_training_with_visible_adam_densifies_and_resumes_bit_for_bit(tiny_spot, tmp_path, monkeypatch):
    m, _, _ = setup_method("3dgs", tiny_spot, "train.optimizer=visible_adam")
    assert isinstance(m.optimizer, VisibleAdam)
    straight, resumed = straight_and_resumed("3dgs", tiny_spot, tmp_path, monkeypatch, "train.optimizer=visible_adam",
                                             "train.iterations=40", "train.checkpoint_every=20", crash_after=25)
    assert isinstance(straight, Trainer) and straight.step == resumed.step == 40
    for name, value in straight.method.gaussians.params.items():
        assert torch.equal(value, resumed.method.gaussians.params[name]), name
