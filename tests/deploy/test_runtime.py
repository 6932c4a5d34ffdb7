"""Every process on loopback, fault-free: the deployed student succeeds on the trials the
in-process evaluation of the same student succeeds on (within the paired interval)."""
from __future__ import annotations

import pytest

pytest.importorskip("grpc")
pytest.importorskip("onnxruntime")

from pnp.deploy.config import deploy_config  # noqa: E402
from pnp.deploy.run import run  # noqa: E402
from pnp.deploy.student_io import load_student  # noqa: E402
from pnp.training.paired import paired_comparison  # noqa: E402
from pnp.training.protocol import resolve_seed  # noqa: E402
from pnp.training.rollout import run_trials  # noqa: E402
from tests.training._tiny import ROOT  # noqa: E402

TRIALS = 4


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_fault_free_runtime_matches_the_in_process_student(tmp_path):
    checkpoint = str(ROOT / "results" / "eval_student_single_checkpoint.pt")
    cfg = deploy_config([f"checkpoint={checkpoint}", f"trials={TRIALS}", f"worlds={TRIALS}", "time_scale=1",
                         "progress=false"])
    deployed = run(cfg, tmp_path)
    student = load_student(checkpoint, num_worlds=TRIALS, seed=resolve_seed(cfg.seed))
    in_process = run_trials(student.env, student.actor, TRIALS)
    student.env.close()
    comparison = paired_comparison(deployed["records"], in_process)
    low, high = comparison["success_diff_interval"]
    assert low <= 0.0 <= high, comparison
    world = deployed["world"]
    assert world["watchdog"][0] <= 2  # at most the first tick(s) before the first command
    assert world["stale_commands"][0] <= 0.05 * world["ticks"] and world["late_ticks"] <= 0.05 * world["ticks"]
    assert deployed["clients"]["robot_0"]["missed_world_ticks"] <= 0.05 * world["ticks"]
    assert deployed["clients"]["robot_0"]["steps"] > 0 and deployed["coordinator"]["refused"] == {}


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_killed_client_restarts_reconnects_and_the_episode_carries_on(tmp_path):
    """Robot 0's client killed 1 s into the run, started again 1 s later: the low level holds
    while no command comes (watchdog), the new client connects with a fresh GRU state and
    commands again, and the trial set ends."""
    checkpoint = str(ROOT / "results" / "eval_student_single_checkpoint.pt")
    cfg = deploy_config([f"checkpoint={checkpoint}", "trials=2", "worlds=2", "time_scale=1", "progress=false",
                         "faults.restart.robot=0", "faults.restart.at_s=1.0", "faults.restart.down_s=1.0"])
    deployed = run(cfg, tmp_path)
    assert [e["event"] for e in deployed["restart_events"]] == ["killed", "restarted"]
    assert len(deployed["records"]) == 2  # every trial finished
    assert deployed["world"]["watchdog"][0] >= 5  # ~10 ticks without a command: held, and counted
    restarted = deployed["clients"]["robot_0"]  # written by the restarted client on its way out
    assert restarted is not None and restarted["steps"] > 0
    assert (tmp_path / "client0_restarted.log").is_file()
