"""Batched locomotion env for the learned low level (issue 24): N worlds, each a floor and one
``Quadruped(legs="actuated")`` tracking a base-velocity command at 50 Hz (task in
``pnp.legs.locomotion``).

Keys (group ``"agents"``, one robot), laid out as the other envs:
  ("agents", "action")            [N, 1, 12] leg joint offsets in [-1, 1], LEG_JOINTS order;
                                              target = stand + 0.5 * action (legged_gym)
  ("agents", "observation")       [N, 1, 54] base lin/ang velocity (base frame), projected
                                              gravity, command, leg q - stand, leg qd, last
                                              action, arm q (``LOCO_OBS_FIELDS``)
  ("agents", "reward_terms")      [N, 1, 11] ``LOCO_REWARD_TERMS``, raw
  ("agents", "stage_conditions")  [N, 1, 0]  none: the task has one stage
  ("agents", "reward")            [N, 1, 1]  terms at their fixed weights
  ("agents", "action_clipped")    [N, 1]     the action was out of [-1, 1] and clipped
  "success", "diverged"           [N, 1]     reached the step limit standing / physics diverged
  "done", "terminated", "truncated" [N, 1]   fall / step limit or divergence

Disturbances, per world: the command is resampled every ``command_resample_s``; the arm
moves to a random EE pose of the HL action's box every ``arm_resample_s`` at its rated
speed; a payload (constant downward force on the gripper) is drawn at reset; every
``push_interval_s`` (first push at a random time) the trunk's horizontal velocity gets a
kick of ``push_speed`` m/s in a random direction. ``settings`` carries these: any object
with the fields of ``pnp.training.config.LocomotionConfig`` (where their defaults live).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded

from pnp.envs.pnp_env import RobotEnvBase, _torch_single_threaded
from pnp.legs.locomotion import (
    DECIMATION, EPISODE_S, LOCO_OBS_DIM, LOCO_REWARD_TERMS, N_LEG, POLICY_DT, STAND, LocomotionPhysics,
    LegServo, base_readouts, build_locomotion_scene, default_reward, fallen, feet_air_time, observation,
    reward_terms, sample_arm_goals, sample_commands, sample_uniform,
)
from pnp.sim.robot import ARM_DEFAULT, ARM_SPEED, FINGER_STROKE

SETTINGS = ("command_low", "command_high", "command_resample_s", "stand_share", "arm_resample_s", "payload_mass",
             "push_interval_s", "push_speed", "fall_height", "fall_tilt", "leg_kp", "leg_kd", "action_scale", "tracking_sigma")


def _steps(seconds: float, name: str) -> int:
    if not seconds > 0:
        raise ValueError(f"env.locomotion.{name} must be > 0 s, got {seconds!r}")
    return max(1, int(round(seconds / POLICY_DT)))


def _range(value, name: str, low: float = 0.0) -> tuple[float, float]:
    lo, hi = (float(v) for v in value)
    if not low <= lo <= hi:
        raise ValueError(f"env.locomotion.{name} must be [low, high] with {low} <= low <= high, got {list(value)}")
    return lo, hi


def leg_action_spec() -> Bounded:
    """The leg policy's action: 12 joint offsets in [-1, 1] (scaled by the servo), one robot."""
    return Bounded(-torch.ones(1, N_LEG), torch.ones(1, N_LEG), shape=(1, N_LEG))


class LocomotionEnv(RobotEnvBase):
    """Velocity tracking with a moving, loaded arm; episodes of ``max_episode_steps`` policy
    steps (default 1000 = 20 s, legged_gym's)."""

    def __init__(self, num_worlds: int, settings, seed: int = 0, nthread: int | None = None,
                 max_episode_steps: int = int(round(EPISODE_S / POLICY_DT)), device="cpu"):
        self._init_worlds(num_worlds, 1, max_episode_steps, device)
        self._read_settings(settings)
        self.model, self.idx = build_locomotion_scene()
        self.servo.apply(self.model, self.idx.leg_ctrl)
        self.backend = LocomotionPhysics(self.model, num_worlds, nthread)  # RobotEnvBase's name for it
        self._gravity = float(-self.model.opt.gravity[2])
        self._make_specs()
        N = num_worlds
        self._command = torch.zeros(N, 3)
        self._last_action = torch.zeros(N, 1, N_LEG)
        self._last_qd = torch.zeros(N, N_LEG)
        self._air = torch.zeros(N, 4)
        self._last_contact = torch.zeros(N, 4, dtype=torch.bool)
        self._arm_target = torch.tensor(ARM_DEFAULT).expand(N, 6).clone()
        self._arm_goal = self._arm_target.clone()
        self._payload = torch.zeros(N)
        self._push_in = torch.zeros(N, dtype=torch.long)
        self._steps = torch.zeros(N, dtype=torch.long)
        self.clipped_count = 0  # actions clipped since construction
        self.diverged_count = 0  # worlds reset after a physics divergence
        self._set_seed(seed)
        self._reset_worlds(torch.arange(N))

    def _read_settings(self, s) -> None:
        missing = [k for k in SETTINGS if not hasattr(s, k)]
        if missing:
            raise ValueError(f"locomotion settings lack {missing} (see pnp.training.config.LocomotionConfig)")
        self.command_low, self.command_high = tuple(map(float, s.command_low)), tuple(map(float, s.command_high))
        if len(self.command_low) != 3 or len(self.command_high) != 3 or any(
                lo > hi for lo, hi in zip(self.command_low, self.command_high)):
            raise ValueError(f"env.locomotion.command_low/high must be 3 values (vx, vy, yaw rate) with low <= high, "
                             f"got {list(s.command_low)} and {list(s.command_high)}")
        if not 0.0 <= float(s.stand_share) <= 1.0:
            raise ValueError(f"env.locomotion.stand_share must be in [0, 1], got {s.stand_share!r}")
        self.stand_share = float(s.stand_share)
        self.command_steps = _steps(float(s.command_resample_s), "command_resample_s")
        self.arm_steps = _steps(float(s.arm_resample_s), "arm_resample_s")
        self.push_steps = _steps(float(s.push_interval_s), "push_interval_s")
        self.payload_mass = _range(s.payload_mass, "payload_mass")
        self.push_speed = _range(s.push_speed, "push_speed")
        self.fall_height, self.fall_tilt = float(s.fall_height), float(s.fall_tilt)
        self.servo = LegServo(float(s.leg_kp), float(s.leg_kd), float(s.action_scale))
        self.tracking_sigma = float(s.tracking_sigma)
        if not self.tracking_sigma > 0:
            raise ValueError(f"env.locomotion.tracking_sigma must be > 0, got {s.tracking_sigma!r}")
        if not (self.fall_height >= 0.0 and 0.0 < self.fall_tilt <= math.pi):
            raise ValueError(f"env.locomotion.fall_height must be >= 0 m and fall_tilt in (0, pi] rad, "
                             f"got {s.fall_height!r} and {s.fall_tilt!r}")

    def _make_specs(self):
        agents = lambda d: Composite(d, shape=(1,))  # noqa: E731
        self.full_action_spec_unbatched = Composite({"agents": agents({"action": leg_action_spec()})})
        flag = lambda: Categorical(2, shape=(1,), dtype=torch.bool)  # noqa: E731
        obs = {"observation": Unbounded(shape=(1, LOCO_OBS_DIM)),
               "reward_terms": Unbounded(shape=(1, len(LOCO_REWARD_TERMS))),
               "stage_conditions": Binary(n=0, shape=(1, 0), dtype=torch.bool),
               "action_clipped": Categorical(2, shape=(1,), dtype=torch.bool)}
        self.full_observation_spec_unbatched = Composite({"agents": agents(obs), "success": flag(), "diverged": flag()})
        self.full_reward_spec_unbatched = Composite({"agents": agents({"reward": Unbounded(shape=(1, 1))})})
        self.full_done_spec_unbatched = Composite({"done": flag(), "terminated": flag(), "truncated": flag()})

    # --- disturbances ----------------------------------------------------------------------
    def _resample(self, ids: torch.Tensor, what: str) -> None:
        if not len(ids):
            return
        if what == "command":
            self._command[ids] = sample_commands(self._rng, len(ids), self.command_low, self.command_high,
                                                 self.stand_share)
        elif what == "arm":
            self._arm_goal[ids] = sample_arm_goals(self._rng, len(ids))

    def _push(self, ids: torch.Tensor) -> None:
        """Add a horizontal velocity kick to the trunks of worlds ``ids`` (world frame)."""
        if not len(ids):
            return
        speed = sample_uniform(self._rng, len(ids), self.push_speed)
        heading = sample_uniform(self._rng, len(ids), (-math.pi, math.pi))
        kick = torch.stack([speed * torch.cos(heading), speed * torch.sin(heading)], -1)
        dof = self.idx.base_qvel
        self.backend.qvel[ids.numpy(), dof : dof + 2] += kick.double().numpy()
        self._push_in[ids] = self.push_steps

    # --- EnvBase hooks -------------------------------------------------------------------
    def _reset_worlds(self, ids: torch.Tensor):
        i, n = self.idx, len(ids)
        qpos = np.tile(self.model.qpos0, (n, 1))
        qpos[:, i.arm_qpos] = ARM_DEFAULT
        qpos[:, i.finger_qpos] = FINGER_STROKE
        w = ids.numpy()
        self.backend.reset_worlds(w, qpos)
        self._payload[ids] = sample_uniform(self._rng, n, self.payload_mass)
        self.backend.xfrc[w] = 0.0
        self.backend.xfrc[w, i.gripper_body, 2] = -self._gravity * self._payload[ids].double().numpy()
        self._arm_target[ids] = torch.tensor(ARM_DEFAULT)
        self._resample(ids, "arm")
        self._resample(ids, "command")
        self._push_in[ids] = torch.randint(1, self.push_steps + 1, (n,), generator=self._rng)
        self._last_action[ids] = 0.0
        self._last_qd[ids] = 0.0
        self._air[ids] = 0.0
        self._last_contact[ids] = False
        self._steps[ids] = 0

    def _check_action(self, action: torch.Tensor):
        expected = (self.num_worlds, 1, N_LEG)
        if action is None:
            raise KeyError("missing ('agents', 'action') in the input tensordict")
        if tuple(action.shape) != expected:
            raise ValueError(f"('agents', 'action') has shape {tuple(action.shape)}, expected {expected}")
        if not torch.isfinite(action.sum()):  # fast path, as RobotEnvBase
            bad = ~torch.isfinite(action).all(-1).all(-1)
            if bad.any():
                raise ValueError(f"('agents', 'action') has NaN or Inf in worlds {bad.nonzero().squeeze(-1).tolist()}")
        action = action.float()
        clipped_action = action.clamp(-1.0, 1.0)
        clipped = (clipped_action != action).any(-1)
        self.clipped_count += int(clipped.sum())
        return clipped_action, clipped

    def _read(self) -> tuple[dict, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Base read-outs, leg q and qd [N, 12], arm q [N, 6] of the current state."""
        i = self.idx
        qpos, qvel = torch.from_numpy(self.backend.qpos).float(), torch.from_numpy(self.backend.qvel).float()
        base = base_readouts(qpos, qvel, i.base_qpos, i.base_qvel)
        return base, qpos[:, i.leg_qpos], qvel[:, i.leg_qvel], qpos[:, i.arm_qpos]

    @_torch_single_threaded
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action, clipped = self._check_action(tensordict.get(("agents", "action"), None))
        a = action[:, 0]
        target = self.servo.targets(a)
        # The arm ramps to its goal at its rated speed, as the HL executors move it.
        step = ARM_SPEED * POLICY_DT
        self._arm_target += (self._arm_goal - self._arm_target).clamp(-step, step)
        i = self.idx
        ctrl = np.zeros((self.num_worlds, self.model.nu))
        ctrl[:, i.leg_ctrl] = (target - STAND).double().numpy()
        ctrl[:, i.arm_ctrl] = self._arm_target.double().numpy()
        ctrl[:, i.finger_ctrl] = FINGER_STROKE
        ctrl[:, i.arm_ff_ctrl] = i.arm_gravity.torques(self.backend.qpos)  # held for the tick
        diverged = torch.from_numpy(self.backend.step(ctrl, DECIMATION))
        self._steps += 1
        if diverged.any():
            # Reset the diverged worlds alone; the others carry on. They end as truncated.
            ids = diverged.nonzero().squeeze(-1)
            self.diverged_count += len(ids)
            self._reset_worlds(ids)
            a = torch.where(diverged[:, None], 0.0, a)
            target = torch.where(diverged[:, None], STAND, target)
        base, q, qd, _ = self._read()
        contact = torch.from_numpy(self.backend.sensordata[:, i.foot_contact]) > 0.5
        air_term, self._air = feet_air_time(self._air, contact, self._last_contact, self._command)
        fell = fallen(base["height"], base["gravity"], self.fall_height, self.fall_tilt) & ~diverged
        terms = reward_terms(base, self._command, q, qd, self._last_qd, target, a, self._last_action[:, 0],
                             air_term, fell, self.servo, self.tracking_sigma)
        self._last_contact, self._last_qd = contact, qd
        self._last_action = a.unsqueeze(1)
        limit = self._steps >= self.max_steps
        truncated = (limit | diverged) & ~fell
        # Disturbances for the next step, in worlds that go on.
        live = ~(fell | truncated)
        self._push_in -= 1
        self._push(((self._push_in <= 0) & live).nonzero().squeeze(-1))
        self._resample((((self._steps % self.command_steps) == 0) & live).nonzero().squeeze(-1), "command")
        self._resample((((self._steps % self.arm_steps) == 0) & live).nonzero().squeeze(-1), "arm")
        # Read again: the push above is part of what the policy observes.
        out = self._observe(self._last_action, self._last_action, terms)
        out.set(("agents", "action_clipped"), clipped)
        out.update({"terminated": fell.unsqueeze(-1), "truncated": truncated.unsqueeze(-1),
                    "done": (fell | truncated).unsqueeze(-1), "success": (limit & ~fell & ~diverged).unsqueeze(-1),
                    "diverged": diverged.unsqueeze(-1)})
        return out

    def _observe(self, action, last_action, terms: torch.Tensor | None = None) -> TensorDict:
        """Outputs for the current state; ``terms`` None (at reset): zeros."""
        base, q, qd, arm_q = self._read()
        N = self.num_worlds
        if terms is None:
            terms = torch.zeros(N, 1, len(LOCO_REWARD_TERMS))
        agents = {"observation": observation(base, self._command, q, qd, last_action[:, 0], arm_q),
                  "reward_terms": terms, "reward": default_reward(terms),
                  "stage_conditions": torch.zeros(N, 1, 0, dtype=torch.bool),
                  "action_clipped": torch.zeros(N, 1, dtype=torch.bool)}
        return TensorDict({"agents": TensorDict(agents, batch_size=(N, 1))}, batch_size=(N,))

    _STATE = ("_command", "_last_action", "_last_qd", "_air", "_last_contact", "_arm_target", "_arm_goal",
              "_payload", "_push_in", "_steps")

    # --- for tests and analysis -------------------------------------------------------------
    @property
    def command(self) -> torch.Tensor:
        """Current commands [N, 3] (vx, vy in the base frame, yaw rate)."""
        return self._command.clone()

    @property
    def payload(self) -> torch.Tensor:
        """Payload masses [N] (kg) hanging on each gripper."""
        return self._payload.clone()

    def set_command(self, command) -> None:
        """Set every world's command [N, 3] now (held until its next resample)."""
        command = torch.as_tensor(command, dtype=torch.float32).expand(self.num_worlds, 3)
        if not torch.isfinite(command).all():
            raise ValueError(f"set_command: commands must be finite, got {command.tolist()}")
        self._command = command.clone()
