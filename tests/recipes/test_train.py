"""recipes/train.py and recipes/evaluate.py end to end on the kinematic backend (a few seconds each)."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "recipes"))
import _common  # noqa: E402
import evaluate as evaluate_recipe  # noqa: E402
import plots  # noqa: E402
import train as train_recipe  # noqa: E402

from pnp.scripted import ScriptedPnP  # noqa: E402
from pnp.terms import CONDITIONS, REWARD_TERMS  # noqa: E402

CONFIG_DIR = str(ROOT / "recipes" / "config")
TINY = [
    "env.backend=kinematic", "env.num_worlds=4", "env.max_episode_steps=6", "collect.frames_per_batch=40",
    "collect.minibatch_size=20", "collect.num_epochs=2", "model.actor_cells=[32,32]", "model.critic_cells=[32,32]",
    "logger.backend=csv", "progress=false",
]


def _cfg(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(name, overrides=overrides)


def _train(out_dir: Path, *extra: str) -> dict:
    return train_recipe.train(_cfg("train", [*TINY, f"out_dir={out_dir}", *extra]))


def test_train_then_evaluate(tmp_path):
    run = tmp_path / "run"
    out = _train(run, "total_iterations=3")
    assert out["iteration"] == 3 and out["frames"] == 3 * 40
    ckpt = _common.load_checkpoint(run / "checkpoint.pt")
    assert {"actor", "critic", "optim", "curriculum", "env", "carried", "rng", "counters", "cfg"} <= set(ckpt)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3]
    for key in ("success_rate", "mean_end_stage", "stage_share/S0", "rho/gripper_ready_pose", "train/loss_objective",
                "train/loss_critic", "frames", "wall_s"):
        assert key in rows[-1], key
    for png in ("mean_end_stage.png", "stage_shares.png", "success_rate.png", "rho.png"):
        assert (run / png).stat().st_size > 0
    assert any(run.glob("**/scalars/mean_end_stage.csv"))  # the csv logger's files

    result = evaluate_recipe.evaluate(_cfg("evaluate", [
        f"checkpoint={run}", "trials=6", "env.num_worlds=4", "env.max_episode_steps=15", f"out={tmp_path / 'eval.json'}",
        "progress=false",
    ]))
    saved = json.loads((tmp_path / "eval.json").read_text())
    for key in ("backend", "trials", "success_rate", "completion_time_mean_s", "completion_time_std_s", "failure_causes",
                "command", "commit", "seed", "machine", "wall_s", "env_steps", "train_wall_s", "warm_started_from"):
        assert key in saved, key
    assert saved["backend"] == "kinematic" and saved["trials"] == 6 == result["trials"]
    assert saved["start_range_m"] == [0.6, 5.0] and saved["max_episode_s"] == 1.5  # paper's layouts by default
    failures = round(saved["trials"] * (1 - saved["success_rate"]))
    assert sum(saved["failure_causes"].values()) == failures
    table = (tmp_path / "eval.md").read_text()
    assert table.startswith("| Method | Success rate (%) | Completion time (s) |")


@pytest.mark.parametrize("roll_in", [[], ["collect.roll_in_share=0.5", "collect.roll_in_max_steps=3"]])
def test_resume_is_bit_for_bit(tmp_path, roll_in):
    extra = ["env.max_episode_steps=5", "seed=3", *roll_in]
    _train(tmp_path / "straight", "total_iterations=4", *extra)
    _train(tmp_path / "split", "total_iterations=2", *extra)
    _train(tmp_path / "other", "total_iterations=4", "resume=" + str(tmp_path / "split"), *extra)  # ignored out_dir
    a = _common.load_checkpoint(tmp_path / "straight" / "checkpoint.pt")
    b = _common.load_checkpoint(tmp_path / "split" / "checkpoint.pt")
    assert a["counters"]["iteration"] == b["counters"]["iteration"] == 4
    for part in ("actor", "critic", "curriculum"):
        assert a[part].keys() == b[part].keys()
        for k in a[part]:
            assert torch.equal(a[part][k], b[part][k]), (part, k)
    for k, v in a["env"].items():
        assert torch.equal(v, b["env"][k]), k
    assert (a["carried"] == b["carried"]).all()

    def rows(run):  # every logged number but the wall time
        return [{k: v for k, v in json.loads(line).items() if k != "wall_s"}
                for line in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]

    assert json.dumps(rows("straight")) == json.dumps(rows("split"))


def test_warm_start_copies_weights(tmp_path):
    _train(tmp_path / "src", "total_iterations=1")
    _train(tmp_path / "dst", "total_iterations=0", f"warm_start={tmp_path / 'src'}", "seed=1")
    a = _common.load_checkpoint(tmp_path / "src" / "checkpoint.pt")
    b = _common.load_checkpoint(tmp_path / "dst" / "checkpoint.pt")
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k
    assert a["optim"]["param_groups"][0]["lr"] == b["optim"]["param_groups"][0]["lr"]
    assert torch.equal(a["optim"]["state"][0]["exp_avg"], b["optim"]["state"][0]["exp_avg"])


def test_plots_standalone(tmp_path):
    rows = [{"iteration": i, "mean_end_stage": 0.1 * i, "stage_share/S0": 1 - 0.1 * i, "stage_share/S1": 0.1 * i,
             "rho/a": 0.1 * 2**i} for i in range(1, 6)]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    written = plots.plot_training(tmp_path / "metrics.jsonl", tmp_path / "out")
    assert sorted(p.name for p in written) == ["mean_end_stage.png", "rho.png", "stage_shares.png"]


def test_evaluate_counts_scripted_successes():
    """The scripted policy succeeds on the kinematic backend: trials, successes and times add up."""
    env = _common.make_env(
        _cfg("train", ["env.backend=kinematic", "env.num_worlds=4", "env.max_episode_steps=null",
                       "env.terminate_on_success=true"]).env,  # as evaluate.py sets it
        _cfg("train", []).curriculum, seed=5)
    script = ScriptedPnP(4, 1)

    def policy(td):
        script.reset(td["step_count"].view(-1) == 0)
        return script(td)

    records = evaluate_recipe.run_trials(env, policy, trials=6)
    res = evaluate_recipe.summarise(records)
    assert res["trials"] == 6 and res["success_rate"] == 1.0
    assert 1.0 < res["completion_time_mean_s"] < 45.0 and res["end_stage_counts"]["S6"] == 6
    ends = [(r["end_step"], r["world"]) for r in records]
    assert ends == sorted(ends) and max(sum(r["world"] == w for r in records) for w in range(4)) <= 2


def _ended(success=False, fell=False, terminated=False, grabbed=False, box_goal=2.0, lifted=True):
    """A one-world ``next`` tensordict at the step an episode ended."""
    cond = torch.zeros(1, 1, len(CONDITIONS), dtype=torch.bool)
    cond[..., CONDITIONS.index("object_grabbed")] = grabbed
    terms = torch.zeros(1, 1, len(REWARD_TERMS))
    terms[..., REWARD_TERMS.index("fall")] = float(fell)
    obj, goal = torch.zeros(1, 1, 30), torch.zeros(1, 1, 3)
    obj[..., 0] = box_goal
    agents = TensorDict({"stage_conditions": cond, "reward_terms": terms, "object": obj, "goal": goal,
                         "stage": torch.full((1, 1, 1), 3)}, batch_size=(1, 1))
    flag = lambda v: torch.full((1, 1), v)  # noqa: E731
    nxt = TensorDict({"agents": agents, "success": flag(success), "terminated": flag(terminated or fell),
                      "diverged": flag(False), "step_count": torch.full((1, 1), 450)}, batch_size=(1,))
    return evaluate_recipe._end_records(nxt, torch.tensor([0]), torch.tensor([lifted]), torch.tensor([3]), step=450)[0]


@pytest.mark.parametrize("kwargs, cause", [
    ({"success": True}, None),
    ({"fell": True}, "fall"),
    ({}, "dropped_box"),
    ({"box_goal": 0.2}, "timeout"),  # set down inside the goal, not released
    ({"grabbed": True}, "timeout"),  # still held at 45 s
    ({"lifted": False}, "timeout"),  # never lifted
])
def test_failure_causes(kwargs, cause):
    assert _ended(**kwargs)["cause"] == cause


def test_resolve_checkpoint(tmp_path):
    old, new = tmp_path / "a" / "checkpoint.pt", tmp_path / "b" / "checkpoint.pt"
    for i, p in enumerate((old, new)):
        p.parent.mkdir()
        p.write_bytes(b"x")
        os.utime(p, (1000 + i, 1000 + i))
    assert _common.resolve_checkpoint(True, tmp_path) == new
    assert _common.resolve_checkpoint("latest", tmp_path) == new
    assert _common.resolve_checkpoint(str(old.parent), tmp_path) == old
    with pytest.raises(FileNotFoundError):
        _common.resolve_checkpoint(str(tmp_path / "missing"), tmp_path)


def test_warm_start_curriculum_copies_rho(tmp_path):
    _train(tmp_path / "src", "total_iterations=2")
    _train(tmp_path / "dst", "total_iterations=0", f"warm_start={tmp_path / 'src'}", "warm_start_curriculum=true")
    a = _common.load_checkpoint(tmp_path / "src" / "checkpoint.pt")["curriculum"]
    b = _common.load_checkpoint(tmp_path / "dst" / "checkpoint.pt")["curriculum"]
    assert torch.equal(a["transforms.2.rho"], b["transforms.2.rho"]) and not (a["transforms.2.rho"] == 0.1).all()


def test_fold_constant_inputs_keeps_outputs_and_blinds_the_nets():
    torch.manual_seed(0)
    n_obs = 5
    norm = _common.ObsNorm(n_obs)
    data = torch.randn(256, n_obs)
    data[:, 2] = 0.5  # an entry that never moved
    norm.update(data)
    for centralised in (False, True):
        net = _common.AgentNet(n_obs + 2, 3, 2, centralised, [8], obs_norm=norm)
        old = net(data[:4, None].expand(4, 2, n_obs), torch.zeros(4, 2, 2))
        state = {k: v.clone() for k, v in norm.state_dict().items()}
        assert _common.fold_constant_inputs(norm, [net]) == [2]
        new = net(data[:4, None].expand(4, 2, n_obs), torch.zeros(4, 2, 2))
        torch.testing.assert_close(new, old)
        moved = data[:4, None].expand(4, 2, n_obs).clone()
        moved[..., 2] = 3.0  # the entry moves: the folded nets do not see it
        torch.testing.assert_close(net(moved, torch.zeros(4, 2, 2)), old)
        norm.load_state_dict(state)


def test_grasp_min_scale_floors_only_the_grasp_entry():
    cfg = _cfg("train", [*TINY, "model.grasp_dist=tanh_normal", "model.grasp_min_scale=0.3", "model.init_scale=0.01"])
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    actor, *_ = _common.make_models(cfg.model, env, "none", 0.98)
    scale = actor(env.reset())[_common.SCALE]
    assert torch.all(scale[..., _common.GRASP_ENTRY] == 0.3) and torch.all(scale[..., :7] < 0.3)


def test_min_scale_floors_every_entry():
    cfg = _cfg("train", [*TINY, "model.min_scale=0.2", "model.init_scale=0.01"])
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    actor, *_ = _common.make_models(cfg.model, env, "none", 0.98)
    assert torch.all(actor(env.reset())[_common.SCALE] == 0.2)


def test_bernoulli_gripper_actions_are_binary_and_deterministic_mode_thresholds():
    cfg = _cfg("train", TINY)
    assert cfg.model.grasp_dist == "bernoulli"
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    actor, *_ = _common.make_models(cfg.model, env, "none", 0.98)
    td = env.reset()
    with _common.set_interaction_type(_common.InteractionType.RANDOM):
        out = actor(td.clone())
    grip = out[_common.ACTION][..., _common.GRASP_ENTRY]
    assert set(grip.unique().tolist()) <= {0.0, 1.0}
    logit = out[_common.LOC][..., _common.GRASP_ENTRY]
    with _common.set_interaction_type(_common.InteractionType.DETERMINISTIC):
        det = actor(td.clone())[_common.ACTION][..., _common.GRASP_ENTRY]
    assert torch.equal(det, (logit > 0).float())
    assert _common.policy_kl(actor, out) == pytest.approx(0.0, abs=1e-6)


def test_peak_reading_logs_the_final_stage_too(tmp_path):
    _train(tmp_path / "run", "total_iterations=2", "curriculum.episode_stage=peak")
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    ended = [r for r in rows if r["episodes"] > 0]
    assert ended and all(r["mean_final_stage"] <= r["mean_end_stage"] for r in ended)
    assert all(abs(sum(r[f"final_stage_share/S{i}"] for i in range(7)) - 1) < 1e-6 for r in ended)


def test_evaluate_sample_draws_only_the_named_action_groups(tmp_path):
    _train(tmp_path / "run", "total_iterations=1")
    ev = _cfg("evaluate", ["env.backend=kinematic"]).env
    env, actor, *_ = evaluate_recipe.load_policy(tmp_path / "run" / "checkpoint.pt", ev, 4, seed=0)
    td = env.reset()
    mean = evaluate_recipe._act(actor, td.clone(), ())[_common.ACTION]
    mixed = evaluate_recipe._act(actor, td.clone(), ("ee",))[_common.ACTION]
    ee = evaluate_recipe.ACTION_GROUPS["ee"]
    torch.testing.assert_close(mixed[..., :3], mean[..., :3])
    torch.testing.assert_close(mixed[..., 7:], mean[..., 7:])
    assert not torch.allclose(mixed[..., ee], mean[..., ee])  # drawn, not the mean
    with pytest.raises(ValueError, match="'wrist'"):
        evaluate_recipe.run_trials(env, actor, trials=1, sample=["wrist"])


def test_fixed_weights_override_weights_the_named_term_and_rejects_unknown_names():
    cfg = _cfg("train", [*TINY, "+curriculum.fixed_weights.ee_out_of_reach=-2.0"])
    _, kw = _common.schedule_args(cfg.curriculum)
    assert kw["fixed_weights"]["ee_out_of_reach"] == -2.0
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    td = env.reset()
    td["agents", "action"] = torch.zeros(4, 1, 8)
    td["agents", "action"][..., 3] = 3.0  # far beyond reach (clipped to the 1.3 m bound first)
    nxt = env.step(td)["next"]
    excess = nxt["agents", "reward_terms"][..., REWARD_TERMS.index("ee_out_of_reach")]
    assert torch.all(excess > 0.1)
    with pytest.raises(ValueError, match="'ee_reach'"):
        _common.schedule_args(_cfg("train", [*TINY, "+curriculum.fixed_weights.ee_reach=-1"]).curriculum)


def test_reach_loss_pulls_the_mean_ee_command_into_reach(tmp_path):
    cfg = _cfg("train", [*TINY, "loss.reach_coeff=1.0"])
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    actor, *_ = _common.make_models(cfg.model, env, "none", 0.98)
    td = env.reset()
    bias = [p for n, p in actor.named_parameters() if n.endswith("4.bias")][0]  # the loc/scale layer
    with torch.no_grad():
        bias[..., 3] += 3.0  # EE x loc deep in the tanh's flat end: x ~ 1.3, beyond reach
    before = float(_common.reach_loss(actor, td).detach())
    assert before > 0.1
    opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
    for _ in range(50):
        opt.zero_grad()
        _common.reach_loss(actor, td).backward()
        opt.step()
    assert float(_common.reach_loss(actor, td).detach()) < 0.5 * before
    _train(tmp_path / "run", "total_iterations=1", "loss.reach_coeff=1.0")
    line = json.loads((tmp_path / "run" / "metrics.jsonl").read_text().splitlines()[-1])
    assert line["train/ee_out_of_reach"] >= 0.0


def test_roll_in_takes_the_mean_then_samples_and_stays_out_of_the_loss(tmp_path):
    cfg = _cfg("train", [*TINY, "env.max_episode_steps=4"])
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    actor, *_ = _common.make_models(cfg.model, env, "none", 0.98)
    roll_in = _common.MeanRollIn(4, share=1.0, max_steps=2)
    batch, _ = _common.collect(env, actor, env.reset(), 8, roll_in)  # two 4-step episodes per world
    count = batch["step_count"].squeeze(-1)  # [N, T] steps taken before each action
    flag = batch[_common.ROLL_IN].squeeze(-1)
    assert flag.any() and (~flag).any()
    # share 1: every episode rolls in for 1-2 steps, so its first step is always a mean action
    assert flag[count == 0].all() and not flag[count >= 2].any()
    mean = actor.module[-1].get_dist(batch).deterministic_sample
    act = batch[_common.ACTION]
    torch.testing.assert_close(act[flag], mean[flag])
    assert not torch.allclose(act[~flag][..., :7], mean[~flag][..., :7])  # drawn
    # All roll-in: nothing is left to train on, so the actor does not move.
    loss = _common.make_loss(cfg.loss, actor, _common.make_models(cfg.model, env, "none", 0.98)[1], None)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
    before = [p.clone() for p in actor.parameters()]
    batch[_common.ROLL_IN] = torch.ones_like(batch[_common.ROLL_IN])
    train_recipe.ppo_update(batch, loss, optim, None, cfg)
    assert all(torch.equal(p, q) for p, q in zip(before, actor.parameters()))
    with pytest.raises(ValueError, match="roll_in_share"):
        _common.MeanRollIn(4, share=1.5, max_steps=2)
    _train(tmp_path / "run", "total_iterations=1", "collect.roll_in_share=1.0", "collect.roll_in_max_steps=2")
    line = json.loads((tmp_path / "run" / "metrics.jsonl").read_text().splitlines()[-1])
    assert 0.0 < line["roll_in_frames"] < 1.0


def test_desync_episodes_spreads_the_first_episode_ends():
    cfg = _cfg("train", [*TINY, "env.num_worlds=16", "env.max_episode_steps=6"])
    env = _common.make_env(cfg.env, cfg.curriculum, 0)
    actor, *_ = _common.make_models(cfg.model, env, "none", 0.98)
    torch.manual_seed(0)
    carried = train_recipe.desync_episodes(env.reset(), 6)
    off = carried["step_count"].reshape(-1).clone()
    assert 0 <= int(off.min()) and int(off.max()) < 6 and len(off.unique()) > 2
    batch, _ = _common.collect(env, actor, carried, 6)
    first_end = batch["next", "done"].reshape(16, 6).float().argmax(1)  # step index of each world's first end
    assert torch.equal(first_end, 5 - off)
    with pytest.raises(ValueError, match="max_episode_steps"):
        train_recipe.desync_episodes(env.reset(), None)


def test_resume_takes_only_the_listed_keys_from_the_command_line(tmp_path):
    _train(tmp_path / "run", "total_iterations=1", "env.nthread=2")
    cfg = _cfg("train", [*TINY, "env.nthread=1", "env.num_worlds=8", f"resume={tmp_path / 'run'}"])
    saved, _ = train_recipe._resume_cfg(cfg)
    assert saved.env.nthread == 1 and saved.env.num_worlds == 4  # moved machine; world count is the run's


def test_backward_edges_override_replaces_the_tasks_edges_and_names_bad_stages():
    default = _common.stage_graph(_cfg("train", TINY).curriculum)
    edges = "curriculum.backward_edges=[[gripper_ready,idle],[object_grabbed,idle],[released,object_placed]]"
    graph = _common.stage_graph(_cfg("train", [*TINY, edges]).curriculum)
    placed, on_goal = graph.stages.index("object_placed"), graph.stages.index("object_on_goal")
    assert (placed, on_goal) in default.backward_edges and (placed, on_goal) not in graph.backward_edges
    stage, cond = torch.tensor([placed]), torch.zeros(1, len(CONDITIONS), dtype=torch.bool)
    assert default.next_stage(stage, cond).item() == on_goal  # "placed" lost: back ...
    assert graph.next_stage(stage, cond).item() == placed  # ... or not, without the edge
    with pytest.raises(ValueError, match="'lifted'"):
        _common.stage_graph(_cfg("train", [*TINY, "curriculum.backward_edges=[[lifted,idle]]"]).curriculum)
