"""Each quoted checkpoint (results/quoted.yaml) was trained with the configuration its named
experiment composes to today: a result names its source, and that source still produces it."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from pnp.training.migration import changed_settings, migrate
from pnp.distill.config import distill_config, register
from pnp.training.pipeline import phase_config
from pnp.training.provenance import launch_source
from tests.training._tiny import ROOT, compose_cfg

register()  # the distill schema, for composing distill_experiment
QUOTED = yaml.safe_load((ROOT / "results" / "quoted.yaml").read_text())
# Where the run lived and how it was watched: not part of what it trained.
LOCATION = ("out_dir", "resume", "warm_start", "logger", "progress", "checkpoint_every_min", "runs_root")
# How many threads it ran on: MuJoCo's numbers do not depend on it (pnp.training.trainer.RESUME_OVERRIDES).
EXECUTION = ("env.nthread", "threads.")


def _differences(saved, composed) -> dict:
    diff = changed_settings(composed, saved, resumable=())
    return {k: v for k, v in diff.items() if not k.startswith(LOCATION + EXECUTION)}


@pytest.mark.parametrize("name", sorted(QUOTED))
def test_quoted_checkpoint_matches_its_experiment(name):
    row = QUOTED[name]
    ckpt = torch.load(ROOT / row["checkpoint"], map_location="cpu", weights_only=False)
    kind, _, experiment = row["experiment"].rpartition(":")
    if kind == "distill":  # a student: its distill_experiment plus the launch's own overrides
        launched = launch_source(ckpt["launches"])
        assert launched["experiment"] == experiment
        overrides = [o for o in launched["launch_overrides"] if not o.startswith("logger.")]
        composed = distill_config(compose_cfg("distill", [f"distill_experiment={experiment}", *overrides]))
        saved = distill_config(ckpt["cfg"])
    else:
        composed = compose_cfg("train", [f"experiment={experiment}", "out_dir=runs/x"])
        if composed.pipeline:  # the checkpoint is the last phase's
            composed = phase_config(composed, len(composed.pipeline) - 1, Path("source"))
        saved = migrate(ckpt["cfg"])
    assert _differences(saved, composed) == {}
