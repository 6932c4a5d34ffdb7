"""The evaluation protocol's seeds (docs/guide/evaluation.md): which seed may inform which decision.

Training seeds start runs. Selection seeds choose checkpoints, configurations and every other
A/B. The development seed (12345, the reporting seed until 2026-12-03, when a review found it
had been used for decisions) is for looking around. The reporting seed is only ever used to
write a quoted figure, after every decision was taken: nothing may be tuned on it.
"""
from __future__ import annotations

TRAINING_SEEDS = (0, 1, 2)
SELECTION_SEEDS = (777, 778)
DEVELOPMENT_SEED = 12345
REPORTING_SEED = 314159


def seed_role(seed: int) -> str:
    """``reporting`` | ``selection`` | ``development`` | ``other``."""
    if seed == REPORTING_SEED:
        return "reporting"
    if seed in SELECTION_SEEDS:
        return "selection"
    return "development" if seed == DEVELOPMENT_SEED else "other"


def resolve_seed(seed) -> int:
    """An evaluation's ``seed=``: an integer, or a role name (``reporting``, ``development``)."""
    named = {"reporting": REPORTING_SEED, "development": DEVELOPMENT_SEED}
    if isinstance(seed, str) and not seed.lstrip("-").isdigit():
        if seed not in named:
            raise ValueError(f"seed={seed!r}: an integer or one of {sorted(named)}")
        return named[seed]
    return int(seed)
