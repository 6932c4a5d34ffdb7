"""The cores this process may use: the default of MuJoCo's thread pool and torch's threads."""
from __future__ import annotations

import os


def available_cores() -> int:
    """The cores this process may run on (its affinity mask, where the OS has one): a job
    pinned to 4 cores of a 64-core node gets 4, where ``os.cpu_count()`` says 64."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
