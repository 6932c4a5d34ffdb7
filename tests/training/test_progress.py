"""The pipeline's progress lines: what is left is each backend's unused budget at the rate
this run measured on that backend, not one rate over the sum of iterations."""
from __future__ import annotations

from pnp.training.progress import PhasePlan, PipelineProgress


def _plans():
    return [PhasePlan("kin_a", "kinematic", 10_000_000, 16384, frames=9_000_000, wall_s=1000.0, finished=True),
            PhasePlan("kin_b", "kinematic", 18_000_000, 16384),
            PhasePlan("mj", "mujoco", 6_000_000, 4096)]


def test_left_is_the_unused_budget_at_each_backends_measured_rate():
    progress = PipelineProgress(_plans(), enabled=False)
    text = progress.summary()
    assert text.startswith("pipeline: 9.0 M frames in 0.3 h; left at most 0.6 h")  # 18 M at 9 k/s = 2000 s
    assert "6.0 M mujoco frames (rate not yet measured)" in text
    # Once the MuJoCo phase has run, its own rate prices the rest of it.
    progress.start_phase(2, {"iteration": 100, "frames": 2_000_000, "wall_s": 1000.0})
    progress.plans[1].finished = True  # kin_b ended by its rule after no frames
    assert "left at most 0.6 h (" in progress.summary()  # 4 M at 2 k/s
    assert "not yet measured" not in progress.summary()


def test_a_finished_phase_leaves_nothing_and_the_bar_counts_the_phase_budget():
    progress = PipelineProgress(_plans(), enabled=True)  # a disabled tqdm counts nothing
    progress.start_phase(1, {"iteration": 10, "frames": 163_840, "wall_s": 20.0})
    assert progress.bar.total == -(-18_000_000 // 16384) and progress.bar.n == 10
    progress.finish_phase(1, {"frames": 163_840, "wall_s": 20.0}, [10_000_000, 18_000_000, 7_000_000])
    assert progress.plans[2].budget_frames == 7_000_000  # an unfinished phase takes the new budget
    progress.finish_phase(2, {"frames": 0, "wall_s": 0.0}, [10_000_000, 18_000_000, 7_000_000])
    assert "left at most 0.0 h" in progress.summary()
