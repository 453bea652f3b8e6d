"""Which implementation of a kernel with a fast path and a PyTorch reference runs (SSIM, the 3×3
eigen-solver, the normal consistency, SuGaR's field, IBGS's neighbourhood covariance, NeuSG's dense and hash grids): the
``impl`` argument, else its switch (`gsbench.switches`), else the fast path — and the reference for inputs the
fast path cannot take, unless the fast path was asked for by name."""

from __future__ import annotations

from collections.abc import Callable

from gsbench.switches import Switch


def choose_impl(impl: str | None, switch: Switch, unsupported: Callable[[], str | None] | None = None,
                name: str = "kernel") -> str:
    """``impl`` if given (one of ``switch.values``, else ValueError); otherwise the switch's value (a bad one is a
    ConfigError naming the variable). ``switch.values`` are (fast path, reference).

    ``unsupported()`` (asked only when the fast path is chosen) says why it cannot take the inputs, or None;
    then the reference runs, except when ``impl`` named the fast path: a ValueError naming ``name`` and the
    reason."""
    fast, reference = switch.values
    if impl is None:
        choice = switch.value()
    elif impl not in switch.values:
        raise ValueError(f"impl must be None or one of {switch.values}, got {impl!r}")
    else:
        choice = impl
    if choice != fast or unsupported is None:
        return choice
    reason = unsupported()
    if reason is None:
        return choice
    if impl == fast:
        raise ValueError(f"{name} impl='{impl}' cannot take these inputs: {reason}; use impl=None or '{reference}'")
    return reference
