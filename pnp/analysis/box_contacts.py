"""Which robot parts touch the unheld box, and which touched it just before it tipped (MuJoCo).

    python recipes/analyze/box_contacts.py checkpoint=results/run18_single_pnp_checkpoint.pt \
        out=runs/box_contacts.json trials=100 seed=777 env.num_worlds=100

After every high-level step each world's state is loaded into one ``MjData`` and
``mj_forward`` lists its contacts (a sample at the step's end, not every substep). Per trial:
the robot parts (finger, palm, arm, leg, trunk) in contact with the box while nothing grasps
it, and those in contact during the ``window`` steps up to the first step its tilt passed
``tilt_deg`` (the onset; none if it never did). Reports, per part, the trials in which it
touched the unheld box and the tilted trials in which it touched the box before the onset
(docs/history/pipeline_single/run_8.md: the fingers tip it in every policy; ours press the palm and
legs against it 2-4x as often as the hand-run chain's).
"""
from __future__ import annotations

import collections
import math

import mujoco
import numpy as np
import torch
from omegaconf import OmegaConf

from pnp.sim.physics import FULL
from pnp.training.rollout import GRABBED, box_up_z

from pnp.analysis.analysis_cli import OnsetWindow, hooked_trials, save, settings

DEFAULTS = {"checkpoint": None, "out": "runs/box_contacts.json", "trials": 100, "seed": 777, "tilt_deg": 30.0,
            "window": 6, "env": {"num_worlds": 100, "backend": "mujoco"}}
_LEG_WORDS = ("leg", "shank", "thigh", "foot", "hip")


def part_of(model: mujoco.MjModel, geom: int) -> str | None:
    """The robot part a geom belongs to; ``None`` for the floor, goal and box."""
    body = model.body(model.geom_bodyid[geom]).name
    name = model.geom(geom).name or body
    if not body.startswith("robot"):
        return None
    if "finger" in body or "pad" in name:
        return "finger"
    if "gripper" in body:
        return "palm"
    if "arm_link" in body:
        return "arm"
    return "leg" if any(w in name for w in _LEG_WORDS) else "trunk"


class BoxContacts:
    """A :class:`pnp.training.rollout.TrialHook` collecting the parts touching the unheld box."""

    def __init__(self, backend, n_worlds: int, tilt_deg: float, window: int):
        self.physics, self.model = backend.physics, backend.model
        self.box = {int(g) for g in backend.idx.box_geoms}
        self.parts = {g: part_of(self.model, g) for g in range(self.model.ngeom)}
        self.data = mujoco.MjData(self.model)
        self.cos = math.cos(math.radians(tilt_deg))
        self.onsets = OnsetWindow(n_worlds, window)  # samples: the parts touching the box per step
        self.unheld = [set() for _ in range(n_worlds)]

    def touching(self, world: int) -> set:
        d = self.data
        mujoco.mj_setState(self.physics.models[world], d, self.physics.state[world], FULL)
        mujoco.mj_forward(self.physics.models[world], d)
        found = set()
        for c in d.contact[: d.ncon]:
            g1, g2 = int(c.geom1), int(c.geom2)
            other = g2 if g1 in self.box else g1 if g2 in self.box else None
            if other is not None and other not in self.box and self.parts[other] is not None:
                found.add(self.parts[other])
        return found

    def after_step(self, env, nxt) -> None:
        agents = nxt["agents"]
        held = agents["stage_conditions"][..., GRABBED].any(-1)
        up_z = box_up_z(agents["object"][:, 0])
        for w in torch.nonzero(~held).flatten().tolist():
            parts = self.touching(w)
            self.unheld[w] |= parts
            self.onsets.push(w, parts, float(up_z[w]) < self.cos)

    def record(self, world: int) -> dict:
        onset = self.onsets.onset[world]
        return {"unheld_parts": sorted(self.unheld[world]),
                "onset_parts": None if onset is None else sorted(set().union(*onset))}

    def reset(self, done: torch.Tensor) -> None:
        self.onsets.reset(done)
        for w in torch.nonzero(done).flatten().tolist():
            self.unheld[w] = set()


def box_contacts(checkpoint: str, trials: int, seed: int, tilt_deg: float, window: int, **env) -> dict:
    records, _, header = hooked_trials(
        checkpoint, trials, seed, lambda base: BoxContacts(base.backend, base.num_worlds, tilt_deg, window), env)
    tilted = [r for r in records if r["onset_parts"] is not None]
    count = lambda key, rs: dict(collections.Counter(p for r in rs for p in r[key]))  # noqa: E731
    return {**header, "tilt_deg": tilt_deg, "window": window, "tilted_unheld_trials": len(tilted),
            "tilted_without_contact_before": sum(not r["onset_parts"] for r in tilted),
            "parts_before_onset": count("onset_parts", tilted), "parts_touching_unheld": count("unheld_parts", records),
            "success_rate_tilted": float(np.mean([r["success"] for r in tilted])) if tilted else None}


def main(argv: list[str]) -> dict:
    cfg = settings(argv, DEFAULTS, __doc__)
    out = box_contacts(cfg.checkpoint, int(cfg.trials), int(cfg.seed), float(cfg.tilt_deg), int(cfg.window),
                       **OmegaConf.to_container(cfg.env))
    save(out, cfg.out)
    print({k: out[k] for k in ("success_rate", "tilted_unheld_trials", "parts_before_onset", "parts_touching_unheld")})
    return out
