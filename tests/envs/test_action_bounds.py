"""env.action_bounds: a narrower action box for the pick-and-place env, declared in the config schema."""
from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from pnp.envs.pnp_env import PnPEnv, action_box
from pnp.task import ACTION_HIGH, ACTION_LOW, ACTION_NAMES
from pnp.training.config import CurriculumConfig, EnvConfig
from pnp.training.tasks import make_env

EE_X = ACTION_NAMES.index("ee_x")


def test_default_is_the_papers_box():
    lo, hi = action_box(None)
    assert lo.tolist() == pytest.approx(ACTION_LOW) and hi.tolist() == pytest.approx(ACTION_HIGH)


def test_narrowed_entry_sets_the_spec_and_clips_the_command():
    env = PnPEnv(num_worlds=2, backend="kinematic", seed=0, action_bounds={"ee_x": [0.3, 0.85]})
    spec = env.full_action_spec_unbatched["agents", "action"].space
    assert float(spec.high[0, EE_X]) == pytest.approx(0.85)
    others = [i for i in range(len(ACTION_NAMES)) if i != EE_X]
    assert spec.high[0, others].tolist() == pytest.approx([ACTION_HIGH[i] for i in others])
    td = env.reset()
    action = env._neutral_action().expand(2, 1, 8).clone()
    action[0, 0, EE_X] = 1.2  # inside the paper's box, outside this one
    out = env.step(td.set(("agents", "action"), action))
    assert out["next", "agents", "action_clipped"][:, 0].tolist() == [True, False]
    assert env._last_action[0, 0, EE_X].item() == pytest.approx(0.85)


@pytest.mark.parametrize("bounds, named", [({"ee_reach": [0.3, 0.9]}, "ee_reach"), ({"ee_x": [0.3, 1.5]}, "1.5"),
                                           ({"ee_x": [0.9, 0.8]}, "0.9"), ({"ee_x": [0.3]}, "ee_x")])
def test_bad_bounds_are_refused_by_name(bounds, named):
    with pytest.raises(ValueError, match=named):
        action_box(bounds)


def test_the_config_schema_carries_it_to_the_env_and_other_tasks_refuse_it():
    cfg = OmegaConf.merge(OmegaConf.structured(EnvConfig),
                          {"backend": "kinematic", "num_worlds": 2, "action_bounds": {"ee_y": [-0.45, 0.45]}})
    env = make_env(cfg, OmegaConf.structured(CurriculumConfig), 0)
    high = env.full_action_spec_unbatched["agents", "action"].space.high
    assert float(high[0, ACTION_NAMES.index("ee_y")]) == pytest.approx(0.45)
    cfg.task = "ee_tracking"
    with pytest.raises(ValueError, match="action_bounds"):
        make_env(cfg, OmegaConf.structured(CurriculumConfig), 0)


def test_a_checkpoint_keeps_its_bounds_at_evaluation(tmp_path):
    from pnp.training.rollout import load_policy
    from tests.training._tiny import tiny_train

    tiny_train(tmp_path / "run", "total_iterations=1", "+env.action_bounds.ee_x=[0.3,0.85]")
    pol = load_policy(tmp_path / "run" / "checkpoint.pt", 2, 0)
    try:
        assert float(pol.env.full_action_spec_unbatched["agents", "action"].space.high[0, EE_X]) == pytest.approx(0.85)
        assert float(pol.actor.module[-1].distribution_kwargs["high"][..., EE_X].max()) == pytest.approx(0.85)
    finally:
        pol.env.close()
