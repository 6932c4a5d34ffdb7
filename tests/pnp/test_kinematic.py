"""The kinematic backend: same specs as MuJoCo, TorchRL contract, kinematics, grasp physics,
and the scripted policy completing the task."""
import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from pnp.backend import Layout
from pnp.box import DUAL_ROBOT_BOXES, HANDLE_RADIUS, SINGLE_ROBOT_BOXES
from pnp.envs.pnp_env import PnPEnv
from pnp.kinematic import KinematicBackend, arm_fk, arm_ik
from pnp.kinematics import REACH_MAX, clamp_reach
from pnp.kinematics import ArmKinematics, gripper_down_rotation
from pnp.robot import ARM_DEFAULT, FINGER_STROKE, STANDING_HEIGHT
from pnp.scripted import ScriptedPnP
from pnp.task import ACTION_HIGH, ACTION_LOW, FOOTPRINT_HALF, HL_DT, geometry, rects_overlap
from pnp.terms import CONDITIONS

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
def _layout(n, robots, box=SINGLE_ROBOT_BOXES[0], box_xy=(0.85, 0.0), box_yaw=0.0, bases=None):
    bases = bases or [(0.0, 0.0, 0.0), (2.6, 0.0, math.pi)][:robots]
    return Layout(
        base=torch.tensor(bases, dtype=torch.float32).expand(n, robots, 3).clone(),
        box_xy_yaw=torch.tensor([*box_xy, box_yaw]).expand(n, 3).clone(),
        box_size=torch.tensor(box.size).expand(n, 3).clone(), box_mass=torch.full((n,), box.mass),
    )


def _action(n, robots, ee=(0.75, 0.0, -0.3), yaw=0.0, grasp=0.0, vx=0.0, wz=0.0):
    a = torch.zeros(n, robots, 8)
    a[..., 0], a[..., 2] = vx, wz
    a[..., 3:6] = torch.as_tensor(ee, dtype=torch.float32)
    a[..., 6] = torch.as_tensor(yaw, dtype=torch.float32)
    a[..., 7] = torch.as_tensor(grasp, dtype=torch.float32)
    return a


def _to_world(b, p_base, r=0):
    base = b.base[:, r]
    c, s = torch.cos(base[:, 2]), torch.sin(base[:, 2])
    p_base = p_base.expand(len(base), 3)
    x, y, z = p_base[..., 0], p_base[..., 1], p_base[..., 2]
    return torch.stack([base[:, 0] + c * x - s * y, base[:, 1] + s * x + c * y, z + STANDING_HEIGHT], -1)


def _handle_z_base(box):
    return box.size[2] + 0.06 - STANDING_HEIGHT  # bar axis height with the box on the floor, base frame


def _steps(b, act, n):
    for _ in range(n):
        b.step(act)


def _grasped(b, grasp_cmd):
    s = b.state(torch.zeros(b.num_worlds, 2), torch.ones(b.num_worlds), grasp_cmd)
    return geometry(s).grasped


def test_grasp_carry_release_single():
    box = SINGLE_ROBOT_BOXES[0]
    b = KinematicBackend(1, 1)
    b.reset(torch.arange(1), _layout(1, 1, box))  # handle 1 (-x) right under the default EE
    hz = _handle_z_base(box)
    _steps(b, _action(1, 1, ee=(0.75, 0.0, hz), yaw=math.pi / 2), 10)
    assert not b.grasp.any() and b.finger[0, 0] == pytest.approx(FINGER_STROKE)
    close = _action(1, 1, ee=(0.75, 0.0, hz), yaw=math.pi / 2, grasp=1.0)
    b.step(close)
    assert b.grasp.all()  # one closed command grasps: the stroke takes one HL step, as in MuJoCo
    _steps(b, close, 2)
    assert b.grasp.all() and b.finger[0, 0] == pytest.approx(HANDLE_RADIUS)
    s = b.state(torch.zeros(1, 2), torch.ones(1), torch.ones(1, 1))
    assert s.touch.all() and _grasped(b, torch.ones(1, 1)).all()
    assert not _grasped(b, torch.zeros(1, 1)).any()  # the env's rule also needs the command
    z0 = b.box_pos[0, 2].item()
    offset = b.box_pos[0] - b.ee_pos[0, 0]
    # Lift: the box follows the gripper rigidly.
    lift = _action(1, 1, ee=(0.75, 0.0, hz + 0.3), yaw=math.pi / 2, grasp=1.0)
    b.step(lift)
    assert b.box_vel[0, 2] > 0.5  # finite-difference velocity of the box
    _steps(b, lift, 10)
    assert b.box_pos[0, 2] > z0 + 0.25
    assert torch.allclose(b.box_pos[0] - b.ee_pos[0, 0], offset, atol=1e-5)
    # Carry while walking and turning: relative pose kept in the gripper's frame.
    carry = _action(1, 1, ee=(0.75, 0.0, hz + 0.3), yaw=math.pi / 2, grasp=1.0, vx=0.5, wz=0.4)
    yaw_rel = b.box_yaw[0] - b.base[0, 0, 2]
    _steps(b, carry, 8)
    assert b.grasp.all()
    assert b.box_pos[0, :2].norm() > 0.5
    assert torch.allclose(b.box_pos[0] - b.ee_pos[0, 0], _rotz(b.base[0, 0, 2], offset), atol=1e-4)
    assert torch.sin(b.box_yaw[0] - b.base[0, 0, 2] - yaw_rel).abs() < 1e-4
    assert b.box_vel[0, 5] == pytest.approx(0.4, abs=1e-3)
    assert b.box_vel[0, :2].norm() > 0.3
    # Release: the box falls to the floor and rests there.
    release = _action(1, 1, ee=(0.75, 0.0, hz + 0.3), yaw=math.pi / 2, grasp=0.0)
    b.step(release)
    assert not b.grasp.any() and not b.state(torch.zeros(1, 2), torch.ones(1), torch.zeros(1, 1)).touch.any()
    assert b.box_vel[0, 2] < 0
    _steps(b, release, 5)
    assert b.box_pos[0, 2].item() == pytest.approx(box.size[2] / 2, abs=1e-6)
    assert (b.box_vel[0] == 0).all()
    rest = b.box_pos.clone()
    _steps(b, _action(1, 1, vx=1.0), 3)  # walking away leaves it where it is
    assert torch.equal(b.box_pos, rest) and (b.box_vel == 0).all()


def _rotz(yaw, v):
    c, s = math.cos(yaw), math.sin(yaw)
    return torch.stack([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


def test_no_grasp_when_far_misaligned_or_already_closed():
    box = SINGLE_ROBOT_BOXES[0]
    hz = _handle_z_base(box)
    b = KinematicBackend(3, 1)
    b.reset(torch.arange(3), _layout(3, 1, box))
    ee = torch.tensor([[0.75, 0.0, hz + 0.08], [0.75, 0.0, hz], [0.75, 0.0, hz]])  # above / on / on
    yaw = torch.tensor([math.pi / 2, 0.0, math.pi / 2])  # aligned / along the bar / aligned
    grasp = torch.tensor([1.0, 1.0, 1.0])
    a = _action(3, 1, ee=ee.unsqueeze(1), yaw=yaw.unsqueeze(1), grasp=0.0)
    _steps(b, a, 10)
    a[..., 7] = grasp.unsqueeze(1)
    _steps(b, a, 4)
    assert b.grasp[:, 0].tolist() == [False, False, True]  # world 2 is the control
    assert (b.finger[:2] == 0).all()  # closed on nothing
    # World 0 now descends onto the bar with its fingers already shut: still no grasp.
    a[0, 0, 5] = hz
    _steps(b, a, 6)
    assert not b.grasp[0].any()


def test_slipping_off_the_bar_breaks_the_grasp_and_box_stays():
    box = DUAL_ROBOT_BOXES[0]  # heavy box: one holder cannot move it
    b = KinematicBackend(1, 2)
    b.reset(torch.arange(1), _layout(1, 2, box, box_xy=(1.30, 0.0)))
    hz = _handle_z_base(box)
    yaw = torch.tensor([[math.pi / 2, math.pi / 2]])
    a = _action(1, 2, ee=(0.75, 0.0, hz), yaw=yaw)
    _steps(b, a, 10)
    a[0, 0, 7] = 1.0  # only robot 0 closes
    _steps(b, a, 3)
    assert b.grasp[0].tolist() == [True, False]
    z0 = b.box_pos.clone()
    a[0, 0, 5] = hz + 0.3
    _steps(b, a, 6)
    assert torch.equal(b.box_pos, z0)  # not lifted by one robot
    assert b.grasp[0].tolist() == [False, False]  # the handle slipped out
    assert b.finger[0, 0] == 0.0


def test_dual_lift_needs_both_robots():
    box = DUAL_ROBOT_BOXES[0]
    b = KinematicBackend(1, 2)
    b.reset(torch.arange(1), _layout(1, 2, box, box_xy=(1.30, 0.0)))
    hz = _handle_z_base(box)
    yaw = torch.tensor([[math.pi / 2, math.pi / 2]])
    a = _action(1, 2, ee=(0.75, 0.0, hz), yaw=yaw)
    _steps(b, a, 10)
    a[..., 7] = 1.0
    _steps(b, a, 3)
    assert b.grasp.all()
    assert b.handle[0].tolist() == [True, False]  # robot 0 holds the -x handle, robot 1 the +x one
    a[..., 5] = hz + 0.25
    _steps(b, a, 10)
    assert b.grasp.all()
    assert b.box_pos[0, 2] > box.size[2] / 2 + 0.2
    # One robot lets go: the heavy box drops, and the other loses its handle.
    a[0, 1, 7] = 0.0
    _steps(b, a, 6)
    assert b.box_pos[0, 2].item() == pytest.approx(box.size[2] / 2, abs=1e-6)
    assert not b.grasp.any()



def _robot0_grasps_alone(**options):
    """Two robots facing a dual box's handles; robot 0 grasps, robot 1 stays off.
    Returns the backend, the box, the action (to go on with) and the handle height."""
    box = DUAL_ROBOT_BOXES[0]
    b = KinematicBackend(1, 2, **options)
    b.reset(torch.arange(1), _layout(1, 2, box, box_xy=(1.30, 0.0)))
    hz = _handle_z_base(box)
    a = _action(1, 2, ee=(0.75, 0.0, hz), yaw=torch.tensor([[math.pi / 2, math.pi / 2]]))
    a[0, 1, 3] = 0.4  # robot 1 stays off its handle
    _steps(b, a, 10)
    a[0, 0, 7] = 1.0
    _steps(b, a, 3)
    return b, box, a, hz


def test_a_lone_holder_cannot_lift_the_heavy_box():
    b, box, a, hz = _robot0_grasps_alone()
    assert b.grasp[0].tolist() == [True, False]
    a[0, 0, 5] = hz + 0.25  # robot 0 tries to lift alone: its EE leaves the bar
    _steps(b, a, 10)
    assert not b.grasp[0, 0]
    assert b.box_pos[0, 2].item() == pytest.approx(box.size[2] / 2, abs=1e-6)


def test_a_held_bar_holds_the_hand_through_noisy_commands():
    """grasp_holds: EE commands jittering 5-10 cm per step (a std-floored policy) keep the
    grasp, alone on the resting box and while the pair lifts it; opening lets go."""
    b, box, a, hz = _robot0_grasps_alone(grasp_holds=True)
    grasp_pt = b.ee_pos[0, 0].clone()
    gen = torch.Generator().manual_seed(0)
    jitter = torch.tensor([0.1, 0.1, 0.05])  # (more in z and, this close, the wrist pitch j5 runs out of range)
    for _ in range(20):  # robot 0 jitters alone: the box stays, its hand stays on the bar
        noisy = a.clone()
        noisy[..., 3:6] += jitter * torch.randn(1, 2, 3, generator=gen)
        b.step(noisy)
        assert b.grasp[0].tolist() == [True, False]
    assert (b.ee_pos[0, 0] - grasp_pt).norm() < 1e-3
    assert b.box_pos[0, 2].item() == pytest.approx(box.size[2] / 2, abs=1e-6)
    a[0, 1, 3] = 0.75
    _steps(b, a, 10)
    a[0, 1, 7] = 1.0
    _steps(b, a, 3)
    xy0 = b.box_pos[0, :2].clone()
    a[0, 0, 4], a[0, 1, 4] = 0.1, -0.1  # both pull one way (they face each other): no sliding on the floor
    _steps(b, a, 5)
    assert b.grasp.all() and torch.allclose(b.box_pos[0, :2], xy0)
    a[..., 5] = hz + 0.15
    for _ in range(15):  # both lift through the same jitter
        noisy = a.clone()
        noisy[..., 3:6] += jitter * torch.randn(1, 2, 3, generator=gen)
        b.step(noisy)
    assert b.grasp.all() and b.box_pos[0, 2] > box.size[2] / 2 + 0.1
    assert abs(b.box_pos[0, 1] - xy0[1]) > 0.05  # lifted, the pull carries it
    a[0, 0, 7] = 0.0  # robot 0 lets go: the heavy box drops
    _steps(b, a, 6)
    assert b.box_pos[0, 2].item() == pytest.approx(box.size[2] / 2, abs=1e-6)


# --- the task, end to end --------------------------------------------------------------------------
def test_scripted_policy_succeeds():
    n = 16
    env = PnPEnv(num_worlds=n, num_robots=1, backend="kinematic", seed=0)
    pol = ScriptedPnP(n)
    td = env.reset()
    first = torch.full((n, len(CONDITIONS)), -1, dtype=torch.long)  # first step each condition held
    success = torch.zeros(n, dtype=torch.bool)
    ended = torch.zeros(n, dtype=torch.bool)  # first episode over
    for t in range(env.max_steps):
        td = env.step(pol(td))
        nxt = td["next"]
        cond = nxt["agents", "stage_conditions"][:, 0] & ~ended.unsqueeze(-1)
        first = torch.where(cond & (first < 0), torch.full_like(first, t), first)
        done = nxt["done"].squeeze(-1)
        success |= nxt["success"].squeeze(-1) & ~ended
        ended |= done
        td = env.step_mdp(td)
        if ended.all():
            break
        if done.any():
            pol.reset(done)
            td = env.reset(td.set("_reset", done.unsqueeze(-1)))
    assert success.sum() >= 13, success
    ok = first[success]
    assert (ok >= 0).all()  # all six conditions reached ...
    assert (ok[:, 1:] >= ok[:, :-1]).all(), ok  # ... in order


def test_two_scripted_robots_split_the_handles_and_deliver_the_box():
    n = 16
    env = PnPEnv(num_worlds=n, num_robots=2, backend="kinematic", seed=1)
    pol = ScriptedPnP(n, 2)
    td = env.reset()
    success = torch.zeros(n, dtype=torch.bool)
    for _ in range(env.max_steps):
        td = env.step(pol(td))
        success |= td["next", "success"].squeeze(-1)
        done = td["next", "done"].squeeze(-1)
        td = env.step_mdp(td)
        if (success | done).all():
            break
    assert (pol.handle.sum(-1) == 1).all()  # one handle each
    assert success.all()


def test_episode_goes_on_after_success_without_termination():
    n = 8
    env = PnPEnv(num_worlds=n, num_robots=1, backend="kinematic", seed=0, terminate_on_success=False)
    pol = ScriptedPnP(n)
    td = env.reset()
    assert (td["success_step"] == -1).all()
    first = torch.full((n,), -1, dtype=torch.long)
    for t in range(env.max_steps):
        td = env.step(pol(td))
        nxt = td["next"]
        assert not nxt["terminated"].any()  # nobody falls in the scripted run; success does not end it
        now = nxt["success"].squeeze(-1)
        assert (now | (first < 0)).all()  # success is sticky
        first = torch.where(now & (first < 0), torch.full_like(first, t + 1), first)
        td = env.step_mdp(td)
    assert (first > 0).sum() >= 6
    assert torch.equal(td["success_step"].squeeze(-1), first)  # the step it first held


@pytest.mark.parametrize("blocks", [False, True])
def test_box_blocks_base_keeps_a_walking_robot_out_of_the_box(blocks):
    n = 4
    be = KinematicBackend(n, 1, box_blocks_base=blocks)
    env = PnPEnv(num_worlds=n, num_robots=1, backend=be, seed=0)
    td = env.reset()
    st = be._st
    # Each robot 1.5 m from its box centre along the box's x axis, facing it.
    st["bx"][:, 0] = st["box_x"] - 1.5 * st["box_c"]
    st["by"][:, 0] = st["box_y"] - 1.5 * st["box_s"]
    st["yaw"][:, 0] = st["box_yaw"]
    action = torch.zeros(n, 1, 8)
    action[..., 0] = 0.5  # m/s forward, into the box
    action[..., 3], action[..., 5] = 0.6, -0.2
    for _ in range(30):
        td["agents", "action"] = action
        td = env.step(td)["next"]
    st = be._st  # each step returns a new state dict
    dx, dy = st["box_x"] - st["bx"][:, 0], st["box_y"] - st["by"][:, 0]
    c, s = torch.cos(st["yaw"][:, 0]), torch.sin(st["yaw"][:, 0])
    inside = rects_overlap(c * dx + s * dy, c * dy - s * dx, torch.ones(n), torch.zeros(n), st["box_size"][:, 0] / 2,
                           st["box_size"][:, 1] / 2, *FOOTPRINT_HALF)
    walked = torch.hypot(dx, dy)
    if blocks:
        assert not inside.any() and (walked < 1.5 - 0.4).all()  # walked up to the box, then stopped
    else:
        assert inside.all() and (walked < 0.05).all()  # 1.5 m walked: into the box, to its centre
