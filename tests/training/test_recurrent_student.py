"""The recurrent student (``student.recurrent_cells``) on the kinematic backend: its GRU
state is carried from step to step and zeroed at episode starts, the PPO minibatches replay
it over whole segments to the same outputs, and a run resumes bit for bit and evaluates."""
from __future__ import annotations

import json

import pytest
import torch

from pnp.training.checkpoint import load_checkpoint
from pnp.training.collect import collect
from pnp.distill.trainer import distill
from pnp.distill.config import register
from pnp.training.keys import LOC, SCALE, STUDENT_OBS
from pnp.training.recurrent import HIDDEN, HIDDEN_NEXT, init_state
from pnp.distill.student import make_student_env, make_student_models
from tests.training._tiny import TINY, compose_cfg, tiny_train
from pnp.distill import evaluation as evaluate_recipe

register()
GRU = ["student.recurrent_cells=8", "task=dual_pnp"]


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    path = tmp_path_factory.mktemp("teacher")
    tiny_train(path, "total_iterations=1", "task=dual_pnp")
    return path


def _cfg(*extra):
    return compose_cfg("distill", [*TINY, *GRU, *extra])


def _models(cfg, env):
    return make_student_models(cfg.model, cfg.loss, env, recurrent_cells=int(cfg.student.recurrent_cells))


def test_the_state_is_carried_and_zeroed_at_an_episode_start():
    cfg = _cfg()
    env = make_student_env(cfg, 0)
    actor = _models(cfg, env).actor
    assert actor.in_keys[:2] == [STUDENT_OBS, HIDDEN]
    td = actor(init_state(env.reset(), actor))
    assert td[HIDDEN].shape == td[HIDDEN_NEXT].shape == (4, 2, 8) and not td[HIDDEN].any()
    later = td.clone().set(HIDDEN, torch.ones_like(td[HIDDEN])).set("step_count", torch.ones_like(td["step_count"]))
    assert not torch.equal(actor(later.clone())[LOC], td[LOC])  # the state reaches the output...
    later.set("step_count", torch.zeros_like(td["step_count"]))
    torch.testing.assert_close(actor(later)[LOC], td[LOC])  # ...except on an episode's first step


def test_segments_replay_the_collected_steps():
    """The update's forward over [N, T] segments (from the state stored at their first step,
    through episode restarts) gives the distribution the policy acted with."""
    cfg = _cfg("env.max_episode_steps=4")
    env = make_student_env(cfg, 0)
    actor = _models(cfg, env).actor
    carried = init_state(env.reset(), actor)
    _, carried = collect(env, actor, carried, 3)  # a segment that starts mid-episode, with a state
    batch, _ = collect(env, actor, carried, 7)
    assert batch[HIDDEN][:, 0].any() and (batch["step_count"] == 0).any()
    torch.testing.assert_close(batch[HIDDEN][:, 1:], batch[HIDDEN_NEXT][:, :-1])
    replay = actor(batch.select(STUDENT_OBS, HIDDEN, "step_count").clone())
    torch.testing.assert_close(replay[LOC], batch[LOC])
    torch.testing.assert_close(replay[SCALE], batch[SCALE])


def test_a_recurrent_student_resumes_bit_for_bit_and_evaluates(teacher, tmp_path):
    extra = [f"distill.teacher={teacher}", "env.max_episode_steps=5", "seed=3"]
    distill(_cfg(*extra, f"out_dir={tmp_path / 'straight'}", "total_iterations=3"))
    distill(_cfg(*extra, f"out_dir={tmp_path / 'split'}", "total_iterations=2"))
    distill(_cfg(*extra, f"out_dir={tmp_path / 'split'}", "total_iterations=3"))
    a, b = (load_checkpoint(tmp_path / run / "checkpoint.pt") for run in ("straight", "split"))
    assert any("gru" in k for k in a["actor"])
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k
    assert (a["carried"] == b["carried"]).all() and a["carried"][HIDDEN].any()
    evaluate_recipe.evaluate(compose_cfg("evaluate_student", [
        f"checkpoint={tmp_path / 'straight'}", "trials=4", "env.num_worlds=2", "env.max_episode_steps=8",
        f"out={tmp_path / 'eval.json'}", "progress=false"]))
    assert json.loads((tmp_path / "eval.json").read_text())["student"]["trials"] == 4


def test_the_gru_state_can_be_trained_to_tell_the_stage(teacher, tmp_path):
    distill(_cfg(f"distill.teacher={teacher}", f"out_dir={tmp_path}", "total_iterations=2",
                 "student.stage_loss_coeff=0.5"))
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert all(r["train/loss_stage"] > 0 and 0 <= r["train/stage_accuracy"] <= 1 for r in rows)
    assert "stage_head.weight" in "".join(load_checkpoint(tmp_path / "checkpoint.pt")["actor"])
    cfg = _cfg()
    with pytest.raises(ValueError, match="needs student.recurrent_cells > 0"):
        make_student_models(cfg.model, cfg.loss, make_student_env(cfg, 0), stage_loss_coeff=0.5)


def test_roll_ins_and_the_stage_input_are_refused_with_a_gru(teacher, tmp_path):
    with pytest.raises(ValueError, match="roll_in_share=0.5"):
        distill(_cfg(f"distill.teacher={teacher}", f"out_dir={tmp_path}", "total_iterations=1",
                     "collect.roll_in_share=0.5"))
    cfg = _cfg()
    with pytest.raises(ValueError, match="pick one"):
        make_student_models(cfg.model, cfg.loss, make_student_env(cfg, 0), sees_stage=True, recurrent_cells=8)
