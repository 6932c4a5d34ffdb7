"""The seeds of one pipeline gathered: per seed, mean, worst, spread, goals, paired layouts."""
from __future__ import annotations

import json

import pytest
from omegaconf import OmegaConf

from pnp.studies.seeds import plot_seeds, seed_study, seeds_markdown
from pnp.training.protocol import REPORTING_SEED
from tests.training._tiny import compose_cfg


def _eval(folder, seed, solved, wall_s=9000.0, mujoco=20_000_000, empty=True, commits=("abc1234",), machines=()):
    folder.mkdir(parents=True)
    result = {"seed": REPORTING_SEED, "train_seed": seed, "trials": len(solved),
              "success_rate": sum(solved) / len(solved), "completion_time_mean_s": 10.0,
              "failure_causes": {"timeout": len(solved) - sum(solved)}, "train_wall_s": wall_s,
              "mujoco_frames": mujoco, "env_frames": mujoco + 10, "from_empty_folder": empty,
              "launch_commits": list(commits), "checkpoint": str(folder / "c.pt"), "checkpoint_iteration": 5,
              "pipeline_launches": [{"commit": commits[0], "machine": m} for m in machines],
              "phases": [{"name": "a"}], "trial_records": [[i, int(s), 50, None] for i, s in enumerate(solved)]}
    (folder / "eval_single_pnp.json").write_text(json.dumps(result))
    return folder


def _goals():
    cfg = compose_cfg("seed_study", ["runs=[a]"])  # the YAML's goals, through the schema
    return OmegaConf.to_container(cfg.goals)


def test_seeds_are_gathered_with_their_goals(tmp_path):
    runs = [_eval(tmp_path / "s1", 1, [1, 1, 0, 1]), _eval(tmp_path / "s0", 0, [1, 1, 1, 0], wall_s=12000.0)]
    result = seed_study(runs, "eval_single_pnp.json", _goals(), "cmd")
    assert list(result["seeds"]) == ["0", "1"] and result["commit"] == "abc1234"
    assert result["success_rate_mean"] == 0.75 and result["success_rate_worst"] == 0.75
    assert (result["trials_all_solved"], result["trials_none_solved"]) == (2, 0)
    goals = result["goals"]
    assert goals["mean_success"]["met"] is False and goals["max_train_wall_s"] == {"goal": 10800, "measured": 12000.0,
                                                                                  "met": False}
    assert goals["max_mujoco_frames"]["met"] and goals["from_empty_folders"]["met"] and goals["one_commit"]["met"]
    assert "NOT met (12000.0 against 10800.0)" in seeds_markdown(result, "t")
    plot_seeds(result, tmp_path / "s.png")
    assert (tmp_path / "s.png").stat().st_size > 0


def test_two_commits_an_unknown_folder_and_a_repeated_seed_are_said(tmp_path):
    runs = [_eval(tmp_path / "s0", 0, [1, 0], commits=("abc1234", "def5678")), _eval(tmp_path / "s1", 1, [1, 1], empty=None)]
    result = seed_study(runs, "eval_single_pnp.json", _goals(), "cmd")
    assert result["commit"] is None and not result["goals"]["one_commit"]["met"]
    assert not result["goals"]["from_empty_folders"]["met"]  # unknown is not met
    with pytest.raises(ValueError, match="both trained with seed 0"):
        seed_study([runs[0], _eval(tmp_path / "again", 0, [1, 1])], "eval_single_pnp.json", _goals(), "cmd")
    by_file = seed_study([runs[1] / "eval_single_pnp.json", runs[0]], "eval_single_pnp.json", _goals(), "cmd")
    assert by_file["seeds"]["1"]["eval_file"] == str(runs[1] / "eval_single_pnp.json")
    with pytest.raises(FileNotFoundError, match="no evaluation of this seed's run"):
        seed_study([tmp_path / "missing"], "eval_single_pnp.json", _goals(), "cmd")


def test_each_seed_names_the_machines_it_trained_on(tmp_path):
    runs = [_eval(tmp_path / "s0", 0, [1, 0], machines=("Intel Xeon", "AMD EPYC", "Intel Xeon")),
            _eval(tmp_path / "s1", 1, [1, 1])]  # a folder older than the launch records
    result = seed_study(runs, "eval_single_pnp.json", _goals(), "cmd")
    assert result["seeds"]["0"]["launch_machines"] == ["AMD EPYC", "Intel Xeon"]
    assert result["seeds"]["1"]["launch_machines"] is None
    table = seeds_markdown(result, "t")
    assert "| AMD EPYC + Intel Xeon |" in table and "| not recorded |" in table
