"""How many threads torch gets in each part of an iteration (``cfg.threads``)."""
from __future__ import annotations

import os

from omegaconf import DictConfig


def available_cores() -> int:
    """The cores this process may run on (its affinity mask, where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


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
