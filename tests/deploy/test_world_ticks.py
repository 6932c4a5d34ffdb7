"""The world's low level per tick: a fresh command of this episode acts, a held world or a
command older than the time-out or than the episode holds (zero base velocity, last EE target)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip("grpc")

from pnp.deploy.config import deploy_config  # noqa: E402
from pnp.deploy.server import WorldClock  # noqa: E402
from pnp.deploy.world import RemoteActor, Robots  # noqa: E402

W = 3


def _actor():
    cfg = deploy_config([f"worlds={W}", "command_timeout_s=0.1"])
    robots = Robots(cfg, 1, W, WorldClock(1.0), seed=0)
    last = torch.full((W, 1, 8), 0.5)
    env = SimpleNamespace(base_env=SimpleNamespace(_last_action=last))
    return RemoteActor(cfg, env, robots, coordinator=None, seed=0), robots


def _send(robots, tick, value, hold=(False,) * W):
    robots.bus[0].push((tick, np.full((W, 8), value, np.float32), np.asarray(hold)))


def test_fresh_held_stale_and_previous_episode_commands():
    actor, robots = _actor()
    actor.tick = 5
    actor.episode_start = np.array([0, 0, 5])  # world 2's episode began at this tick
    _send(robots, 5, 0.9, hold=(False, True, False))
    a = actor._collect()
    assert torch.allclose(a[0, 0], torch.full((8,), 0.9))       # fresh, of its episode
    assert torch.allclose(a[1, 0, :3], torch.zeros(3))          # held by the client: no base motion
    assert torch.allclose(a[1, 0, 3:], torch.full((5,), 0.5))   # the last EE target and gripper kept
    assert torch.allclose(a[2, 0], torch.full((8,), 0.9))
    actor.tick = 6  # no new command: the one answering tick 5 is 0.1 s old, still within the time-out
    actor.episode_start[0] = 6  # world 0 began a new episode: tick 5's command is of the last one
    a = actor._collect()
    assert torch.allclose(a[0, 0, :3], torch.zeros(3)) and torch.allclose(a[2, 0], torch.full((8,), 0.9))
    assert actor.counts["stale_commands"] == [1] and actor.counts["watchdog"] == [0]
    actor.tick = 7  # 0.2 s old: the watchdog holds every world
    a = actor._collect()
    assert torch.allclose(a[:, 0, :3], torch.zeros(W, 3)) and actor.counts["watchdog"] == [1]
