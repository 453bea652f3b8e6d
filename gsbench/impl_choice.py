"""Which implementation of a kernel with a fast path and a PyTorch reference runs (SSIM, the 3×3
eigen-solver, the normal consistency, SuGaR's field): the ``impl`` argument, else an environment
variable, else the fast path."""

from __future__ import annotations

import os

from gsbench.errors import ConfigError


def choose_impl(impl: str | None, env: str, impls: tuple[str, ...]) -> str:
    """``impl`` if given (one of ``impls``, else ValueError); otherwise ``$env`` if set (one of ``impls``,
    else ConfigError naming the variable); otherwise ``impls[0]``, the fast path."""
    if impl is None:
        value = os.environ.get(env, "").strip().lower()
        if value not in ("",) + impls:
            raise ConfigError(f"{env}='{value}' is not one of {impls}; unset it to use the default ({impls[0]})")
        return value or impls[0]
    if impl not in impls:
        raise ValueError(f"impl must be None or one of {impls}, got {impl!r}")
    return impl
