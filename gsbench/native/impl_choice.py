"""Which implementation of a kernel with a fast path and a PyTorch reference runs (SSIM, the 3×3
eigen-solver, the normal consistency, SuGaR's field, IBGS's neighbourhood covariance): the ``impl``
argument, else an environment variable, else the fast path — and the reference for inputs the fast
path cannot take, unless the fast path was asked for by name."""

from __future__ import annotations

import os
from collections.abc import Callable

from gsbench.errors import ConfigError


def choose_impl(impl: str | None, env: str, impls: tuple[str, ...],
                unsupported: Callable[[], str | None] | None = None, name: str = "kernel") -> str:
    """``impl`` if given (one of ``impls``, else ValueError); otherwise ``$env`` if set (one of ``impls``,
    else ConfigError naming the variable); otherwise ``impls[0]``, the fast path.

    ``unsupported()`` (asked only when the fast path is chosen) says why it cannot take the inputs, or None;
    then the reference ``impls[1]`` runs, except when ``impl`` named the fast path: a ValueError naming
    ``name`` and the reason."""
    if impl is None:
        value = os.environ.get(env, "").strip().lower()
        if value not in ("",) + impls:
            raise ConfigError(f"{env}='{value}' is not one of {impls}; unset it to use the default ({impls[0]})")
        choice = value or impls[0]
    elif impl not in impls:
        raise ValueError(f"impl must be None or one of {impls}, got {impl!r}")
    else:
        choice = impl
    if choice != impls[0] or unsupported is None:
        return choice
    reason = unsupported()
    if reason is None:
        return choice
    if impl == impls[0]:
        raise ValueError(f"{name} impl='{impl}' cannot take these inputs: {reason}; use impl=None or '{impls[1]}'")
    return impls[1]
