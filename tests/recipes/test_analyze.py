"""Smoke tests of the analysis scripts in recipes/analyze/ (tiny sizes, a tiny checkpoint)."""
from __future__ import annotations

import json
import sys

import pytest

from tests.training._tiny import ROOT, tiny_train

sys.path.insert(0, str(ROOT / "recipes" / "analyze"))
import grasp_losses  # noqa: E402
import profile_iteration  # noqa: E402


def test_grasp_losses_counts_and_writes_provenance(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1", "task=dual_pnp")
    out = grasp_losses.main([f"checkpoint={tmp_path / 'run'}/checkpoint.pt", f"out={tmp_path / 'g.json'}",
                             "worlds=3", "steps=4", "env.handle_claim=true"])
    saved = json.loads((tmp_path / "g.json").read_text())
    assert saved == json.loads(json.dumps(out))
    assert saved["worlds"] == 3 and saved["env"] == {"handle_claim": True}
    assert min(saved["grasps_ended_opened"], saved["grasps_lost_closed"], saved["grasp_steps_kept"]) >= 0
    assert 0.0 <= saved["world_lifted"] <= 1.0 and saved["commit"] and saved["machine"]


def test_profile_iteration_splits_the_time(tmp_path):
    out = profile_iteration.main(["backend=kinematic", "env.num_worlds=4", "collect.frames_per_batch=16",
                                  "collect.minibatch_size=8", "model.actor_cells=[16]", "model.critic_cells=[16]",
                                  "iterations=1", f"out={tmp_path / 'p.json'}"])
    assert out["frames_per_iteration"] == 16 and out["seconds_per_iteration"] > 0
    assert abs(out["policy_share"] + out["env_step_share"] + out["ppo_update_share"] - 1) < 1e-6
    assert json.loads((tmp_path / "p.json").read_text())["backend"] == "kinematic"


def test_profile_iteration_compares_thread_splits(tmp_path):
    out = profile_iteration.main(["backend=kinematic", "env.num_worlds=4", "collect.frames_per_batch=16",
                                  "collect.minibatch_size=8", "model.actor_cells=[16]", "model.critic_cells=[16]",
                                  "iterations=1", "threads=1/1,1/2", f"out={tmp_path / 'p.json'}"])
    assert (out["collect_threads"], out["update_threads"]) == (1, 1) and out["time_ratio_to_first"] == 1.0
    assert [(r["collect_threads"], r["update_threads"]) for r in out["runs"]] == [(1, 2)]
    with pytest.raises(ValueError, match="threads='1-2'"):
        profile_iteration.main(["backend=kinematic", "threads=1-2"])
