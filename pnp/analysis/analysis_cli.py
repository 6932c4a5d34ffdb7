"""What the checkpoint analyses share: ``key=value`` settings over the script's defaults,
deterministic trials with a hook, the steps before a box tipped, and one JSON result with its
provenance."""
from __future__ import annotations

import collections
import json
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError

from pnp.training.provenance import provenance
from pnp.training.rollout import load_policy, run_trials, summarise


def settings(argv: list[str], defaults: dict, usage: str, required: tuple[str, ...] = ("checkpoint",)) -> DictConfig:
    """``defaults`` overridden by ``argv`` (``key=value``); a key the script does not declare is
    refused by name (a typo would otherwise run the defaults), except inside a dict-valued group
    (env overrides: the run's config schema checks those). Without the ``required`` keys, ``usage`` is shown."""
    base = OmegaConf.create(defaults)
    OmegaConf.set_struct(base, True)
    for key, value in defaults.items():
        if isinstance(value, dict):
            OmegaConf.set_struct(base[key], False)
    try:
        cfg = OmegaConf.merge(base, OmegaConf.from_dotlist(argv))
    except ConfigKeyError as e:
        raise ValueError(f"unknown setting {e.full_key!r}: this script takes {sorted(defaults)}") from None
    missing = [k for k in required if cfg[k] is None]
    if missing:
        raise SystemExit(f"set {missing} (key=value)\n{usage}")
    return cfg


def save(result: dict, out) -> dict:
    """``result`` with the command, commit and machine added, as JSON at ``out``."""
    result.update(provenance())
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(result, indent=1) + "\n")
    return result


def hooked_trials(checkpoint: str, trials: int, seed: int, make_hook, env: dict) -> tuple[list, object, dict]:
    """``trials`` deterministic trials of ``checkpoint`` (``pnp.training.rollout.run_trials``) with the
    hook ``make_hook(base_env)`` builds; ``env`` may set ``num_worlds`` (default: one per trial).
    Returns the per-trial records, the hook and the result's header (checkpoint, iteration, seed,
    env, worlds, the trials' summary and their wall time)."""
    env = dict(env)
    num_worlds = int(env.pop("num_worlds", trials))
    pol = load_policy(checkpoint, min(num_worlds, trials), seed, **env)
    t0, base = time.monotonic(), pol.env.base_env
    hook = make_hook(base)
    try:
        records = run_trials(pol.env, pol.actor, trials, hook=hook)
    finally:
        pol.env.close()
    header = {"checkpoint": str(checkpoint), "iteration": int(pol.ckpt["counters"]["iteration"]), "seed": seed,
              "env": env, "num_worlds": base.num_worlds, **summarise(records), "wall_s": time.monotonic() - t0}
    return records, hook, header


class OnsetWindow:
    """Per world, the last ``window`` samples up to the first step a box tipped (the onset).

    A hook pushes one sample per high-level step while the box is unheld; once ``tipped`` is
    true the window is kept as the world's onset and later samples are ignored until its reset.
    """

    def __init__(self, n_worlds: int, window: int):
        self.recent = [collections.deque(maxlen=int(window)) for _ in range(n_worlds)]
        self.onset: list[list | None] = [None] * n_worlds

    def push(self, world: int, sample, tipped: bool) -> None:
        if self.onset[world] is None:
            self.recent[world].append(sample)
            if tipped:
                self.onset[world] = list(self.recent[world])

    def reset(self, done: torch.Tensor) -> None:
        for w in torch.nonzero(done).flatten().tolist():
            self.recent[w].clear()
            self.onset[w] = None
