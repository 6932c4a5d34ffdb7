"""A training pipeline: phases run back to back in one run folder, each warm-started from
the last, each ended by a rule measured in training or by its frame budget.

Layout of ``out_dir``: ``pipeline.json`` (the phases finished so far: name, overrides,
iterations, frames, wall time, how each ended) and one folder per phase,
``<index>_<name>/``, a normal run folder (checkpoint, metrics, plots). Re-running the same
command resumes: finished phases are skipped, the current one resumes bit for bit from
its checkpoint, and the next starts from the last one's final checkpoint. Raising the
``max_frames`` (or ``until_total_frames``) of the last finished phase, if its budget ended
it, trains it on.

What used to be done by hand between runs happens here: the weights, Adam state and
observation statistics carry over; the curriculum state (rho per world) carries over and
is resized to the new world count (and from one robot to two); a change of backend or
robot count folds the inputs that never moved before (``warm_start_fold_constant``).
"""
from __future__ import annotations

import contextlib
import copy
import json
import math
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from pnp.training.checkpoint import load_checkpoint
from pnp.training.collect import windowed_mean
from pnp.training.migration import changed_settings, migrate
from pnp.training.plots import plot_pipeline
from pnp.training.progress import PhasePlan, PipelineProgress
from pnp.training.provenance import launch_record
from pnp.training.trainer import RESUMABLE, Trainer

STATE = "pipeline.json"


class ExitCheck:
    """``rule`` (an ``ExitRule``) over the metric rows of a phase, fed one row at a time.
    ``reason`` says which part ended it: "rule" (the threshold) or "plateau"."""

    def __init__(self, rule: DictConfig | None, rows: list[dict]):
        self.rule, self.rows, self.reason = rule, [], None
        self.best, self.best_at = -math.inf, 0  # the plateau's reference: best windowed value, and its row count
        self.value = None  # the windowed metric at the last row (None before a window)
        for row in rows:  # a resumed phase replays its rows, so the plateau counts from the same best
            self.rows.append(row)
            self._track()

    def __call__(self, row: dict) -> bool:
        self.rows.append(row)
        self._track()
        return self.met()

    def _track(self) -> None:
        if self.rule is None:
            return
        self.value = windowed_mean(self.rows, self.rule.metric, int(self.rule.window))
        if self.value is not None and self.value > self.best + float(self.rule.min_delta):
            self.best, self.best_at = self.value, len(self.rows)

    def met(self) -> bool:
        if self.rule is None or not self.rows:
            return False
        if self.rule.metric not in self.rows[-1]:
            raise KeyError(f"exit rule metric {self.rule.metric!r} is not logged; metrics are {sorted(self.rows[-1])}")
        if self.value is not None and self.value >= float(self.rule.min):
            self.reason = "rule"
        elif self.rule.plateau is not None and self.best_at and len(self.rows) - self.best_at >= int(self.rule.plateau):
            self.reason = "plateau"
        return self.reason is not None


def phase_dir(out_dir: Path, index: int, name: str) -> Path:
    return out_dir / f"{index}_{name}"


def pipeline_phases(cfg: DictConfig) -> list[tuple[str, DictConfig]]:
    """``(name, phase)`` for each name in ``cfg.pipeline``, from ``cfg.phases``."""
    unknown = [name for name in cfg.pipeline if name not in cfg.phases]
    if unknown:
        raise ValueError(f"pipeline names phases {unknown} that `phases` does not declare "
                         f"(declared: {sorted(cfg.phases)})")
    return [(name, _resolved(cfg.phases, name)) for name in cfg.pipeline]


def _resolved(phases: DictConfig, name: str) -> DictConfig:
    """Phase ``name`` with the overrides of the phases it extends folded in, nearest last."""
    chain = [name]
    while phases[chain[-1]].get("extends") is not None:
        parent = phases[chain[-1]].extends
        if parent not in phases:
            raise ValueError(f"phase {chain[-1]!r} extends {parent!r}, which `phases` does not declare "
                             f"(declared: {sorted(phases)})")
        if parent in chain:
            raise ValueError(f"phases extend each other in a cycle: {' -> '.join(chain + [parent])}")
        chain.append(parent)
    phase = copy.deepcopy(phases[name])
    merged = {}
    for link in reversed(chain):
        merged.update(OmegaConf.to_container(phases[link].overrides))
    with open_dict(phase):
        phase.overrides = merged
    return phase


def _planned_frames(cfg: DictConfig, done: list[dict] = ()) -> list[int]:
    """Every phase's frame budget in one pass: its ``max_frames``, or with
    ``until_total_frames`` what the earlier phases leave of it (their frames from ``done``
    where finished, else their budgets)."""
    budgets, earlier = [], 0
    for i, (name, phase) in enumerate(pipeline_phases(cfg)):
        frames = int(phase.max_frames)
        if phase.until_total_frames is not None:
            frames = int(phase.until_total_frames) - earlier
            if frames <= 0:
                raise ValueError(f"phase {name!r}: until_total_frames={phase.until_total_frames} leaves nothing "
                                 f"after the earlier phases' {earlier} frames")
        budgets.append(frames)
        earlier += int(done[i]["frames"]) if i < len(done) else frames
    return budgets


def _budgets(cfg: DictConfig, done: list[dict]) -> list[int]:
    """Every phase's budget in iterations (:func:`_planned_frames` over its batch)."""
    return [math.ceil(f / int(_phase_value(cfg, i, "collect.frames_per_batch")))
            for i, f in enumerate(_planned_frames(cfg, done))]


def _plans(cfg: DictConfig, done: list[dict]) -> list[PhasePlan]:
    """The phases as the progress lines see them: finished ones as run, the others at their
    budgets (an exit by rule shrinks one, or moves frames to a phase that trains until a total)."""
    plans = []
    for i, ((name, _), frames) in enumerate(zip(pipeline_phases(cfg), _planned_frames(cfg, done))):
        plan = PhasePlan(name, str(_phase_value(cfg, i, "env.backend")), frames,
                         int(_phase_value(cfg, i, "collect.frames_per_batch")))
        if i < len(done):
            plan.frames, plan.wall_s, plan.finished = int(done[i]["frames"]), float(done[i]["wall_s"]), True
        plans.append(plan)
    return plans


def phase_frames(cfg: DictConfig, index: int, done: list[dict] = ()) -> int:
    """Phase ``index``'s frame budget (:func:`_planned_frames`)."""
    return _planned_frames(cfg, done)[index]


def total_frames(cfg: DictConfig, names: list[str] | None = None) -> int:
    """The planned frames of the phases ``names`` (all by default), exit rules aside."""
    planned = _planned_frames(cfg)
    return sum(f for f, (name, _) in zip(planned, pipeline_phases(cfg)) if names is None or name in names)


def phase_config(cfg: DictConfig, index: int, source: Path | None, done: list[dict] = ()) -> DictConfig:
    """The run configuration of phase ``index``: ``cfg`` with the phase's overrides, its
    folder, its frame budget as iterations (``phase_frames``), and a warm start from ``source``."""
    name, phase = pipeline_phases(cfg)[index]
    frames = phase_frames(cfg, index, done)
    pcfg = copy.deepcopy(cfg)  # keeps the schema: overrides are type-checked
    pcfg.pipeline, pcfg.phases, pcfg.branch_from = [], {}, None
    for key, value in phase.overrides.items():
        node = OmegaConf.select(pcfg, key, default="<missing>")
        if node == "<missing>":
            raise ValueError(f"pipeline phase {name!r} overrides unknown key {key!r}")
        # A mapping merges into its node (e.g. env.kinematic's keys, checked by its
        # schema; a free-form map such as curriculum.stage_gates takes new keys); anything else replaces.
        mapping = isinstance(value, (dict, DictConfig))
        with open_dict(node) if mapping and OmegaConf.get_type(node) is dict else contextlib.nullcontext():
            OmegaConf.update(pcfg, key, value, merge=mapping)
    pcfg.out_dir = str(phase_dir(Path(cfg.out_dir), index, name))
    pcfg.total_iterations = math.ceil(frames / int(pcfg.collect.frames_per_batch))
    pcfg.resume = False
    if (Path(pcfg.out_dir) / "checkpoint.pt").is_file():
        pcfg.resume = pcfg.out_dir
    elif source is not None:
        pcfg.warm_start, pcfg.warm_start_curriculum = str(source), True
        # Inputs that never moved before move now: a new backend's (wrist roll, box tilt) or,
        # from one robot to two, the neighbour block's.
        pcfg.warm_start_fold_constant = any(_phase_value(cfg, index - 1, k) != OmegaConf.select(pcfg, k)
                                            for k in ("env.backend", "env.num_robots"))
    return pcfg


def _phase_value(cfg: DictConfig, index: int, key: str):
    """``key`` as phase ``index`` sets it (or the pipeline's configuration)."""
    overrides = pipeline_phases(cfg)[index][1].overrides
    return overrides[key] if key in overrides else OmegaConf.select(cfg, key)


def changed_since_start(pcfg: DictConfig, saved: dict) -> dict:
    """``{key: (at start, now)}`` for every setting of a resumed phase that differs from its
    checkpoint's: a resume runs the checkpoint's settings, so such an edit would be ignored."""
    return changed_settings(pcfg, migrate(saved), RESUMABLE)


def load_state(out_dir: Path) -> list[dict]:
    path = out_dir / STATE
    return json.loads(path.read_text())["phases"] if path.is_file() else []


def load_launches(out_dir: Path) -> list[dict]:
    """Every launch of the pipeline in ``out_dir`` (command, commit, machine, date, whether
    the folder was empty and what it branched from); older folders did not record them."""
    path = out_dir / STATE
    return json.loads(path.read_text()).get("launches", []) if path.is_file() else []


def _save_state(out_dir: Path, done: list[dict], launch: dict | None = None) -> None:
    """``pipeline.json``: the finished phases, and each launch (``launch`` is appended)."""
    launches = load_launches(out_dir) + ([launch] if launch else [])
    (out_dir / STATE).write_text(json.dumps({"phases": done, "launches": launches}, indent=1) + "\n")


def shared_phases(source_dir: Path, phases: list) -> list[dict]:
    """The finished phases of the pipeline in ``source_dir`` that ``phases`` declares alike
    (same names and overrides, from the first on): a branch reuses them and their checkpoints."""
    shared = []
    for d, (name, phase) in zip(load_state(source_dir), phases):
        if d["name"] != name or d["overrides"] != OmegaConf.to_container(phase.overrides):
            break
        shared.append(dict(d))
    if not shared:
        raise ValueError(f"branch_from={source_dir}: no finished phase there is declared alike by this pipeline "
                         f"({[name for name, _ in phases]}); nothing to branch from")
    return shared


def _read_rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line] if path.is_file() else []


def _reopen_grown_budget(done: list[dict], budgets: list[int]) -> None:
    """A finished phase that ended by its budget, now larger, resumes (the records drop it):
    raising the last phase's ``max_frames`` and rerunning the command trains on."""
    grown = [i for i, d in enumerate(done) if d["exit"] == "budget" and budgets[i] > d["iterations"]]
    if not grown:
        return
    i = grown[0]
    if i != len(done) - 1:
        raise ValueError(f"phase {done[i]['name']!r} ended by its budget at {done[i]['iterations']} iterations and "
                         f"its budget is now {budgets[i]}, but later phases started from its end: restore its "
                         "max_frames or use another out_dir")
    done.pop()


def run_pipeline(cfg: DictConfig) -> dict:
    """Run (or resume) ``cfg.pipeline`` in ``cfg.out_dir``; returns the phase records and
    whether the pipeline finished (``False`` when a signal stopped it)."""
    if not cfg.pipeline:
        raise ValueError("run_pipeline needs a non-empty pipeline (an experiment that declares one)")
    if cfg.out_dir is None:
        raise ValueError("out_dir is not set (the hydra entry point sets it to the run folder)")
    out_dir = Path(cfg.out_dir)
    empty = not out_dir.exists() or not any(out_dir.iterdir())
    out_dir.mkdir(parents=True, exist_ok=True)
    phases = pipeline_phases(cfg)
    names = [name for name, _ in phases]
    done = load_state(out_dir)
    if not done and cfg.branch_from:
        done = shared_phases(Path(cfg.branch_from), phases)
    _save_state(out_dir, done, {**launch_record(), "folder_was_empty": empty, "branch_from": cfg.branch_from})
    if [d["name"] for d in done] != names[: len(done)]:
        raise ValueError(f"{out_dir / STATE} records phases {[d['name'] for d in done]}, this pipeline is {names}: "
                         "a different pipeline; use another out_dir")
    for d, (_, phase) in zip(done, phases):
        if d["overrides"] != OmegaConf.to_container(phase.overrides):
            raise ValueError(f"{out_dir / STATE}: finished phase {d['name']!r} ran with overrides {d['overrides']}, "
                             f"this pipeline declares {OmegaConf.to_container(phase.overrides)}; use another out_dir")
    _reopen_grown_budget(done, _budgets(cfg, done))
    progress = PipelineProgress(_plans(cfg, done), bool(cfg.progress))
    for index in range(len(done), len(names)):
        source = Path(done[-1]["checkpoint"]) if done else None
        pcfg = phase_config(cfg, index, source, done)
        ckpt_path, rows = Path(pcfg.out_dir) / "checkpoint.pt", []
        if pcfg.resume:  # the rows up to its checkpoint: later ones are redone
            ckpt = load_checkpoint(ckpt_path)
            changed = changed_since_start(pcfg, ckpt["cfg"])
            if changed:
                raise ValueError(f"phase {names[index]!r} in {pcfg.out_dir} started with other settings "
                                 f"(key: (then, now)) {changed}; a resume would run the old ones: restore them "
                                 "or use another out_dir")
            counters = ckpt["counters"]
            rows = [r for r in _read_rows(ckpt_path.parent / "metrics.jsonl") if r["iteration"] <= counters["iteration"]]
        check = ExitCheck(phases[index][1].exit, rows)
        if check.met():  # it stopped by its rule after its last checkpoint, before the record
            by_rule = True
        else:
            trainer = Trainer(pcfg)
            progress.start_phase(index, trainer.counters, check)
            result = trainer.run(stop_when=check, progress=progress)
            counters, by_rule, ckpt_path = trainer.counters, result["stopped_by_rule"], trainer.ckpt_path
            if result["stopped_by_signal"] or (not by_rule and counters["iteration"] < int(pcfg.total_iterations)):
                progress.close()  # a signal or the wall-time limit: the same command resumes here
                return {"out_dir": str(out_dir), "phases": done, "finished": False}
        done.append({
            "name": names[index], "overrides": OmegaConf.to_container(phases[index][1].overrides),
            "iterations": int(counters["iteration"]), "frames": int(counters["frames"]),
            "wall_s": float(counters["wall_s"]), "exit": check.reason if by_rule else "budget", "checkpoint": str(ckpt_path),
            "backend": str(pcfg.env.backend),
        })
        _save_state(out_dir, done)
        plot_pipeline(out_dir, done)
        progress.finish_phase(index, done[-1], _planned_frames(cfg, done))
    progress.close()
    return {"out_dir": str(out_dir), "phases": done, "finished": True}
