"""The kinematic backend: same specs as MuJoCo, TorchRL contract, kinematics and its state
(grasping and the scripted policies: test_kinematic_grasp.py)."""
import math

import pytest
import torch
from pnp.envs.pnp_env import PnPEnv
from torchrl.envs.utils import check_env_specs

from pnp.kinematic.backend import KinematicBackend, arm_fk, arm_ik
from pnp.sim.arm_ik import REACH_MAX, ArmKinematics, clamp_reach, gripper_down_rotation
from pnp.sim.robot import ARM_DEFAULT, STANDING_HEIGHT
from pnp.task.scripted import ScriptedPnP
from pnp.task import ACTION_HIGH, ACTION_LOW, HL_DT
from tests.pnp._kinematic_helpers import _action, _layout, _to_world

SPECS = ("full_observation_spec", "full_action_spec", "full_reward_spec", "full_done_spec")


# --- contract ------------------------------------------------------------------------------
@pytest.mark.parametrize("robots", [1, 2])
def test_specs_equal_mujoco(robots):
    mj = PnPEnv(num_worlds=4, num_robots=robots, backend="mujoco")
    kin = PnPEnv(num_worlds=4, num_robots=robots, backend="kinematic")
    try:
        for name in SPECS:
            assert getattr(kin, name) == getattr(mj, name), name
        # The states they produce have the same keys, shapes and dtypes too.
        a, b = mj.reset(), kin.reset()
        assert set(a.keys(True, True)) == set(b.keys(True, True))
        for k in a.keys(True, True):
            assert a[k].shape == b[k].shape and a[k].dtype == b[k].dtype, k
    finally:
        mj.close()


@pytest.mark.parametrize("robots", [1, 2])
def test_check_env_specs(robots):
    env = PnPEnv(num_worlds=8, num_robots=robots, backend="kinematic", seed=1)
    check_env_specs(env)
    td = env.rollout(20, break_when_any_done=False)
    assert torch.isfinite(td["next", "agents", "observation"]).all()
    assert torch.isfinite(td["next", "agents", "reward"]).all()


def test_env_passes_backend_options_through():
    env = PnPEnv(num_worlds=2, num_robots=2, backend="kinematic",
                 backend_options={"box_blocks_base": True, "grasp_holds": True})
    assert env.backend.params.box_blocks_base and env.backend.params.grasp_holds
    with pytest.raises(TypeError, match="no_such_option"):
        PnPEnv(num_worlds=2, num_robots=2, backend="kinematic", backend_options={"no_such_option": True})


def _rollout(seed, robots=1, steps=15, n=6):
    env = PnPEnv(num_worlds=n, num_robots=robots, backend="kinematic", seed=seed)
    g = torch.Generator().manual_seed(123)
    lo, hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)
    td = env.reset()
    obs = [td["agents", "observation"]]
    for _ in range(steps):
        td["agents", "action"] = lo + (hi - lo) * torch.rand(n, robots, 8, generator=g)
        td = env.step(td)
        obs.append(td["next", "agents", "observation"])
        td = env.step_mdp(td)
    return torch.stack(obs)


@pytest.mark.parametrize("robots", [1, 2])
def test_seeding_determinism(robots):
    a, b, c = _rollout(7, robots), _rollout(7, robots), _rollout(8, robots)
    assert torch.equal(a, b)
    assert not torch.allclose(a[0], c[0])


def test_partial_reset_touches_masked_worlds_only():
    n = 6
    env = PnPEnv(num_worlds=n, num_robots=2, backend="kinematic", seed=3)
    td = env.reset()
    for _ in range(5):
        td = env.step_mdp(env.rand_step(td))
    before = env.backend.get_state()
    obs_before = td["agents", "observation"].clone()
    mask = torch.tensor([True, False, False, True, False, False])
    out = env.reset(td.clone().set("_reset", mask.unsqueeze(-1)))
    after = env.backend.get_state()
    for k, v in before.items():
        assert torch.equal(after[k][~mask], v[~mask]), k
    assert torch.equal(out["agents", "observation"][~mask], obs_before[~mask])
    assert not torch.allclose(after["bx"][mask], before["bx"][mask])
    assert torch.allclose(after["q"][mask], torch.tensor(ARM_DEFAULT).expand(2, 2, 6))
    assert (after["qd"][mask] == 0).all() and (after["box_vel"][mask] == 0).all()
    assert torch.allclose(env.backend.arm_q[mask], torch.tensor(ARM_DEFAULT).expand(2, 2, 6))
    assert torch.equal(env._steps[mask], torch.zeros(2, dtype=torch.long))


def test_get_set_state_resumes_exactly():
    env = PnPEnv(num_worlds=4, num_robots=1, backend="kinematic", seed=5)
    pol = ScriptedPnP(4)
    td = env.reset()
    for _ in range(40):
        td = env.step_mdp(env.step(pol(td)))
    saved, td_saved = env.get_state(), td.clone()
    phase = pol.phase.clone(), pol.timer.clone(), pol.z_grasp.clone(), pol.box_z0.clone(), pol.ee_grasp.clone()

    def run(td):
        outs = []
        for _ in range(20):
            td = env.step(pol(td))
            outs.append(td["next", "agents", "observation"])
            td = env.step_mdp(td)
        return torch.stack(outs)

    first = run(td)
    env.set_state(saved)
    pol.phase, pol.timer, pol.z_grasp, pol.box_z0, pol.ee_grasp = (x.clone() for x in phase)
    assert torch.equal(first, run(td_saved))


# --- arm kinematics ----------------------------------------------------------------------------
def test_closed_form_ik_and_fk_match_arm_kinematics():
    kin = ArmKinematics()
    g = torch.Generator().manual_seed(0)
    lo, hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)
    a = lo + (hi - lo) * torch.rand(4000, 8, generator=g)
    ee = clamp_reach(a[:, 3:6])
    q = arm_ik(ee, a[:, 6])
    p, r = kin.fk(q)
    assert (p - ee).norm(dim=-1).max() < 1e-4
    assert (r - gripper_down_rotation(a[:, 6])).abs().max() < 1e-4
    # FK for arbitrary joints (j4 = 0) equals the pytorch-kinematics chain.
    q = kin.q_low + (kin.q_high - kin.q_low) * torch.rand(500, 6, generator=g)
    q[:, 3] = 0
    p2, r2 = arm_fk(q)
    p, r = kin.fk(q)
    assert (p2 - p).abs().max() < 1e-5 and (r2 - r).abs().max() < 1e-5
    # Default pose: the IK reproduces ARM_DEFAULT from its own EE position.
    p0, _ = kin.fk(torch.tensor(ARM_DEFAULT))
    assert torch.allclose(arm_ik(p0, torch.tensor(0.0)), torch.tensor(ARM_DEFAULT), atol=0.02)
    # Reach: far targets are pulled in to REACH_MAX of the shoulder (wrist centre).
    far = clamp_reach(torch.tensor([[3.0, 0.0, -0.3]]))
    assert far[0, 0] < 0.25 + REACH_MAX + 1e-4


def test_arm_state_is_consistent_and_ee_lags():
    b = KinematicBackend(3, 1)
    b.reset(torch.arange(3), _layout(3, 1, box_xy=(3.0, 3.0)))
    target = torch.tensor([0.9, 0.2, -0.2])
    act = _action(3, 1, ee=target, yaw=0.5)
    b.step(act)
    err1 = (b.ee_pos[:, 0] - _to_world(b, target)).norm(dim=-1)
    for _ in range(15):
        b.step(act)
    err = (b.ee_pos[:, 0] - _to_world(b, target)).norm(dim=-1)
    assert (err1 > 0.02).all() and (err < 1e-3).all()  # a lag, then convergence
    p, r = ArmKinematics().fk(b.arm_q)
    assert torch.allclose(_to_world(b, p[:, 0]), b.ee_pos[:, 0], atol=1e-5)
    assert torch.allclose(r[:, 0], b.ee_rot[:, 0], atol=1e-5)  # base yaw 0
    assert torch.allclose(b.ee_rot[:, 0], gripper_down_rotation(torch.tensor(0.5)).expand(3, 3, 3), atol=1e-4)
    assert (b.arm_qd.abs() <= 4.0 + 1e-4).all()


def test_base_integrates_body_velocity():
    b = KinematicBackend(1, 1)
    b.reset(torch.arange(1), _layout(1, 1, box_xy=(3.0, 3.0)))
    act = _action(1, 1, vx=0.5, wz=0.5)
    for _ in range(int(round(2 * math.pi / 0.5 / HL_DT))):  # ~ one full circle of radius 1
        b.step(act)
    assert b.base[0, 0, :2].norm() < 0.05
    assert b.base_vel[0, 0, :2].norm().item() == pytest.approx(0.5, abs=1e-5)
    assert (b.state(torch.zeros(1, 2), torch.ones(1), torch.zeros(1, 1)).base_z == STANDING_HEIGHT).all()


# --- grasp, carry, release ---------------------------------------------------------------------
