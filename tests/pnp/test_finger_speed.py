"""MuJoCo's finger targets with a speed limit (``finger_speed``): the pads meet a bar instead
of passing through it."""
import pytest
import torch

from pnp.envs.pnp_env import PnPEnv
from pnp.sim.executor import IdealExecutor
from pnp.sim.robot import FINGER_STROKE
from pnp.task.scripted import ScriptedPnP
from pnp.task import geometry
from tests.pnp._kinematic_helpers import _action


def test_targets_ramp_at_the_speed_and_resume_from_where_they_were():
    ex = IdealExecutor(2, 1, finger_speed=1.0)
    close = _action(2, 1, grasp=1.0)
    _, _, f = ex.controls(close, torch.zeros(2, 1), ex.q_target, 4, 0.005)
    assert f.shape == (2, 4, 1, 2)
    assert torch.allclose(f[0, :, 0, 0], torch.tensor([0.065, 0.06, 0.055, 0.05]))  # 5 mm per 5 ms
    for _ in range(5):
        _, _, f = ex.controls(close, torch.zeros(2, 1), ex.q_target, 4, 0.005)
    assert (f[:, -1] == 0).all()  # closed, and held there
    ex.reset(torch.tensor([True, False]), ex.q_target)
    assert ex.finger_target[0, 0] == FINGER_STROKE and ex.finger_target[1, 0] == 0
    _, _, jump = IdealExecutor(1, 1).controls(close[:1], torch.zeros(1, 1), ex.q_target[:1], 4, 0.005)
    assert (jump == 0).all()  # without a speed the targets jump (the default)
    with pytest.raises(ValueError, match="finger_speed"):
        IdealExecutor(1, 1, finger_speed=0.0)


@pytest.mark.parametrize("speed,crossed", [(None, True), (1.0, False)])
def test_the_scripted_grasp_keeps_the_bar_between_the_pads_only_with_a_speed(speed, crossed):
    torch.manual_seed(0)
    env = PnPEnv(num_worlds=4, num_robots=1, backend="mujoco", seed=0, nthread=1,
                 backend_options=None if speed is None else {"finger_speed": speed})
    try:
        pol, td, openings = ScriptedPnP(4, 1), env.reset(), []
        for _ in range(45):
            td = env.step(pol(td))
            s = env.backend.state(env._goal, env._init_goal_dist, env._last_action[..., 7])
            openings.append(s.finger_q[:, 0].sum(-1)[geometry(s).grasped[:, 0]])
            td = env.step_mdp(td)
        opening = torch.cat(openings)
        assert len(opening) >= 5  # grasps happened
        # Crossed pads read a negative summed opening (q = 0 is pads touching at the centre).
        assert bool((opening < 0).float().mean() > 0.5) == crossed
    finally:
        env.close()
