"""Kinematic backend: grasping, carrying and releasing, the scripted policies on it, and its
stand-ins for contacts (split from test_kinematic.py)."""
import math

import pytest
import torch
from pnp.envs.pnp_env import PnPEnv

from pnp.sim.box import DUAL_ROBOT_BOXES, HANDLE_RADIUS, SINGLE_ROBOT_BOXES
from pnp.kinematic.backend import KinematicBackend
from pnp.sim.robot import FINGER_STROKE
from pnp.task.scripted import ScriptedPnP
from pnp.task import FOOTPRINT_HALF, rects_overlap
from pnp.task.terms import CONDITIONS
from tests.pnp._kinematic_helpers import (
    _action,
    _grasped,
    _handle_z_base,
    _layout,
    _steps,
)


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
