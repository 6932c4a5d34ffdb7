"""PnP on legs: the closed-loop low level (pnp.legs.backend) with hand-made leg policies."""
import math

import pytest
import torch

from pnp.sim.box import SINGLE_ROBOT_BOXES
from pnp.legs.locomotion import LOCO_OBS_DIM, LOCO_OBS_FIELDS, LegServo
from pnp.legs.backend import LeggedMujocoBackend
from tests.pnp._kinematic_helpers import _action, _layout

BOX = SINGLE_ROBOT_BOXES[0]


class Recorder:
    """Stands (zero actions: the stand pose) and keeps what it was asked."""

    def __init__(self):
        self.calls = []

    def __call__(self, obs):
        self.calls.append(obs.clone())
        return torch.zeros(obs.shape[0], 12)


def _backend(n=2, robots=1, policy=None):
    b = LeggedMujocoBackend(n, robots, BOX, policy or Recorder(), nthread=1)
    b.reset(torch.arange(n), _layout(n, robots, BOX, box_xy=(3.0, 0.0)))
    return b


def test_standing_policy_holds_the_trunk_and_the_arm_tracks():
    b = _backend()
    a = _action(2, 1, ee=(0.6, 0.0, -0.2), vx=0.3, wz=0.2)
    for _ in range(10):  # 1 s
        assert not b.step(a).any()
    s = b.state(torch.zeros(2, 2), torch.ones(2), torch.zeros(2, 1))
    assert ((s.base_z > 0.5) & (s.base_z < 0.7)).all()  # stands (0.633 m measured)
    # A standing policy does not walk: the kp-80 stand, carrying the arm's weight since the
    # lift was removed, settles back ~0.10 m in 1 s (was < 0.1 m with it).
    assert s.base[..., :2].abs().max() < 0.15
    calls = b.policy.calls
    assert len(calls) == 10 * 5 and calls[0].shape == (2, LOCO_OBS_DIM)  # 50 Hz, one row per robot
    assert torch.allclose(calls[-1][:, LOCO_OBS_FIELDS["command"]], torch.tensor([0.3, 0.0, 0.2]).expand(2, 3))
    # EE in the trunk frame near its command (the arm rides a standing, not a planar, trunk).
    rel = s.ee_pos[:, 0] - torch.cat([s.base[:, 0, :2], s.base_z], -1)
    assert (rel[:, 2] - (-0.2)).abs().max() < 0.05


def test_the_leg_policys_servo_reaches_every_simulated_world():
    # The physics steps one copy of the model per world: gains written into the backend's
    # model after those copies were made never reached the servos (a kp 250 policy ran on
    # kp 80 legs, sagged and fell).
    servo = LegServo(kp=250.0, kd=6.0)
    b = LeggedMujocoBackend(3, 2, BOX, Recorder(), nthread=1, servo=servo)
    legs = b.idx.leg_ctrl.reshape(-1)
    for m in [b.model, *b.physics.models]:
        assert (m.actuator_gainprm[legs, 0] == 250.0).all()
        assert (m.actuator_biasprm[legs, 1] == -250.0).all() and (m.actuator_biasprm[legs, 2] == -6.0).all()
    b.close()


def test_two_robots_each_get_their_own_observation():
    b = _backend(n=1, robots=2)
    b.step(_action(1, 2, ee=(0.6, 0.0, -0.2)))
    obs = b.policy.calls[-1]
    assert obs.shape == (2, LOCO_OBS_DIM)
    grav = obs[:, LOCO_OBS_FIELDS["projected_gravity"]]
    assert torch.allclose(grav, torch.tensor([0.0, 0.0, -1.0]).expand(2, 3), atol=0.05)


def test_a_non_finite_leg_action_is_refused():
    b = _backend(policy=lambda obs: torch.full((obs.shape[0], 12), math.nan))
    with pytest.raises(ValueError, match="non-finite"):
        b.step(_action(2, 1))


def test_state_round_trip_continues_exactly():
    b = _backend(policy=lambda obs: 0.3 * torch.tanh(obs[:, :12]))
    a = _action(2, 1, ee=(0.6, 0.1, -0.2), vx=0.2)
    b.step(a)
    saved = b.get_state()
    b.step(a)
    first = b.physics.state.copy()
    b.set_state(saved)
    b.step(a)
    assert (b.physics.state == first).all()
