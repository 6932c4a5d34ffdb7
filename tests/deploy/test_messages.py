"""A robot forms from the wire exactly the observation the env forms; the delay line and
the mocap dropouts do what their configuration says."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from pnp.deploy.client import observation
from pnp.deploy.config import LinkFaults, MocapFaults, deploy_config
from pnp.deploy.faults import DelayLine, MocapDropouts
from pnp.deploy.messages import (BadMessage, box_pose, episode_info, read_box_pose, read_episode_info,
                                 read_robot_state, robot_state)
from pnp.deploy.world import box_arrays, build_world_env, robot_arrays
from pnp.training.keys import OBS
from tests.training._tiny import ROOT

pytest.importorskip("grpc")


@pytest.mark.parametrize("student", ["single", "dual"])
def test_observation_from_messages_equals_the_env(student):
    cfg = deploy_config([f"checkpoint={ROOT}/results/eval_student_{student}_checkpoint.pt", "worlds=3", "trials=3",
                         "backend=kinematic"])
    scfg, env, _ = build_world_env(cfg)
    robots, base = int(scfg.env.num_robots), env.base_env
    torch.manual_seed(0)
    td = env.reset()
    for _ in range(4):
        s = base.physical_state()
        episodes, steps = base.trial.numpy(), base._steps.numpy()
        states = {r: read_robot_state(robot_state(r, robot_arrays(s, base._last_action, r), steps, episodes, 0, 0.0, 1), 3)
                  for r in range(robots)}
        box = read_box_pose(box_pose(box_arrays(s), np.ones(3, bool), episodes, 0, 0.0, 1), 3)
        info = read_episode_info(episode_info(episodes, s.goal.numpy(), s.box_size.numpy(), base._claim.numpy(), robots,
                                              0.0, 1), 3, robots)
        for r in range(robots):
            mine = observation(r, states, box, info, robots, scfg.env.handle_order)
            assert torch.equal(mine, td.get(OBS)[:, r : r + 1])
        td = env.step(env.rand_action(td))["next"]
    env.close()


def test_a_short_field_and_a_nan_are_refused_by_name():
    arrays = {k: np.zeros((2, w), np.float32) for k, w in
              {"pos": 3, "rot": 9, "vel": 6}.items()}
    msg = box_pose(arrays, np.ones(2, bool), np.zeros(2, np.int64), 0, 0.0, 1)
    with pytest.raises(BadMessage, match=r"worlds=2, this run has 3"):
        read_box_pose(msg, 3)
    del msg.vel[-1]
    with pytest.raises(BadMessage, match=r"BoxPose.vel: 11 values, expected 12"):
        read_box_pose(msg, 2)
    msg.vel.append(float("nan"))
    with pytest.raises(BadMessage, match=r"BoxPose.vel: non-finite values at \[11\]"):
        read_box_pose(msg, 2)


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_delay_line_delays_drops_and_reorders():
    clock = _Clock()
    line = DelayLine(OmegaConf.structured(LinkFaults(delay_s=0.2)), clock, seed=0)
    line.push("a")
    clock.t = 0.19
    assert line.pop_due() == []
    clock.t = 0.2
    assert line.pop_due() == ["a"]
    lossy = DelayLine(OmegaConf.structured(LinkFaults(loss=0.3)), clock, seed=0)
    for i in range(2000):
        lossy.push(i)
    assert 0.25 < lossy.stats()["dropped"] / 2000 < 0.35
    delivered = lossy.pop_due()
    assert len(delivered) == 2000 - lossy.dropped and delivered == sorted(delivered)  # no delay: sending order
    held = DelayLine(OmegaConf.structured(LinkFaults(reorder=1.0, reorder_s=0.3)), clock, seed=0)
    held.push("old")
    held.faults = OmegaConf.structured(LinkFaults())
    clock.t += 0.1
    held.push("new")
    clock.t += 0.5
    assert held.pop_due() == ["new", "old"]  # the held-back message arrives after the one sent later


def test_mocap_dropouts_last_their_configured_time():
    drops = MocapDropouts(OmegaConf.structured(MocapFaults(rate_hz=0.5, min_s=1.0, max_s=1.0)), 200, 0.1, seed=0)
    seen = np.stack([drops.visible() for _ in range(600)])  # [ticks, worlds]
    runs = []
    for w in range(200):
        edges = np.flatnonzero(np.diff(np.r_[1, seen[:, w].astype(int), 1]))
        runs += [b - a for a, b in zip(edges[::2], edges[1::2]) if b < len(seen)]  # not cut by the end
    assert drops.started > 100 and set(runs) == {10}  # 1 s = 10 ticks


def test_unknown_config_keys_are_refused():
    with pytest.raises(Exception, match="dealy_s"):
        deploy_config(["faults.link.dealy_s=0.1"])
    with pytest.raises(ValueError, match=r"faults.link.loss=1.5"):
        deploy_config(["faults.link.loss=1.5"])
