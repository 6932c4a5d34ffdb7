"""Smoke tests of the analysis scripts in recipes/analyze/ (tiny sizes, a tiny checkpoint)."""
from __future__ import annotations

import json
import shlex

import pytest
import torch
from tensordict import TensorDict

from pnp.task import OBS_FIELDS
from pnp.task.terms import CONDITIONS

from tests.training._tiny import tiny_train
from pnp.analysis import analysis_cli
from pnp.analysis import approach
from pnp.analysis import box_contacts
from pnp.analysis import grasp_losses
from pnp.analysis import knock_overs
from pnp.analysis import profile_iteration
from pnp.analysis import scaling
from pnp.analysis import swap_critic


def test_grasp_losses_counts_and_writes_provenance(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1", "task=dual_pnp")
    out = grasp_losses.main([f"checkpoint={tmp_path / 'run'}/checkpoint.pt", f"out={tmp_path / 'g.json'}",
                             "worlds=3", "steps=4", "env.handle_claim=true"])
    saved = json.loads((tmp_path / "g.json").read_text())
    assert saved == json.loads(json.dumps(out))
    assert saved["worlds"] == 3 and saved["env"] == {"handle_claim": True}
    # Transitions of (world, robot) grasps between consecutive steps: at most 3 x 2 x 3 of them.
    counts = [saved[k] for k in ("grasps_ended_opened", "grasps_lost_closed", "grasp_steps_kept")]
    assert all(isinstance(c, int) for c in counts) and sum(counts) <= 3 * 2 * 3
    # Shares of the 3 worlds, not of robots or steps.
    for key in ("world_lifted", "world_both_grasped_at_once"):
        assert saved[key] * 3 == pytest.approx(round(saved[key] * 3)), key
    assert saved["commit"] and saved["machine"]


def _step_td(up_z: list[float], held: list[bool], stage: list[int], grasp: list[float]) -> TensorDict:
    """Two worlds' step output with the box tilted to ``up_z`` = cos(tilt) about its x axis."""
    n = len(up_z)
    obj, ego = torch.zeros(n, 1, 30), torch.zeros(n, 1, 31)
    obj[:, 0, 3] = 1.0
    obj[:, 0, 7], obj[:, 0, 8] = torch.tensor(up_z), (1 - torch.tensor(up_z) ** 2).sqrt()
    ego[:, 0, OBS_FIELDS["ego"]["last_action"].start + 7] = torch.tensor(grasp)
    cond = torch.zeros(n, 1, len(CONDITIONS), dtype=torch.bool)
    cond[:, 0, CONDITIONS.index("object_grabbed")] = torch.tensor(held)
    agents = TensorDict({"object": obj, "ego": ego, "stage_conditions": cond,
                         "stage": torch.tensor(stage).view(n, 1, 1)}, batch_size=(n, 1))
    return TensorDict({"agents": agents}, batch_size=(n,))


def test_knock_overs_counts_tips_after_lie_steps_and_s0_toggles():
    hook = knock_overs.KnockOvers(2, tilt_rad=1.0, lie_steps=3)
    # World 0: on its side (cos 0.1), unheld, for 3 steps; world 1: upright, or on its side but held.
    for step, grasp in enumerate([0.0, 1.0, 0.0]):
        hook.after_step(None, _step_td([0.1, 1.0 if step < 2 else 0.1], [False, step == 2], [0, 1], [grasp, grasp]))
    assert [hook.record(w)["tipped"] for w in (0, 1)] == [True, False]
    assert [hook.record(w)["s0_toggles"] for w in (0, 1)] == [2, 0]  # world 1 is in S1
    assert hook.record(0)["s0_steps"] == 3
    hook.reset(torch.tensor([True, False]))
    assert hook.record(0) == {"tipped": False, "s0_toggles": 0, "s0_steps": 0}


def test_onset_window_keeps_the_steps_up_to_the_first_tip_until_reset():
    win = analysis_cli.OnsetWindow(2, window=2)
    for step, tipped in enumerate([False, False, True, True]):
        win.push(0, step, tipped)
    win.push(1, "a", False)
    assert win.onset == [[1, 2], None]  # the last 2 samples up to the first tip; later ones ignored
    win.reset(torch.tensor([True, False]))
    win.push(0, 9, True)
    win.push(1, "b", True)
    assert win.onset == [[9], ["a", "b"]]


def test_knock_overs_writes_its_summary(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1")
    out = knock_overs.main([f"checkpoint={tmp_path / 'run'}/checkpoint.pt", f"out={tmp_path / 'k.json'}",
                            "trials=3", "env.num_worlds=3", "env.max_episode_steps=5"])
    assert json.loads((tmp_path / "k.json").read_text()) == json.loads(json.dumps(out))
    assert out["trials"] == 3 and 0 <= out["tipped_and_succeeded"] <= out["tipped_trials"] <= 3
    assert set(out["failure_causes"]) >= {"tipped_box", "timeout"} and out["commit"] and out["machine"]


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


def test_profile_iteration_resumes_a_run_where_it_stopped_and_leaves_its_folder_alone(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=2")
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "run").iterdir()}
    out = profile_iteration.main([f"resume={tmp_path / 'run'}/checkpoint.pt", "env.num_worlds=7", "iterations=1",
                                  f"out={tmp_path / 'p.json'}"])
    assert out["resumed_from"] == str(tmp_path / "run" / "checkpoint.pt") and out["resumed_iteration"] == 2
    assert out["num_worlds"] == 4 and out["frames_per_iteration"] == 40  # the run's settings, not the command's
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "run").iterdir()} == before


def test_scaling_profiles_each_thread_count_against_the_first(tmp_path):
    tiny = ["env.num_worlds=4", "collect.frames_per_batch=16", "collect.minibatch_size=8", "model.actor_cells=[16]",
            "model.critic_cells=[16]"]
    out = scaling.main(["backends=kinematic", "threads=1,2", "iterations=1", f"out={tmp_path / 's.json'}", *tiny])
    rows = out["rows"]
    assert [(r["backend"], r["device"], r["threads"], r["update_threads"]) for r in rows] == [
        ("kinematic", "cpu", 1, 1), ("kinematic", "cpu", 2, 2)]
    assert rows[0]["frames_per_s_ratio_to_first"] == 1.0 and rows[1]["frames_per_s_ratio_to_first"] > 0
    assert "env.nthread=2" in rows[1]["overrides"] and rows[1]["command"].endswith(shlex.join(tiny))
    assert json.loads((tmp_path / "s.json").read_text())["rows"][1]["threads"] == 2
    assert (tmp_path / "s.png").stat().st_size > 0
    with pytest.raises(ValueError, match="threads='0,2'"):
        scaling.main(["threads=0,2"])
    with pytest.raises(ValueError, match=r"\['gpu'\] not among"):
        scaling.main(["backends=gpu"])


def test_profile_iteration_times_the_same_physics_raw_on_mujoco(tmp_path):
    out = profile_iteration.main(["backend=mujoco", "env.num_worlds=4", "collect.frames_per_batch=16",
                                  "collect.minibatch_size=8", "model.actor_cells=[16]", "model.critic_cells=[16]",
                                  "iterations=1", f"out={tmp_path / 'p.json'}"])
    assert 0 < out["raw_physics_s"] < out["env_step_s"]  # the env's step holds that physics and more
    assert out["ratio_to_raw_physics"] == out["raw_physics_s"] / out["seconds_per_iteration"]


@pytest.mark.parametrize("method", ["erskine", "bendikas"])
def test_profile_iteration_runs_the_per_stage_baselines(tmp_path, method):
    # Their rewards and loss are the trainer's (per-stage reward columns, Erskine's critics).
    out = profile_iteration.main([f"experiment=table1_{method}", "env.num_worlds=4", "collect.frames_per_batch=16",
                                  "collect.minibatch_size=8", "model.actor_cells=[16]", "model.critic_cells=[16]",
                                  "iterations=1", f"out={tmp_path / 'p.json'}"])
    assert out["frames_per_iteration"] == 16 and out["ppo_update_s"] > 0


def test_box_contacts_names_robot_parts_and_writes_its_summary(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1")
    out = box_contacts.main([f"checkpoint={tmp_path / 'run'}/checkpoint.pt", f"out={tmp_path / 'c.json'}",
                             "trials=3", "env.num_worlds=3", "env.max_episode_steps=5", "env.nthread=1"])
    assert json.loads((tmp_path / "c.json").read_text()) == json.loads(json.dumps(out))
    assert out["trials"] == 3 and out["env"]["backend"] == "mujoco" and 0 <= out["tilted_unheld_trials"] <= 3
    parts = {"finger", "palm", "arm", "leg", "trunk"}
    assert set(out["parts_touching_unheld"]) <= parts and set(out["parts_before_onset"]) <= parts
    from pnp.training.rollout import load_policy
    backend = load_policy(f"{tmp_path / 'run'}/checkpoint.pt", 1, 0, backend="mujoco", nthread=1).env.base_env.backend
    model = backend.model
    named = {box_contacts.part_of(model, g) for g in range(model.ngeom)}
    assert {"finger", "palm", "arm"} <= named and None in named  # the floor, goal and box are no robot part
    assert all(box_contacts.part_of(model, int(g)) is None for g in backend.idx.box_geoms)


def test_approach_reports_the_ee_handle_geometry_and_writes_its_summary(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1")
    out = approach.main([f"checkpoint={tmp_path / 'run'}/checkpoint.pt", f"out={tmp_path / 'a.json'}", "trials=3",
                         "near_m=10.0", "env.num_worlds=3", "env.max_episode_steps=5", "env.nthread=1"])
    assert json.loads((tmp_path / "a.json").read_text()) == json.loads(json.dumps(out))
    assert out["trials"] == 3 and out["near_steps"] > 0  # within 10 m every unheld step counts
    xy, dz, speed, align = (out["near"][k] for k in approach.COLUMNS)
    assert xy[0] <= xy[1] <= xy[2] and dz[0] <= dz[1] <= dz[2] and speed[0] >= 0.0 and 0.0 <= align[0] <= align[2] <= 1.0


def test_a_swapped_critic_computes_what_it_computed_under_its_own_statistics():
    g = torch.Generator().manual_seed(0)
    n, k = 5, 2  # observation entries, stage one-hot

    def critic(scale):
        return {"module.obs_norm.mean": torch.randn(n, generator=g), "module.obs_norm.var": scale * torch.rand(n, generator=g) + 0.1,
                "module.obs_norm.count": torch.tensor(10.0), "module.mlp.params.0.weight": torch.randn(8, n + k, generator=g),
                "module.mlp.params.0.bias": torch.randn(8, generator=g)}

    own, other = critic(1.0), critic(3.0)
    swapped = swap_critic.reexpress_critic(own, other)

    def first_layer(sd, x, stage):
        z = (x - sd["module.obs_norm.mean"]) / sd["module.obs_norm.var"].sqrt()
        return torch.cat([z, stage], -1) @ sd["module.mlp.params.0.weight"].T + sd["module.mlp.params.0.bias"]

    x, stage = 0.3 * torch.randn(16, n, generator=g), torch.eye(k)[torch.randint(0, k, (16,), generator=g)]
    assert torch.allclose(first_layer(swapped, x, stage), first_layer(own, x, stage), atol=1e-4)
    assert torch.equal(swapped["module.obs_norm.var"], other["module.obs_norm.var"])


def test_an_analysis_refuses_a_setting_it_does_not_take_by_name():
    from pnp.analysis import training_curve
    from pnp.analysis.analysis_cli import settings

    with pytest.raises(ValueError, match=r"unknown setting 'windw': this script takes \['metrics', 'out', 'window'\]"):
        training_curve.main(["metrics=m.jsonl", "windw=3"])
    with pytest.raises(SystemExit, match=r"set \['checkpoint'\]"):
        settings(["trials=3"], {"checkpoint": None, "trials": 1}, "usage")
    free = settings(["checkpoint=c.pt", "env.num_worlds=3"], {"checkpoint": None, "env": {}}, "usage")
    assert free.env.num_worlds == 3  # an empty group takes any env override
    grouped = settings(["checkpoint=c.pt", "env.max_episode_steps=50"], {"checkpoint": None, "env": {"num_worlds": 8}},
                       "usage")
    assert (grouped.env.num_worlds, grouped.env.max_episode_steps) == (8, 50)  # a group with defaults too


def test_training_curve_weights_by_episodes_and_stops_at_phases(tmp_path, capsys):
    from pnp.analysis import training_curve
    rows = [{"phase": p, "iteration": i, "frames": 10 * i, "episodes": e, "success_rate": s,
             "final_stage_share/S0": 1.0 - s, "train/kl": 0.01, "train/lr": 1e-4}
            for p, i, e, s in [(0, 1, 1, 0.0), (0, 2, 3, 1.0), (0, 3, 2, 0.5), (1, 4, 0, float("nan")), (1, 5, 4, 0.25)]]
    path = tmp_path / "pipeline_metrics.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = training_curve.main([f"metrics={path}", "window=2", f"out={tmp_path / 'c.json'}"])
    assert [(w["phase"], w["first"], w["last"]) for w in out] == [(0, 1, 2), (0, 3, 3), (1, 4, 5)]
    assert out[0]["success"] == 0.75 and out[0]["end_s0"] == 0.25  # 3 of 4 episodes, not the rows' mean 0.5
    assert out[2]["success"] == 0.25 and out[2]["episodes"] == 4  # the row without episodes is skipped
    assert "| 0 | 1 | 2 |" in capsys.readouterr().out
    assert json.loads((tmp_path / "c.json").read_text())["window"] == 2
    with pytest.raises(ValueError, match="window must be >= 1, got 0"):
        training_curve.windows(rows, 0)
