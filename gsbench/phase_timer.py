"""Wall time of one computation inside training, forward *and* backward (e.g. IBGS's eigen-decomposition).

`PhaseTimer.run(key, fn, *inputs)` times ``fn`` and wraps its inputs and outputs in identity autograd
nodes: the backward of the output node starts a stopwatch and the backward of the input node stops
it, so the seconds autograd spends between them (the backward of ``fn``) are added to ``key`` too.
PyTorch's CPU engine runs ready nodes newest first, so nodes created after ``fn`` (the rasterizer)
finish their backward before the stopwatch starts; ``fn``'s own nodes run inside it.
"""

from __future__ import annotations

import time

import torch


class _Stopwatch(torch.autograd.Function):
    """Identity on tensors; its backward starts (``start``) or stops the timer's stopwatch for ``key``."""

    @staticmethod
    def forward(ctx, timer, key, start, *tensors):
        ctx.timer, ctx.key, ctx.start = timer, key, start
        return tuple(t.view_as(t) for t in tensors)

    @staticmethod
    def backward(ctx, *grads):
        if ctx.start:
            ctx.timer.started[ctx.key] = time.perf_counter()
        else:
            began = ctx.timer.started.pop(ctx.key, None)
            if began is not None:
                ctx.timer.add(ctx.key, time.perf_counter() - began)
        return (None, None, None, *grads)


class PhaseTimer:
    """Seconds per named phase (forward + backward), cumulative; part of a method's checkpoint."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.started: dict[str, float] = {}

    def add(self, key: str, seconds: float) -> None:
        self.seconds[key] = self.seconds.get(key, 0.0) + seconds

    def run(self, key: str, fn, *inputs: torch.Tensor):
        """``fn(*inputs)`` (a tensor or tuple of tensors), timed forward and backward (module docstring)."""
        track = torch.is_grad_enabled() and any(t.requires_grad for t in inputs)
        if track:
            inputs = _Stopwatch.apply(self, key, False, *inputs)
        began = time.perf_counter()
        out = fn(*inputs)
        self.add(key, time.perf_counter() - began)
        single = isinstance(out, torch.Tensor)
        outs = (out,) if single else tuple(out)
        if track and any(t.requires_grad for t in outs):
            outs = _Stopwatch.apply(self, key, True, *outs)
        return outs[0] if single else outs

    def state_dict(self) -> dict:
        return dict(self.seconds)

    def load_state_dict(self, state: dict) -> None:
        self.seconds = dict(state)
        self.started = {}
