"""``PnPEnv.displace_box`` on both backends: a box carried by the scripted policy is moved,
set down on the floor at rest and released; the other worlds are untouched."""
from __future__ import annotations

import math

import pytest
import torch

from pnp.sim.backend import BOX_DROP
from pnp.envs.pnp_env import PnPEnv
from pnp.task.scripted import ScriptedPnP
from pnp.task.terms import CONDITIONS

GRABBED, LIFTED = CONDITIONS.index("object_grabbed"), CONDITIONS.index("object_lifted")


def _lifted_env(backend: str) -> tuple[PnPEnv, ScriptedPnP, object]:
    """Two worlds stepped by the scripted policy until world 0 holds its box up."""
    env = PnPEnv(num_worlds=2, num_robots=1, backend=backend, seed=0, nthread=1)
    pol = ScriptedPnP(2)
    td = env.reset()
    for _ in range(200):
        td = env.step_mdp(env.step(pol(td)))
        if td["agents", "stage_conditions"][0, 0, LIFTED]:
            return env, pol, td
    raise AssertionError(f"the scripted policy did not lift the box on {backend} in 20 s")


def _world_state(env: PnPEnv, w: int) -> dict:
    return {k: v[w].clone() for k, v in env.get_state().items() if k not in ("rng", "counters") and v.ndim}


def _yaw(rot: torch.Tensor) -> float:
    return math.atan2(float(rot[1, 0]), float(rot[0, 0]))


@pytest.mark.parametrize("backend", ["kinematic", "mujoco"])
def test_a_carried_box_is_set_down_at_the_requested_place_at_rest_and_released(backend):
    env, pol, td = _lifted_env(backend)
    before, other = env.physical_state(), _world_state(env, 1)
    xy, yaw, c = before.box_pos[0, :2].clone(), _yaw(before.box_rot[0]), float(before.box_size[0, 2])
    assert before.touch[0].all() and before.box_pos[0, 2] > c / 2 + 0.1
    away = xy - before.base[0, 0, :2]
    offset = 0.7 * away / away.norm()  # on, away from the robot: not onto its legs
    env.displace_box([0], offset[None])
    s = env.physical_state()
    torch.testing.assert_close(s.box_pos[0, :2], xy + offset, atol=1e-5, rtol=0)
    drop = BOX_DROP if backend == "mujoco" else 0.0
    assert s.box_pos[0, 2].item() == pytest.approx(c / 2 + drop, abs=1e-6)  # on the floor
    assert s.box_rot[0, 2, 2].item() == pytest.approx(1.0, abs=1e-6)  # level ...
    assert _yaw(s.box_rot[0]) == pytest.approx(yaw, abs=2e-2)  # ... at its heading (a hanging box tilts a little)
    assert not s.box_vel[0].any() and not s.touch[0].any()  # at rest, out of the gripper
    assert not env._was_lifted[0]  # success needs a new lift
    after = _world_state(env, 1)
    for k in other:
        assert torch.equal(after[k], other[k]), k
    td = env.step_mdp(env.step(pol(td)))  # the policy still closes its gripper: on nothing
    assert not td["agents", "stage_conditions"][0, 0, GRABBED]
    s = env.physical_state()
    assert (s.box_pos[0, :2] - xy - offset).norm() < 5e-3  # it stays where it was put
    assert s.box_pos[0, 2].item() == pytest.approx(c / 2, abs=3e-3) and s.box_vel[0, :3].norm() < 0.05
    env.close()


def test_bad_worlds_and_offsets_are_refused():
    env = PnPEnv(num_worlds=2, backend="kinematic")
    with pytest.raises(ValueError, match=r"offsets must have shape \(1, 2\).*got \(2,\)"):
        env.displace_box([0], [0.5, 0.5])
    with pytest.raises(ValueError, match=r"distinct indices in \[0, 2\), got \[0, 2\]"):
        env.displace_box([0, 2], torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"distinct indices in \[0, 2\), got \[1, 1\]"):
        env.displace_box([1, 1], torch.zeros(2, 2))
    with pytest.raises(ValueError, match="offsets must be finite"):
        env.displace_box([1], [[math.nan, 0.0]])
