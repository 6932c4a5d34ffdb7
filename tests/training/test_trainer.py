"""The trainer end to end on the kinematic backend (a few seconds each): metrics, plots,
checkpoints, bit-for-bit resume, warm starts, roll-ins and desynchronised episodes."""
from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Composite, Unbounded

from pnp.training.checkpoint import adapt_curriculum, load_checkpoint, load_module
from pnp.training.collect import MeanRollIn, collect, desync_episodes
from pnp.training.keys import ACTION, ROLL_IN
from pnp.training.models import AgentNet, dist_from_params, make_models
from pnp.training.ppo import ppo_update
from pnp.training.tasks import make_env
from pnp.training.checkpoint import conform_to_spec
from pnp.training.trainer import make_loss, resume_config
from tests.training._tiny import TINY, compose_cfg, tiny_train


def _rows(run) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_train_writes_metrics_plots_and_a_full_checkpoint(tmp_path):
    run = tmp_path / "run"
    out = tiny_train(run, "total_iterations=3")
    assert out["iteration"] == 3 and out["frames"] == 3 * 40
    ckpt = load_checkpoint(run / "checkpoint.pt")
    assert {"actor", "critic", "optim", "curriculum", "env", "carried", "rng", "counters", "cfg"} <= set(ckpt)
    rows = _rows(run)
    assert [r["iteration"] for r in rows] == [1, 2, 3]
    for key in ("success_rate", "mean_end_stage", "stage_share/S0", "rho/gripper_ready_pose", "train/loss_objective",
                "train/loss_critic", "train/kl", "train/lr", "frames", "wall_s"):
        assert key in rows[-1], key
    for png in ("mean_end_stage.png", "stage_shares.png", "success_rate.png", "rho.png"):
        assert (run / png).stat().st_size > 0
    assert any(run.glob("**/scalars/mean_end_stage.csv"))  # the csv logger's files


@pytest.mark.parametrize("roll_in", [[], ["collect.roll_in_share=0.5", "collect.roll_in_max_steps=3"]])
def test_resume_is_bit_for_bit(tmp_path, roll_in):
    extra = ["env.max_episode_steps=5", "seed=3", *roll_in]
    tiny_train(tmp_path / "straight", "total_iterations=4", *extra)
    tiny_train(tmp_path / "split", "total_iterations=2", *extra)
    tiny_train(tmp_path / "other", "total_iterations=4", "resume=" + str(tmp_path / "split"), *extra)  # ignored out_dir
    a = load_checkpoint(tmp_path / "straight" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "split" / "checkpoint.pt")
    assert a["counters"]["iteration"] == b["counters"]["iteration"] == 4
    for part in ("actor", "critic", "curriculum"):
        assert a[part].keys() == b[part].keys()
        for k in a[part]:
            assert torch.equal(a[part][k], b[part][k]), (part, k)
    for k, v in a["env"].items():
        assert torch.equal(v, b["env"][k]), k
    assert (a["carried"] == b["carried"]).all()
    strip = lambda run: [{k: v for k, v in r.items() if k != "wall_s"} for r in _rows(tmp_path / run)]  # noqa: E731
    assert json.dumps(strip("straight")) == json.dumps(strip("split"))
    # The split run records both its launches (command, commit, machine), the straight one its one.
    assert len(a["launches"]) == 1 and len(b["launches"]) == 2
    assert {"command", "commit", "machine", "date_utc"} <= set(b["launches"][1])


def test_snapshots_are_the_checkpoints_of_their_iterations(tmp_path):
    tiny_train(tmp_path / "snap", "total_iterations=4", "snapshot_every=2", "seed=5")
    tiny_train(tmp_path / "two", "total_iterations=2", "seed=5")
    snaps = sorted(p.name for p in (tmp_path / "snap" / "snapshots").iterdir())
    assert snaps == ["iteration_000002.pt", "iteration_000004.pt"]
    a = load_checkpoint(tmp_path / "snap" / "snapshots" / snaps[0])
    b = load_checkpoint(tmp_path / "two" / "checkpoint.pt")
    assert a["counters"]["iteration"] == 2
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k


def test_resume_takes_only_the_listed_keys_from_the_command_line(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=1", "env.nthread=2")
    cfg = compose_cfg("train", [*TINY, "env.nthread=1", "env.num_worlds=8", "snapshot_every=50",
                                f"resume={tmp_path / 'run'}"])
    saved, _ = resume_config(cfg)
    assert saved.env.nthread == 1 and saved.env.num_worlds == 4  # moved machine; world count is the run's
    assert saved.snapshot_every == 50


def test_warm_start_copies_weights_adam_and_optionally_the_curriculum(tmp_path):
    tiny_train(tmp_path / "src", "total_iterations=2")
    tiny_train(tmp_path / "dst", "total_iterations=0", f"warm_start={tmp_path / 'src'}", "seed=1",
               "warm_start_curriculum=true")
    a, b = load_checkpoint(tmp_path / "src" / "checkpoint.pt"), load_checkpoint(tmp_path / "dst" / "checkpoint.pt")
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k
    assert a["optim"]["param_groups"][0]["lr"] == b["optim"]["param_groups"][0]["lr"]
    assert torch.equal(a["optim"]["state"][0]["exp_avg"], b["optim"]["state"][0]["exp_avg"])
    rho_a, rho_b = a["curriculum"]["transforms.2.rho"], b["curriculum"]["transforms.2.rho"]
    assert torch.equal(rho_a, rho_b) and not (rho_a == 0.1).all()


def test_a_warm_start_at_a_fixed_lr_runs_at_that_lr_not_the_carried_one(tmp_path):
    # A branched phase with optim.lr_schedule=fixed once ran at the adapted lr it carried (1e-5, asked 1e-4).
    tiny_train(tmp_path / "src", "total_iterations=2", "optim.lr=3e-4")
    tiny_train(tmp_path / "dst", "total_iterations=1", f"warm_start={tmp_path / 'src'}",
               "optim.lr_schedule=fixed", "optim.lr=1e-4")
    carried = load_checkpoint(tmp_path / "src" / "checkpoint.pt")["optim"]["param_groups"][0]["lr"]
    lr = load_checkpoint(tmp_path / "dst" / "checkpoint.pt")["optim"]["param_groups"][0]["lr"]
    assert carried != 1e-4 and lr == 1e-4
    rows = [json.loads(line) for line in (tmp_path / "dst" / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["train/lr"] == 1e-4


def test_start_final_puts_every_warm_started_slot_in_the_final_stage(tmp_path):
    tiny_train(tmp_path / "src", "total_iterations=2")
    tiny_train(tmp_path / "dst", "total_iterations=0", f"warm_start={tmp_path / 'src'}", "warm_start_curriculum=true",
               "curriculum.start_final=true")
    cur = load_checkpoint(tmp_path / "dst" / "checkpoint.pt")["curriculum"]
    assert cur["transforms.2.in_final"].all()
    assert not load_checkpoint(tmp_path / "src" / "checkpoint.pt")["curriculum"]["transforms.2.in_final"].all()
    with pytest.raises(ValueError, match="liu_max"):
        tiny_train(tmp_path / "liu", "total_iterations=0", "curriculum.schedule=liu_max", "curriculum.start_final=true")


def test_single_robot_checkpoint_warm_starts_the_dual_task(tmp_path):
    tiny_train(tmp_path / "one", "total_iterations=2")
    tiny_train(tmp_path / "two", "total_iterations=0", "task=dual_pnp", f"warm_start={tmp_path / 'one'}",
               "warm_start_curriculum=true", "env.num_worlds=3")
    a, b = load_checkpoint(tmp_path / "one" / "checkpoint.pt"), load_checkpoint(tmp_path / "two" / "checkpoint.pt")
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k
    w1, w2 = a["critic"]["module.mlp.params.0.weight"], b["critic"]["module.mlp.params.0.weight"]
    assert w2.shape[-1] == 2 * w1.shape[-1]
    assert torch.equal(w2[..., : w1.shape[-1]], w1) and not w2[..., w1.shape[-1]:].any()
    rho1, rho2 = a["curriculum"]["transforms.2.rho"], b["curriculum"]["transforms.2.rho"]
    assert rho2.shape == (3, 2, rho1.shape[-1]) and torch.equal(rho2[:, 1], rho1[:3, 0])
    # the widened critic values each robot as the single-robot critic valued it alone
    nets = []
    for task, state in (("single_pnp", a["critic"]), ("dual_pnp", b["critic"])):
        cfg = compose_cfg("train", [*TINY, f"task={task}"])
        critic = make_models(cfg.model, cfg.loss, make_env(cfg.env, cfg.curriculum, 0)).critic
        critic.load_state_dict(state)
        nets.append(critic.module)
    obs, stage = torch.randn(4, 2, 74), torch.eye(7)[torch.randint(0, 7, (4, 2))]
    alone = nets[0](obs.reshape(8, 1, 74), stage.reshape(8, 1, 7)).reshape(4, 2, 1)
    torch.testing.assert_close(nets[1](obs, stage), alone)


def test_widening_anything_but_the_first_layer_is_refused():
    net = AgentNet(5, 1, 1, False, [8])
    with pytest.raises(ValueError, match="only the critic's first layer may widen"):
        load_module(net, AgentNet(5, 1, 1, False, [16]).state_dict())


def test_adapt_curriculum_reuses_worlds_cyclically():
    state = {"rho": torch.arange(6.0).reshape(3, 1, 2), "hist": torch.arange(7)}
    out = adapt_curriculum(state, 5, 1)
    assert out["rho"][:, 0, 0].tolist() == [0, 2, 4, 0, 2] and torch.equal(out["hist"], state["hist"])
    with pytest.raises(ValueError, match="2 robots"):
        adapt_curriculum({"rho": torch.zeros(3, 2, 2)}, 3, 1)


def test_peak_reading_logs_the_final_stage_too(tmp_path):
    tiny_train(tmp_path / "run", "total_iterations=2", "curriculum.episode_stage=peak")
    ended = [r for r in _rows(tmp_path / "run") if r["episodes"] > 0]
    assert ended and all(r["mean_final_stage"] <= r["mean_end_stage"] for r in ended)
    assert all(abs(sum(r[f"final_stage_share/S{i}"] for i in range(7)) - 1) < 1e-6 for r in ended)


def _tiny_models(*extra):
    cfg = compose_cfg("train", [*TINY, *extra])
    env = make_env(cfg.env, cfg.curriculum, 0)
    return cfg, env, make_models(cfg.model, cfg.loss, env)


def test_roll_in_takes_the_mean_then_samples_and_stays_out_of_the_loss(tmp_path):
    cfg, env, models = _tiny_models("env.max_episode_steps=4")
    roll_in = MeanRollIn(4, share=1.0, max_steps=2)
    batch, _ = collect(env, models.actor, env.reset(), 8, roll_in)  # two 4-step episodes per world
    count = batch["step_count"].squeeze(-1)  # [N, T] steps taken before each action
    flag = batch[ROLL_IN].squeeze(-1)
    assert flag.any() and (~flag).any()
    # share 1: every episode rolls in for 1-2 steps, so its first step is always a mean action
    assert flag[count == 0].all() and not flag[count >= 2].any()
    mean = dist_from_params(models.actor, batch).deterministic_sample
    act = batch[ACTION]
    torch.testing.assert_close(act[flag], mean[flag])
    assert not torch.allclose(act[~flag][..., :7], mean[~flag][..., :7])  # drawn
    # All roll-in: nothing is left to train on, so the actor does not move.
    loss = make_loss(cfg.loss, models)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
    before = [p.clone() for p in models.actor.parameters()]
    batch[ROLL_IN] = torch.ones_like(batch[ROLL_IN])
    ppo_update(batch, loss, optim, cfg)
    assert all(torch.equal(p, q) for p, q in zip(before, models.actor.parameters()))
    with pytest.raises(ValueError, match="roll_in_share"):
        MeanRollIn(4, share=1.5, max_steps=2)
    tiny_train(tmp_path / "run", "total_iterations=1", "collect.roll_in_share=1.0", "collect.roll_in_max_steps=2")
    assert 0.0 < _rows(tmp_path / "run")[-1]["roll_in_frames"] < 1.0


def test_desync_episodes_spreads_the_first_episode_ends():
    cfg, env, models = _tiny_models("env.num_worlds=16", "env.max_episode_steps=6")
    torch.manual_seed(0)
    carried = desync_episodes(env.reset(), 6)
    off = carried["step_count"].reshape(-1).clone()
    assert 0 <= int(off.min()) and int(off.max()) < 6 and len(off.unique()) > 2
    batch, _ = collect(env, models.actor, carried, 6)
    first_end = batch["next", "done"].reshape(16, 6).float().argmax(1)  # step index of each world's first end
    assert torch.equal(first_end, 5 - off)
    with pytest.raises(ValueError, match="max_episode_steps"):
        desync_episodes(env.reset(), None)


def test_a_step_with_a_non_finite_gradient_is_skipped_and_an_iteration_of_them_is_an_error():
    cfg, env, models = _tiny_models("env.max_episode_steps=4")
    batch, _ = collect(env, models.actor, env.reset(), 8)
    loss = make_loss(cfg.loss, models)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
    param = next(models.actor.parameters())
    calls = []

    def poison_first(grad):  # a saturated log-probability's gradient, once
        calls.append(1)
        return grad * float("nan") if len(calls) == 1 else grad

    hook = param.register_hook(poison_first)
    out = ppo_update(batch, loss, optim, cfg)
    assert out["train/skipped_steps"] == 1 and len(calls) > 1 and math.isfinite(out["train/grad_norm"])
    assert all(torch.isfinite(p).all() for p in loss.parameters())
    hook.remove()
    param.register_hook(lambda grad: grad * float("nan"))
    before = [p.clone() for p in models.actor.parameters()]  # (PopArt rescales the critic's head anyway)
    with pytest.raises(FloatingPointError, match=r"every one of this iteration's \d+ PPO steps had a non-finite") as err:
        ppo_update(batch, loss, optim, cfg)
    named = str(err.value).split("(first in [")[1].split("]")[0].split(", ")
    assert len(named) == 1 and named[0].endswith("0.weight'")  # the poisoned one alone, named before clipping spreads NaN
    assert all(torch.equal(p, q) for p, q in zip(before, models.actor.parameters()))


def test_a_resumed_carried_step_takes_the_shape_of_an_observation_entry_that_grew():
    agents = Composite(reward_terms=Unbounded(shape=(4, 1, 17)), observation=Unbounded(shape=(4, 1, 3)), shape=(4, 1))
    spec = Composite(agents=agents, shape=(4,))
    carried = TensorDict({"agents": TensorDict({"reward_terms": torch.ones(4, 1, 16), "observation": torch.ones(4, 1, 3)},
                                               [4, 1])}, [4])
    assert conform_to_spec(carried, spec) == [("agents", "reward_terms")]
    assert carried["agents", "reward_terms"].shape == (4, 1, 17) and not carried["agents", "reward_terms"].any()
    assert carried["agents", "observation"].eq(1).all()  # the entries that still fit are kept
