"""LocomotionEnv (the learned low level's leg policy task): specs, standing, falls, pushes,
payloads, reward terms, partial resets, bad input, divergence, exact resumes, and two
iterations of the trainer on it. Checks are tolerance-based (no exact trajectories)."""
import dataclasses
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torchrl.envs.utils import check_env_specs

from pnp.envs.locomotion_env import LocomotionEnv
from pnp.legs.locomotion import (
    LOCO_OBS_DIM, LOCO_OBS_FIELDS, LOCO_REWARD_TERMS, LOCO_REWARD_WEIGHTS, POLICY_DT, REWARD_SCALES, STAND,
    LegServo, locomotion_reward_config, locomotion_stage_graph,
)
from pnp.sim.robot import LEGGED_STAND_HEIGHT
from pnp.task import ACTION_HIGH, ACTION_LOW
from pnp.training.config import LocomotionConfig
from pnp.training.models import make_models
from pnp.training.tasks import make_env
from pnp.training.trainer import train
from tests.training._tiny import TINY, compose_cfg

NO_PUSH = 1e4  # s: no push within a test


def _env(n=4, seed=0, **settings) -> LocomotionEnv:
    return LocomotionEnv(n, LocomotionConfig(**settings), seed=seed, nthread=1)


def _zero(env):
    return torch.zeros(env.num_worlds, 1, 12)


def _run(env, td, steps, action=None):
    """``steps`` steps (resetting done worlds); returns the last td and the stacked "next" outputs."""
    outs = []
    for _ in range(steps):
        a = _zero(env) if action is None else action()
        out, td = env.step_and_maybe_reset(td.set(("agents", "action"), a))
        outs.append(out["next"])
    return td, torch.stack(outs, 0)


def _obs(out, field):
    return out["agents", "observation"][..., 0, LOCO_OBS_FIELDS[field]]


def test_specs_and_layout():
    env = _env(3)
    check_env_specs(env)
    td = env.reset()
    assert td["agents", "observation"].shape == (3, 1, LOCO_OBS_DIM) == (3, 1, 54)
    assert td["agents", "reward_terms"].shape == (3, 1, len(LOCO_REWARD_TERMS)) == (3, 1, 11)
    assert td["agents", "stage_conditions"].shape == (3, 1, 0)
    spec = env.full_action_spec["agents", "action"]
    assert spec.shape == (3, 1, 12) and (spec.space.low == -1).all() and (spec.space.high == 1).all()
    assert env.max_steps == round(20.0 / POLICY_DT) == 1000 and POLICY_DT == pytest.approx(0.02)
    assert sum(s.stop - s.start for s in LOCO_OBS_FIELDS.values()) == LOCO_OBS_DIM
    # Commands within the HL policy's base-velocity bounds, the default ranges.
    cmd = _obs(td, "command")
    assert (cmd >= torch.tensor(ACTION_LOW[:3]) - 1e-6).all() and (cmd <= torch.tensor(ACTION_HIGH[:3]) + 1e-6).all()
    assert (_obs(td, "projected_gravity")[:, 2] < -0.99).all()  # upright at reset
    env.close()


def test_reward_config_is_legged_gym_times_dt_with_one_stage():
    cfg = locomotion_reward_config()
    assert cfg["term_stage"] == {} and cfg["mu"] == {} and cfg["n_stages"] == 1
    assert cfg["fixed_weights"] == LOCO_REWARD_WEIGHTS
    scales = dict(REWARD_SCALES)
    anchor = {"tracking_lin_vel": 1.0, "tracking_ang_vel": 0.5, "lin_vel_z": -2.0, "ang_vel_xy": -0.05,
              "orientation": -5.0, "torques": -2.5e-5, "dof_acc": -2.5e-7, "action_rate": -0.01, "feet_air_time": 2.0}
    assert {n: scales[n] for n in anchor} == anchor  # legged_gym's ANYmal C flat
    assert all(LOCO_REWARD_WEIGHTS[n] == pytest.approx(s * 0.02) for n, s in REWARD_SCALES)
    graph = locomotion_stage_graph()
    assert graph.n_stages == 1 and graph.conditions == ()
    assert graph.next_stage(torch.zeros(2, 1, dtype=torch.long), torch.zeros(2, 1, 0, dtype=torch.bool)).eq(0).all()


def test_zero_action_keeps_standing_for_two_seconds():
    # The pipeline's servos (kp 250 / kd 6): at kp 80 the arm's weight, carried by the legs
    # since the gravcomp lift was removed, sinks a zero-action stand to 0.49 m.
    env = _env(8, push_interval_s=NO_PUSH, leg_kp=250.0, leg_kd=6.0)  # the arm still moves and carries its payload
    td = env.reset()
    env.set_command(torch.zeros(3))
    _, outs = _run(env, td, round(2.0 / POLICY_DT))
    assert not outs["done"].any()
    # A 2.5 kg payload at a low arm pose leans it by up to ~0.4 rad and ~11 cm (measured).
    assert (_obs(outs, "projected_gravity")[..., 2] < -math.cos(0.6)).all()
    assert env.backend.qpos[:, env.idx.base_qpos + 2].min() > LEGGED_STAND_HEIGHT - 0.15
    terms = outs["agents", "reward_terms"][..., 0, :]
    assert (terms[..., LOCO_REWARD_TERMS.index("fall")] == 0).all()


def test_stiffer_leg_servos_sag_less_and_the_action_scale_widens_the_targets():
    heights = {}
    for kp in (80.0, 300.0):
        env = _env(2, push_interval_s=NO_PUSH, payload_mass=[0.0, 0.0], arm_resample_s=NO_PUSH, leg_kp=kp)
        td = env.reset()
        env.set_command(torch.zeros(3))
        _run(env, td, round(1.0 / POLICY_DT))
        legs = env.idx.leg_ctrl
        assert (env.model.actuator_gainprm[legs, 0] == kp).all() and (env.model.actuator_biasprm[legs, 1] == -kp).all()
        heights[kp] = float(env.backend.qpos[:, env.idx.base_qpos + 2].mean())
    # kp 80 sags ~2 cm below the stand's geometry (robot.py); kp 300 a quarter of that
    assert LEGGED_STAND_HEIGHT - heights[80.0] > 0.01 and heights[300.0] - heights[80.0] > 0.01
    wide, narrow = LegServo(action_scale=1.0), LegServo()
    a = torch.full((1, 12), 0.1)
    assert torch.allclose(wide.targets(a) - STAND, 2 * (narrow.targets(a) - STAND))
    with pytest.raises(ValueError, match="kp=-1.0"):
        LegServo(kp=-1.0)


def test_fall_terminates_and_the_world_restarts_standing():
    env = _env(3, push_interval_s=NO_PUSH)
    td, _ = _run(env, env.reset(), 3)
    b = env.idx.base_qpos
    env.backend.qpos[1, b + 3 : b + 7] = (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0)  # on its side
    out, td = env.step_and_maybe_reset(td.set(("agents", "action"), _zero(env)))
    nxt = out["next"]
    assert nxt["terminated"].squeeze(-1).tolist() == [False, True, False]
    assert nxt["done"].squeeze(-1).tolist() == [False, True, False] and not nxt["truncated"].any()
    assert not nxt["success"].any()
    fall = nxt["agents", "reward_terms"][:, 0, LOCO_REWARD_TERMS.index("fall")]
    assert fall.tolist() == [0.0, 1.0, 0.0]
    assert nxt["agents", "reward"][1, 0, 0] < nxt["agents", "reward"][0, 0, 0] - 0.5
    # step_and_maybe_reset restarted world 1 upright at the stand; the others went on.
    assert env._steps.tolist() == [4, 0, 4]
    assert abs(env.backend.qpos[1, b + 2] - LEGGED_STAND_HEIGHT) < 1e-9 and env.backend.time[1] == 0.0


def test_low_trunk_is_a_fall_and_the_step_limit_truncates():
    env = LocomotionEnv(2, LocomotionConfig(push_interval_s=NO_PUSH), seed=0, nthread=1, max_episode_steps=3)
    td, outs = _run(env, env.reset(), 3)
    assert outs["truncated"][-1].all() and outs["success"][-1].all() and not outs["terminated"].any()
    env.backend.qpos[0, env.idx.base_qpos + 2] = 0.2  # trunk below fall_height (0.35 m)
    out = env.step(td.set(("agents", "action"), _zero(env)))["next"]
    assert out["terminated"].squeeze(-1).tolist() == [True, False]


def test_pushes_kick_the_trunk_sideways():
    def max_speed(push_interval_s):
        env = _env(6, seed=1, push_interval_s=push_interval_s, push_speed=[0.8, 0.8])
        td = env.reset()
        env.set_command(torch.zeros(3))
        _, outs = _run(env, td, 5)
        return _obs(outs, "base_lin_vel")[..., :2].norm(dim=-1).amax(0)

    # With a push every 0.1 s (5 steps) every world is kicked once in 5 steps, first at a random step.
    assert (max_speed(0.1) > 0.5).all()
    assert (max_speed(NO_PUSH) < 0.2).all()


def test_payload_hangs_on_the_gripper_and_is_drawn_per_world():
    env = _env(16)
    m = env.payload
    assert ((m >= 0.0) & (m <= 2.5)).all() and m.std() > 0.2
    g = env.idx.gripper_body
    np.testing.assert_allclose(env.backend.xfrc[:, g, 2], -9.81 * m.double().numpy(), rtol=1e-6)
    assert np.count_nonzero(env.backend.xfrc) == 16  # one downward force per world, nothing else
    td = env.reset()  # a full reset draws new payloads
    assert not torch.equal(env.payload, m)
    # It acts: the same arm motion (same seed) sags under 5 kg against none.
    arms = []
    for mass in (0.0, 5.0):
        e = _env(4, seed=3, payload_mass=[mass, mass], push_interval_s=NO_PUSH)
        _, outs = _run(e, e.reset(), 25)
        arms.append(_obs(outs, "arm_q")[-1])
    assert (arms[0] - arms[1]).abs().max() > 0.02
    del td


def test_reward_terms_are_finite_and_signed():
    env = _env(6, push_interval_s=0.2)
    g = torch.Generator().manual_seed(0)
    _, outs = _run(env, env.reset(), 30, action=lambda: torch.rand(6, 1, 12, generator=g) * 2 - 1)
    terms = outs["agents", "reward_terms"][..., 0, :]
    assert torch.isfinite(terms).all() and torch.isfinite(outs["agents", "observation"]).all()
    col = {n: terms[..., i] for i, n in enumerate(LOCO_REWARD_TERMS)}
    for n in ("tracking_lin_vel", "tracking_ang_vel"):
        assert ((col[n] > 0) & (col[n] <= 1)).all()
    for n in ("lin_vel_z", "ang_vel_xy", "orientation", "torques", "dof_acc", "action_rate", "joint_speed"):
        assert (col[n] >= 0).all(), n
    assert (col["torques"] <= 12 * 80.0**2 + 1e-3).all()  # the servos' published limit
    assert (col["action_rate"] > 0).any() and (col["torques"] > 0).all()
    w = torch.tensor([LOCO_REWARD_WEIGHTS[n] for n in LOCO_REWARD_TERMS])
    torch.testing.assert_close(outs["agents", "reward"][..., 0, 0], terms @ w)


def test_a_narrower_tracking_kernel_pays_less_for_the_same_error():
    g = torch.Generator().manual_seed(0)
    actions = [torch.rand(4, 1, 12, generator=g) * 2 - 1 for _ in range(10)]
    tracking = []
    for sigma in (0.25, 0.05):
        env = _env(4, tracking_sigma=sigma, push_interval_s=NO_PUSH)
        it = iter(actions)
        _, outs = _run(env, env.reset(), 10, action=lambda: next(it))
        tracking.append(outs["agents", "reward_terms"][..., 0, LOCO_REWARD_TERMS.index("tracking_lin_vel")])
    wide, narrow = tracking
    assert (narrow <= wide + 1e-6).all() and (narrow < wide - 1e-3).any()
    with pytest.raises(ValueError, match="tracking_sigma must be > 0, got 0.0"):
        _env(1, tracking_sigma=0.0)


def test_partial_reset_leaves_other_worlds_untouched():
    env = _env(4)
    td, _ = _run(env, env.reset(), 5)
    before = env.backend.state.copy()
    command = env.command
    mask = torch.tensor([False, True, False, False]).unsqueeze(-1)
    out = env.reset(td.set("_reset", mask))
    keep = [0, 2, 3]
    np.testing.assert_array_equal(env.backend.state[keep], before[keep])
    torch.testing.assert_close(env.command[keep], command[keep])
    assert env._steps.tolist() == [5, 0, 5, 5] and env.backend.time[1] == 0.0
    assert out["agents", "observation"].shape == (4, 1, LOCO_OBS_DIM)


def test_bad_actions_and_settings_raise_naming_the_value():
    env = _env(4)
    td = env.reset()
    a = _zero(env)
    a[2, 0, 5] = float("nan")
    with pytest.raises(ValueError, match=r"\('agents', 'action'\) has NaN or Inf in worlds \[2\]"):
        env.step(td.set(("agents", "action"), a))
    with pytest.raises(ValueError, match=r"shape \(4, 1, 8\), expected \(4, 1, 12\)"):
        env.step(td.set(("agents", "action"), torch.zeros(4, 1, 8)))
    big = _zero(env)
    big[1, 0, 0] = 3.0
    out = env.step(td.set(("agents", "action"), big))["next"]
    assert out["agents", "action_clipped"].squeeze(-1).tolist() == [False, True, False, False]
    with pytest.raises(ValueError, match="payload_mass"):
        _env(1, payload_mass=[2.0, 1.0])
    with pytest.raises(ValueError, match="command_low/high"):
        _env(1, command_low=[0.0, 0.0])
    with pytest.raises(ValueError, match="lack"):
        LocomotionEnv(1, object())


def test_diverging_world_is_reset_alone():
    env = _env(4, push_interval_s=NO_PUSH)
    td, _ = _run(env, env.reset(), 2)
    base = env.model.body("robot0/base").id
    env.backend.xfrc[1, base] = (1e13, 0, 0, 0, 0, 1e13)
    out = env.step(td.set(("agents", "action"), _zero(env)))["next"]
    assert out["diverged"].squeeze(-1).tolist() == [False, True, False, False]
    assert out["truncated"].squeeze(-1).tolist() == [False, True, False, False] and not out["success"].any()
    assert env.diverged_count == 1 and torch.isfinite(out["agents", "observation"]).all()
    np.testing.assert_allclose(env.backend.time[[0, 2, 3]], 3 * POLICY_DT, atol=1e-9)
    assert env.backend.time[1] == 0.0 and env._steps[1] == 0
    assert np.count_nonzero(env.backend.xfrc[1]) <= 1  # the push is gone, the payload back


def test_get_set_state_continues_exactly():
    env = _env(3, push_interval_s=0.1)
    g = torch.Generator().manual_seed(1)
    actions = [torch.rand(3, 1, 12, generator=g) * 2 - 1 for _ in range(6)]
    td, _ = _run(env, env.reset(), 2)
    state, carried = env.get_state(), td.clone()
    it = iter(actions)
    _, a = _run(env, td, 6, action=lambda: next(it))
    env.set_state(state)
    it = iter(actions)
    _, b = _run(env, carried, 6, action=lambda: next(it))
    assert (a == b).all()


def test_task_is_registered_and_refuses_the_kinematic_backend():
    cfg = compose_cfg("train", ["experiment=locomotion", "env.num_worlds=2", "env.nthread=1"])
    assert cfg.env.task == "locomotion" and cfg.model.grasp_dist == "tanh_normal"
    assert cfg.env.locomotion == dataclasses.asdict(LocomotionConfig())
    env = make_env(cfg.env, cfg.curriculum, seed=0)
    td = env.rollout(3, break_when_any_done=False)
    assert td["next", "agents", "stage_one_hot"].eq(1).all() and td["next", "agents", "reward"].shape == (2, 3, 1, 1)
    with pytest.raises(ValueError, match="grasp_dist='bernoulli' needs the pick-and-place action"):
        make_models(OmegaConf.merge(cfg.model, {"grasp_dist": "bernoulli"}), cfg.loss, env)  # a knee is no gripper
    env.close()
    bad = compose_cfg("train", ["task=locomotion", "backend=kinematic"])
    with pytest.raises(ValueError, match="env.backend=mujoco"):
        make_env(bad.env, bad.curriculum, seed=0)


def test_two_training_iterations(tmp_path):
    tiny = [o for o in TINY if not o.startswith("backend=")]  # the task runs on MuJoCo only
    out = train(compose_cfg("train", [*tiny, "experiment=locomotion", "env.nthread=1", "total_iterations=2",
                                      f"out_dir={tmp_path / 'run'}"]))
    assert out["iteration"] == 2 and out["frames"] == 80
    assert math.isfinite(out["train/loss_objective"]) and math.isfinite(out["reward"])
