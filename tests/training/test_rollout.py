"""The rollout API: trial bookkeeping, failure causes, sampled action groups, evaluate.py."""
from __future__ import annotations

import json
import math
from types import SimpleNamespace

import pytest
import torch
from tensordict import TensorDict

from pnp.task.scripted import ScriptedPnP
from pnp.task.terms import CONDITIONS, REWARD_TERMS
from pnp.training.keys import ACTION
from pnp.training.rollout import ACTION_GROUPS, TrialNoise, _act, classify_failures, load_policy, run_trials, summarise
from pnp.distill.student import add_observation_noise
from pnp.training.tasks import make_env
from tests.training._tiny import compose_cfg, tiny_train
from pnp.training import evaluation as evaluate_recipe


def test_evaluate_recipe_writes_the_table_and_its_provenance(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=2")
    result = evaluate_recipe.evaluate(compose_cfg("evaluate", [
        f"checkpoint={tmp_path / 'run'}", "trials=6", "env.num_worlds=4", "env.max_episode_steps=15",
        f"out={tmp_path / 'eval.json'}", "progress=false", f"compare={tmp_path / 'run'}",
    ]))
    saved = json.loads((tmp_path / "eval.json").read_text())
    for key in ("backend", "trials", "success_rate", "completion_time_mean_s", "completion_time_std_s", "failure_causes",
                "command", "commit", "seed", "machine", "wall_s", "env_steps", "train_wall_s", "warm_started_from",
                "reporting_seed", "config_sha", "experiment"):
        assert key in saved, key
    assert saved["paired"] is True and saved["seed_role"] == "development"
    assert [t[0] for t in saved["trial_records"]] == list(range(6))
    # The same checkpoint compared with itself on the same trials: no discordant trial.
    c = saved["comparison"]
    assert c["only_a_succeeded"] == c["only_b_succeeded"] == 0 and c["success_diff"] == 0.0
    assert saved["backend"] == "kinematic" and saved["trials"] == 6 == result["trials"]
    assert saved["start_range_m"] == [0.6, 5.0] and saved["max_episode_s"] == 1.5  # paper's layouts by default
    assert sum(saved["failure_causes"].values()) == round(saved["trials"] * (1 - saved["success_rate"]))
    assert (tmp_path / "eval.md").read_text().startswith("| Method | Success rate (%) | Completion time (s) |")


def test_scripted_policy_trials_add_up():
    """The scripted policy succeeds on the kinematic backend: trials, successes and times add up."""
    cfg = compose_cfg("train", ["backend=kinematic", "env.num_worlds=4", "env.terminate_on_success=true"])
    env = make_env(cfg.env, cfg.curriculum, seed=5)
    script = ScriptedPnP(4, 1)

    def policy(td):
        script.reset(td["step_count"].view(-1) == 0)
        return script(td)

    records = run_trials(env, policy, trials=6)
    res = summarise(records)
    assert res["trials"] == 6 and res["success_rate"] == 1.0
    assert 1.0 < res["completion_time_mean_s"] < 45.0 and res["end_stage_counts"]["S6"] == 6
    ends = [(r["end_step"], r["world"]) for r in records]
    assert ends == sorted(ends) and max(sum(r["world"] == w for r in records) for w in range(4)) <= 2


def _cause(success=False, fell=False, terminated=False, grabbed=False, box_goal=2.0, lifted=True, tilt=0.0):
    """The cause given to a one-world episode that ended with these flags."""
    cond = torch.zeros(1, 1, len(CONDITIONS), dtype=torch.bool)
    cond[..., CONDITIONS.index("object_grabbed")] = grabbed
    terms = torch.zeros(1, 1, len(REWARD_TERMS))
    terms[..., REWARD_TERMS.index("fall")] = float(fell)
    obj, goal = torch.zeros(1, 1, 30), torch.zeros(1, 1, 3)
    obj[..., 0] = box_goal
    obj[..., 3] = 1.0  # box x axis; y axis tilted about it by ``tilt`` (rad)
    obj[..., 7], obj[..., 8] = math.cos(tilt), math.sin(tilt)
    agents = TensorDict({"stage_conditions": cond, "reward_terms": terms, "object": obj, "goal": goal},
                        batch_size=(1, 1))
    flag = lambda v: torch.full((1, 1), v)  # noqa: E731
    nxt = TensorDict({"agents": agents, "success": flag(success), "terminated": flag(terminated or fell),
                      "diverged": flag(False)}, batch_size=(1,))
    return classify_failures(nxt, torch.tensor([0]), torch.tensor([lifted]))[0]


@pytest.mark.parametrize("kwargs, cause", [
    ({"success": True}, None),
    ({"fell": True}, "fall"),
    ({}, "dropped_box"),
    ({"box_goal": 0.2}, "timeout"),  # set down inside the goal, not released
    ({"grabbed": True}, "timeout"),  # still held at 45 s
    ({"lifted": False}, "timeout"),  # never lifted
    ({"lifted": False, "tilt": 1.2}, "tipped_box"),  # knocked over, on its side
    ({"lifted": False, "tilt": 0.9}, "timeout"),  # leaning, within 60 deg
    ({"lifted": False, "tilt": 1.5, "grabbed": True}, "timeout"),  # held tilted: hanging from a handle
    ({"tilt": 1.5}, "dropped_box"),  # lifted, then dropped on its side
])
def test_failure_causes(kwargs, cause):
    assert _cause(**kwargs) == cause


def test_sample_draws_only_the_named_action_groups(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1")
    pol = load_policy(tmp_path / "run" / "checkpoint.pt", 4, seed=0)
    td = pol.env.reset()
    mean = _act(pol.actor, td.clone(), ())[ACTION]
    mixed = _act(pol.actor, td.clone(), ("ee",))[ACTION]
    ee = ACTION_GROUPS["ee"]
    torch.testing.assert_close(mixed[..., :3], mean[..., :3])
    torch.testing.assert_close(mixed[..., 7:], mean[..., 7:])
    assert not torch.allclose(mixed[..., ee], mean[..., ee])  # drawn, not the mean
    with pytest.raises(ValueError, match="'wrist'"):
        run_trials(pol.env, pol.actor, trials=1, sample=["wrist"])
    # Per-trial draws: world w's draw follows its (trial, step), not its place in the batch.
    one = pol.actor(pol.env.reset()[:1])
    rows = torch.cat([one] * 3)
    draws = {}
    for trials, steps in (([5, 2, 9], [0, 3, 0]), ([9, 5, 2], [0, 0, 3])):
        base = SimpleNamespace(_trial_seed=11, trial=torch.tensor(trials))
        rows.set("step_count", torch.tensor(steps).view(3, 1))
        for t, k, d in zip(trials, steps, TrialNoise(base).draw(pol.actor, rows)):
            draws.setdefault((t, k), []).append(d)
    assert all(torch.equal(a, b) for a, b in draws.values()) and len(draws) == 3
    again = SimpleNamespace(_trial_seed=11, trial=torch.tensor([5, 5, 6]))
    rows.set("step_count", torch.tensor([0, 1, 0]).view(3, 1))
    d = TrialNoise(again).draw(pol.actor, rows)
    assert torch.equal(d[0], draws[(5, 0)][0]) and not torch.equal(d[0], d[1]) and not torch.equal(d[0], d[2])
    short = load_policy(tmp_path / "run" / "checkpoint.pt", 2, seed=0, max_episode_steps=5)
    assert [r["trial"] for r in run_trials(short.env, short.actor, trials=3, sample=["ee"])] == [0, 1, 2]
    with pytest.raises(ValueError, match="'gravity'"):
        load_policy(tmp_path / "run" / "checkpoint.pt", 4, seed=0, gravity=1.0)


def test_a_corrupt_checkpoint_is_named(tmp_path):
    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="checkpoint.pt is unreadable"):
        load_policy(bad, 4, seed=0)


def test_a_kinematic_run_with_options_is_evaluated_on_mujoco(tmp_path):
    """The kinematic options go back to their defaults on MuJoCo, whatever their type."""
    tiny_train(tmp_path / "run", "total_iterations=1", "env.kinematic.box_blocks_base=true", "env.kinematic.grasp_dist=0.02")
    pol = load_policy(tmp_path / "run" / "checkpoint.pt", 1, 0, backend="mujoco", nthread=1, max_episode_steps=2)
    assert not pol.env.base_env.backend.__class__.__name__.startswith("Kinematic")


def test_evaluate_recipe_takes_the_box_displacement_as_a_condition(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1")
    evaluate_recipe.evaluate(compose_cfg("evaluate", [
        f"checkpoint={tmp_path / 'run'}", "trials=4", "env.num_worlds=4", "env.max_episode_steps=6",
        f"out={tmp_path / 'eval.json'}", "progress=false", "displacement={delay_s: 0.0, distance: [0.5, 0.6]}",
    ]))
    saved = json.loads((tmp_path / "eval.json").read_text())["displacement"]
    assert saved["settings"]["distance"] == [0.5, 0.6] and saved["settings"]["delay_s"] == 0.0
    assert saved["trials"] == 4 and 0 <= saved["displaced"] <= 4 and "records" not in saved
    with pytest.raises(ValueError, match=r"displacement: unknown keys \['angle'\]"):
        evaluate_recipe.evaluate(compose_cfg("evaluate", [
            f"checkpoint={tmp_path / 'run'}", "trials=2", "env.num_worlds=2", "env.max_episode_steps=4",
            f"out={tmp_path / 'eval2.json'}", "progress=false", "displacement={angle: 1.0}"]))


def test_evaluate_recipe_puts_the_students_noise_on_a_teacher(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1")
    args = [f"checkpoint={tmp_path / 'run'}", "trials=4", "env.num_worlds=4", "env.max_episode_steps=6",
            f"out={tmp_path / 'eval.json'}", "progress=false"]
    evaluate_recipe.evaluate(compose_cfg("evaluate", [*args, "dropout_p=0.5"]))
    saved = json.loads((tmp_path / "eval.json").read_text())
    assert saved["observation_noise"]["dropout"]["p"] == 0.5 and saved["observation_noise"]["scale"] > 0
    evaluate_recipe.evaluate(compose_cfg("evaluate", args))
    assert json.loads((tmp_path / "eval.json").read_text())["observation_noise"] is None
    with pytest.raises(ValueError, match="noise.scale=-1.0"):
        evaluate_recipe.evaluate(compose_cfg("evaluate", [*args, "noise_scale=-1"]))
    # The noise reaches what the policy reads: the same paired trial, another observation.
    pol = load_policy(tmp_path / "run" / "checkpoint.pt", 2, seed=0)
    clean = pol.env.reset()["agents", "observation"]
    add_observation_noise(pol.env, 0, scale=1.0, dropout_p=0.0)
    assert not torch.allclose(pol.env.reset()["agents", "observation"], clean)
