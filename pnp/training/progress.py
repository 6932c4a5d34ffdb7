"""Progress lines of a training run and of a pipeline of phases.

A pipeline's phases run on backends whose frames cost 3x apart (kinematic ~9 k frames/s,
MuJoCo ~3 k on 2 cores) and end early by their exit rules, so one bar over the sum of the
phases' maximum iterations read 13-38 h at the start of a 5 h run. Here the phase has its
own bar against its budget, and a second line says what the pipeline has used and at most
how long the rest takes, each backend's frames at the rate this run measured on it.
"""
from __future__ import annotations

from dataclasses import dataclass

from tqdm import tqdm


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h"


class RunProgress:
    """One bar: a run's iterations against its total (``update`` takes each metrics row)."""

    def __init__(self, total: int, initial: int, enabled: bool, desc: str = "train"):
        self.bar = tqdm(total=total, initial=initial, disable=not enabled, desc=desc)

    def update(self, row: dict) -> None:
        self.bar.set_postfix(success=f"{row['success_rate']:.2f}", stage=f"{row['mean_end_stage']:.2f}", refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


@dataclass
class PhasePlan:
    """A phase as the progress lines see it."""

    name: str
    backend: str
    budget_frames: int
    frames_per_iteration: int
    frames: int = 0  # used so far (all of them once finished)
    wall_s: float = 0.0
    finished: bool = False


class PipelineProgress:
    """The current phase's bar (iterations against its budget, its exit rule's windowed value
    against the threshold) and a line for the whole pipeline."""

    def __init__(self, plans: list[PhasePlan], enabled: bool):
        self.plans, self.enabled, self.index = plans, enabled, 0
        self.bar = tqdm(total=1, disable=not enabled, position=0, leave=False)
        self.line = tqdm(total=1, disable=not enabled, position=1, bar_format="{desc}", leave=False)
        self.exit_check = None
        self._start = (0, 0.0)  # the phase's frames and wall time when this launch took it up

    def start_phase(self, index: int, counters: dict, exit_check=None) -> None:
        """Phase ``index`` begins (or resumes at ``counters``, its trainer's)."""
        self.index, self.exit_check = index, exit_check
        plan = self.plans[index]
        plan.frames, plan.wall_s = int(counters["frames"]), float(counters["wall_s"])
        self.bar.reset(total=-(-plan.budget_frames // plan.frames_per_iteration))
        self.bar.update(int(counters["iteration"]))
        self.bar.set_description(f"{index + 1}/{len(self.plans)} {plan.name}")
        self._refresh_line()

    def update(self, row: dict) -> None:
        plan = self.plans[self.index]
        plan.frames, plan.wall_s = int(row["frames"]), float(row["wall_s"])
        post = {"success": f"{row['success_rate']:.2f}", "stage": f"{row['mean_end_stage']:.2f}"}
        check = self.exit_check
        if check is not None and check.rule is not None and check.value is not None:
            post["exit"] = f"{check.value:.2f}/{float(check.rule.min):.2f}"
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(1)
        self._refresh_line()

    def finish_phase(self, index: int, record: dict, budgets: list[int]) -> None:
        """Phase ``index`` ended with ``record``; ``budgets``: every phase's frame budget now
        (a phase that trains until a total takes over what an early exit left)."""
        plan = self.plans[index]
        plan.frames, plan.wall_s, plan.finished = int(record["frames"]), float(record["wall_s"]), True
        for p, frames in zip(self.plans, budgets):
            if not p.finished:
                p.budget_frames = int(frames)
        self._refresh_line()

    def summary(self) -> str:
        """What the pipeline used, and at most what is left: each unfinished phase's unused
        budget at its backend's rate in this run (frames only where none was measured yet)."""
        used_f = sum(p.frames for p in self.plans)
        used_s = sum(p.wall_s for p in self.plans)
        rates = {}
        for p in self.plans:
            if p.frames and p.wall_s > 0:
                f, s = rates.get(p.backend, (0, 0.0))
                rates[p.backend] = (f + p.frames, s + p.wall_s)
        left_s, unmeasured = 0.0, {}
        for p in self.plans:
            if p.finished:
                continue
            left = max(0, p.budget_frames - p.frames)
            if p.backend in rates:
                f, s = rates[p.backend]
                left_s += left * s / f
            else:
                unmeasured[p.backend] = unmeasured.get(p.backend, 0) + left
        text = f"pipeline: {used_f / 1e6:.1f} M frames in {_hours(used_s)}; left at most {_hours(left_s)}"
        for backend, frames in unmeasured.items():
            text += f" + {frames / 1e6:.1f} M {backend} frames (rate not yet measured)"
        return text + " (phases end early by their exit rules)"

    def _refresh_line(self) -> None:
        if self.enabled:
            self.line.set_description_str(self.summary())

    def close(self) -> None:
        self.bar.close()
        self.line.close()
        if self.enabled:
            print(self.summary())
