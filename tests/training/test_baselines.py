"""The per-stage baselines: Bendikas' sub-task (its end at S_{k+1}, its reward), its
switching by success threshold and frame cap with the k -> k+1 initialisation, Erskine's
stage rewards, parameter counts, and recipes/table1.py end to end at toy size."""
from __future__ import annotations

import json
import shutil

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict

from pnp.losses.erskine import CooperativeMAPPOLoss
from pnp.losses.mappo import PopArtMAPPOLoss
from pnp.task.terms import REWARD_TABLE, REWARD_TERMS, STAGE_GATES, TERM_STAGE
from pnp.training.checkpoint import load_checkpoint
from pnp.training.keys import OBS, STAGE_ONE_HOT
from pnp.training.pipeline import load_state
from pnp.training.models import AgentNet, ObsNorm, fold_constant_inputs
from pnp.training.rollout import load_policy, run_trials
from pnp.baselines.bendikas import SequentialSchedule
from pnp.training.stage_ensemble import StageEnsemble, parameter_count
from pnp.training.tasks import schedule_args, schedule_of
from pnp.training.trainer import make_training
from pnp.transforms.baselines import SequentialSubtask, StageRewards
from tests.training._tiny import ROOT, TINY, compose_cfg, tiny_train
from pnp.studies import table1

BENDIKAS = ["model.per_stage=bendikas", "curriculum.schedule=fixed"]
MU = {t.name: t.mu for t in REWARD_TABLE}
GAMMA = 0.9


def _schedule(cls, **extra):
    _, kw = schedule_args(compose_cfg("train", ["curriculum.schedule=fixed"]).curriculum)
    base = {k: kw[k] for k in ("term_names", "term_stage", "mu", "fixed_weights", "n_stages", "stage_progress_term",
                               "stage_gates")}
    return cls(**base, **({"high": kw["high"], "gamma": GAMMA} if cls is SequentialSubtask else {}), **extra)


def _step(stage_next: list[int], terms: torch.Tensor | None = None) -> TensorDict:
    """One env-free step of len(stage_next) one-robot worlds, none done yet, at step 7."""
    n = len(stage_next)
    flag = lambda: torch.zeros(n, 1, dtype=torch.bool)  # noqa: E731
    agents = TensorDict({"reward_terms": terms if terms is not None else torch.ones(n, 1, len(REWARD_TERMS)),
                         "stage": torch.tensor(stage_next).reshape(n, 1, 1),
                         "episode_stage": torch.full((n, 1, 1), -1)}, [n, 1])
    nxt = TensorDict({"agents": agents, "done": flag(), "terminated": flag(), "truncated": flag(), "success": flag(),
                      "success_step": torch.full((n, 1), -1), "step_count": torch.full((n, 1), 7)}, [n])
    now = TensorDict({"stage": torch.zeros(n, 1, 1, dtype=torch.long)}, [n, 1])
    return TensorDict({"agents": now, "next": nxt}, [n])


def _expected_reward(stage: int, up_to: int) -> float:
    """All raw terms 1: R_fixed plus mu_j of the terms of stages <= up_to (stage progress = the stage, gates)."""
    staged = sum(MU[n] * (stage if n == "stage_progress" else 1.0) for n, s in TERM_STAGE.items()
                 if s <= up_to and stage >= STAGE_GATES.get(n, 0))
    return staged + sum(t.mu for t in REWARD_TABLE if t.stage is None)


def test_subtask_ends_at_the_next_stage_with_success_and_pays_only_its_stages():
    t = _schedule(SequentialSubtask, subtask=1, success_bonus=1.0)
    td = t(_step([2, 1]))["next"]  # world 0 reached S2, world 1 is still in S1
    assert td["done"].reshape(-1).tolist() == [True, False] == td["terminated"].reshape(-1).tolist()
    assert td["success"].reshape(-1).tolist() == [True, False] and not td["truncated"].any()
    assert td["agents", "episode_stage"].reshape(-1).tolist() == [2, -1]
    assert td["success_step"].reshape(-1).tolist() == [7, -1]
    best = sum(MU[n] * h for n, h in (("gripper_ready_pose", 1), ("gripper_grasp_pose", 1), ("object_grabbed", 1),
                                      ("grab_action", 1)))  # the terms of S0 and S1, at their highs
    reward = td["agents", "reward"].reshape(-1)
    torch.testing.assert_close(reward[1], torch.tensor(_expected_reward(1, 1)))
    torch.testing.assert_close(reward[0], torch.tensor(_expected_reward(2, 1) + best / (1 - GAMMA)))
    assert t.pop_stage_histogram().tolist() == [0, 0, 1, 0, 0, 0, 0]  # the ended episode is counted
    # the last sub-task is the whole task: FixedScales' reward, the env's own episode ends
    t.set_subtask(6)
    td = t(_step([6, 5]))["next"]
    assert not td["done"].any() and t.bonus == 0.0
    torch.testing.assert_close(td["agents", "reward"].reshape(-1), torch.tensor([_expected_reward(6, 6),
                                                                              _expected_reward(5, 6)]))
    with pytest.raises(ValueError, match=r"subtask must be in \[0, 7\), got 7"):
        t.set_subtask(7)


def test_stage_rewards_pay_each_stage_in_its_own_column():
    t = _schedule(StageRewards)
    td = t(_step([0, 2, 5]))["next"]
    cols = td["agents", "stage_rewards"].reshape(3, 7)
    fixed = sum(r.mu for r in REWARD_TABLE if r.stage is None)
    for world, stage in enumerate([0, 2, 5]):
        own = sum(MU[n] for n, s in TERM_STAGE.items() if s == stage and stage >= STAGE_GATES.get(n, 0))
        expected = torch.zeros(7)
        expected[stage] = own + fixed
        torch.testing.assert_close(cols[world], expected)
    torch.testing.assert_close(td["agents", "reward"].reshape(-1), torch.tensor([_expected_reward(s, 6) for s in
                                                                                 (0, 2, 5)]))


def test_a_completed_stage_keeps_paying_its_best_step_in_its_column():
    _, kw = schedule_args(compose_cfg("train", ["curriculum.schedule=fixed"]).curriculum)
    high = kw["high"]
    t = _schedule(StageRewards, high=high, completed_share=0.5)
    terms = torch.full((3, 1, len(REWARD_TERMS)), 0.25)
    cols = t(_step([0, 2, 6], terms))["next"]["agents", "stage_rewards"].reshape(3, 7)
    plain = _schedule(StageRewards)(_step([0, 2, 6], terms))["next"]["agents", "stage_rewards"].reshape(3, 7)
    best = [0.5 * sum(MU[n] * max(high[n], 0.0) for n, s in TERM_STAGE.items() if s == i) for i in range(7)]
    for world, stage in enumerate([0, 2, 6]):
        expected = plain[world].clone()
        expected[:stage] = torch.tensor(best[:stage])  # below: completed; its own: as without; above: 0
        torch.testing.assert_close(cols[world], expected)
    assert best[1] == 0.5 * (20.0 + 10.0 + 0.2)  # S1: grasp pose, grabbed, grab action at their highs
    with pytest.raises(ValueError, match="completed_share > 0 needs `high`"):
        _schedule(StageRewards, completed_share=1.0)
    with pytest.raises(ValueError, match="completed_share must be >= 0, got -1"):
        _schedule(StageRewards, high=high, completed_share=-1.0)


def _bendikas(*extra, max_frames=100, window=2):
    torch.manual_seed(0)
    cfg = compose_cfg("train", [*TINY, *BENDIKAS, f"baseline.bendikas.max_frames={max_frames}",
                                f"baseline.bendikas.window={window}", *extra])
    env, models, _ = make_training(cfg)  # as a run builds them
    optim = torch.optim.Adam([*models.actor.parameters(), *models.critic.parameters()], lr=1e-2)
    return SequentialSchedule(cfg.baseline.bendikas, schedule_of(env), models.actor_net, models.critic_net, optim), env


def test_the_subtasks_member_acts_in_every_stage():
    sched, env = _bendikas()
    actor = sched.actor
    td = env.reset()[:1].expand(7).clone()
    td[STAGE_ONE_HOT] = torch.eye(7).reshape(7, 1, 7)
    td[OBS] = torch.randn_like(td[OBS])
    with torch.no_grad():
        out = actor(td[OBS], td[STAGE_ONE_HOT])
        alone = actor.head(actor.members[0](actor.obs_norm(td[OBS]), td[STAGE_ONE_HOT]))
    for a, b in zip(out, alone):
        torch.testing.assert_close(a, b)  # every stage by member 0 in sub-task 0
    assert actor.used_members() == [0]


def test_routing_is_per_robot_and_folding_reaches_every_member():
    torch.manual_seed(0)
    norm = ObsNorm(3)
    members = [AgentNet(3 + 3, 2, 2, centralised=True, cells=[8]) for _ in range(3)]
    ens = StageEnsemble(members, norm)
    obs, stage = torch.randn(5, 2, 3), torch.eye(3)[torch.tensor([[0, 2], [1, 1], [2, 0], [0, 0], [1, 2]])]
    out = ens(obs, stage)
    for w in range(5):
        for r in range(2):  # robot r of world w: its own stage's member, on the whole world (centralised)
            s = int(stage[w, r].argmax())
            torch.testing.assert_close(out[w, r], members[s](norm(obs[w:w + 1]), stage[w:w + 1])[0, r])
    data = torch.randn(64, 3)
    data[:, 1] = 0.5  # an entry that never moved: folded in every member
    norm.update(data)
    before = ens(data[:5, None].expand(5, 2, 3), stage)
    assert fold_constant_inputs(norm, [ens]) == [1]
    moved = data[:5, None].expand(5, 2, 3).clone()
    moved[..., 1] = 3.0
    torch.testing.assert_close(ens(moved, stage), before)


def test_a_subtask_ends_at_the_success_threshold_and_the_next_starts_as_a_copy():
    sched, env = _bendikas()
    # an Adam step on member 0, so that there are moments to carry over
    obs, stage = torch.randn(4, 1, 74), torch.eye(7)[torch.zeros(4, 1, dtype=torch.long)]
    (sched.actor(obs, stage)[0].sum() + sched.critic(obs, stage).sum()).backward()
    sched.optim.step()
    good = {"success_rate": 0.95, "episodes": 10.0}
    assert sched.update(good, 40) == {"subtask": 0.0, "subtask_exit": 0.0}  # a window of 2 iterations is not full yet
    assert sched.update(good, 40) == {"subtask": 0.0, "subtask_exit": 1.0}  # 0.95 >= 0.9: success
    assert sched.subtask == 1 and schedule_of(env).subtask == 1 and sched.critic.route.tolist() == [1] * 7
    for net in (sched.actor, sched.critic):
        for p0, p1 in zip(net.members[0].parameters(), net.members[1].parameters()):
            assert torch.equal(p0, p1) and p0 is not p1
            for k, v in sched.optim.state[p0].items():
                copy = sched.optim.state[p1][k]
                assert torch.equal(v, copy) and v is not copy
    assert sched.history == [{"subtask": 0, "exit": "success", "frames": 80, "frames_total": 80, "success_rate": 0.95}]


def test_a_subtask_ends_at_its_frame_cap_and_the_last_never_ends():
    sched, _ = _bendikas(max_frames=100)
    bad = {"success_rate": 0.1, "episodes": 10.0}
    assert sched.update(bad, 60)["subtask_exit"] == 0.0
    assert sched.update(bad, 60)["subtask_exit"] == 2.0 and sched.subtask == 1  # 120 >= 100 frames
    state = sched.state_dict()
    for _ in range(5 * 2):
        sched.update(bad, 60)
    assert sched.subtask == 6 and [h["exit"] for h in sched.history] == ["frames"] * 6
    assert sched.update(bad, 10**9) == {"subtask": 6.0, "subtask_exit": 0.0}
    with pytest.raises(ValueError, match="sub-task 6 is the last"):
        sched.advance("frames")
    sched.load_state_dict(state)
    assert sched.frames == 0 and len(sched.history) == 1
    with pytest.raises(ValueError, match="min_success must be in"):
        _bendikas("baseline.bendikas.min_success=1.5")


def test_bendikas_resumes_bit_for_bit_and_evaluates_its_last_policy(tmp_path):
    extra = [*BENDIKAS, "baseline.bendikas.max_frames=40", "env.max_episode_steps=5"]
    tiny_train(tmp_path / "straight", "total_iterations=4", *extra)
    tiny_train(tmp_path / "split", "total_iterations=2", *extra)
    tiny_train(tmp_path / "split", "total_iterations=4", f"resume={tmp_path / 'split'}", *extra)
    a, b = (load_checkpoint(tmp_path / r / "checkpoint.pt") for r in ("straight", "split"))
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k
    assert a["subtasks"] == b["subtasks"] and len(a["subtasks"]["history"]) == 4
    assert a["actor"]["module.0.module.route"].tolist() == [4] * 7  # sub-tasks 0-3 ended at their 40-frame cap
    pol = load_policy(tmp_path / "straight" / "checkpoint.pt", 2, seed=0)
    assert pol.actor.module[0].module.used_members() == [4]
    assert len(run_trials(pol.env, pol.actor, 2)) == 2


def test_parameter_counts():
    counts = {}
    for ps in ("none", "bendikas", "erskine"):
        fixed = [] if ps == "none" else ["curriculum.schedule=fixed"]  # the baselines train on mu_j
        env, models, _ = make_training(compose_cfg("train", [*TINY, f"model.per_stage={ps}", *fixed]))
        env.close()
        counts[ps] = parameter_count(models.actor_net, models.critic_net)
    ours = counts["none"]
    assert counts["bendikas"]["actor"] == 7 * ours["actor"] and counts["bendikas"]["inference"] == ours["actor"]
    assert counts["erskine"]["inference"] == counts["erskine"]["actor"] == 7 * ours["actor"]
    assert counts["bendikas"]["critic"] == 7 * (ours["critic"] - 2) + 2  # PopArt's weight and bias once
    assert counts["erskine"]["critic"] == 7 * ours["critic"]  # and one PopArt pair per stage


@pytest.mark.parametrize("per_stage, schedule, loss_cls", [
    ("none", "AdaptiveRewardScaling", PopArtMAPPOLoss), ("bendikas", "SequentialSubtask", PopArtMAPPOLoss),
    ("erskine", "StageRewards", CooperativeMAPPOLoss)])
def test_make_training_builds_each_methods_reward_schedule_and_loss(per_stage, schedule, loss_cls):
    # The trainer, profile_iteration and table1 all build a run through make_training.
    extra = [] if per_stage == "none" else [*BENDIKAS[1:], f"model.per_stage={per_stage}"]
    env, models, loss = make_training(compose_cfg("train", [*TINY, *extra]))
    try:
        assert type(env.transform[-1]).__name__ == schedule
        assert type(loss) is loss_cls
        if per_stage == "erskine":
            assert loss.mix == 0.5  # baseline.erskine.mix reaches the loss
        # the loss optimises the models it was given
        assert {id(p) for p in models.actor_net.parameters()} <= {id(p) for p in loss.parameters()}
    finally:
        env.close()


def test_thresholds_count_only_the_whole_task():
    runs = [(6, 5), (6, 5), (2, 6), (6, 6), (6, 6), (5, 6)]  # (end stage, sub-task) per iteration
    rows = [{"iteration": i, "frames": 10 * i, "wall_s": float(i), "episodes": 4.0, "end_stage": s,
             "success_rate": s / 6, "subtask": k} for i, (s, k) in enumerate(runs, start=1)]
    eff = table1.efficiency(rows, OmegaConf.create({"mean_end_stage": 5.5, "success_rate": 0.9}), 2)
    assert eff["frames_to_stage_5_5"] == 50 and eff["wall_s_to_success_0_9"] == 5.0  # S6 in sub-task 5 is not the task
    assert table1.efficiency(rows, OmegaConf.create({"success_rate": 0.99}), 6)["frames_to_success_0_99"] is None
    mean, std = table1.pooled_times([{"trials": 4, "success_rate": 0.5, "completion_time_mean_s": 10.0,
                                      "completion_time_std_s": 0.0},
                                     {"trials": 4, "success_rate": 0.5, "completion_time_mean_s": 12.0,
                                      "completion_time_std_s": 0.0}])
    assert (mean, std) == (11.0, 1.0)
    seeds = lambda *f: {str(i): {"frames_to_x": v} for i, v in enumerate(f)}  # noqa: E731
    methods = {"ours": {"seeds": seeds(10, 20), "success_rate": 0.9, "completion_time_mean_s": 8.0},
               "a": {"seeds": seeds(30, 30), "success_rate": 0.8, "completion_time_mean_s": 12.0},
               "b": {"seeds": seeds(20, None), "success_rate": 0.5, "completion_time_mean_s": 4.0}}
    r = table1.ratios(methods, "ours", ["frames_to_x"])
    # b is not the best: one of its seeds never got there
    assert r["efficiency"]["frames_to_x"] == 2.0 and r["best_baseline"]["frames_to_x"] == "a"
    assert r["execution_time"] == 8.0 / 12.0 and r["best_baseline"]["execution_time"] == "a"
    # a seed that never got there counts as the budget: b's (20 + 100) / 2 = 60 against a's 30
    assert r["efficiency_at_least"]["frames_to_x"] is None  # no budget given
    assert table1.ratios(methods, "ours", ["frames_to_x"], 100)["efficiency_at_least"]["frames_to_x"] == 2.0
    methods["a"]["seeds"] = seeds(30, None)  # now b's 60 is the smaller: at least 60 / 15
    assert table1.ratios(methods, "ours", ["frames_to_x"], 100)["efficiency_at_least"]["frames_to_x"] == 4.0
    methods["ours"]["seeds"] = seeds(10, None)  # ours never got there on a seed: no bound
    assert table1.ratios(methods, "ours", ["frames_to_x"], 100)["efficiency_at_least"]["frames_to_x"] is None


def _table1_cfg(tmp_path, methods, seeds, *phases):
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose("table1", overrides=[f"methods={methods}", f"seeds={seeds}", f"runs_dir={tmp_path / 'runs'}", f"records_dir={tmp_path / 'records'}",
                                           f"out={tmp_path / 'table1.json'}", "eval.trials=3", "eval.backend=kinematic",
                                           "eval.num_worlds=3", "eval.max_episode_steps=5", "eval_kinematic.trials=3",
                                           "eval_kinematic.num_worlds=3", "eval_kinematic.max_episode_steps=5", "curve_bins=4"])
    cfg.train = [t for t in TINY if not t.startswith("backend=")] + ["baseline.bendikas.max_frames=40", *phases]
    return cfg


def _check_form(doc, methods, seeds):
    assert set(doc["methods"]) == set(methods)
    for m in doc["methods"].values():
        assert set(m["seeds"]) == {str(s) for s in seeds}
        for s in m["seeds"].values():
            assert {"frames_to_stage_5_5", "frames_to_success_0_9", "wall_s"} <= set(s)
        for key in ("trials", "backend", "success_rate", "completion_time_mean_s", "completion_time_std_s",
                    "budget_frames", "command", "parameters"):
            assert key in m, key
    for key in ("efficiency_ratio", "execution_time_ratio", "efficiency_ratio_ci95", "execution_time_ratio_ci95",
                "commit", "machine"):
        assert key in doc, key


def test_table1_recipe_trains_evaluates_and_resumes(tmp_path):
    # seed 0 goes on to the MuJoCo phase and its evaluation, seed 1 stops after the kinematic one
    cfg = _table1_cfg(tmp_path, "[dynamic,bendikas]", "[0,1]", "pipeline=[kin,mj]",
                      "++phases={kin: {max_frames: 80}, mj: {max_frames: 40, overrides: {env.backend: mujoco}}}")
    cfg.eval.backend = "mujoco"
    doc = table1.run_table1(cfg)
    saved = json.loads((tmp_path / "table1.json").read_text())
    _check_form(saved, ["dynamic", "bendikas"], [0, 1])
    m = saved["methods"]["bendikas"]
    assert m["budget_frames"] == 120 and m["kinematic_budget_frames"] == 80
    assert m["trials"] == 3 and m["backend"] == "mujoco" and m["seeds_evaluated"] == 1
    assert m["kinematic"]["backend"] == "kinematic" and m["kinematic"]["seeds_evaluated"] == 2
    assert "eval" in m["seeds"]["0"] and "eval" not in m["seeds"]["1"]
    assert [p["name"] for p in load_state(tmp_path / "runs" / "bendikas_s0")] == ["kin", "mj"]
    assert [p["name"] for p in load_state(tmp_path / "runs" / "bendikas_s1")] == ["kin"]
    assert m["seeds"]["1"]["frames"] == 80  # efficiency and curves over the kinematic phases only
    assert [h["exit"] for h in m["seeds"]["1"]["subtasks"]] == ["frames", "frames"]
    assert m["parameters"]["inference"] * 7 == m["parameters"]["actor"]
    for png in ("table1_end_stage.png", "table1_success_rate.png"):
        assert (tmp_path / png).stat().st_size > 0
    md = (tmp_path / "table1.md").read_text()
    assert "| Bendikas et al. | 91.2 | 13.25 ± 0.41 |" in md and "success_0_9 | stage_5_5" in md
    # a rerun trains nothing and reuses the evaluations, from the records even without the run folders
    again = table1.run_table1(cfg)
    assert again["methods"]["dynamic"]["seeds"] == doc["methods"]["dynamic"]["seeds"]
    shutil.rmtree(tmp_path / "runs")
    kept = table1.run_table1(cfg)
    assert kept["methods"] == again["methods"] and not (tmp_path / "runs").exists()
    # thresholds are read off the recorded rows: a new one needs no run folder either
    cfg.thresholds, cfg.window = {"mean_end_stage": 0.0}, 1
    first = table1.run_table1(cfg)["methods"]["dynamic"]["seeds"]["0"]["frames_to_stage_0"]
    assert 0 < first < kept["methods"]["dynamic"]["seeds"]["0"]["frames"]
    assert not (tmp_path / "runs").exists()
    # a record of other settings is not reused: that run trains again
    cfg.train = [*cfg.train, "loss.clip_epsilon=0.25"]
    cfg.methods, cfg.seeds, cfg.mujoco_seeds = ["dynamic"], [1], []
    table1.run_table1(cfg)
    assert [p["name"] for p in load_state(tmp_path / "runs" / "dynamic_s1")] == ["kin"]


@pytest.mark.slow
def test_table1_recipe_with_every_method_and_three_seeds(tmp_path):
    methods = ["dynamic", "liu_max", "liu_min", "bendikas", "erskine"]
    cfg = _table1_cfg(tmp_path, f"[{','.join(methods)}]", "[0,1,2]",
                      "pipeline=[explore,sharp]",
                      "++phases={explore: {max_frames: 40, overrides: {loss.entropy_coeff: 0.02}}, sharp: {max_frames: 40}}")
    _check_form(table1.run_table1(cfg), methods, [0, 1, 2])
