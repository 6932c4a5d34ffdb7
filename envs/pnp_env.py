"""Batched pick-and-place TorchRL environment: N worlds, one or two robots.

Keys (multi-agent group ``"agents"``, A robots):
  ("agents", "action")            [N, A, 8]  base vx, vy (m/s), yaw rate (rad/s), EE x, y, z
                                              (m, base frame), EE yaw (rad), grasp probability
  ("agents", "observation")       [N, A, 74] ego | goal | object | neighbour, concatenated
  ("agents", "ego"|"goal"|"object"|"neighbour")  the same blocks, named
  ("agents", "reward_terms")      [N, A, T]  Table II + fixed terms (``pnp.task.terms``)
  ("agents", "stage_conditions")  [N, A, 6]  forward condition of each stage edge
  ("agents", "reward")            [N, A, 1]  default reward: terms at mu_j, no curriculum
  ("agents", "action_clipped")    [N, A]     the action was out of bounds and clipped
  "success", "diverged"           [N, 1]     episode has succeeded / physics diverged and reset
  "success_step"                  [N, 1]     step of the first success, -1 before it
  "done", "terminated", "truncated" [N, 1]   success (if ``terminate_on_success``) or fall /
                                              45 s or divergence

``terminate_on_success=False`` keeps an episode running after the box is released in the
goal, so the S6 terms of Table II (released in goal, stage progress, arm in default pose)
pay for staying there; with termination they would pay for one step, and every positive
per-step reward the policy still collects in S5 would argue against releasing. Training
runs that way (``EnvConfig.terminate_on_success`` is False); this class's default, True, is
the evaluation's (a trial ends at its success, which times its completion).

The grasp entry is a probability p; the gripper gets a binary command (paper: "a binary
command for the gripper"): it closes when p > 0.5 (the recipes' Bernoulli policy already
emits 0 or 1, see ``pnp.losses.distributions``). Sampling the command from p inside the env
was tried and removed: PPO never sees that coin flip, and it stalled learning to hold a grasp.
"""
from __future__ import annotations

import functools
from typing import Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from pnp.sim.backend import Backend, MujocoBackend
from pnp.sim.box import DUAL_ROBOT_BOXES, SINGLE_ROBOT_BOXES, BoxAsset
from pnp.sim.layout import START_RANGE, paired_layouts, sample_layout
from pnp.task import (
    ACTION_HIGH, ACTION_LOW, ACTION_NAMES, EPISODE_S, GRASP_POSES, HANDLE_ORDERS, HL_DT, OBS_BLOCKS, BaseFrame,
    PnPState, default_reward, geometry, observations, reward_terms, stage_conditions, update_claims,
)
from pnp.task.terms import CONDITIONS, REWARD_TERMS

BLOCKS = tuple(OBS_BLOCKS)


def _torch_single_threaded(fn):
    """Run the env's torch ops on one intra-op thread.

    Measured on 2 cores: torch's OpenMP workers spin after each op and starve the MuJoCo
    rollout threads; with 2 torch threads a batch-256 step took 636 ms, with 1 thread
    102 ms. The caller's thread count is restored, so policy updates keep theirs.
    """

    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        prev = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return fn(self, *args, **kwargs)
        finally:
            torch.set_num_threads(prev)

    return wrapper
_ACTION_LO, _ACTION_HI = torch.tensor(ACTION_LOW), torch.tensor(ACTION_HIGH)  # built once, not per step


def action_box(bounds: Mapping[str, Sequence[float]] | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The action's (low, high): the paper's (pnp.task ACTION_LOW/HIGH), with the entries
    ``bounds`` names ({action name: [lo, hi]}) narrowed; a bound outside the paper's is refused."""
    lo, hi = _ACTION_LO.clone(), _ACTION_HI.clone()
    for name, pair in (bounds or {}).items():
        if name not in ACTION_NAMES:
            raise ValueError(f"action bounds: unknown action {name!r}; actions are {list(ACTION_NAMES)}")
        pair = [float(x) for x in pair]
        i = ACTION_NAMES.index(name)
        if len(pair) != 2 or not ACTION_LOW[i] <= pair[0] < pair[1] <= ACTION_HIGH[i]:
            raise ValueError(f"action bounds: {name}={pair} must be [lo, hi] with "
                             f"{ACTION_LOW[i]} <= lo < hi <= {ACTION_HIGH[i]} (the paper's range)")
        lo[i], hi[i] = pair
    return lo, hi


class RobotEnvBase(EnvBase):
    """What every batched env of this robot shares: seeding, (partial) resets through
    ``_reset_worlds``/``_observe``, action checks, exact-resume state and closing.

    Subclasses set ``num_worlds``, ``num_robots``, ``backend``, ``_last_action``,
    ``clipped_count``, ``diverged_count`` and ``_STATE`` (their episode bookkeeping).
    """

    batch_locked = True
    _STATE: tuple[str, ...] = ()
    _action_lo, _action_hi = _ACTION_LO, _ACTION_HI  # PnPEnv may narrow them (action_box)

    def _init_worlds(self, num_worlds: int, num_robots: int, max_episode_steps: int, device) -> None:
        """Checks the batch sizes, then sets up the EnvBase over ``num_worlds`` worlds."""
        if num_worlds < 1:
            raise ValueError(f"num_worlds must be >= 1, got {num_worlds!r}")
        if max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps!r}")
        EnvBase.__init__(self, batch_size=torch.Size([num_worlds]), device=device)
        self.num_worlds, self.num_robots, self.max_steps = num_worlds, num_robots, int(max_episode_steps)

    def _make_backend(self, backend, nthread, box: BoxAsset, options: dict | None = None) -> Backend:
        """``options``: keyword arguments of the named backend's constructor."""
        if isinstance(backend, Backend):
            return backend
        if backend == "mujoco":
            return MujocoBackend(self.num_worlds, self.num_robots, box, nthread=nthread, **(options or {}))
        if backend == "kinematic":
            from pnp.kinematic.backend import KinematicBackend  # optional second backend

            return KinematicBackend(self.num_worlds, self.num_robots, **(options or {}))
        raise ValueError(f"unknown backend {backend!r}; expected 'mujoco' or 'kinematic'")

    def _set_seed(self, seed: int | None):
        self._rng = torch.Generator().manual_seed(int(seed) if seed is not None else 0)
        if hasattr(getattr(self, "backend", None), "seed"):  # a backend with its own draws
            self.backend.seed(int(seed) if seed is not None else 0)

    @_torch_single_threaded
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(self.num_worlds)
        ids = torch.arange(self.num_worlds) if mask is None else mask.nonzero().squeeze(-1)
        if len(ids):
            self._reset_worlds(ids)
        out = self._observe(self._last_action, self._last_action)
        zeros = torch.zeros(self.num_worlds, 1, dtype=torch.bool)
        out.update({"done": zeros, "terminated": zeros.clone(), "truncated": zeros.clone(),
                    "success": zeros.clone(), "diverged": zeros.clone(), **self._reset_extras()})
        out.del_(("agents", "reward"))
        return out

    def _reset_extras(self) -> dict:
        """Task-specific entries of the reset output."""
        return {}

    def _check_action(self, action: torch.Tensor):
        expected = (self.num_worlds, self.num_robots, 8)
        if action is None:
            raise KeyError("missing ('agents', 'action') in the input tensordict")
        if tuple(action.shape) != expected:
            raise ValueError(f"('agents', 'action') has shape {tuple(action.shape)}, expected {expected}")
        # Fast path: a finite sum means every entry is finite (NaN/Inf propagate); a sum that
        # overflows on huge finite values falls through to the exact per-world check.
        if not torch.isfinite(action.sum()):
            bad = ~torch.isfinite(action).all(-1).all(-1)
            if bad.any():
                worlds = bad.nonzero().squeeze(-1).tolist()
                raise ValueError(f"('agents', 'action') has NaN or Inf in worlds {worlds}")
        action = action.float()
        clipped_action = torch.clamp(action, self._action_lo, self._action_hi)
        clipped = (clipped_action != action).any(-1)
        self.clipped_count += int(clipped.sum())
        return clipped_action, clipped

    def get_state(self) -> dict:
        """Full env state (backend, episode bookkeeping, RNG, counters) for exact resumes."""
        st = {f"backend.{k}": v for k, v in self.backend.get_state().items()}
        st.update({k: getattr(self, k).clone() for k in self._STATE})
        st["rng"] = self._rng.get_state()
        st["counters"] = torch.tensor([self.clipped_count, self.diverged_count])
        return st

    def set_state(self, state: dict) -> None:
        missing = [k for k in (*self._STATE, "rng", "counters") if k not in state]
        if missing:
            raise KeyError(f"env state is missing {missing}; present: {sorted(state)}")
        self.backend.set_state({k.split(".", 1)[1]: v for k, v in state.items() if k.startswith("backend.")})
        for k in self._STATE:
            setattr(self, k, state[k].clone())
        self._rng.set_state(state["rng"])
        self.clipped_count, self.diverged_count = (int(x) for x in state["counters"])

    def close(self, *, raise_if_closed: bool = True):
        self.backend.close()
        super().close(raise_if_closed=raise_if_closed)


class PnPEnv(RobotEnvBase):
    """Pick-and-place with ``num_robots`` in 1 or 2, on ``backend`` "mujoco" or "kinematic"."""

    def __init__(self, num_worlds: int = 64, num_robots: int = 1, backend: str | Backend = "mujoco",
                 box_assets: tuple[BoxAsset, ...] | None = None, seed: int = 0, nthread: int | None = None,
                 start_range: tuple[float, float] = START_RANGE,
                 terminate_on_success: bool = True, backend_options: dict | None = None, device="cpu",
                 handle_order: str = "identity", handle_claim: bool = False, paired_trials: bool = False,
                 box_mass: tuple[float, float] | None = None,
                 action_bounds: Mapping[str, Sequence[float]] | None = None, grasp_pose: str = "height"):
        if num_robots not in (1, 2):
            raise ValueError(f"num_robots must be 1 or 2, got {num_robots!r}")
        if handle_order not in HANDLE_ORDERS:
            raise ValueError(f"handle_order must be one of {HANDLE_ORDERS}, got {handle_order!r}")
        if grasp_pose not in GRASP_POSES:
            raise ValueError(f"grasp_pose must be one of {GRASP_POSES}, got {grasp_pose!r}")
        self.terminate_on_success = bool(terminate_on_success)
        self.handle_order = handle_order
        self.grasp_pose = str(grasp_pose)  # what gripper_grasp_pose pays (pnp.task.rewards.GRASP_POSES)
        # Each robot keeps the handle it was given at the episode start (pnp.task.update_claims).
        self.handle_claim = bool(handle_claim)
        # Evaluation: each reset starts the next trial, whose layout comes from (seed, trial).
        self.paired_trials = bool(paired_trials)
        self.box_mass = None if box_mass is None else tuple(float(x) for x in box_mass)
        self._action_lo, self._action_hi = action_box(action_bounds)
        self._init_worlds(num_worlds, num_robots, int(round(EPISODE_S / HL_DT)), device)
        self.box_assets = box_assets or (SINGLE_ROBOT_BOXES if num_robots == 1 else DUAL_ROBOT_BOXES)
        self.start_range = tuple(float(x) for x in start_range)
        self.backend = self._make_backend(backend, nthread, self.box_assets[0], backend_options)
        self._make_specs()
        N, R = num_worlds, num_robots
        self._goal = torch.zeros(N, 2)
        self._init_goal_dist = torch.ones(N)
        self._last_action = self._neutral_action().expand(N, R, 8).clone()
        self._steps = torch.zeros(N, dtype=torch.long)
        self._was_lifted = torch.zeros(N, dtype=torch.bool)
        self._success_step = torch.full((N,), -1, dtype=torch.long)
        self._claim = torch.full((N, R), -1, dtype=torch.long)
        self.trial = torch.full((N,), -1, dtype=torch.long)  # the trial each world runs (paired_trials)
        self.clipped_count = 0  # (world, robot) actions clipped since construction
        self.diverged_count = 0  # worlds reset after a physics divergence
        self._set_seed(seed)
        self._reset_worlds(torch.arange(N))

    # --- specs -------------------------------------------------------------------------
    def _make_specs(self):
        R = self.num_robots
        agents = lambda d: Composite(d, shape=(R,))  # noqa: E731
        self.full_action_spec_unbatched = Composite({"agents": agents({
            "action": Bounded(self._action_lo.expand(R, 8), self._action_hi.expand(R, 8), shape=(R, 8)),
        })})
        obs = {k: Unbounded(shape=(R, n)) for k, n in OBS_BLOCKS.items()}
        obs["observation"] = Unbounded(shape=(R, sum(OBS_BLOCKS.values())))
        obs["reward_terms"] = Unbounded(shape=(R, len(REWARD_TERMS)))
        obs["stage_conditions"] = Binary(n=len(CONDITIONS), shape=(R, len(CONDITIONS)), dtype=torch.bool)
        obs["action_clipped"] = Categorical(2, shape=(R,), dtype=torch.bool)
        flag = lambda: Categorical(2, shape=(1,), dtype=torch.bool)  # noqa: E731
        self.full_observation_spec_unbatched = Composite({
            "agents": agents(obs), "success": flag(), "diverged": flag(),
            "success_step": Unbounded(shape=(1,), dtype=torch.long)})
        self.full_reward_spec_unbatched = Composite({"agents": agents({"reward": Unbounded(shape=(R, 1))})})
        self.full_done_spec_unbatched = Composite({"done": flag(), "terminated": flag(), "truncated": flag()})

    def _neutral_action(self):
        a = torch.zeros(8)
        a[3:6] = torch.tensor([0.75, 0.0, -0.30])  # the default EE pose
        return a.clamp(self._action_lo, self._action_hi)

    # --- EnvBase hooks -------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if self.paired_trials and (tensordict is None or "_reset" not in tensordict.keys()):
            self._next_trial = 0  # a full reset starts the trials over; a partial one goes on
        return super()._reset(tensordict, **kwargs)

    def _set_seed(self, seed: int | None):
        super()._set_seed(seed)
        self._trial_seed, self._next_trial = int(seed) if seed is not None else 0, 0

    def _reset_worlds(self, ids: torch.Tensor, next_trials: bool = True):
        if self.paired_trials:  # trials numbered in reset order; worlds in index order
            if next_trials:
                self.trial[ids] = self._next_trial + torch.arange(len(ids))
                self._next_trial += len(ids)
            layout = paired_layouts(self._trial_seed, self.trial[ids], self.num_robots, self.box_assets,
                                    start_range=self.start_range, box_mass=self.box_mass)
        else:
            layout = sample_layout(self._rng, len(ids), self.num_robots, self.box_assets, start_range=self.start_range,
                                   box_mass=self.box_mass)
        self.backend.reset(ids, layout)
        self._goal[ids] = 0.0
        self._init_goal_dist[ids] = layout.box_xy_yaw[:, :2].norm(dim=-1)
        self._last_action[ids] = self._neutral_action()
        self._steps[ids] = 0
        self._was_lifted[ids] = False
        self._success_step[ids] = -1
        self._claim[ids] = -1

    @_torch_single_threaded
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action, clipped = self._check_action(tensordict.get(("agents", "action")))
        closed = action[..., 7] > 0.5
        command = action.clone()
        command[..., 7] = closed.float()
        diverged = self.backend.step(command)
        self._steps += 1
        if diverged.any():
            # Reset the diverged worlds alone; the others carry on. They end as truncated.
            ids = diverged.nonzero().squeeze(-1)
            self.diverged_count += len(ids)
            self._reset_worlds(ids, next_trials=False)  # the episode ends here: its trial is spent
            action = torch.where(diverged[:, None, None], self._last_action, action)
            command = torch.where(diverged[:, None, None], self._last_action, command)
            command[..., 7] = (command[..., 7] > 0.5).float()
        out = self._observe(action, self._last_action, command[..., 7])
        self._last_action = action
        cond = out.get(("agents", "stage_conditions"))
        self._was_lifted |= (cond[..., 2]).any(-1)
        now = self._was_lifted & cond[..., 5].all(-1)
        self._success_step = torch.where(now & (self._success_step < 0), self._steps, self._success_step)
        success = self._success_step >= 0
        fell = out.get(("agents", "reward_terms"))[..., REWARD_TERMS.index("fall")].bool().any(-1)
        terminated = ((success & self.terminate_on_success) | fell).unsqueeze(-1)
        truncated = ((self._steps >= self.max_steps) | diverged).unsqueeze(-1)
        out.set(("agents", "action_clipped"), clipped)
        out.update({"terminated": terminated, "truncated": truncated & ~terminated, "done": terminated | truncated,
                    "success": success.unsqueeze(-1), "diverged": diverged.unsqueeze(-1),
                    "success_step": self._success_step.unsqueeze(-1).clone()})
        return out

    def _observe(self, action, last_action, closed=None) -> TensorDict:
        if closed is None:  # at reset: the neutral action's command
            closed = (action[..., 7] > 0.5).float()
        s = self.backend.state(self._goal, self._init_goal_dist, closed)
        frame = BaseFrame(s)  # each robot's base frame, shared by the terms and the observations
        g = geometry(s, self._claim if self.handle_claim else None)
        cond = stage_conditions(s, g)
        if self.handle_claim:
            self._claim = update_claims(self._claim, g)
        terms = reward_terms(s, g, action, last_action, cond, frame, self.grasp_pose)
        blocks = observations(s, g, action, frame, self.handle_order)
        agents = {k: blocks[k] for k in BLOCKS}
        agents["observation"] = torch.cat([blocks[k] for k in BLOCKS], -1)
        agents.update(reward_terms=terms, stage_conditions=cond, reward=default_reward(terms),
                      action_clipped=torch.zeros(self.num_worlds, self.num_robots, dtype=torch.bool))
        return TensorDict({"agents": TensorDict(agents, batch_size=(self.num_worlds, self.num_robots))},
                          batch_size=(self.num_worlds,))

    def _reset_extras(self) -> dict:
        return {"success_step": self._success_step.unsqueeze(-1).clone()}

    # --- extras ------------------------------------------------------------------------------
    _STATE = ("_goal", "_init_goal_dist", "_last_action", "_steps", "_was_lifted", "_success_step")

    def get_state(self) -> dict:
        return {**super().get_state(), "_claim": self._claim.clone()}

    def set_state(self, state: dict) -> None:
        super().set_state(state)
        # States saved before handle claims lack them: every robot unclaimed.
        self._claim = state["_claim"].clone() if "_claim" in state else torch.full_like(self._claim, -1)

    def physical_state(self) -> PnPState:
        """The backend's current state, world frame (for analysis and disturbances; read only)."""
        closed = self._last_action[..., 7] > 0.5
        return self.backend.state(self._goal, self._init_goal_dist, closed.float())

    def ee_positions(self) -> torch.Tensor:
        """World-frame EE positions [N, R, 3] of the current state (for analysis)."""
        return self.physical_state().ee_pos.clone()

    def push_box(self, world: int, force) -> None:
        """Apply an external wrench (N, N m; world frame) to one world's box for one step."""
        self.backend.push(world, np.asarray(force, dtype=np.float64))

    def displace_box(self, worlds, offsets) -> None:
        """Move the boxes of ``worlds`` (indices [M]) by horizontal ``offsets`` [M, 2] (m, world
        frame) and set them down now: on the floor, level at their yaw, at rest, released by
        any gripper. The policy sees it in the next step's observation. The episode's lift
        is forgotten: success needs the box lifted again (else one dropped into the goal
        would count)."""
        worlds = torch.as_tensor(worlds, dtype=torch.long).reshape(-1)
        offsets = torch.as_tensor(offsets, dtype=torch.float32)
        if tuple(offsets.shape) != (len(worlds), 2):
            raise ValueError(f"displace_box: offsets must have shape ({len(worlds)}, 2), one (dx, dy) per world, "
                             f"got {tuple(offsets.shape)}")
        bad = [w for w in worlds.tolist() if not 0 <= w < self.num_worlds]
        if bad or len(set(worlds.tolist())) != len(worlds):
            raise ValueError(f"displace_box: worlds must be distinct indices in [0, {self.num_worlds}), "
                             f"got {worlds.tolist()}")
        if not torch.isfinite(offsets).all():
            raise ValueError(f"displace_box: offsets must be finite, got {offsets.tolist()}")
        if len(worlds):
            self.backend.displace_box(worlds, offsets)
            self._was_lifted[worlds] = False

