"""Where a checkpoint's robots fall: in which stage, carrying or not, and under what commands.

    python recipes/analyze/falls.py checkpoint=results/eval_dual_pnp_learned_ll_checkpoint.pt \
        out=runs/falls.json trials=200 seed=777

Per trial (``pnp.training.rollout.run_trials``), for an episode that ended in a fall: which
robots fell (the ``fall`` reward term at the last step), each robot's stage and whether it held
the box then, and over the last ``window`` high-level steps (1 s at 10 Hz) the fallen robot's
commanded planar speed and yaw rate, its velocity-tracking error (command minus measured base
velocity) and, with two robots, how much their spacing changed (a partner's pull moves it).
The same window statistics over every step of every robot, split by carrying or not, are the
reference a fall's window is read against: a fall under commands the policy gives everywhere
points at the legs, one under rare commands at the high level.
"""
from __future__ import annotations

import collections

import torch
from omegaconf import OmegaConf

from pnp.studies.ll_carry import value_stats
from pnp.task import OBS_FIELDS
from pnp.training.keys import STAGE
from pnp.training.rollout import FALL, GRABBED

from pnp.analysis.analysis_cli import hooked_trials, save, settings

_VEL, _CMD = OBS_FIELDS["ego"]["base_vel"], OBS_FIELDS["ego"]["last_action"]
_PARTNER = OBS_FIELDS["neighbour"]["base_xy"]
DEFAULTS = {"checkpoint": None, "out": "runs/falls.json", "trials": 200, "seed": 777, "window": 10, "env": {}}


def _step_stats(agents) -> dict[str, torch.Tensor]:
    """Per world and robot [N, R]: commanded planar speed, |yaw rate|, tracking error, box held,
    fallen; and the robots' spacing [N] (zero with one robot)."""
    ego = agents["ego"]
    cmd, vel = ego[..., _CMD.start:_CMD.start + 3], ego[..., _VEL]
    spacing = (agents["neighbour"][..., _PARTNER].norm(dim=-1).mean(-1) if "neighbour" in agents.keys()
               else torch.zeros(ego.shape[0]))
    return {"speed": cmd[..., :2].norm(dim=-1), "yaw_rate": cmd[..., 2].abs(), "track_err": (cmd - vel).norm(dim=-1),
            "held": agents["stage_conditions"][..., GRABBED].bool(),
            "fell": agents["reward_terms"][..., FALL].bool(), "spacing": spacing}


class Falls:
    """A :class:`pnp.training.rollout.TrialHook` keeping each world's last ``window`` steps (a ring
    shared by all worlds, which step together) and, over all steps, the command statistics with
    and without the box held."""

    def __init__(self, n_worlds: int, window: int):
        self.window, self.t = int(window), -1
        self.ring: dict[str, torch.Tensor] = {}
        self.valid = torch.zeros(n_worlds, dtype=torch.long)  # steps of the current episode in the ring
        self.stage = None
        self.everywhere = {"carrying": collections.defaultdict(list), "not_carrying": collections.defaultdict(list)}

    def after_step(self, env, nxt) -> None:
        agents = nxt["agents"]
        stats = _step_stats(agents)
        if not self.ring:
            self.ring = {k: torch.zeros((self.window, *v.shape), dtype=v.dtype) for k, v in stats.items()}
        self.t += 1
        for k, v in stats.items():
            self.ring[k][self.t % self.window] = v
        self.valid = (self.valid + 1).clamp(max=self.window)
        self.stage = nxt[STAGE].reshape(stats["speed"].shape).long()
        for key in ("speed", "yaw_rate", "track_err"):
            for part, mask in (("carrying", stats["held"]), ("not_carrying", ~stats["held"])):
                self.everywhere[part][key].append(stats[key][mask])

    def record(self, world: int) -> dict:
        idx = [(self.t - i) % self.window for i in range(int(self.valid[world]))]  # newest first
        last = {k: v[idx[0], world] for k, v in self.ring.items()}
        fell = torch.nonzero(last["fell"]).flatten().tolist()
        out = {"fell_robots": fell, "stage_per_robot": self.stage[world].tolist(),
               "held_per_robot": last["held"].tolist()}
        if fell:
            r = fell[0]
            series = {k: self.ring[k][idx, world, r] for k in ("speed", "yaw_rate", "track_err")}
            spacing = self.ring["spacing"][idx, world]
            out |= {"speed_max": float(series["speed"].max()), "yaw_rate_max": float(series["yaw_rate"].max()),
                    "track_err_mean": float(series["track_err"].mean()),
                    "spacing_change": float(spacing.max() - spacing.min())}
        return out

    def reset(self, done: torch.Tensor) -> None:
        self.valid[done] = 0

    def reference(self) -> dict:
        """Per part (carrying, not): the robot-step count and each statistic's summary."""
        out = {}
        for part, series in self.everywhere.items():
            values = {k: torch.cat(v) if v else torch.zeros(0) for k, v in series.items()}
            out[part] = {"robot_steps": len(values["speed"])} | {k: value_stats(v) for k, v in values.items()}
        return out


def falls(checkpoint: str, trials: int, seed: int, window: int, **env) -> dict:
    records, hook, header = hooked_trials(checkpoint, trials, seed, lambda base: Falls(base.num_worlds, window), env)
    fallen = [r for r in records if r["cause"] == "fall"]
    by_stage = collections.Counter(f"S{r['stage_per_robot'][r['fell_robots'][0]]}" for r in fallen if r["fell_robots"])
    carrying = [r for r in fallen if r["fell_robots"] and r["held_per_robot"][r["fell_robots"][0]]]
    return {**header, "window_steps": window, "falls": len(fallen),
            "falls_by_stage": dict(sorted(by_stage.items())), "falls_while_holding": len(carrying),
            "falls_both_robots": sum(len(r["fell_robots"]) > 1 for r in fallen),
            "fall_step": value_stats(torch.tensor([float(r["steps"]) for r in fallen])),
            "before_fall": {k: value_stats(torch.tensor([r[k] for r in fallen if k in r]))
                            for k in ("speed_max", "yaw_rate_max", "track_err_mean", "spacing_change")},
            "everywhere": hook.reference(),
            "fall_trials": [{k: r[k] for k in ("trial", "world", "steps", "fell_robots", "stage_per_robot", "held_per_robot",
                                               "speed_max", "yaw_rate_max", "track_err_mean", "spacing_change")
                             if k in r} for r in fallen]}


def main(argv: list[str]) -> dict:
    cfg = settings(argv, DEFAULTS, __doc__)
    out = falls(cfg.checkpoint, int(cfg.trials), int(cfg.seed), int(cfg.window), **OmegaConf.to_container(cfg.env))
    save(out, cfg.out)
    print({k: out[k] for k in ("success_rate", "falls", "falls_by_stage", "falls_while_holding", "before_fall")})
    return out
