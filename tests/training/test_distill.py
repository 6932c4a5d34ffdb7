"""Teacher-student distillation on the kinematic backend (a few seconds each): the student's
observation, the teacher's labels, a run that checkpoints and resumes bit for bit, the
configuration and its refusals, and the evaluation recipe. (beta = 0 giving the MAPPO
loss is tested with the loss, in tests/losses/test_distillation.py.)"""
from __future__ import annotations

import json

import pytest
import torch
from hydra.errors import ConfigCompositionException

from pnp.training.checkpoint import load_checkpoint
from pnp.training.collect import collect
from pnp.training.migration import migrate
from pnp.distill.trainer import beta_at, distill
from pnp.distill.config import register
from pnp.training.keys import LOC, OBS, SCALE, STAGE_ONE_HOT, STUDENT_OBS, TEACHER_LOC, TEACHER_SCALE
from pnp.training.rollout import load_policy
from pnp.distill.student import FIELD_COLUMNS, Teacher, check_teacher, make_student_env, make_student_models
from tests.training._tiny import ROOT, TINY, compose_cfg, tiny_train
from pnp.distill import evaluation as evaluate_recipe

register()
DROPPED = ("ego.arm_q", "ego.ee_pos", "ego.ee_yaw_sincos", "object.handles_from_ee")  # the default drop_fields
ARM_Q = slice(*FIELD_COLUMNS["ego.arm_q"])


def _cols(*names) -> list[int]:
    return [c for n in names for c in range(*FIELD_COLUMNS[n])]


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    path = tmp_path_factory.mktemp("teacher")
    tiny_train(path, "total_iterations=1")
    return path


def _cfg(teacher=None, *extra):
    return compose_cfg("distill", [*TINY, "student.recurrent_cells=0", *([f"distill.teacher={teacher}"] if teacher else []), *extra])


def _rows(run) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("task", ["single_pnp", "dual_pnp"])
def test_student_observation_drops_the_ee_pose_for_an_arm_history_and_has_no_stage(task):
    env = make_student_env(_cfg(None, f"task={task}"), 0)
    kept = [c for c in range(74) if c not in _cols(*DROPPED)]
    assert env.observation_spec[STUDENT_OBS].shape[-1] == len(kept) + 5 * 6 == 87
    assert make_student_models(_cfg().model, _cfg().loss, env).actor.in_keys == [STUDENT_OBS]  # no stage, no clean obs
    td = env.rollout(4)
    clean, seen = td["next", OBS], td["next", STUDENT_OBS]
    assert torch.equal(td["next", "agents", "ego"], clean[..., :31])  # OBS stays the teacher's clean one
    exact = [kept.index(c) for c in _cols("ego.pad_touch", "ego.last_action")]
    assert torch.equal(seen[..., exact], clean[..., _cols("ego.pad_touch", "ego.last_action")])
    noisy = [kept.index(c) for c in _cols("goal.goal_xy", "object.box_pos")]
    assert (seen[..., noisy] != clean[..., _cols("goal.goal_xy", "object.box_pos")]).all()
    neighbour = seen[..., [kept.index(c) for c in range(64, 74)]]
    if task == "single_pnp":  # no neighbour: its block stays exactly zero
        assert not neighbour.any()
    history = seen[..., len(kept):].unflatten(-1, (5, 6))
    assert torch.equal(history[..., 1, :], td[STUDENT_OBS][..., len(kept):len(kept) + 6])  # shifts by one step
    assert (history[..., 0, :] - clean[..., ARM_Q]).abs().max() < 0.1  # noisy arm joints (sigma 0.01 rad)


def test_a_diagnostic_student_can_be_given_the_stage():
    cfg = _cfg(None, "task=dual_pnp", "student.sees_stage=true")
    env = make_student_env(cfg, 0)
    actor = make_student_models(cfg.model, cfg.loss, env, sees_stage=True).actor
    assert actor.in_keys == [STUDENT_OBS, STAGE_ONE_HOT]
    td = actor(env.reset())
    stage_only = td.clone().set(STAGE_ONE_HOT, torch.roll(td[STAGE_ONE_HOT], 1, -1))
    assert not torch.equal(actor(stage_only)[LOC], td[LOC])  # the stage reaches the output


def test_without_noise_the_student_sees_the_clean_columns_and_their_history():
    env = make_student_env(_cfg(None, "noise.scale=0", "noise.dropout.p=0"), 0)
    td = env.rollout(4)
    kept = [c for c in range(74) if c not in _cols(*DROPPED)]
    seen, clean = td["next", STUDENT_OBS], td["next", OBS]
    assert torch.equal(seen[..., : len(kept)], clean[..., kept])
    history = seen[..., len(kept):].unflatten(-1, (5, 6))
    assert torch.equal(history[..., 0, :], clean[..., ARM_Q]) and torch.equal(history[..., 1, :], td[OBS][..., ARM_Q])


def test_the_noisy_teacher_view_adds_the_same_noise_in_place():
    env = make_student_env(_cfg(), 0, view="noisy")
    td = env.rollout(3)
    obs, goal = td["next", OBS], td["next", "agents", "goal"]  # the named blocks stay clean
    assert (obs[..., 31:34] != goal).all() and (obs[..., 31:34] - goal).abs().max() < 0.2
    assert STUDENT_OBS not in td["next"].keys(True)


def test_teacher_labels_are_its_actor_on_the_clean_observation_and_stage(teacher):
    cfg = _cfg(teacher)
    env = make_student_env(cfg, 0)
    labeller = Teacher(cfg, env)
    student = make_student_models(cfg.model, cfg.loss, env)
    batch, _ = collect(env, student.actor, env.reset(), 3)
    labeller.label(batch)
    reference = load_policy(teacher / "checkpoint.pt", 4, 0).actor  # loaded the evaluation's way
    ref = reference(batch.select(OBS, STAGE_ONE_HOT).clone())
    torch.testing.assert_close(batch[TEACHER_LOC], ref[LOC], rtol=0, atol=0)
    torch.testing.assert_close(batch[TEACHER_SCALE], ref[SCALE], rtol=0, atol=0)
    assert not torch.allclose(batch[TEACHER_LOC], batch[LOC])  # the student's own parameters are untouched
    assert not any(p.requires_grad for p in labeller.actor.parameters())


def test_distillation_checkpoints_and_resumes_bit_for_bit(teacher, tmp_path):
    extra = [f"distill.teacher={teacher}", "env.max_episode_steps=5", "seed=3", "collect.roll_in_share=0.5",
             "collect.roll_in_max_steps=3", "noise.dropout.p=0.3"]
    distill(compose_cfg("distill", [*TINY, "student.recurrent_cells=0", *extra, f"out_dir={tmp_path / 'straight'}", "total_iterations=3"]))
    distill(compose_cfg("distill", [*TINY, "student.recurrent_cells=0", *extra, f"out_dir={tmp_path / 'split'}", "total_iterations=2"]))
    assert load_checkpoint(tmp_path / "split" / "checkpoint.pt")["counters"]["iteration"] == 2
    # same folder: resumes; an edit outside the trainer's resume overrides would be ignored, so it is refused
    with pytest.raises(ValueError, match=r"started with other settings .*'distill.beta': \(1.0, 5.0\)"):
        distill(compose_cfg("distill", [*TINY, "student.recurrent_cells=0", *extra, f"out_dir={tmp_path / 'split'}", "total_iterations=3",
                                        "distill.beta=5"]))
    distill(compose_cfg("distill", [*TINY, "student.recurrent_cells=0", *extra, f"out_dir={tmp_path / 'split'}", "total_iterations=3"]))
    a, b = (load_checkpoint(tmp_path / run / "checkpoint.pt") for run in ("straight", "split"))
    assert a["counters"]["iteration"] == b["counters"]["iteration"] == 3
    assert "transforms.3.held" in a["curriculum"] and "transforms.4.history" in a["curriculum"]  # noise, history
    for part in ("actor", "critic", "env"):
        for k in a[part]:
            assert torch.equal(a[part][k], b[part][k]), (part, k)
    assert (a["carried"] == b["carried"]).all()
    # the split run records both its launches; the refused one never opened the run
    assert len(a["launches"]) == 1 and len(b["launches"]) == 2
    assert (tmp_path / "split" / "student_kinematic_1r_s3").is_dir()  # the student's own log name
    strip = lambda run: [{k: v for k, v in r.items() if k != "wall_s"} for r in _rows(tmp_path / run)]  # noqa: E731
    assert json.dumps(strip("straight")) == json.dumps(strip("split"))
    row = _rows(tmp_path / "split")[-1]
    assert row["beta"] == 1.0 and row["train/kl_teacher"] > 0 and "success_rate" in row and "train/loss_distill" in row


def test_the_critic_starts_as_the_teachers(teacher, tmp_path):
    distill(_cfg(teacher, f"out_dir={tmp_path}", "total_iterations=0"))
    student, source = load_checkpoint(tmp_path / "checkpoint.pt"), load_checkpoint(teacher / "checkpoint.pt")
    for k, v in source["critic"].items():
        assert torch.equal(student["critic"][k], v), k


def test_a_student_warm_starts_from_a_students_actor(teacher, tmp_path):
    """warm_start moves a student to a new teacher or env (the legs): its actor, input statistics included."""
    distill(_cfg(teacher, f"out_dir={tmp_path / 'a'}", "total_iterations=1"))
    distill(_cfg(teacher, f"out_dir={tmp_path / 'b'}", "total_iterations=0", f"warm_start={tmp_path / 'a'}"))
    a, b = (load_checkpoint(tmp_path / run / "checkpoint.pt")["actor"] for run in ("a", "b"))
    assert a.keys() == b.keys() and any("obs_norm" in k for k in a)
    for k, v in a.items():
        assert torch.equal(b[k], v), k
    with pytest.raises(ValueError, match="holds a teacher"):
        distill(_cfg(teacher, f"out_dir={tmp_path / 'c'}", f"warm_start={teacher}"))
    with pytest.raises(ConfigCompositionException):  # a teacher's option: a student has no curriculum to carry
        _cfg(teacher, "warm_start_curriculum=true")


def test_beta_anneals_linearly_then_stays():
    kl = _cfg(None, "distill.beta=1.0", "distill.beta_final=0.2", "distill.anneal_iterations=4").distill
    assert [round(beta_at(kl, i), 6) for i in (0, 2, 4, 9)] == [1.0, 0.6, 0.2, 0.2]
    assert beta_at(_cfg().distill, 100) == 1.0


def test_unknown_keys_and_bad_settings_are_refused(teacher, tmp_path):
    for bad in ("distill.nonsense=1", "noise.dropout.rate=0.1", "student.history_length=many"):
        with pytest.raises(ConfigCompositionException):
            _cfg(teacher, bad)
    with pytest.raises(ValueError, match="unknown observation field 'ego.wrist'"):
        make_student_env(_cfg(None, "+noise.sigma.ego.wrist=0.1"), 0)
    with pytest.raises(ValueError, match="must be adjacent columns"):
        make_student_env(_cfg(None, "noise.dropout.fields=[object.box_pos,object.handles]"), 0)
    with pytest.raises(ValueError, match="env.num_robots=1, this run has env.num_robots=2"):
        distill(_cfg(teacher, "task=dual_pnp", f"out_dir={tmp_path / 'dual'}"))
    with pytest.raises(ValueError, match="curriculum.schedule must be 'fixed'"):
        distill(_cfg(teacher, "curriculum.schedule=dynamic", f"out_dir={tmp_path / 'dyn'}"))
    with pytest.raises(ValueError, match="distill.teacher is not set"):
        distill(_cfg(None, f"out_dir={tmp_path / 'none'}"))


@pytest.mark.parametrize("name", ["single", "dual", "single_legs", "dual_legs"])
def test_each_experiment_has_its_teachers_settings(name):
    cfg = compose_cfg("distill", [f"distill_experiment={name}"])
    saved = migrate(torch.load(ROOT / cfg.distill.teacher, weights_only=False, map_location="cpu")["cfg"])
    check_teacher(cfg, saved, cfg.distill.teacher)
    assert cfg.curriculum.schedule == "fixed"
    for group in ("env", "model", "loss"):
        mine, theirs = cfg[group].copy(), saved[group].copy()
        if group == "env":  # how many threads ran MuJoCo, not what it trained (RESUME_OVERRIDES)
            mine.nthread = theirs.nthread = None
        assert mine == theirs, group
    # A recurrent student collects without roll-ins (they cut the episodes its GRU needs whole).
    differs = {"roll_in_share"} if cfg.student.recurrent_cells else set()
    rest = lambda c: {k: v for k, v in c.items() if k not in differs}  # noqa: E731
    assert rest(cfg.collect) == rest(saved.collect)
    assert not differs or cfg.collect.roll_in_share == 0.0
    # the lr is fixed: the KL-adaptive one sat at its floor under the teacher's KL
    fixed = lambda optim: {k: v for k, v in optim.items() if k not in ("lr", "lr_schedule")}  # noqa: E731
    assert cfg.optim.lr_schedule == "fixed" and fixed(cfg.optim) == fixed(saved.optim)
    if cfg.warm_start:  # a student of the same shape
        source = torch.load(ROOT / cfg.warm_start, weights_only=False, map_location="cpu")["cfg"]
        assert "distill" in source and source["student"] == dict(cfg.student)


def test_evaluate_student_recipe_writes_all_three_runs_and_the_provenance(teacher, tmp_path):
    distill(_cfg(teacher, f"out_dir={tmp_path / 'run'}", "total_iterations=1"))
    result = evaluate_recipe.evaluate(compose_cfg("evaluate_student", [
        f"checkpoint={tmp_path / 'run'}", "trials=4", "env.num_worlds=4", "env.max_episode_steps=8",
        f"out={tmp_path / 'eval.json'}", "progress=false",
    ]))
    saved = json.loads((tmp_path / "eval.json").read_text())
    for run in ("student", "teacher_noisy", "teacher_clean"):
        assert saved[run]["trials"] == 4 and sum(saved[run]["failure_causes"].values()) <= 4, run
    for key in ("backend", "trials", "success_rate", "noise", "teacher", "command", "commit", "machine", "wall_s"):
        assert key in saved, key
    assert saved["success_rate"] == saved["student"]["success_rate"] and saved["backend"] == "kinematic"
    # Paired: each policy met trials 0..3 of the seed, and the comparisons count them.
    assert all([t[0] for t in saved["trial_records"][run]] == [0, 1, 2, 3] for run in saved["trial_records"])
    assert saved["paired"] is True and saved["comparisons"]["student_vs_teacher_clean"]["trials"] == 4
    assert result["trials"] == 4 and (tmp_path / "eval.md").read_text().startswith("| Policy |")


def test_evaluate_student_recipe_can_switch_the_noise_off(teacher, tmp_path):
    distill(_cfg(teacher, f"out_dir={tmp_path / 'run'}", "total_iterations=1"))
    args = [f"checkpoint={tmp_path / 'run'}", "trials=2", "env.num_worlds=2", "env.max_episode_steps=4",
            f"out={tmp_path / 'eval.json'}", "progress=false"]
    evaluate_recipe.evaluate(compose_cfg("evaluate_student", args + ["noise_scale=0", "dropout_p=0"]))
    saved = json.loads((tmp_path / "eval.json").read_text())
    assert saved["noise"]["scale"] == 0.0 and saved["noise"]["dropout"]["p"] == 0.0
    with pytest.raises(ValueError, match=r"probability must be in \[0, 1\], got 1.5"):
        evaluate_recipe.evaluate(compose_cfg("evaluate_student", args + ["dropout_p=1.5"]))
    with pytest.raises(ValueError, match="noise.scale=-1.0: must be >= 0"):
        evaluate_recipe.evaluate(compose_cfg("evaluate_student", args + ["noise_scale=-1"]))


def test_a_student_may_add_backward_edges_to_its_teachers_graph_but_not_drop_any():
    cfg = compose_cfg("distill", ["distill_experiment=dual"])
    saved = migrate(torch.load(ROOT / cfg.distill.teacher, weights_only=False, map_location="cpu")["cfg"])
    theirs = [list(e) for e in saved.curriculum.backward_edges]
    more = [*theirs, ["object_lifted", "object_grabbed"]]
    with pytest.raises(ValueError, match="distill.add_backward_edges=true allows"):
        check_teacher(compose_cfg("distill", ["distill_experiment=dual", f"curriculum.backward_edges={more}"]),
                      saved, cfg.distill.teacher)
    check_teacher(compose_cfg("distill", ["distill_experiment=dual", f"curriculum.backward_edges={more}",
                                          "distill.add_backward_edges=true"]), saved, cfg.distill.teacher)
    with pytest.raises(ValueError, match="its stage one-hot would differ"):  # dropping one is never allowed
        check_teacher(compose_cfg("distill", ["distill_experiment=dual", f"curriculum.backward_edges={theirs[1:]}",
                                              "distill.add_backward_edges=true"]), saved, cfg.distill.teacher)
