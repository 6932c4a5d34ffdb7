"""The optimised task functions of ``pnp.task`` give the outputs of the frozen plain
(matmul/gather) implementation in ``tests/pnp/_task_reference.py``: on states of both
backends, one and two robots (random and scripted steps, box grasped and lifted), through
the env's ``_observe`` too, and on random states with tilted boxes and grippers."""
import dataclasses
import math

import pytest
import torch

import pnp.task as T
from pnp.envs.pnp_env import BLOCKS, PnPEnv
from pnp.task.scripted import ScriptedPnP
from pnp.task import ACTION_HIGH, ACTION_LOW, PnPState
from pnp.task.terms import CONDITIONS, REWARD_TERMS
from tests.pnp import _task_reference as REF

ATOL, RTOL = 1e-5, 1e-5  # float32; rewards reach ~100



def _close(a, b, what):
    assert a.shape == b.shape and a.dtype == b.dtype, (what, a.shape, b.shape, a.dtype, b.dtype)
    if a.dtype == torch.bool:
        assert torch.equal(a, b), (what, (a != b).nonzero())
    else:
        assert torch.allclose(a, b, rtol=RTOL, atol=ATOL), (what, (a - b).abs().max())


def _compare(s: PnPState, action, last_action, out=None):
    """Every output of pnp.task against the reference on state ``s``; ``out``: the env's."""
    g, g_ref = T.geometry(s), REF.geometry(s)
    for f in dataclasses.fields(g_ref):
        _close(getattr(g, f.name), getattr(g_ref, f.name), f"geometry.{f.name}")
    _close(T.handles(s), REF.handles(s), "handles")
    _close(T.to_base(s, s.ee_pos), REF.to_base(s, s.ee_pos), "to_base")
    h = T.handles(s).unsqueeze(1).expand(-1, s.ee_pos.shape[1], -1, -1)
    _close(T.to_base(s, h), REF.to_base(s, h), "to_base [N, R, 2, 3]")
    _close(T.collisions(s), REF._collisions(s), "collisions")
    cond = T.stage_conditions(s, g)
    _close(cond, REF.stage_conditions(s, g_ref), "stage_conditions")
    terms = T.reward_terms(s, g, action, last_action, cond)
    terms_ref = REF.reward_terms(s, g_ref, action, last_action, cond)
    _close(terms, terms_ref, "reward_terms")
    _close(T.default_reward(terms), REF.default_reward(terms_ref), "default_reward")
    obs, obs_ref = T.observations(s, g, action), REF.observations(s, g_ref, action)
    assert set(obs) == set(obs_ref)
    for k in obs_ref:
        _close(obs[k], obs_ref[k], f"observations.{k}")
    if out is not None:  # the env's own outputs (its _observe) match the reference too
        a = out["agents"]
        for k in BLOCKS:
            _close(a[k], obs_ref[k], f"env {k}")
        _close(a["observation"], torch.cat([obs_ref[k] for k in BLOCKS], -1), "env observation")
        _close(a["stage_conditions"], cond, "env stage_conditions")
        _close(a["reward_terms"], terms_ref, "env reward_terms")
        _close(a["reward"], REF.default_reward(terms_ref), "env reward")
    return cond


# (backend, robots, scripted steps from reset): enough to grasp (and, one robot, lift).
CASES = [("kinematic", 1, 40), ("mujoco", 1, 40), ("kinematic", 2, 42), ("mujoco", 2, 0)]
RANDOM_STEPS = 5


@pytest.mark.parametrize("backend,robots,steps", CASES)
def test_task_matches_reference_on_env_states(backend, robots, steps):
    torch.manual_seed(0)
    n = 8
    env = PnPEnv(num_worlds=n, num_robots=robots, backend=backend, seed=0, nthread=1)
    try:
        pol = ScriptedPnP(n, robots)
        td = env.reset()
        seen = torch.zeros(len(CONDITIONS), dtype=torch.bool)
        for t in range(steps + RANDOM_STEPS):
            if t < steps:
                td = pol(td)
            else:  # then a few random steps
                td.update(env.full_action_spec.rand())
            last = env._last_action.clone()
            td = env.step(td)
            if t % 3 == 2 or t >= steps:  # every step costs ~8 ms of comparisons
                action = env._last_action  # the (clipped) action just applied
                s = env.backend.state(env._goal, env._init_goal_dist, action[..., 7])
                seen |= _compare(s, action, last, td["next"]).flatten(0, 1).any(0)
            td = env.step_mdp(td)
        if steps:
            assert seen[1], "the box was never grasped: the comparison missed the grasped states"
        if steps and robots == 1:
            assert seen[2], "the box was never lifted"
    finally:
        env.close()


def _random_rot(n, g):
    q = torch.randn(n, 4, generator=g)
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


@pytest.mark.parametrize("robots", [1, 2])
def test_task_matches_reference_on_random_states(robots):
    """Arbitrary rotations (tilted box, any gripper orientation), EEs near the handles."""
    g = torch.Generator().manual_seed(robots)
    N, R = 512, robots
    u = lambda *shape, lo=-1.0, hi=1.0: lo + (hi - lo) * torch.rand(*shape, generator=g)  # noqa: E731
    box_pos = torch.cat([u(N, 2, lo=-2, hi=2), u(N, 1, lo=0.0, hi=0.6)], -1)
    s0 = PnPState(
        base=torch.cat([u(N, R, 2, lo=-3, hi=3), u(N, R, 1, lo=-math.pi, hi=math.pi)], -1),
        base_z=u(N, R, lo=0.3, hi=0.6), base_vel=u(N, R, 3), arm_q=u(N, R, 6, lo=-3, hi=3), arm_qd=u(N, R, 6),
        finger_q=u(N, R, 2, lo=0, hi=0.07), touch=torch.rand(N, R, 2, generator=g) < 0.7,
        ee_pos=torch.zeros(N, R, 3), ee_rot=_random_rot(N * R, g).reshape(N, R, 3, 3), box_pos=box_pos,
        box_rot=_random_rot(N, g), box_vel=u(N, 6), box_size=u(N, 3, lo=0.3, hi=1.2), goal=u(N, 2),
        init_goal_dist=u(N, lo=0.5, hi=3), grasp_cmd=torch.rand(N, R, generator=g),
    )
    # EEs within a few cm of a handle, so "ready"/"grasped" occur; a box level in a quarter.
    h = REF.handles(s0)
    k = torch.randint(0, 2, (N, R), generator=g)
    ee = h[torch.arange(N)[:, None], k] + 0.04 * torch.randn(N, R, 3, generator=g)
    level = torch.rand(N, generator=g) < 0.25
    yaw = u(N, lo=-math.pi, hi=math.pi)
    box_rot = torch.where(level[:, None, None], T.yaw_rotation(yaw), s0.box_rot)
    s = dataclasses.replace(s0, ee_pos=ee, box_rot=box_rot)
    lo, hi = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)
    action, last = lo + (hi - lo) * torch.rand(N, R, 8, generator=g), lo + (hi - lo) * torch.rand(N, R, 8, generator=g)
    action[..., 7] = s.grasp_cmd  # the reference reads the grab-action probability from the state
    cond = _compare(s, action, last)
    assert cond[..., 0].any() and cond[..., 1].any()


def test_check_action_fast_path_keeps_errors_and_clipping():
    """The env's finite-sum fast path: huge finite actions (the sum overflows) are clipped,
    not rejected; NaN/Inf still name their worlds."""
    env = PnPEnv(num_worlds=4, num_robots=1, backend="kinematic")
    a = env._last_action.clone()  # the neutral action, in bounds
    a[1, 0, :] = 3e38  # finite, but the float32 sum overflows to inf
    clipped_action, clipped = env._check_action(a)
    assert clipped.squeeze(-1).tolist() == [False, True, False, False] and env.clipped_count == 1
    assert torch.equal(clipped_action[1, 0], torch.tensor(ACTION_HIGH))
    a[2, 0, 3], a[3, 0, 0] = float("nan"), -float("inf")
    with pytest.raises(ValueError, match=r"^\('agents', 'action'\) has NaN or Inf in worlds \[2, 3\]$"):
        env._check_action(a)


def test_gripper_toggle_counts_flips_of_the_command_while_nothing_is_held():
    env = PnPEnv(num_worlds=2, num_robots=1, backend="kinematic", seed=0, nthread=1)
    try:
        td = env.reset()
        col = REWARD_TERMS.index("gripper_toggle")
        seen = []
        for grip in (1.0, 0.0, 0.0, 1.0):  # from the reset's open command: flip, flip, hold, flip
            a = env._last_action.clone()
            a[..., 7] = grip
            td["agents", "action"] = a
            td = env.step(td)
            seen.append(td["next", "agents", "reward_terms"][:, 0, col].tolist())
            td = env.step_mdp(td)
        assert seen == [[1.0, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, 1.0]]
        action, last = env._last_action, env._last_action.clone()
        last[..., 7] = 0.0
        s = env.backend.state(env._goal, env._init_goal_dist, action[..., 7])
        held = dataclasses.replace(T.geometry(s), grasped=torch.ones(2, 1, dtype=torch.bool))
        assert T.reward_terms(s, held, action, last, T.stage_conditions(s, held))[..., col].eq(0).all()
    finally:
        env.close()


def test_object_tilt_costs_the_unheld_box_leaving_upright():
    env = PnPEnv(num_worlds=3, num_robots=1, backend="kinematic", seed=0, nthread=1)
    try:
        env.reset()
        col = REWARD_TERMS.index("object_tilt")
        action = env._last_action.clone()
        s = env.backend.state(env._goal, env._init_goal_dist, action[..., 7])
        c, sn = math.cos(math.pi / 3), math.sin(math.pi / 3)  # upright, tilted 60 deg about x, on its side
        rots = [torch.eye(3), torch.tensor([[1.0, 0, 0], [0, c, -sn], [0, sn, c]]),
                torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])]
        s = dataclasses.replace(s, box_rot=torch.stack(rots))
        g = dataclasses.replace(T.geometry(s), grasped=torch.zeros(3, 1, dtype=torch.bool))
        tilt = T.reward_terms(s, g, action, action, T.stage_conditions(s, g))[:, 0, col]
        assert torch.allclose(tilt, torch.tensor([0.0, 0.5, 1.0]), atol=1e-6)
        held = dataclasses.replace(g, grasped=torch.ones(3, 1, dtype=torch.bool))
        assert T.reward_terms(s, held, action, action, T.stage_conditions(s, held))[..., col].eq(0).all()
    finally:
        env.close()


def test_base_approach_pays_the_speed_towards_the_handle_only_while_far_and_unheld():
    env = PnPEnv(num_worlds=4, num_robots=1, backend="kinematic", seed=0, nthread=1)
    try:
        env.reset()
        col = REWARD_TERMS.index("base_approach")
        action = env._last_action.clone()
        s = env.backend.state(env._goal, env._init_goal_dist, action[..., 7])
        g = dataclasses.replace(T.geometry(s), grasped=torch.zeros(4, 1, dtype=torch.bool))
        to_handle = g.ee_handle[..., :2] / g.ee_handle[..., :2].norm(dim=-1, keepdim=True)
        assert (g.ee_handle[..., :2].norm(dim=-1) > 0.6).all()  # every start is beyond the radius

        def paid(vel_xy, geom=g, state=s):
            moving = dataclasses.replace(state, base_vel=torch.cat([vel_xy, torch.zeros(4, 1, 1)], -1))
            return T.reward_terms(moving, geom, action, action, T.stage_conditions(moving, geom))[:, 0, col]

        speed = torch.tensor([0.5, -0.5, 3.0, 0.0]).view(4, 1, 1)
        assert torch.allclose(paid(speed * to_handle), torch.tensor([0.5, -0.5, 1.0, 0.0]), atol=1e-5)
        sideways = torch.stack([-to_handle[..., 1], to_handle[..., 0]], -1)
        assert paid(sideways).abs().max() < 1e-5
        held = dataclasses.replace(g, grasped=torch.ones(4, 1, dtype=torch.bool))
        assert paid(to_handle, held).eq(0).all()
        near = dataclasses.replace(g, ee_handle=g.ee_handle * 0.4 / g.ee_handle[..., :2].norm(dim=-1, keepdim=True))
        assert paid(to_handle, near).eq(0).all()  # within 0.5 m the stage terms take over
    finally:
        env.close()


def test_base_stance_pays_for_the_base_near_its_handle_only_while_unheld():
    env = PnPEnv(num_worlds=4, num_robots=1, backend="kinematic", seed=0, nthread=1)
    try:
        env.reset()
        col = REWARD_TERMS.index("base_stance")
        action = env._last_action.clone()
        s = env.backend.state(env._goal, env._init_goal_dist, action[..., 7])
        g = dataclasses.replace(T.geometry(s), grasped=torch.zeros(4, 1, dtype=torch.bool))
        dist = torch.tensor([0.6, 0.9, 1.2, 3.0]).view(4, 1)  # inside, halfway, beyond, far
        handle = torch.stack([s.base[..., 0] + 0.6 * dist, s.base[..., 1] - 0.8 * dist, g.handle[..., 2]], -1)
        placed = dataclasses.replace(g, handle=handle)
        paid = T.reward_terms(s, placed, action, action, T.stage_conditions(s, placed))[:, 0, col]
        assert torch.allclose(paid, torch.tensor([1.0, 0.5, 0.0, 0.0]), atol=1e-5)
        held = dataclasses.replace(placed, grasped=torch.ones(4, 1, dtype=torch.bool))
        assert T.reward_terms(s, held, action, action, T.stage_conditions(s, held))[..., col].eq(0).all()
    finally:
        env.close()
