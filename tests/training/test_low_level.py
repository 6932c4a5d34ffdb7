"""env.low_level=learned: a task=locomotion checkpoint walks the legs of the PnP env."""

import pytest
from hydra.errors import ConfigCompositionException
import torch

from pnp.envs.pnp_env import PnPEnv
from pnp.legs.backend import LeggedMujocoBackend
from pnp.legs.locomotion import LOCO_OBS_DIM, LegServo
from pnp.training.low_level import load_locomotion_policy
from pnp.training.rollout import load_policy, run_trials
from pnp.training.tasks import make_env, schedule_of
from pnp.training.trainer import train
from tests.training._tiny import TINY, compose_cfg

MUJOCO_TINY = [o for o in TINY if not o.startswith("backend=")]
SERVO = ["env.locomotion.leg_kp=250", "env.locomotion.leg_kd=5", "env.locomotion.action_scale=0.8"]


@pytest.fixture(scope="module")
def locomotion_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("loco") / "run"
    train(compose_cfg("train", [*MUJOCO_TINY, "experiment=locomotion", "env.nthread=1", "total_iterations=1",
                                *SERVO, f"out_dir={out}"]))
    return out


@pytest.fixture(scope="module")
def pnp_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("pnp") / "run"
    train(compose_cfg("train", [*TINY, "total_iterations=1", f"out_dir={out}"]))
    return out


def test_a_locomotion_checkpoint_drives_the_pnp_legs(locomotion_run):
    policy = load_locomotion_policy(str(locomotion_run))
    act = policy(torch.zeros(3, LOCO_OBS_DIM))
    assert act.shape == (3, 12) and torch.isfinite(act).all()
    with pytest.raises(ValueError, match=rf"\[M, {LOCO_OBS_DIM}\]"):
        policy(torch.zeros(3, 5))
    cfg = compose_cfg("train", [*MUJOCO_TINY, "backend=mujoco", "env.nthread=1", "env.num_worlds=2",
                                "env.low_level=learned", f"env.low_level_checkpoint={locomotion_run}"])
    env = make_env(cfg.env, cfg.curriculum, seed=0)
    backend = env.base_env.backend
    assert isinstance(backend, LeggedMujocoBackend)
    # the legs run under the servos the leg policy was trained with
    assert policy.servo == backend.servo == LegServo(250.0, 5.0, 0.8)
    legs = backend.idx.leg_ctrl.reshape(-1)
    assert (backend.model.actuator_gainprm[legs, 0] == 250.0).all()
    assert (backend.model.actuator_biasprm[legs, 1:3] == [-250.0, -5.0]).all()
    td = env.rollout(2, break_when_any_done=False)
    assert td["next", "agents", "observation"].isfinite().all()
    env.close()


def test_a_trained_high_level_is_evaluated_on_legs(locomotion_run, pnp_run, tmp_path):
    """recipes/evaluate.py with env.low_level=learned: trials on the legs, and the result names them."""
    pol = load_policy(pnp_run / "checkpoint.pt", 2, 0, backend="mujoco", nthread=1, max_episode_steps=4, low_level="learned",
                      low_level_checkpoint=str(locomotion_run))
    assert isinstance(pol.env.base_env.backend, LeggedMujocoBackend)
    records = run_trials(pol.env, pol.actor, 2)
    assert len(records) == 2 and all(r["cause"] == "timeout" for r in records)
    from pnp.training import evaluation as evaluate_recipe

    result = evaluate_recipe.evaluate(compose_cfg("evaluate", [
        f"checkpoint={pnp_run}", "trials=2", "env.num_worlds=2", "env.nthread=1", "env.max_episode_steps=4",
        "env.backend=mujoco", "env.low_level=learned", f"env.low_level_checkpoint={locomotion_run}",
        f"out={tmp_path / 'eval.json'}", "progress=false"]))
    assert result["low_level"] == "learned" and result["low_level_checkpoint"] == str(locomotion_run / "checkpoint.pt")
    assert f"legs: `{locomotion_run / 'checkpoint.pt'}`" in (tmp_path / "eval.md").read_text()


def test_wrong_low_level_settings_are_refused(locomotion_run, pnp_run):
    def env_of(*extra):
        cfg = compose_cfg("train", [*MUJOCO_TINY, "env.nthread=1", "env.num_worlds=1", *extra])
        return make_env(cfg.env, cfg.curriculum, seed=0)

    with pytest.raises(ConfigCompositionException, match="wheels"):  # a typed field: refused at compose time
        env_of("backend=mujoco", "env.low_level=wheels")
    with pytest.raises(ValueError, match="needs env.low_level_checkpoint"):
        env_of("backend=mujoco", "env.low_level=learned")
    with pytest.raises(ValueError, match="needs env.backend=mujoco"):
        env_of("backend=kinematic", "env.low_level=learned", f"env.low_level_checkpoint={locomotion_run}")
    with pytest.raises(ValueError, match="applies to env.task=pnp only"):
        env_of("task=ee_tracking", "backend=mujoco", "env.low_level=learned")
    with pytest.raises(ValueError, match="trained on env.task='pnp', not locomotion"):
        load_locomotion_policy(str(pnp_run))


def test_a_teacher_is_rendered_walking(locomotion_run, pnp_run, tmp_path):
    """recipes/render.py --low-level-checkpoint: the GIF of a pick-and-place on legs."""
    pytest.importorskip("imageio")
    from pnp.analysis import render_gif as render_recipe

    try:
        from pnp.sim.render import WorldRenderer

        WorldRenderer(PnPEnv(num_worlds=1, nthread=1).backend, 0, width=32, height=32).close()
    except Exception as e:  # noqa: BLE001 - any GL failure means no offscreen context here
        pytest.skip(f"no offscreen GL context: {e}")
    out = tmp_path / "walking.gif"
    info = render_recipe.main(["--checkpoint", str(pnp_run), "--low-level-checkpoint", str(locomotion_run),
                               "--out", str(out), "--tries", "1", "--max-steps", "3"])
    assert out.stat().st_size > 0 and info["low_level"] == "learned" and info["steps"] == 3


def test_only_positive_rewards_clips_each_steps_reward_at_zero():
    """env.locomotion.only_positive_rewards (legged_gym's): the same steps, the reward max(r, 0)."""
    def env_of(clip):
        cfg = compose_cfg("train", [*MUJOCO_TINY, "experiment=locomotion", "env.nthread=1", "env.num_worlds=3",
                                    f"env.locomotion.only_positive_rewards={clip}"])
        return make_env(cfg.env, cfg.curriculum, seed=0)

    plain, clipped = env_of(False), env_of(True)
    assert schedule_of(clipped) is clipped.transform[2]  # the schedule, not the clipping after it
    td_plain, td_clip, lowest = plain.reset(), clipped.reset(), 0.0
    actions = 2 * torch.rand(10, 3, 1, 12, generator=torch.Generator().manual_seed(0)) - 1  # big random steps
    for a in actions:
        td_plain = plain.step(td_plain.set(("agents", "action"), a))
        td_clip = clipped.step(td_clip.set(("agents", "action"), a))
        r_plain, r_clip = td_plain["next", "agents", "reward"], td_clip["next", "agents", "reward"]
        assert torch.equal(r_clip, r_plain.clamp_min(0.0))
        lowest = min(lowest, float(r_plain.min()))
        td_plain, td_clip = plain.step_mdp(td_plain), clipped.step_mdp(td_clip)
    assert lowest < -1e-3  # random leg steps cost more than they earn: the clip did something
    plain.close(), clipped.close()
