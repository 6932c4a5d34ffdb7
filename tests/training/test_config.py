"""The configuration schema: experiments compose, unknown keys are refused, old checkpoints
migrate, kinematic-only options are refused on MuJoCo."""
from __future__ import annotations

import pytest
import torch
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from pnp.sim.box import DUAL_ROBOT_BOXES
from pnp.task.terms import CONDITIONS
from pnp.distill.config import register as register_distill
from pnp.training.migration import changed_settings, migrate
from pnp.training.pipeline import phase_config
from pnp.training.rollout import load_policy
from pnp.training.tasks import TASKS, kinematic_options, make_env, stage_graph
from tests.training._tiny import ROOT, TINY, compose_cfg

EXPERIMENT_DIR = ROOT / "recipes" / "config" / "experiment"
EXPERIMENTS = sorted(p.relative_to(EXPERIMENT_DIR).with_suffix("").as_posix() for p in EXPERIMENT_DIR.rglob("*.yaml"))
QUOTED_CHECKPOINTS = ["results/train_single/checkpoint_mujoco.pt", "results/train_single/checkpoint_kinematic.pt",
                      "results/train_dual/dual_mj2/checkpoint.pt", "results/run18_single_pnp_checkpoint.pt",
                      "results/repro_dual_pnp_checkpoint.pt", "results/repro_dual_pnp_free_handles_checkpoint.pt"]


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_composes_and_builds_its_env(name):
    cfg = compose_cfg("train", [f"experiment={name}", "env.num_worlds=2", "out_dir=/nonexistent/run"])
    assert cfg.env.task in TASKS
    kinematic_options(cfg.env)  # kinematic options only where the backend is kinematic
    if cfg.warm_start is not None:
        assert (ROOT / cfg.warm_start).is_file(), cfg.warm_start
    if cfg.env.backend == "kinematic":
        make_env(cfg.env, cfg.curriculum, 0).close()
    for index in range(len(cfg.pipeline)):  # every phase's overrides name schema keys
        kinematic_options(phase_config(cfg, index, None).env)


def test_quoted_experiments_have_their_files():
    quoted = {"single_pnp_mujoco", "single_pnp_kinematic", "dual_pnp_mujoco", "ee_tracking_ablation"}
    assert quoted <= set(EXPERIMENTS)


def test_experiment_folder_holds_what_is_named():
    """experiment/ holds what README, RESULTS, the quoted rows, the Makefile or a recipe's
    config names (and what those build on); records of A/Bs live in experiment/archive/."""
    named = "".join((ROOT / f).read_text() for f in ("README.md", "RESULTS.md", "Makefile", "results/quoted.yaml",
                                                     "recipes/sweep.yaml", "recipes/config/ablation_ee.yaml",
                                                     "pnp/studies/table1.py"))
    top = [name for name in EXPERIMENTS if "/" not in name]
    parents = {line.strip()[2:] for name in top for line in (EXPERIMENT_DIR / f"{name}.yaml").read_text().splitlines()
               if line.startswith("  - ") and "_self_" not in line and "/" not in line}
    table1 = {name for name in top if name.startswith("table1_")}  # recipes/table1.py: experiment=table1_<method>
    unnamed = [name for name in top if name not in named and name not in parents | table1]
    assert not unnamed, f"move to experiment/archive/ or name them: {unnamed}"


def test_the_dual_experiment_matches_its_checkpoint():
    """experiment=dual_pnp_mujoco is the configuration results/train_dual/dual_mj2 trained with."""
    saved = migrate(torch.load(ROOT / QUOTED_CHECKPOINTS[2], weights_only=False, map_location="cpu")["cfg"])
    cfg = compose_cfg("train", ["experiment=dual_pnp_mujoco"])
    for group in ("env", "curriculum", "model", "loss", "optim", "collect"):
        mine, theirs = OmegaConf.to_container(cfg[group]), OmegaConf.to_container(saved[group])
        if group == "env":  # how many threads ran MuJoCo, not what it trained (RESUME_OVERRIDES)
            mine.pop("nthread"), theirs.pop("nthread")
        assert mine == theirs, group


def test_unknown_keys_and_bad_types_are_refused():
    with pytest.raises(ConfigCompositionException, match="lone_holder_pinned"):
        compose_cfg("train", ["env.lone_holder_pinned=true"])
    with pytest.raises(ConfigCompositionException, match="num_worlds"):
        compose_cfg("train", ["env.num_worlds=many"])


def test_kinematic_options_are_refused_on_mujoco():
    cfg = compose_cfg("train", ["backend=kinematic", "env.kinematic.grasp_holds=true"])
    assert kinematic_options(cfg.env) == {"grasp_holds": True}
    cfg.env.backend = "mujoco"
    with pytest.raises(ValueError, match=r"\['grasp_holds'\] apply to the kinematic backend only"):
        kinematic_options(cfg.env)
    cfg = compose_cfg("train", ["backend=kinematic", "env.finger_speed=1.0"])
    with pytest.raises(ValueError, match="env.finger_speed=1.0 applies to MuJoCo"):
        make_env(cfg.env, cfg.curriculum, 0)
    # Non-boolean options count where they leave their default.
    cfg = compose_cfg("train", ["backend=kinematic", "env.kinematic.grasp_dist=0.02"])
    assert kinematic_options(cfg.env) == {"grasp_dist": 0.02}
    cfg.env.backend = "mujoco"
    with pytest.raises(ValueError, match=r"\['grasp_dist'\]"):
        kinematic_options(cfg.env)


def test_migrate_maps_old_keys_and_refuses_retired_ones_that_did_something():
    old = {"env": {"backend": "kinematic", "box_blocks_base": True, "lone_holder_pinned": False},
           "loss": {"reach_coeff": 0.0}}
    cfg = migrate(old)
    assert cfg.env.kinematic.box_blocks_base and not cfg.env.kinematic.grasp_holds
    assert cfg.env.terminate_on_success and cfg.curriculum.episode_stage == "final"  # the code defaults of then
    with pytest.raises(ValueError, match="loss.reach_coeff=10.0"):
        migrate({"loss": {"reach_coeff": 10.0}})
    # a retired key inside a group, at its neutral value and not
    assert "slip" not in migrate({"env": {"backend": "kinematic", "kinematic": {"slip": False}}}).env.kinematic
    with pytest.raises(ValueError, match="env.kinematic.slip=True"):
        migrate({"env": {"backend": "kinematic", "kinematic": {"slip": True}}})


@pytest.mark.parametrize("path", QUOTED_CHECKPOINTS)
def test_quoted_checkpoints_load(path):
    pol = load_policy(ROOT / path, 2, seed=0, backend="kinematic")
    td = pol.actor(pol.env.reset())
    assert td["agents", "action"].shape == (2, pol.cfg.env.num_robots, 8)
    pol.env.close()


def test_fixed_weights_override_weights_the_named_term_and_rejects_unknown_names():
    cfg = compose_cfg("train", [*TINY, "+curriculum.fixed_weights.action_rate=-2.0"])
    assert make_env(cfg.env, cfg.curriculum, 0).transform[-1].fixed_weights["action_rate"] == -2.0
    bad = compose_cfg("train", [*TINY, "+curriculum.fixed_weights.ee_reach=-1"])
    with pytest.raises(ValueError, match="'ee_reach'"):
        make_env(bad.env, bad.curriculum, 0)


def test_stage_gates_silence_a_term_below_its_stage_and_reject_bad_entries():
    gate = "+curriculum.stage_gates.object_to_goal_vel=3"
    cfg = compose_cfg("train", [*TINY, "curriculum.schedule=fixed", gate])
    sched = make_env(cfg.env, cfg.curriculum, 0).transform[-1]
    assert sched.stage_gates == {"grab_action_in_range": 5, "object_to_goal_vel": 3}
    stage, still = torch.tensor([[2], [3]]), torch.zeros(2, 1, len(sched.term_names))
    moving = still.clone()
    moving[..., sched.term_names.index("object_to_goal_vel")] = 1.0  # the box moving to the goal
    paid = (sched._reward(moving, stage) - sched._reward(still, stage)).view(-1).tolist()
    assert paid == [0.0, sched.mu["object_to_goal_vel"]]
    for bad in ("+curriculum.stage_gates.ee_reach=3", "+curriculum.stage_gates.object_to_goal_vel=7"):
        with pytest.raises(ValueError, match="stage_gates"):
            c = compose_cfg("train", [*TINY, bad])
            make_env(c.env, c.curriculum, 0)


def test_env_boxes_picks_the_assets():
    cfg = compose_cfg("train", [*TINY, "env.boxes=dual"])
    assert make_env(cfg.env, cfg.curriculum, 0).base_env.box_assets == DUAL_ROBOT_BOXES
    bad = compose_cfg("train", [*TINY, "env.boxes=huge"])
    with pytest.raises(ValueError, match="'huge'"):
        make_env(bad.env, bad.curriculum, 0)


def test_backward_edges_override_replaces_the_tasks_edges_and_names_bad_stages():
    default = stage_graph(compose_cfg("train", TINY).curriculum)
    edges = "curriculum.backward_edges=[[gripper_ready,idle],[object_grabbed,idle],[released,object_placed]]"
    graph = stage_graph(compose_cfg("train", [*TINY, edges]).curriculum)
    placed, on_goal = graph.stages.index("object_placed"), graph.stages.index("object_on_goal")
    assert (placed, on_goal) in default.backward_edges and (placed, on_goal) not in graph.backward_edges
    stage, cond = torch.tensor([placed]), torch.zeros(1, len(CONDITIONS), dtype=torch.bool)
    assert default.next_stage(stage, cond).item() == on_goal  # "placed" lost: back ...
    assert graph.next_stage(stage, cond).item() == placed  # ... or not, without the edge
    with pytest.raises(ValueError, match="'lifted'"):
        stage_graph(compose_cfg("train", [*TINY, "curriculum.backward_edges=[[lifted,idle]]"]).curriculum)


def test_the_near_pipelines_mujoco_phase_is_mujoco_explore_on_near_starts():
    cfg = compose_cfg("train", ["experiment=archive/single_pnp_pipeline_near", "out_dir=/nonexistent/run"])
    near, explore = (phase_config(cfg, list(cfg.pipeline).index(n), None) for n in ("mujoco_near", "mujoco_explore"))
    differ = changed_settings(near, explore, {"out_dir", "total_iterations"})
    assert sorted(differ) == ["env.max_episode_steps", "env.start_range"]


@pytest.mark.parametrize("name", sorted(p.stem for p in (ROOT / "recipes" / "config").glob("*.yaml")))
def test_every_top_level_config_has_a_schema_and_composes(name):
    """Each recipe's YAML composes against its schema, which refuses a key it does not declare."""
    register_distill()  # distill_schema
    overrides = {"train": ["out_dir=/nonexistent/run"], "distill": ["out_dir=/nonexistent/run"]}.get(name, [])
    cfg = compose_cfg(name, overrides)
    assert OmegaConf.get_type(cfg) is not dict, f"{name}.yaml has no schema in its defaults"
    with pytest.raises(ConfigCompositionException, match="not_a_key"):
        compose_cfg(name, [*overrides, "not_a_key=1"])


def test_closed_choices_are_refused_when_composed():
    """Typed fields: a value outside an enum's is refused by hydra, naming the choices, and a
    checkpoint stores the plain strings (no enum class in the pickle)."""
    with pytest.raises(ConfigCompositionException, match="env.backend=bullet") as err:
        compose_cfg("train", ["env.backend=bullet"])
    assert "expected one of [mujoco, kinematic]" in str(err.value.__cause__)
    cfg = compose_cfg("train", ["env.backend=kinematic", "loss.value_norm=none"])
    assert cfg.env.backend == "kinematic" and f"{cfg.env.backend}" == "kinematic" and cfg.loss.value_norm == "none"
    stored = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    assert type(stored["env"]["backend"]) is str and migrate(stored).env.backend == "kinematic"
