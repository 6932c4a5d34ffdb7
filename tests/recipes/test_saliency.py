"""recipes/analyze/saliency.py: the gradient maths, the field map, the claims, a smoke run."""
from __future__ import annotations

import json

import torch

from pnp.task import OBS_BLOCKS
from tests.training._tiny import tiny_train
from pnp.analysis import saliency


def test_saliency_of_a_linear_toy_actor_is_its_weight_magnitudes():
    w = torch.tensor([[0.5, -2.0, 0.0, 1.5]])
    x = torch.randn(6, 4)
    torch.testing.assert_close(saliency.input_saliency(lambda v: v @ w.T, x), w.abs().expand(6, 4))


def test_fields_cover_the_observation_once():
    cols = sorted(c for sl in saliency.field_slices().values() for c in range(sl.start, sl.stop))
    assert cols == list(range(sum(OBS_BLOCKS.values())))


def test_claims_compare_shares_with_the_uniform_baseline():
    fields = saliency.field_slices()
    uniform = {k: (sl.stop - sl.start) / 74 for k, sl in fields.items()}
    focused = {k: (0.4 if k.startswith("object/handles[") else 0.0) for k in fields}
    focused["neighbour/base_xy"] = 0.2
    result = {"uniform_share": uniform, "by_stage": {"S0": {"robot_steps": 10, "fields": focused}}}
    (approach,) = saliency.claims(result)
    assert approach["holds"] and approach["parts"]["both handles"]["share"] == 0.8
    focused["neighbour/base_xy"] = 0.0
    assert not saliency.claims(result)[0]["holds"]


def test_saliency_smoke_on_a_tiny_dual_checkpoint(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1", "task=dual_pnp")
    out = saliency.main([f"checkpoint={tmp_path / 'run'}/checkpoint.pt", f"out={tmp_path / 'sal'}", "episodes=2",
                         "max_episode_steps=3", "nthread=1"])
    saved = json.loads((tmp_path / "sal.json").read_text())
    assert saved["num_robots"] == 2 and "claims" in saved and out["episodes"] == 2
    shares = saved["by_stage"]["S0"]["blocks"]
    assert abs(sum(shares.values()) - 1) < 1e-3
    assert (tmp_path / "sal.png").stat().st_size > 0 and (tmp_path / "sal_episode.png").stat().st_size > 0
