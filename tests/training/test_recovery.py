"""The recovery measurement (kinematic backend, a few seconds each): the box displacement
comes exactly once per episode, 10 steps after the first lift; the offsets keep clear of
the robots; the recipe writes both comparisons."""
from __future__ import annotations

import json
import math

import pytest
import torch

from pnp.task.scripted import ScriptedPnP
from pnp.distill.trainer import distill
from pnp.distill.config import register
from pnp.training.keys import OBS
from pnp.studies.recovery import BoxDisplacement, choose_offsets, dropout_config
from pnp.training.rollout import run_trials
from pnp.distill.student import FIELD_COLUMNS, make_student_env
from pnp.training.tasks import make_env
from tests.training._tiny import TINY, compose_cfg, tiny_train
from pnp.studies import student_recovery as recovery_recipe

register()


def test_the_box_is_displaced_once_per_episode_ten_steps_after_its_first_lift():
    cfg = compose_cfg("train", ["backend=kinematic", "env.num_worlds=4", "env.max_episode_steps=150"])
    env = make_env(cfg.env, cfg.curriculum, seed=5)
    script, hook = ScriptedPnP(4, 1), BoxDisplacement(4, seed=1)
    moves = []
    displace = env.base_env.displace_box

    def spy(worlds, offsets):  # every displacement the env receives
        moves.append((torch.as_tensor(worlds).tolist(), torch.as_tensor(offsets).clone()))
        displace(worlds, offsets)

    env.base_env.displace_box = spy

    def policy(td):
        script.reset(td["step_count"].view(-1) == 0)
        return script(td)

    records = run_trials(env, policy, trials=4, hook=hook)
    assert hook.delay == 10
    moved = [r for r in records if r["displaced_step"] is not None]
    assert len(moved) >= 3, records  # the scripted policy lifts within 15 s
    for r in records:
        if r["lift_step"] is None:
            assert r["displaced_step"] is None and r["stage_history"] == [] and not r["regrasped"]
        elif r["displaced_step"] is not None:
            assert r["displaced_step"] == r["lift_step"] + 10 < r["steps"]
            assert 0.5 <= r["displacement_m"] <= 1.0 and r["clear"]
            assert r["stage_history"][0] == [0, r["stage_at_displacement"]] and r["stage_at_displacement"] >= 3
    # exactly once per episode, and each event is the trial's own
    episodes = [(w, k) for w, k, _ in hook.events]
    assert len(episodes) == len(set(episodes)) == sum(len(m[0]) for m in moves)
    for r in moved:
        assert (r["world"], r["episode"], r["displaced_step"]) in hook.events
    for _, offsets in moves:
        assert all(0.5 <= float(o.norm()) <= 1.0 for o in offsets)


def test_offsets_keep_clear_of_the_bases_or_take_the_clearest():
    u = torch.rand(2, 32, 2, generator=torch.Generator().manual_seed(0))
    box, half = torch.zeros(2, 2), torch.tensor([[0.2, 0.1]]).expand(2, 2)
    bases = torch.tensor([[[0.8, 0.0]], [[0.0, 0.9]]])
    offsets, clear = choose_offsets(u, box, torch.zeros(2), half, bases, (0.5, 1.0), 0.59)
    assert clear.all() and ((offsets.norm(dim=-1) >= 0.5) & (offsets.norm(dim=-1) <= 1.0)).all()
    for m in range(2):  # the moved footprint (axis-aligned here) is 0.59 m from the base
        d = (bases[m, 0] - offsets[m]).abs() - half[m]
        assert float(d.clamp(min=0).norm()) >= 0.59
    # 2 m cannot be kept: the candidate farthest from the base is taken
    far, clear = choose_offsets(u[:1], box[:1], torch.zeros(1), half[:1], bases[:1], (0.5, 1.0), 2.0)
    angle, radius = 2 * math.pi * u[0, :, 0], 0.5 + 0.5 * u[0, :, 1]
    candidates = radius.unsqueeze(-1) * torch.stack([torch.cos(angle), torch.sin(angle)], -1)
    gaps = ((bases[0, 0] - candidates).abs() - half[0]).clamp(min=0).norm(dim=-1)
    assert not clear[0] and torch.equal(far[0], candidates[gaps.argmax()])
    with pytest.raises(ValueError, match=r"distance must be \[lo, hi\].*got \[1.0, 0.5\]"):
        BoxDisplacement(2, 0, distance=(1.0, 0.5))


def test_dropout_settings_are_checked_and_only_change_the_dropouts():
    cfg = compose_cfg("distill", [*TINY, "student.recurrent_cells=0"])
    out = dropout_config(cfg, 0.05, 0.5, 2.0, ["object.box_pos", "object.box_x_axis"])
    assert out.noise.dropout.p == 0.05 and out.noise.dropout.fields == ["object.box_pos", "object.box_x_axis"]
    assert cfg.noise.dropout.p == 0.01 and out.noise.sigma == cfg.noise.sigma
    # every step starts a dropout: the object pose, handles_from_ee included, holds its reset value
    frozen = dropout_config(cfg, 1.0, 0.5, 0.5, ["object.box_pos", "object.box_x_axis", "object.box_y_axis",
                            "object.box_lin_vel", "object.box_ang_vel", "object.handles", "object.handles_from_ee"])
    td = make_student_env(frozen, 0, view="noisy").rollout(5)
    cols = slice(FIELD_COLUMNS["object.box_pos"][0], FIELD_COLUMNS["object.handles_from_ee"][1])
    seen = td["next", OBS][..., cols]
    assert torch.equal(seen, td[OBS][:, :1, ..., cols].expand_as(seen))
    assert not torch.equal(td["next", "agents", "object"][:, 1:, ..., :27], td["next", "agents", "object"][:, :-1, ..., :27])
    with pytest.raises(ValueError, match=r"dropout.p must be in \(0, 1\].*got 0"):
        dropout_config(cfg, 0, 0.5, 2.0, [])
    with pytest.raises(ValueError, match="min_s=2.0, max_s=0.5"):
        dropout_config(cfg, 0.1, 2.0, 0.5, [])


def test_recipe_writes_both_comparisons_and_the_provenance(tmp_path):
    tiny_train(tmp_path / "teacher", "total_iterations=1")
    distill(compose_cfg("distill", [*TINY, "student.recurrent_cells=0", f"distill.teacher={tmp_path / 'teacher'}", f"out_dir={tmp_path / 'run'}",
                                    "total_iterations=1"]))
    result = recovery_recipe.evaluate(compose_cfg("student_recovery", [
        f"checkpoint={tmp_path / 'run'}", "trials=4", "env.num_worlds=4", "env.max_episode_steps=8",
        f"out={tmp_path / 'recovery.json'}", "progress=false",
    ]))
    saved = json.loads((tmp_path / "recovery.json").read_text())
    assert sorted(saved["displacement"]) == ["student", "teacher_clean", "teacher_noisy"]
    assert sorted(saved["dropout"]) == ["student", "teacher_noisy"]
    for run in saved["displacement"].values():
        assert run["trials"] == 4 and len(run["records"]) == 4 and "regrasped" in run["records"][0]
        assert run["displaced"] + run["never_lifted"] <= 4 and "recovery_rate" in run
    for run in saved["dropout"].values():
        assert run["trials"] == 4 and "success_rate" in run
    assert saved["dropout_settings"]["p"] == 0.05 and saved["noise"]["dropout"]["p"] == 0.01  # the student's own
    assert saved["displacement_settings"]["clearance"] == pytest.approx(math.hypot(0.45, 0.2) + 0.1)
    for key in ("backend", "trials", "seed", "teacher", "checkpoint", "command", "commit", "machine", "wall_s"):
        assert key in saved, key
    assert saved["backend"] == "kinematic" and result["trials"] == 4
    assert (tmp_path / "recovery.md").read_text().startswith("| Policy | Success (%) | Displaced |")
