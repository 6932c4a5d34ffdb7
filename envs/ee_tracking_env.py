"""Batched 4-stage end-effector tracking env (the paper's curriculum ablation): one robot
touches four points in order with its gripper (task in ``pnp.task.ee_tracking``).

Keys (group ``"agents"``, one robot), laid out as in ``PnPEnv``:
  ("agents", "action")            [N, 1, 8]  as PnPEnv (the grasp entry only moves the fingers)
  ("agents", "observation")       [N, 1, 47] ego | points, concatenated
  ("agents", "ego"|"points")      the same blocks, named
  ("agents", "reward_terms")      [N, 1, 6]  track_1..track_4, action_rate, joint_limits
  ("agents", "stage_conditions")  [N, 1, 4]  touch_1..touch_4: EE within TOUCH_TOL of point k
  ("agents", "reward")            [N, 1, 1]  default reward: terms at mu_j, no curriculum
  ("agents", "action_clipped")    [N, 1]     the action was out of bounds and clipped
  "success", "diverged"           [N, 1]     all four points touched / physics diverged
  "success_step"                  [N, 1]     step at which the fourth point was touched, -1 before
  "done", "terminated", "truncated" [N, 1]   success (if ``terminate_on_success``) / time limit or
                                              divergence

``terminate_on_success=False`` (training, as in PnPEnv) keeps the episode going after the fourth
touch: at S4 every point's gated term pays. Ending it there gives up the touched points' per-step
terms, which taught the policy to stay away from point 4 (docs/history/ablation_ee.md, probe E5).

The stage belongs to ``StageTransition(ee_stage_graph())``; the env keeps its own count
of points touched (:attr:`points_touched`), advanced by the same forward-only rule, to end
the episode on success, so the two agree by construction.

Both backends are built for pick-and-place and always simulate a box: it is parked
``BOX_PARK_X`` = 50 m away, where nothing reads it and no robot can walk to it.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded

from pnp.sim.backend import Backend
from pnp.sim.box import SINGLE_ROBOT_BOXES
from pnp.task.ee_tracking import (
    EE_CONDITIONS, EE_OBS_BLOCKS, EE_REWARD_TERMS, EPISODE_S, N_POINTS, POINT_RING, TRACK_RULES, TRACK_SIGMA,
    default_reward, observations,
    point_distances, reward_terms, sample_ee_layout, stage_conditions,
)
from pnp.envs.pnp_env import RobotEnvBase, _torch_single_threaded
from pnp.task import ACTION_HIGH, ACTION_LOW, HL_DT, BaseFrame

_ACTION_LO, _ACTION_HI = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)
_NEUTRAL = torch.tensor([0.0, 0.0, 0.0, 0.75, 0.0, -0.30, 0.0, 0.0])  # as PnPEnv: the default EE pose


class EETrackingEnv(RobotEnvBase):
    """Four-point EE tracking on ``backend`` "mujoco" or "kinematic"; episodes of
    ``max_episode_steps`` HL steps (default 200 = 20 s). ``track_rule``, ``track_sigma`` and
    ``point_ring``: the task's reward rule, kernel lengths and point distances
    (``pnp.task.ee_tracking``)."""

    def __init__(self, num_worlds: int = 64, backend: str | Backend = "mujoco", seed: int = 0,
                 nthread: int | None = None, max_episode_steps: int = int(round(EPISODE_S / HL_DT)),
                 track_rule: str = "gated", track_sigma: tuple[float, float] = TRACK_SIGMA,
                 point_ring: tuple[float, float] = POINT_RING, terminate_on_success: bool = True, device="cpu"):
        if track_rule not in TRACK_RULES:
            raise ValueError(f"track_rule must be one of {TRACK_RULES}, got {track_rule!r}")
        if len(track_sigma) != 2 or min(track_sigma) <= 0:
            raise ValueError(f"track_sigma must be two positive lengths (m), got {list(track_sigma)}")
        if len(point_ring) != 2 or not 0 < point_ring[0] <= point_ring[1]:
            raise ValueError(f"point_ring must be [lo, hi] in m with 0 < lo <= hi, got {list(point_ring)}")
        self._init_worlds(num_worlds, 1, max_episode_steps, device)
        self.backend = self._make_backend(backend, nthread, SINGLE_ROBOT_BOXES[0])
        if self.backend.num_robots != 1:
            raise ValueError(f"the EE tracking task has one robot; the backend has {self.backend.num_robots}")
        self.track_rule = track_rule  # see pnp.task.ee_tracking.TRACK_RULES
        self.terminate_on_success = bool(terminate_on_success)
        self.track_sigma, self.point_ring = tuple(map(float, track_sigma)), tuple(map(float, point_ring))
        self._make_specs()
        N = num_worlds
        self._goal, self._init_goal_dist = torch.zeros(N, 2), torch.ones(N)  # unused PnPState fields
        self._points = torch.zeros(N, N_POINTS, 3)
        self._touched = torch.zeros(N, dtype=torch.long)
        self._last_action = _NEUTRAL.expand(N, 1, 8).clone()
        self._steps = torch.zeros(N, dtype=torch.long)
        self._success_step = torch.full((N,), -1, dtype=torch.long)
        self.clipped_count = 0  # actions clipped since construction
        self.diverged_count = 0  # worlds reset after a physics divergence
        self._set_seed(seed)
        self._reset_worlds(torch.arange(N))

    @property
    def points_touched(self) -> torch.Tensor:
        """Points touched so far in each world's episode, long [N] (= the stage index)."""
        return self._touched.clone()

    def _make_specs(self):
        agents = lambda d: Composite(d, shape=(1,))  # noqa: E731
        self.full_action_spec_unbatched = Composite({"agents": agents({
            "action": Bounded(_ACTION_LO.expand(1, 8), _ACTION_HI.expand(1, 8), shape=(1, 8)),
        })})
        obs = {k: Unbounded(shape=(1, n)) for k, n in EE_OBS_BLOCKS.items()}
        obs["observation"] = Unbounded(shape=(1, sum(EE_OBS_BLOCKS.values())))
        obs["reward_terms"] = Unbounded(shape=(1, len(EE_REWARD_TERMS)))
        obs["stage_conditions"] = Binary(n=len(EE_CONDITIONS), shape=(1, len(EE_CONDITIONS)), dtype=torch.bool)
        obs["action_clipped"] = Categorical(2, shape=(1,), dtype=torch.bool)
        flag = lambda: Categorical(2, shape=(1,), dtype=torch.bool)  # noqa: E731
        self.full_observation_spec_unbatched = Composite({
            "agents": agents(obs), "success": flag(), "diverged": flag(),
            "success_step": Unbounded(shape=(1,), dtype=torch.long)})
        self.full_reward_spec_unbatched = Composite({"agents": agents({"reward": Unbounded(shape=(1, 1))})})
        self.full_done_spec_unbatched = Composite({"done": flag(), "terminated": flag(), "truncated": flag()})

    # --- EnvBase hooks -------------------------------------------------------------------
    def _reset_worlds(self, ids: torch.Tensor):
        layout, points = sample_ee_layout(self._rng, len(ids), ring=self.point_ring)
        self.backend.reset(ids, layout)
        self._points[ids] = points
        self._touched[ids] = 0
        self._last_action[ids] = _NEUTRAL
        self._steps[ids] = 0
        self._success_step[ids] = -1

    @_torch_single_threaded
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action, clipped = self._check_action(tensordict.get(("agents", "action"), None))
        diverged = self.backend.step(action)
        self._steps += 1
        if diverged.any():
            # Reset the diverged worlds alone; the others carry on. They end as truncated.
            ids = diverged.nonzero().squeeze(-1)
            self.diverged_count += len(ids)
            self._reset_worlds(ids)
            action = torch.where(diverged[:, None, None], self._last_action, action)
        out = self._observe(action, self._last_action, advance=~diverged)
        self._last_action = action
        success = self._touched >= N_POINTS
        self._success_step = torch.where(success & (self._success_step < 0), self._steps, self._success_step)
        terminated = success & self.terminate_on_success
        truncated = ((self._steps >= self.max_steps) | diverged) & ~terminated
        out.set(("agents", "action_clipped"), clipped)
        out.update({"terminated": terminated.unsqueeze(-1), "truncated": truncated.unsqueeze(-1),
                    "done": (terminated | truncated).unsqueeze(-1), "success": success.unsqueeze(-1),
                    "diverged": diverged.unsqueeze(-1), "success_step": self._success_step.unsqueeze(-1).clone()})
        return out

    def _observe(self, action, last_action, advance: torch.Tensor | None = None) -> TensorDict:
        """Outputs for the current state; ``advance`` [N]: worlds whose touch count may move."""
        s = self.backend.state(self._goal, self._init_goal_dist, action[..., 7])
        frame = BaseFrame(s)
        dist = point_distances(s, self._points)
        cond = stage_conditions(dist)
        if advance is not None:  # the forward-only graph's rule: only the next point's touch counts
            nxt = self._touched.clamp(max=N_POINTS - 1).unsqueeze(-1)
            self._touched += (cond[:, 0].gather(-1, nxt).squeeze(-1) & (self._touched < N_POINTS) & advance).long()
        terms = reward_terms(s, dist, action, last_action, self._touched, self.track_rule, self.track_sigma)
        blocks = observations(s, self._points, dist, action, frame)
        agents = dict(blocks, observation=torch.cat([blocks[k] for k in EE_OBS_BLOCKS], -1), reward_terms=terms,
                      stage_conditions=cond, reward=default_reward(terms),
                      action_clipped=torch.zeros(self.num_worlds, 1, dtype=torch.bool))
        N = self.num_worlds
        return TensorDict({"agents": TensorDict(agents, batch_size=(N, 1))}, batch_size=(N,))

    def _reset_extras(self) -> dict:
        return {"success_step": self._success_step.unsqueeze(-1).clone()}

    _STATE = ("_points", "_touched", "_last_action", "_steps", "_success_step")  # episode bookkeeping (get_state)
