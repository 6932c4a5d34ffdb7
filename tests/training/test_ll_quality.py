"""The learned low level's quality measurements (pnp.studies.ll_quality, recipes/ll_quality.py)."""

import pytest
import torch

from pnp.envs.pnp_env import PnPEnv
from pnp.sim.backend import MujocoBackend
from pnp.sim.box import SINGLE_ROBOT_BOXES
from pnp.envs.locomotion_env import LocomotionEnv
from pnp.legs.backend import LeggedMujocoBackend
from pnp.sim.robot import LEG_TORQUE, leg_ranges
from pnp.training.config import LocomotionConfig
from pnp.studies.ll_carry import dual_carry
from pnp.studies.ll_quality import (
    Saturation, command_grid, ee_tracking, locomotion_settings, push_recovery, velocity_tracking,
)
from pnp.legs.locomotion import STAND, LegServo
from tests.training._tiny import compose_cfg
from pnp.analysis import benchmark_env as benchmark_recipe
from pnp.studies import ll_quality_report as ll_quality_recipe


def stand(obs):
    return torch.zeros(obs.shape[0], 12)


# The pipeline's servos: a zero-action stand at kp 80 sways too much under the arm's own
# weight (carried by the legs since the gravcomp lift was removed) to stand in for a policy.
SERVO = dict(leg_kp=250.0, leg_kd=6.0)


def _env(**changes):
    settings = locomotion_settings(LocomotionConfig(), **SERVO, **changes)
    return lambda n: LocomotionEnv(n, settings, seed=0, nthread=1, max_episode_steps=10**6)


def test_a_standing_policy_misses_a_walking_command_by_its_speed():
    r = velocity_tracking(_env(command_resample_s=1e6, push_interval_s=1e6), stand,
                          [[0.0, 0.0, 0.0], [0.6, 0.0, 0.0]], repeats=2, settle_s=0.4, measure_s=0.6)
    still, walk = r["per_command"]
    assert still["falls"] == walk["falls"] == 0
    assert still["lin_vel_error"] < 0.15  # the arm's motion sways a standing trunk a little
    assert abs(walk["lin_vel_error"] - 0.6) < 0.15
    assert r["joint_steps"] == 2 * 2 * 50 * 12


def test_pushes_are_counted_and_falls_end_the_count():
    r = push_recovery(_env(push_interval_s=0.5, push_speed=[1.0, 1.0], payload_mass=[2.0, 2.0]), stand, 3, 1.5)
    assert r["episodes"] == 3 and r["pushes"] >= 3  # each world is kicked in its first 0.5 s
    assert 0 <= r["falls"] <= 3 and r["fall_rate"] == pytest.approx(r["falls"] / 3)
    assert r["payload_kg"] == [2.0, 2.0]


def test_saturation_counts_torque_limits_and_range_ends():
    s = Saturation(LegServo())
    q = STAND.expand(2, 12).clone()
    q[0, 0] = float(leg_ranges()[0, 1])  # at its upper end
    qd = torch.zeros(2, 12)
    qd[1, 1] = 10 * LEG_TORQUE  # the damping alone saturates it
    s.add(torch.zeros(2, 12), q, qd, torch.tensor([True, True]))
    s.add(torch.zeros(2, 12), q, qd, torch.tensor([False, False]))  # fallen worlds do not count
    r = s.rates()
    assert r["joint_steps"] == 24
    assert r["joint_limit_rate"] == pytest.approx(1 / 24)
    assert r["torque_saturation_rate"] >= 1 / 24  # the joint at its end pushes back as well


def test_ee_tracking_converges_on_both_low_levels():
    box = SINGLE_ROBOT_BOXES[0]
    for backend in (MujocoBackend(3, 1, box, nthread=1), LeggedMujocoBackend(3, 1, box, stand, nthread=1, servo=LegServo(kp=250.0, kd=6.0))):
        r = ee_tracking(backend, switches=2, delays_s=(0.1, 1.0), hold_s=1.0, fall_height=LocomotionConfig().fall_height)
        early, late = r["after"]["0.1s"], r["after"]["1s"]
        assert early["samples"] == late["samples"] == 6 and r["falls"] == 0
        assert late["median_m"] < 0.05 < early["median_m"]  # a 0.1 s ramp covers a fraction of a jump
        # A trunk below the fall height is a fall, and its errors are left out.
        r = ee_tracking(backend, switches=1, delays_s=(0.1,), hold_s=0.2, fall_height=10.0)
        backend.close()
        assert r["falls"] == 3 and r["after"]["0.1s"]["samples"] == 0 and r["after"]["0.1s"]["mean_m"] is None
        assert r["trunk_height_mean_m"] is None


def test_a_scripted_pair_carries_without_drift_on_the_kinematic_backend():
    make = lambda n: PnPEnv(n, 2, "kinematic", seed=1, paired_trials=True)  # noqa: E731
    r = dual_carry(make, episodes=4, max_steps=400)
    assert r["carried"] == r["success"] == 4 and r["falls"] == 0 and r["grasps_lost_while_carrying"] == 0
    # Rigid kinematic grasps: the grippers keep their spacing and follow their commands.
    assert r["spacing_drift_m"]["max"] < 1e-3 and r["ee_error_m"]["samples"] > 4 * 10
    assert r["trunk_height_min_m"]["samples"] == 4
    with pytest.raises(ValueError, match="num_robots=1"):
        dual_carry(lambda n: PnPEnv(n, 1, "kinematic"), episodes=1, max_steps=1)


def test_settings_and_grid():
    with pytest.raises(ValueError, match="unknown locomotion settings.*'push_sped'"):
        locomotion_settings(LocomotionConfig(), push_sped=[1.0, 1.0])
    grid = command_grid([-1.0, -0.5, -1.0], [1.0, 0.5, 1.0], 3)
    assert len(grid) == 9 + 2 and [0.0, 0.5, 0.0] in grid and [1.0, 0.0, -1.0] in grid


def test_the_recipes_measure_a_leg_policy(tmp_path):
    from pnp.training.trainer import train
    from tests.training.test_low_level import MUJOCO_TINY

    run = tmp_path / "loco"
    train(compose_cfg("train", [*MUJOCO_TINY, "experiment=locomotion", "env.nthread=1", "total_iterations=1",
                                f"out_dir={run}"]))
    out = tmp_path / "q.json"
    r = ll_quality_recipe.measure(compose_cfg("ll_quality", [
        f"checkpoint={run}", f"out={out}", "nthread=1", "velocity.grid_steps=2", "velocity.repeats=1",
        "velocity.settle_s=0.2", "velocity.measure_s=0.2", "pushes.episodes=2", "pushes.seconds=0.4",
        "ee.worlds=2", "ee.switches=1", "ee.base_commands=[[0.0,0.0,0.0]]", "carry.episodes=1", "carry.max_steps=3"]))
    assert out.exists() and out.with_suffix(".md").exists()
    assert len(r["velocity_tracking"]["per_command"]) == 4 + 2
    assert set(r["ee_tracking"]["+0.00, +0.00, +0.00"]) == {"ideal", "learned"}
    assert set(r["dual_carry"]) == {"ideal", "learned"} and r["dual_carry"]["learned"]["episodes"] == 1
    assert "Two robots carrying" in out.with_suffix(".md").read_text()
    assert r["checkpoint_iteration"] == 1 and "commit" in r
    row = benchmark_recipe.bench_low_level(str(run), robots=1, batch=2, steps=2, repeats=1, nthread=1)
    assert row["learned_env_steps_per_s"] > 0 and row["leg_policy_ms_per_env_step"] > 0
    assert row["learned_over_ideal_speed"] == pytest.approx(row["ideal_env_step_ms"] / row["learned_env_step_ms"])
