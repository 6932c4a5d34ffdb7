"""How many threads torch gets in each part of an iteration (``cfg.threads``)."""
from __future__ import annotations

from omegaconf import DictConfig

from pnp.sim.cores import available_cores


def torch_threads(threads: DictConfig) -> dict[str, int]:
    """``{"collect": n, "update": m}`` from ``cfg.threads``, nulls resolved to the available cores."""
    out = {}
    for part in ("collect", "update"):
        value = threads[part]
        n = available_cores() if value is None else value
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise ValueError(f"threads.{part}={value!r}: expected a positive thread count, or null for the "
                             f"{available_cores()} cores available")
        out[part] = n
    return out
