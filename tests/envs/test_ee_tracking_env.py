"""EETrackingEnv (4-stage EE tracking ablation) on both backends: specs, sampling, the stage
count against StageTransition, the reward schedules, bad input, exact resumes."""
import math

import pytest
import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from pnp import task
from pnp.task.ee_scripted import ScriptedEETracking
from pnp.task.ee_tracking import (
    BOX_PARK_X, EE_CONDITIONS, EE_OBS_BLOCKS, EE_REWARD_TERMS, MIN_GAP, N_POINTS, POINT_HEIGHT, POINT_RING,
    TOUCH_TOL, ee_reward_config, ee_stage_graph, reward_terms, sample_ee_layout,
)
from pnp.envs.ee_tracking_env import EETrackingEnv
from pnp.task import ACTION_HIGH, ACTION_LOW, BaseFrame, ego_block
from pnp.task.terms import REWARD_TERMS
from pnp.transforms import StageTransition, make_reward_schedule


def _env(n=4, backend="kinematic", **kw):
    return EETrackingEnv(num_worlds=n, backend=backend, nthread=1, **kw)


def _neutral(env):
    return env._last_action.clone()


def _curriculum_env(schedule="dynamic", n=8, **kw):
    base = _env(n, **kw)
    sched = make_reward_schedule(schedule, **ee_reward_config(), K=2.0, mu_min=0.1)
    stages = StageTransition(ee_stage_graph(), one_hot_key=("agents", "stage_one_hot"))
    return TransformedEnv(base, Compose(stages, sched)), sched


@pytest.mark.parametrize("backend", ["kinematic", "mujoco"])
def test_specs(backend):
    env = _env(3, backend)
    check_env_specs(env)
    td = env.reset()
    assert td["agents", "observation"].shape == (3, 1, sum(EE_OBS_BLOCKS.values())) == (3, 1, 47)
    assert td["agents", "reward_terms"].shape == (3, 1, len(EE_REWARD_TERMS))
    assert td["agents", "stage_conditions"].shape == (3, 1, len(EE_CONDITIONS))
    assert torch.equal(torch.cat([td["agents", k] for k in EE_OBS_BLOCKS], -1), td["agents", "observation"])
    spec = env.full_action_spec["agents", "action"]
    assert torch.equal(spec.space.low[0, 0], torch.tensor(ACTION_LOW))
    assert torch.equal(spec.space.high[0, 0], torch.tensor(ACTION_HIGH))
    assert env.max_steps == 200
    env.close()


def test_points_are_sampled_within_reach_and_apart():
    layout, pts = sample_ee_layout(torch.Generator().manual_seed(0), 2000)
    r = pts[..., :2].norm(dim=-1)
    assert (r >= POINT_RING[0] - 1e-5).all() and (r <= POINT_RING[1] + 1e-5).all()
    assert (pts[..., 2] >= POINT_HEIGHT[0]).all() and (pts[..., 2] <= POINT_HEIGHT[1]).all()
    assert ((pts[:, 1:] - pts[:, :-1]).norm(dim=-1) >= MIN_GAP).all()
    assert (layout.base[..., :2] == 0).all() and (layout.box_xy_yaw[:, 0] == BOX_PARK_X).all()
    # Spread over every direction, not only ahead of the robot.
    rel = torch.remainder(torch.atan2(pts[..., 1], pts[..., 0]) - layout.base[:, :, 2], 2 * math.pi)
    assert torch.histc(rel, 4, 0, 2 * math.pi).min() > 0.2 * rel.numel() / 4


def test_nothing_touched_at_reset_and_observed_points_match_the_world():
    env = _env(64)
    td = env.reset()
    assert not td["agents", "stage_conditions"].any()
    pts = td["agents", "points"][:, 0]
    ee_b = td["agents", "ego"][:, 0, task.OBS_FIELDS["ego"]["ee_pos"]]
    d = (pts[:, :12].unflatten(-1, (N_POINTS, 3)) - ee_b[:, None]).norm(dim=-1)
    torch.testing.assert_close(d, pts[:, 12:], atol=1e-5, rtol=0)
    assert (pts[:, 12] >= MIN_GAP - 1e-4).all()


def test_shared_blocks_match_the_pnp_task():
    env = _env(8)
    td = env.reset()
    a = torch.rand(8, 1, 8) * (torch.tensor(ACTION_HIGH) - torch.tensor(ACTION_LOW)) + torch.tensor(ACTION_LOW)
    last = _neutral(env)
    td = env.step(td.set(("agents", "action"), a))
    s = env.backend.state(env._goal, env._init_goal_dist, a[..., 7])
    frame = BaseFrame(s)
    g = task.geometry(s)
    pnp_terms = task.reward_terms(s, g, a, last, task.stage_conditions(s, g), frame)
    torch.testing.assert_close(ego_block(s, frame, a), task.observations(s, g, a, frame)["ego"], rtol=0, atol=0)
    ours = reward_terms(s, torch.ones(8, 1, N_POINTS), a, last)
    for name in ("action_rate", "joint_limits"):
        torch.testing.assert_close(ours[..., EE_REWARD_TERMS.index(name)], pnp_terms[..., REWARD_TERMS.index(name)])
    torch.testing.assert_close(td["next", "agents", "ego"], ego_block(s, frame, a))


def test_scripted_policy_passes_the_stages_in_order_and_the_counts_agree():
    """The env's own count, StageTransition's stage and the policy's count agree at every
    step; stages rise by at most one; success is exactly reaching S4."""
    n = 32
    env, _ = _curriculum_env("liu_max", n)
    pol = ScriptedEETracking(n)
    td = env.reset()
    prev = torch.zeros(n, dtype=torch.long)
    successes, seen = 0, torch.zeros(n, N_POINTS + 1, dtype=torch.bool)
    for _ in range(200):
        td = pol(td)
        assert torch.equal(pol.touched, prev)  # the policy counts from the observed distances
        td = env.step(td)
        nxt = td["next"]
        stage = nxt["agents", "stage"].reshape(n)
        assert torch.equal(stage, env.base_env.points_touched)
        assert ((stage - prev) >= 0).all() and ((stage - prev) <= 1).all()
        assert torch.equal(nxt["success"].reshape(n), stage == N_POINTS)
        assert torch.equal(nxt["terminated"].reshape(n), stage == N_POINTS)
        seen[torch.arange(n), stage] = True
        done = nxt["done"].reshape(n)
        successes += int(nxt["success"].sum())
        td = env.step_mdp(td)
        if done.any():
            td = env.reset(td.set("_reset", done.unsqueeze(-1)))
            pol.reset(done)
        prev = td["agents", "stage"].reshape(n)
    assert successes >= 0.9 * n  # every world passes S4 at least once (most of them twice)
    assert seen.all(-1).float().mean() > 0.9


def test_without_termination_the_episode_goes_on_at_s4_and_every_term_pays():
    """terminate_on_success=False (training): the fourth touch ends nothing, success_step keeps
    its step, and at S4 all four gated terms pay 1 whatever the EE does next."""
    n, steps = 16, 200
    env = _env(n, max_episode_steps=steps, terminate_on_success=False)
    pol = ScriptedEETracking(n)
    td = env.reset()
    assert (td["success_step"] == -1).all()
    first = torch.full((n,), -1)
    for t in range(1, steps + 1):
        td = env.step(pol(td))
        nxt = td["next"]
        stage = env.points_touched
        first = torch.where((stage == N_POINTS) & (first < 0), t, first)
        assert not nxt["terminated"].any()
        assert torch.equal(nxt["success_step"].reshape(n), first)
        assert torch.equal(nxt["success"].reshape(n), first >= 0)
        at_end = stage == N_POINTS
        assert (nxt["agents", "reward_terms"][at_end, 0, :N_POINTS] == 1.0).all()
        assert torch.equal(nxt["done"].reshape(n), torch.full((n,), t == steps))
        td = env.step_mdp(td)
    assert (first >= 0).float().mean() > 0.9  # most worlds finished, and none of them ended there


def test_touch_needs_the_tolerance_and_the_order():
    env = _env(3)
    td = env.reset()
    for _ in range(3):  # let the EE settle on the neutral command
        td = env.step_mdp(env.step(td.set(("agents", "action"), _neutral(env))))
    ee = env.backend.ee_pos[:, 0].clone()
    off = torch.tensor([1.0, 0.0, 0.0])
    env._points[:] = ee[:, None] + 2.0 * off  # far from every point
    env._points[0, 0] = ee[0] + (TOUCH_TOL - 0.01) * off  # inside the tolerance
    env._points[1, 0] = ee[1] + (TOUCH_TOL + 0.01) * off  # just outside
    env._points[2, 1] = ee[2]  # point 2 before point 1: an out-of-order touch
    out = env.step(td.set(("agents", "action"), _neutral(env)))["next"]
    cond = out["agents", "stage_conditions"][:, 0]
    assert cond[:, 0].tolist() == [True, False, False] and cond[2, 1]
    assert env.points_touched.tolist() == [1, 0, 0]

@pytest.mark.parametrize("schedule", ["dynamic", "liu_max", "liu_min"])
def test_schedules_run_on_the_env(schedule):
    n = 8
    env, sched = _curriculum_env(schedule, n, max_episode_steps=40)
    check_env_specs(env)
    pol = ScriptedEETracking(n)
    td = env.reset()
    mu = torch.tensor(list(ee_reward_config()["mu"].values()))
    w = torch.tensor([ee_reward_config()["fixed_weights"][k] for k in ("action_rate", "joint_limits")])
    ended = 0
    for _ in range(60):
        td = env.step(pol(td))
        nxt = td["next"]
        terms, stage = nxt["agents", "reward_terms"][:, 0], nxt["agents", "stage"].reshape(n, 1)
        fixed = terms[:, 4:] @ w
        k = torch.arange(N_POINTS)
        if schedule == "dynamic":
            expected = fixed + (sched.rho[:, 0] * terms[:, :4]).sum(-1)
        else:
            frozen = 1.0 if schedule == "liu_max" else 0.0  # high / low of track_k
            expected = fixed + (mu * (terms[:, :4] * (k == stage) + frozen * (k < stage))).sum(-1)
        torch.testing.assert_close(nxt["agents", "reward"].reshape(n), expected)
        done = nxt["done"].reshape(n)
        ended += int(done.sum())
        td = env.step_mdp(td)
        if done.any():
            td = env.reset(td.set("_reset", done.unsqueeze(-1)))
            pol.reset(done)
    assert ended >= n
    hist = sched.pop_stage_histogram()
    assert hist.sum() == ended and hist[1:].sum() > 0
    if schedule == "dynamic":  # episodes ended past S0, so some S0 scales went down
        assert (sched.rho[..., 0] < 10.0).any()


def test_under_the_gated_rule_liu_max_pays_what_fixed_scales_pay():
    # A touched point's gated term is 1, Liu (max)'s constant for it mu * high = mu * 1; a later
    # point's term is 0 under both: the two schedules are one reward (the ablation runs liu_max only).
    n = 8
    envs = [_curriculum_env(schedule, n, max_episode_steps=40)[0] for schedule in ("fixed", "liu_max")]
    pols = [ScriptedEETracking(n) for _ in envs]
    tds = [env.reset() for env in envs]
    stages_seen = set()
    for _ in range(60):
        tds = [env.step(pol(td)) for env, pol, td in zip(envs, pols, tds)]
        a, b = (td["next"] for td in tds)
        torch.testing.assert_close(a["agents", "reward_terms"], b["agents", "reward_terms"], rtol=0, atol=0)
        torch.testing.assert_close(a["agents", "reward"], b["agents", "reward"], rtol=1e-6, atol=1e-5)
        stages_seen |= set(a["agents", "stage"].flatten().tolist())
        done = a["done"].reshape(n)
        tds = [env.step_mdp(td) for env, td in zip(envs, tds)]
        if done.any():
            tds = [env.reset(td.set("_reset", done.unsqueeze(-1))) for env, td in zip(envs, tds)]
            for pol in pols:
                pol.reset(done)
    assert len(stages_seen) >= 3  # the comparison covered completed, current and later points


def test_truncation_at_the_episode_limit():
    env = _env(2, max_episode_steps=3)
    td = env.reset()
    for t in range(3):
        td = env.step(td.set(("agents", "action"), _neutral(env)))
        assert td["next", "truncated"].all() == (t == 2) and not td["next", "terminated"].any()
        td = env.step_mdp(td)


def test_partial_reset_touches_only_masked_worlds():
    env = _env(4)
    td = env.reset()
    a = _neutral(env)
    a[..., 0] = 0.5
    td = env.step_mdp(env.step(td.set(("agents", "action"), a)))
    pts, base = env._points.clone(), env.backend.base.clone()
    env._touched[:] = 2
    out = env.reset(td.clone().set("_reset", torch.tensor([[False], [True], [False], [True]])))
    assert torch.equal(env._points[[0, 2]], pts[[0, 2]]) and not torch.equal(env._points[[1, 3]], pts[[1, 3]])
    assert torch.equal(env.backend.base[[0, 2]], base[[0, 2]])
    assert env.points_touched.tolist() == [2, 0, 2, 0] and env._steps.tolist() == [1, 0, 1, 0]
    torch.testing.assert_close(out["agents", "observation"][[0, 2]], td["agents", "observation"][[0, 2]])


def test_bad_actions_raise_naming_the_value():
    env = _env(4)
    td = env.reset()
    a = _neutral(env)
    a[1, 0, 3] = float("nan")
    a[3, 0, 0] = float("-inf")
    with pytest.raises(ValueError, match=r"\('agents', 'action'\) has NaN or Inf in worlds \[1, 3\]"):
        env.step(td.set(("agents", "action"), a))
    with pytest.raises(ValueError, match=r"shape \(4, 1, 7\).*expected \(4, 1, 8\)"):
        env.step(td.set(("agents", "action"), torch.zeros(4, 1, 7)))
    with pytest.raises(ValueError, match="'bullet'"):
        EETrackingEnv(num_worlds=2, backend="bullet")
    a = _neutral(env)
    a[2, 0, 1] = 3.0
    out = env.step(td.set(("agents", "action"), a))
    assert out["next", "agents", "action_clipped"][:, 0].tolist() == [False, False, True, False]


@pytest.mark.parametrize("backend", ["kinematic", "mujoco"])
def test_get_set_state_continues_exactly(backend):
    env = _env(3, backend)
    pol = ScriptedEETracking(3)
    td = env.reset()
    for _ in range(3):
        td = env.step_mdp(env.step(pol(td)))
    saved, td_saved = env.get_state(), td.clone()
    a = pol(td)["agents", "action"].clone()
    mask = torch.tensor([[True], [False], [False]])
    ref = [env.step_mdp(env.step(td.set(("agents", "action"), a)))["agents", "observation"]]
    ref.append(env.reset(td.clone().set("_reset", mask))["agents", "observation"])
    other = _env(3, backend, seed=99)
    other.set_state(saved)
    got = [other.step_mdp(other.step(td_saved.set(("agents", "action"), a)))["agents", "observation"]]
    got.append(other.reset(td_saved.clone().set("_reset", mask))["agents", "observation"])
    for r, g in zip(ref, got):
        torch.testing.assert_close(r, g, rtol=0, atol=0)
    with pytest.raises(KeyError, match="_points"):
        other.set_state({k: v for k, v in saved.items() if k != "_points"})


@pytest.mark.slow
def test_scripted_policy_on_mujoco_touches_all_points_in_time():
    """Measured: 32 worlds all succeed, median 10 s, max ~15 s of the 20 s limit."""
    n = 16
    env = _env(n, "mujoco")
    pol = ScriptedEETracking(n)
    td = env.reset()
    ended = torch.zeros(n, dtype=torch.bool)
    for _ in range(env.max_steps):
        td = env.step(pol(td))
        ended |= td["next", "success"].reshape(n)
        td = env.step_mdp(td)
        if ended.all():
            break
    assert ended.all()
    box = torch.from_numpy(env.backend.physics.qpos[:, env.backend.idx.box_qpos : env.backend.idx.box_qpos + 2])
    assert ((box[:, 0] - BOX_PARK_X).abs() < 0.01).all()  # the parked box stayed where it was put


@pytest.mark.parametrize("rule", ["plain", "saturated", "gated"])
def test_track_rules(rule):
    """World 0 has touched point 1, world 1 none: point 1's term is 1 once touched unless
    plain; point 3's term is 0 before its turn when gated."""
    env = EETrackingEnv(num_worlds=2, backend="kinematic", track_rule=rule)
    td = env.reset()
    env._touched[:] = torch.tensor([1, 0])
    td = env.step(td.set(("agents", "action"), _neutral(env)))
    terms = td["next", "agents", "reward_terms"][:, 0]
    track_1, track_3 = terms[:, EE_REWARD_TERMS.index("track_1")], terms[:, EE_REWARD_TERMS.index("track_3")]
    assert track_1[1] < 0.9  # the start EE is >= MIN_GAP from point 1
    assert (track_1[0] == 1.0) == (rule != "plain")
    assert (track_3 == 0.0).all() == (rule == "gated") and (track_3 > 0).all() == (rule != "gated")
    with pytest.raises(ValueError, match="track_rule must be one of"):
        EETrackingEnv(num_worlds=1, backend="kinematic", track_rule="sometimes")


def test_the_task_settings_reach_the_env_and_bad_ones_are_named():
    """env.ee_tracking: points within point_ring of the start; a longer coarse kernel pays
    more for the same distance; bad values and a non-EE task's settings are refused."""
    from omegaconf import OmegaConf

    from pnp.training.config import EnvConfig
    from pnp.training.tasks import _ee_tracking_env, _task

    cfg = OmegaConf.structured(EnvConfig)
    cfg.task, cfg.backend, cfg.num_worlds = "ee_tracking", "kinematic", 64
    cfg.ee_tracking.point_ring, cfg.ee_tracking.track_sigma = [1.0, 1.2], [3.0, 0.1]
    cfg.terminate_on_success = False
    env = _ee_tracking_env(cfg, seed=0)
    assert env.terminate_on_success is False
    horizontal = env._points[..., :2].norm(dim=-1)  # the robot starts at the origin
    assert ((horizontal >= 1.0 - 1e-5) & (horizontal <= 1.2 + 1e-5)).all()
    wide = env._observe(_neutral(env), _neutral(env))["agents", "reward_terms"][:, 0, 0]
    narrow = EETrackingEnv(num_worlds=64, backend="kinematic", point_ring=(1.0, 1.2), seed=0)
    narrow._points = env._points.clone()
    assert (wide > narrow._observe(_neutral(env), _neutral(env))["agents", "reward_terms"][:, 0, 0]).all()
    with pytest.raises(ValueError, match=r"track_sigma must be two positive lengths \(m\), got \[0.0, 0.1\]"):
        EETrackingEnv(num_worlds=1, backend="kinematic", track_sigma=(0.0, 0.1))
    with pytest.raises(ValueError, match=r"point_ring must be \[lo, hi\] in m with 0 < lo <= hi, got \[2.0, 1.0\]"):
        EETrackingEnv(num_worlds=1, backend="kinematic", point_ring=(2.0, 1.0))
    cfg.task = "pnp"
    with pytest.raises(ValueError, match=r"env.ee_tracking=.* sets the EE-tracking task; this run's env.task is 'pnp'"):
        _task(cfg)
