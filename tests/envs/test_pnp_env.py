"""PnPEnv on the MuJoCo backend: specs, episode rules, determinism, resets, bad input."""
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from pnp.envs.pnp_env import PnPEnv
from pnp.task import ACTION_HIGH, ACTION_LOW, OBS_BLOCKS, OBS_FIELDS
from pnp.task.terms import CONDITIONS, REWARD_TERMS


def _env(n=4, robots=1, seed=0):
    return PnPEnv(num_worlds=n, num_robots=robots, seed=seed, nthread=1)


def _const_action(env, **fields):
    a = env._neutral_action().expand(env.num_worlds, env.num_robots, 8).clone()
    for i, v in fields.items():
        a[..., int(i[1:])] = v
    return a


@pytest.mark.parametrize("robots", [1, 2])
def test_specs(robots):
    env = _env(robots=robots)
    check_env_specs(env)
    td = env.reset()
    R = robots
    assert td["agents", "observation"].shape == (4, R, sum(OBS_BLOCKS.values()))
    assert td["agents", "reward_terms"].shape == (4, R, len(REWARD_TERMS))
    assert td["agents", "stage_conditions"].shape == (4, R, len(CONDITIONS))
    flat = torch.cat([td["agents", k] for k in OBS_BLOCKS], -1)
    assert torch.equal(flat, td["agents", "observation"])
    nb = td["agents", "neighbour"]
    assert (nb.abs().sum() == 0) == (robots == 1)
    spec = env.full_action_spec["agents", "action"]
    assert torch.equal(spec.space.low[0, 0], torch.tensor(ACTION_LOW))
    assert torch.equal(spec.space.high[0, 0], torch.tensor(ACTION_HIGH))
    env.close()


def test_hl_step_is_a_tenth_of_a_second():
    env = _env(n=2)
    env.reset()
    t0 = env.backend.physics.time.copy()
    env.rand_step()
    np.testing.assert_allclose(env.backend.physics.time - t0, 0.1, atol=1e-9)
    assert env.max_steps == 450  # 45 s


def test_seeding_is_deterministic():
    outs = []
    for _ in range(2):
        env = _env(seed=7)
        env.set_seed(3)
        td = env.reset()
        g = torch.Generator().manual_seed(0)
        for _ in range(3):
            a = torch.rand(4, 1, 8, generator=g) * (torch.tensor(ACTION_HIGH) - torch.tensor(ACTION_LOW)) + torch.tensor(ACTION_LOW)
            td = env.step_mdp(env.step(td.set(("agents", "action"), a)))
        outs.append(td["agents", "observation"].clone())
        env.close()
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0)
    env = _env(seed=8)
    other = env.reset()["agents", "observation"]
    assert not torch.allclose(other, outs[0])


def test_partial_reset_touches_only_masked_worlds():
    env = _env(n=4)
    td = env.reset()
    td = env.step_mdp(env.step(td.set(("agents", "action"), _const_action(env, a0=0.5))))
    qpos = env.backend.physics.qpos.copy()
    mask = torch.tensor([[False], [True], [False], [True]])
    out = env.reset(td.clone().set("_reset", mask))
    after = env.backend.physics.qpos
    np.testing.assert_array_equal(after[[0, 2]], qpos[[0, 2]])
    assert not np.allclose(after[[1, 3]], qpos[[1, 3]])
    torch.testing.assert_close(out["agents", "observation"][[0, 2]], td["agents", "observation"][[0, 2]])
    assert (env._steps[[1, 3]] == 0).all() and (env._steps[[0, 2]] == 1).all()


def test_ee_tracks_commanded_pose():
    """Measured: targets within +-10 cm of the default pose; median error 2.7 cm after one
    HL step (rate limit and actuator lag), max below 1 cm after three (0.3 s)."""
    n = 8
    env = _env(n=n)
    td = env.reset()
    g = torch.Generator().manual_seed(0)
    a = _const_action(env)
    a[..., 3:6] += (torch.rand(n, 1, 3, generator=g) - 0.5) * 0.2
    a[..., 6] = (torch.rand(n, 1, generator=g) - 0.5)
    errs = []
    for _ in range(3):
        td = env.step(td.set(("agents", "action"), a))
        ee = td["next", "agents", "ego"][..., OBS_FIELDS["ego"]["ee_pos"]]
        errs.append((ee - a[..., 3:6]).norm(dim=-1))
        td = env.step_mdp(td)
    assert errs[0].median() < 0.05
    assert errs[2].max() < 0.01


def test_base_tracks_commanded_velocity():
    env = _env(n=2)
    td = env.reset()
    yaw0 = env.backend.physics.qpos[:, 2].copy()
    xy0 = env.backend.physics.qpos[:, :2].copy()
    a = _const_action(env, a0=0.6, a1=0.0, a2=0.0)
    for _ in range(10):
        td = env.step_mdp(env.step(td.set(("agents", "action"), a)))
    moved = env.backend.physics.qpos[:, :2] - xy0
    expected = 0.6 * 1.0 * np.stack([np.cos(yaw0), np.sin(yaw0)], -1)
    np.testing.assert_allclose(moved, expected, atol=0.05)


def test_nan_action_raises_naming_key_and_worlds():
    env = _env(n=4)
    td = env.reset()
    a = _const_action(env)
    a[2, 0, 1] = float("nan")
    a[3, 0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"\('agents', 'action'\).*\[2, 3\]"):
        env.step(td.set(("agents", "action"), a))


def test_wrong_shape_raises():
    env = _env(n=4)
    td = env.reset()
    with pytest.raises(ValueError, match=r"shape \(4, 1, 7\).*expected \(4, 1, 8\)"):
        env.step(td.set(("agents", "action"), torch.zeros(4, 1, 7)))


def test_out_of_bound_actions_are_clipped_and_counted():
    env = _env(n=4)
    td = env.reset()
    a = _const_action(env)
    a[1, 0, 0] = 5.0  # vx far above 1 m/s
    a[2, 0, 7] = -1.0  # grasp probability below 0
    out = env.step(td.set(("agents", "action"), a))
    assert out["next", "agents", "action_clipped"][:, 0].tolist() == [False, True, True, False]
    assert env.clipped_count == 2


def test_diverging_world_is_reset_alone():
    env = _env(n=4)
    td = env.reset()
    a = _const_action(env)
    for _ in range(2):
        td = env.step_mdp(env.step(td.set(("agents", "action"), a)))
    before = env.backend.physics.qpos.copy()
    env.push_box(1, [1e13, 0, 0, 0, 0, 1e13])
    out = env.step(td.set(("agents", "action"), a))["next"]
    assert out["diverged"].squeeze(-1).tolist() == [False, True, False, False]
    assert out["truncated"].squeeze(-1).tolist() == [False, True, False, False]
    assert env.diverged_count == 1
    assert torch.isfinite(out["agents", "observation"]).all()
    # The others carried on from where they were (time advanced, not reset).
    t = env.backend.physics.time
    np.testing.assert_allclose(t[[0, 2, 3]], 0.3, atol=1e-9)
    assert t[1] == 0.0 and env._steps[1] == 0
    assert np.isfinite(env.backend.physics.qpos).all() and not np.allclose(before[1], env.backend.physics.qpos[1])


def test_unknown_backend_and_robot_count():
    with pytest.raises(ValueError, match="'bullet'"):
        PnPEnv(num_worlds=2, backend="bullet")
    with pytest.raises(ValueError, match="num_robots must be 1 or 2, got 3"):
        PnPEnv(num_worlds=2, num_robots=3)


def test_get_set_state_continues_exactly():
    env = _env(n=3)
    td = env.reset()
    a = _const_action(env, a0=0.3, a2=0.2)
    for _ in range(2):
        td = env.step_mdp(env.step(td.set(("agents", "action"), a)))
    saved, td_saved = env.get_state(), td.clone()
    ref = [env.step_mdp(env.step(td.set(("agents", "action"), a)))["agents", "observation"] for _ in range(1)]
    ref.append(env.reset(td.clone().set("_reset", torch.tensor([[True], [False], [False]])))["agents", "observation"])
    other = _env(n=3, seed=99)
    other.set_state(saved)
    got = [other.step_mdp(other.step(td_saved.set(("agents", "action"), a)))["agents", "observation"]]
    got.append(other.reset(td_saved.clone().set("_reset", torch.tensor([[True], [False], [False]])))["agents", "observation"])
    for r, g in zip(ref, got):
        torch.testing.assert_close(r, g, rtol=0, atol=0)
    with pytest.raises(KeyError, match="_goal"):
        other.set_state({k: v for k, v in saved.items() if k != "_goal"})


def test_the_gripper_closes_by_threshold():
    """p = 0.3 never closes the gripper; p = 0.7 always does (the command is p > 0.5)."""
    env = PnPEnv(num_worlds=64, num_robots=1, backend="kinematic")
    for p, expected in ((0.3, 0.0), (0.7, 1.0)):
        td = env.reset()
        action = env._last_action.clone()
        action[..., 7] = p
        td = env.step(td.set(("agents", "action"), action))
        assert (env.backend.finger[..., 0] < 0.035).float().mean().item() == expected  # past mid-stroke
