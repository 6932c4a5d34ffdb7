"""Pipelines: phases back to back with warm starts, exit rules and budgets, resumable."""
from __future__ import annotations

import json

import pytest
import torch
from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError

from pnp.training.checkpoint import load_checkpoint
from pnp.training.config import ExitRule
from pnp.training.pipeline import ExitCheck, load_launches, phase_config, phase_frames, run_pipeline, total_frames
from tests.training._tiny import TINY, compose_cfg
from pnp.training import evaluation as evaluate_recipe

def _budgets(near: int, far: int) -> str:
    return (f"++phases={{near: {{max_frames: {near}, overrides: {{env.start_range: [0.6, 1.5]}}}},"
            f"far: {{max_frames: {far}, overrides: {{env.num_worlds: 8, collect.frames_per_batch: 40}}}}}}")


PHASES = ["pipeline=[near,far]", _budgets(80, 120)]


def _cfg(out_dir, *extra):
    return compose_cfg("train", [*TINY, f"out_dir={out_dir}", *PHASES, *extra])


def test_phases_run_back_to_back_with_warm_starts(tmp_path):
    out = run_pipeline(_cfg(tmp_path / "run"))
    assert out["finished"] and [p["name"] for p in out["phases"]] == ["near", "far"]
    near, far = out["phases"]
    assert (near["iterations"], near["frames"], near["exit"]) == (2, 80, "budget")
    assert (far["iterations"], far["frames"], far["exit"]) == (3, 120, "budget")
    assert near["backend"] == far["backend"] == "kinematic"  # evaluations count MuJoCo's frames by it
    assert json.loads((tmp_path / "run" / "pipeline.json").read_text())["phases"] == out["phases"]
    run_pipeline(_cfg(tmp_path / "run"))  # finished: a second launch is recorded, on a folder not empty
    launches = load_launches(tmp_path / "run")
    assert [entry["folder_was_empty"] for entry in launches] == [True, False]
    assert all(entry["branch_from"] is None and "commit" in entry for entry in launches)
    rows = [json.loads(line) for line in (tmp_path / "run" / "pipeline_metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4, 5] and [r["phase"] for r in rows] == [0, 0, 1, 1, 1]
    for png in ("mean_end_stage.png", "stage_shares.png", "rho.png"):
        assert (tmp_path / "run" / png).stat().st_size > 0
    first, second = (load_checkpoint(tmp_path / "run" / d / "checkpoint.pt") for d in ("0_near", "1_far"))
    assert second["cfg"]["warm_start"].endswith("0_near/checkpoint.pt") and second["cfg"]["warm_start_curriculum"]
    assert second["cfg"]["env"]["num_worlds"] == 8 and first["cfg"]["env"]["start_range"] == [0.6, 1.5]
    rho1, rho2 = first["curriculum"]["transforms.2.rho"], second["curriculum"]["transforms.2.rho"]
    assert rho2.shape[0] == 8 and rho1.shape[0] == 4  # the curriculum carried over, resized
    # a rerun finds the pipeline finished and trains nothing
    assert run_pipeline(_cfg(tmp_path / "run"))["phases"] == out["phases"]


def test_a_pipeline_resumed_mid_phase_ends_as_one_run_straight_through(tmp_path):
    straight = run_pipeline(_cfg(tmp_path / "a"))
    # the same pipeline stopped by the wall-time limit after 1 iteration of its first phase, then resumed
    cut = run_pipeline(_cfg(tmp_path / "b", "max_wall_hours=0.0"))
    assert not cut["finished"] and cut["phases"] == []  # stopped in its first phase
    resumed = run_pipeline(_cfg(tmp_path / "b"))
    assert resumed["finished"]
    for d in ("0_near", "1_far"):
        a, b = (load_checkpoint(tmp_path / r / d / "checkpoint.pt") for r in ("a", "b"))
        for k in a["actor"]:
            assert torch.equal(a["actor"][k], b["actor"][k]), (d, k)
    assert [p["frames"] for p in straight["phases"]] == [p["frames"] for p in resumed["phases"]]


def test_a_phase_edited_after_its_start_is_refused_on_resume(tmp_path):
    cut = run_pipeline(_cfg(tmp_path / "run", "max_wall_hours=0.0"))
    assert not cut["finished"]
    # a resume runs the checkpoint's settings: the edit would be silently ignored
    edited = _cfg(tmp_path / "run", "loss.clip_epsilon=0.1")
    with pytest.raises(ValueError, match=r"phase 'near' .* started with other settings .*'loss.clip_epsilon': \(0.2, 0.1\)"):
        run_pipeline(edited)
    assert run_pipeline(_cfg(tmp_path / "run", "max_wall_hours=1.0"))["finished"]  # run-time keys may change


def test_a_raised_budget_trains_the_last_phase_on_as_if_it_had_been_set_from_the_start(tmp_path):
    straight = run_pipeline(_cfg(tmp_path / "a", _budgets(80, 200)))
    assert run_pipeline(_cfg(tmp_path / "b"))["phases"][-1]["iterations"] == 3  # ended by its budget of 120
    extended = run_pipeline(_cfg(tmp_path / "b", _budgets(80, 200)))
    assert extended["finished"]
    ends = [[(p["iterations"], p["frames"], p["exit"]) for p in r["phases"]] for r in (straight, extended)]
    assert ends[0] == ends[1] == [(2, 80, "budget"), (5, 200, "budget")]
    a, b = (load_checkpoint(tmp_path / r / "1_far" / "checkpoint.pt") for r in ("a", "b"))
    for k in a["actor"]:
        assert torch.equal(a["actor"][k], b["actor"][k]), k
    # an earlier phase's budget cannot grow: the later phases started from its end
    with pytest.raises(ValueError, match=r"phase 'near' ended by its budget at 2 iterations and its budget is now 3"):
        run_pipeline(_cfg(tmp_path / "b", _budgets(120, 200)))


def test_exit_rule_ends_a_phase_and_is_recorded(tmp_path):
    rule = "++phases={near: {max_frames: 80, exit: {metric: frames, min: 40, window: 1}}}"  # met at once
    out = run_pipeline(compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'run'}", "pipeline=[near]", rule]))
    assert out["phases"][0]["exit"] == "rule" and out["phases"][0]["iterations"] == 1


def test_a_phase_until_a_total_gets_the_frames_an_earlier_rule_left(tmp_path):
    # near (budget 120) ends by its rule after 1 iteration (40 frames); far runs to 200 frames in all
    phases = ("++phases={near: {max_frames: 120, exit: {metric: frames, min: 40, window: 1}},"
              "far: {until_total_frames: 200, overrides: {env.num_worlds: 8, collect.frames_per_batch: 40}}}")
    cfg = _cfg(tmp_path / "run", phases)
    assert [phase_frames(cfg, i) for i in (0, 1)] == [120, 80] and total_frames(cfg) == 200  # planned, rules aside
    out = run_pipeline(cfg)
    assert [(p["frames"], p["exit"]) for p in out["phases"]] == [(40, "rule"), (160, "budget")]
    assert phase_frames(cfg, 1, out["phases"]) == 160
    short = _cfg(tmp_path / "other", phases.replace("until_total_frames: 200", "until_total_frames: 120"))
    with pytest.raises(ValueError, match=r"phase 'far': until_total_frames=120 leaves nothing after the earlier "
                                         r"phases' 120 frames"):
        phase_frames(short, 1)


def test_the_progress_lines_count_a_phase_ended_by_its_rule_as_run(tmp_path, monkeypatch):
    import pnp.training.pipeline as pipeline

    seen = []

    class Recorded(pipeline.PipelineProgress):  # keeps what the pipeline told its progress lines
        def __init__(self, plans, enabled):
            super().__init__(plans, enabled)
            seen.append(self)
            self.iterations = 0

        def update(self, row):
            super().update(row)
            self.iterations += 1

    monkeypatch.setattr(pipeline, "PipelineProgress", Recorded)
    rule = "++phases={near: {max_frames: 120, exit: {metric: frames, min: 40, window: 1}}}"  # 1 of 3 iterations
    out = run_pipeline(_cfg(tmp_path / "run", rule))
    plans = seen[0].plans
    assert all(p.finished for p in plans) and seen[0].iterations == 1 + 3
    assert [p.frames for p in plans] == [p["frames"] for p in out["phases"]]
    run_pipeline(_cfg(tmp_path / "run", rule))  # finished: nothing runs, every phase counted as run
    assert seen[1].iterations == 0 and all(p.finished for p in seen[1].plans)
    assert [p.frames for p in seen[1].plans] == [p["frames"] for p in out["phases"]]
    # A phase until a total takes over the frames the rule left: its budget grows once near ends.
    until = rule.replace("}}}", "}}, far: {until_total_frames: 200, overrides: {env.num_worlds: 8}}}")
    out = run_pipeline(_cfg(tmp_path / "until", until))
    assert seen[2].plans[1].budget_frames == 200 - out["phases"][0]["frames"]
    assert seen[2].iterations == sum(p["iterations"] for p in out["phases"]) == 1 + 4


def test_exit_check_weights_by_episodes_and_names_unknown_metrics():
    rule = OmegaConf.structured(ExitRule(metric="success_rate", min=0.5, window=2))
    check = ExitCheck(rule, [{"episodes": 1, "success_rate": 1.0}])
    assert not check({"episodes": 3, "success_rate": 0.2})  # (1 + 0.6) / 4 = 0.4
    assert check({"episodes": 3, "success_rate": 0.8}) and check.reason == "rule"  # (0.6 + 2.4) / 6 = 0.5
    with pytest.raises(KeyError, match="'succes'"):
        ExitCheck(OmegaConf.structured(ExitRule(metric="succes", window=2)), [{"episodes": 1}] * 2).met()


def test_a_plateau_ends_a_phase_counted_from_its_best_window_also_after_a_resume():
    rule = OmegaConf.structured(ExitRule(metric="success_rate", min=0.9, window=1, plateau=3, min_delta=0.05))
    rows = [{"episodes": 1, "success_rate": v} for v in (0.1, 0.3, 0.34, 0.3, 0.32)]  # best 0.3 at row 2
    check = ExitCheck(rule, rows[:2])
    assert [check(r) for r in rows[2:]] == [False, False, True] and check.reason == "plateau"
    resumed = ExitCheck(rule, rows)  # the same rows replayed: the same best, so it ends at once
    assert resumed.met() and resumed.reason == "plateau"
    rising = ExitCheck(rule, rows[:4])
    assert not rising({"episodes": 1, "success_rate": 0.36}) and rising.best_at == 5  # 0.36 > 0.3 + 0.05: new best
    no_plateau = OmegaConf.structured(ExitRule(metric="success_rate", min=0.9, window=1))
    assert not ExitCheck(no_plateau, rows * 10).met()


def test_an_unknown_override_and_another_pipelines_folder_are_refused(tmp_path):
    bad = compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'x'}", "pipeline=[a]", "++phases={a: {overrides: {env.gravity: 1}}}"])
    with pytest.raises(ValueError, match="'env.gravity'"):
        run_pipeline(bad)
    undeclared = compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'x'}", "pipeline=[a,b]", "++phases={a: {}}"])
    with pytest.raises(ValueError, match=r"phases \['b'\] that `phases` does not declare"):
        run_pipeline(undeclared)
    run_pipeline(_cfg(tmp_path / "run"))
    other = compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'run'}", "pipeline=[other]", "++phases={other: {max_frames: 40}}"])
    with pytest.raises(ValueError, match="a different pipeline"):
        run_pipeline(other)
    changed = compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'run'}", PHASES[0], PHASES[1].replace("[0.6, 1.5]", "[0.6, 2.0]")])
    with pytest.raises(ValueError, match="finished phase 'near' ran with overrides"):
        run_pipeline(changed)


def test_a_branch_reuses_the_phases_declared_alike_and_trains_on_from_their_checkpoints(tmp_path):
    base = run_pipeline(_cfg(tmp_path / "a"))
    # the same near phase, another far phase: the branch keeps a's near and trains its own far
    far_b = PHASES[1].replace("collect.frames_per_batch: 40", "collect.frames_per_batch: 40, loss.entropy_coeff: 0.0")
    branch = compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'b'}", PHASES[0], far_b, f"branch_from={tmp_path / 'a'}"])
    out = run_pipeline(branch)
    near, far = out["phases"]
    assert near == base["phases"][0] and near["checkpoint"].startswith(str(tmp_path / "a"))
    assert far["checkpoint"].startswith(str(tmp_path / "b")) and far["overrides"]["loss.entropy_coeff"] == 0.0
    ckpt = load_checkpoint(tmp_path / "b" / "1_far" / "checkpoint.pt")
    assert ckpt["cfg"]["warm_start"] == near["checkpoint"] and ckpt["cfg"]["branch_from"] is None
    assert not (tmp_path / "b" / "0_near").exists()
    # rerun without branch_from: the record in b resumes as any pipeline's
    again = compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'b'}", PHASES[0], far_b])
    assert run_pipeline(again)["phases"] == out["phases"]
    unrelated = compose_cfg("train", [*TINY, f"out_dir={tmp_path / 'c'}", "pipeline=[other]",
                                      "++phases={other: {max_frames: 40}}", f"branch_from={tmp_path / 'a'}"])
    with pytest.raises(ValueError, match="no finished phase there is declared alike"):
        run_pipeline(unrelated)


def test_a_mapping_override_adds_keys_to_a_free_form_map_but_not_to_a_typed_node(tmp_path):
    gates = "++phases={a: {overrides: {curriculum.stage_gates: {object_to_goal_vel: 3}}}}"
    run_gate = "++curriculum.stage_gates.object_to_goal_dist=3"
    pcfg = phase_config(compose_cfg("train", [*TINY, f"out_dir={tmp_path}", "pipeline=[a]", run_gate, gates]), 0, None)
    assert dict(pcfg.curriculum.stage_gates) == {"object_to_goal_dist": 3, "object_to_goal_vel": 3}  # merged
    typed = compose_cfg("train", [*TINY, f"out_dir={tmp_path}", "pipeline=[a]",
                                  "++phases={a: {overrides: {env.kinematic: {widen_by: 0.1}}}}"])
    with pytest.raises(ConfigKeyError, match="widen_by"):  # the schema refuses it
        phase_config(typed, 0, None)


def test_a_phase_extends_another_phases_overrides_and_keeps_its_own_budget(tmp_path):
    phases = ("++phases={a: {max_frames: 40, overrides: {env.start_range: [0.6, 1.5], env.max_episode_steps: 7}},"
              "b: {extends: a, max_frames: 80, overrides: {env.max_episode_steps: 9}}}")
    cfg = compose_cfg("train", [*TINY, f"out_dir={tmp_path}", "pipeline=[a,b]", phases])
    pcfg = phase_config(cfg, 1, None)
    assert (list(pcfg.env.start_range), pcfg.env.max_episode_steps) == ([0.6, 1.5], 9)
    assert pcfg.total_iterations == 80 // cfg.collect.frames_per_batch
    for bad, match in (("{a: {extends: b}, b: {extends: a}}", "cycle: a -> b -> a"),
                       ("{a: {extends: nowhere}}", "extends 'nowhere'")):
        cfg = compose_cfg("train", [*TINY, f"out_dir={tmp_path}", "pipeline=[a]", f"++phases={bad}"])
        with pytest.raises(ValueError, match=match):
            phase_config(cfg, 0, None)


def test_evaluate_on_a_pipeline_folder_reports_every_phase(tmp_path):
    out = run_pipeline(_cfg(tmp_path / "run"))
    result = evaluate_recipe.evaluate(compose_cfg("evaluate", [
        f"checkpoint={tmp_path / 'run'}", "trials=4", "env.num_worlds=4", "env.max_episode_steps=5",
        f"out={tmp_path / 'eval.json'}", "progress=false"]))
    assert result["checkpoint"].endswith("1_far/checkpoint.pt") and result["from_scratch"]
    assert result["phases"] == out["phases"] and result["env_frames"] == 200
    assert result["mujoco_frames"] == 0  # both phases kinematic
    assert result["from_empty_folder"] and len(result["pipeline_launches"]) == 1 and len(result["launch_commits"]) == 1
    first = evaluate_recipe.evaluate(compose_cfg("evaluate", [
        f"checkpoint={tmp_path / 'run'}", "phase=near", "trials=4", "env.num_worlds=4", "env.max_episode_steps=5",
        f"out={tmp_path / 'eval_near.json'}", "progress=false"]))
    assert first["checkpoint"].endswith("0_near/checkpoint.pt") and first["phases"] == out["phases"][:1]
    with pytest.raises(ValueError, match="phase='mid' is not a finished phase"):
        evaluate_recipe.evaluate(compose_cfg("evaluate", [f"checkpoint={tmp_path / 'run'}", "phase=mid"]))


@pytest.mark.slow
def test_the_dual_pipeline_runs_through_every_phase(tmp_path):
    """One robot to two, kinematic to MuJoCo: warm starts, folding and rho resizing in one go."""
    cfg = compose_cfg("train", [*[t for t in TINY if not t.startswith("backend=")], "experiment=dual_pnp_pipeline",
                                f"out_dir={tmp_path / 'run'}", "env.nthread=1"])
    for name in cfg.pipeline:
        cfg.phases[name].max_frames = 40
    for key, value in {"env.num_worlds": 4, "collect.frames_per_batch": 40, "collect.minibatch_size": 20}.items():
        cfg.phases.pair_mujoco.overrides[key] = value
    out = run_pipeline(cfg)
    assert out["finished"] and [p["name"] for p in out["phases"]] == list(cfg.pipeline)
    last = load_checkpoint(tmp_path / "run" / "5_pair_mujoco" / "checkpoint.pt")
    assert last["cfg"]["env"]["num_robots"] == 2 and last["cfg"]["env"]["backend"] == "mujoco"
