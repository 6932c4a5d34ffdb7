"""The command-line shell the checkpoint analyses share: ``key=value`` settings over the
script's defaults, and one JSON result with its provenance."""
from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pnp.training.provenance import provenance


def settings(argv: list[str], defaults: dict, usage: str) -> DictConfig:
    """``defaults`` overridden by ``argv``; without a ``checkpoint`` the script's ``usage`` is shown."""
    cfg = OmegaConf.merge(OmegaConf.create(defaults), OmegaConf.from_dotlist(argv))
    if cfg.checkpoint is None:
        raise SystemExit(usage)
    return cfg


def save(result: dict, out) -> dict:
    """``result`` with the command, commit and machine added, as JSON at ``out``."""
    result.update(provenance())
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(result, indent=1) + "\n")
    return result
