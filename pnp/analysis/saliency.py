"""Saliency of a trained teacher (paper Fig. 7): per step, the gradient of the L2 norm of its
mean action with respect to the *normalised* observation (so blocks are comparable),
as shares per block and field, by each robot's stage, over many deterministic episodes.

    python recipes/analyze/saliency.py checkpoint=results/train_dual/dual_mj2/checkpoint.pt out=results/saliency_dual
    python recipes/analyze/saliency.py checkpoint=results/train_single/checkpoint_mujoco.pt out=results/saliency_single

The mean action is the continuous commands' deterministic value and, for the binary
gripper, its probability (the thresholded command has no gradient). Each world runs its
first episode on MuJoCo; a step's saliency is |d||a||/dx| per input, as shares of its sum
over the observation (the stage one-hot the teacher also sees is left out). Writes
``<out>.json`` (shares per block and field by stage, and the inputs' own share of the
dimensions as the uniform baseline), ``<out>.png`` (per stage, the blocks' shares)
and ``<out>_episode.png`` (world 0: fields x time, each robot's stage along the time axis).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import matplotlib
import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import InteractionType, set_interaction_type

from pnp.analysis.analysis_cli import settings
from pnp.task import OBS_BLOCKS, OBS_FIELDS
from pnp.task.terms import STAGES
from pnp.training.keys import LOC, OBS, SCALE, STAGE, STAGE_ONE_HOT
from pnp.training.models import GRASP_ENTRY, dist_from_params
from pnp.training.provenance import provenance
from pnp.training.rollout import load_policy

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

DEFAULTS = {"checkpoint": None, "out": "runs/saliency", "episodes": 100, "seed": 12345, "nthread": None,
            "max_episode_steps": None,  # null: the paper's 45 s
    "replot": False}  # true: redraw the PNGs from an existing <out>.json


def field_slices() -> dict[str, slice]:
    """Observation columns of every field, ``block/field``; the two handles split, as listed."""
    out, start = {}, 0
    for block, width in OBS_BLOCKS.items():
        for field, sl in OBS_FIELDS[block].items():
            if field in ("handles", "handles_from_ee"):
                mid = sl.start + 3
                out[f"{block}/{field}[listed 1st]"] = slice(start + sl.start, start + mid)
                out[f"{block}/{field}[listed 2nd]"] = slice(start + mid, start + sl.stop)
            else:
                out[f"{block}/{field}"] = slice(start + sl.start, start + sl.stop)
        start += width
    return out


def input_saliency(fn, x: torch.Tensor) -> torch.Tensor:
    """|d ||fn(x)||_2 / dx| per sample, ``fn`` mapping [..., n] to [..., k]."""
    x = x.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(fn(x).norm(dim=-1).sum(), x)
    return grad.abs()


def mean_action_saliency(actor, obs: torch.Tensor, stage: torch.Tensor) -> torch.Tensor:
    """:func:`input_saliency` of each agent's mean action w.r.t. its normalised observation [N, A, n_obs]."""
    net = actor.module[0].module

    def mean_action(x):
        loc, scale = net.head(net.mlp(torch.cat([x, stage], -1)))
        dist = dist_from_params(actor, TensorDict({LOC: loc, SCALE: scale}, batch_size=loc.shape[:1]))
        if not hasattr(dist, "arm"):  # a TanhNormal gripper: its mean is differentiable
            return dist.deterministic_sample
        return torch.cat([dist.arm.deterministic_sample, torch.sigmoid(loc[..., GRASP_ENTRY:GRASP_ENTRY + 1])], -1)

    return input_saliency(mean_action, net.obs_norm(obs))


# The paper's four attention claims for the dual policy (Sec. V), as field groups by stage.
# With handle_order=own_last the robot's own handle is listed 2nd, its partner's 1st.
OWN_GRIPPER = ("ego/ee_pos", "ego/ee_yaw_sincos", "ego/gripper_opening", "ego/pad_touch")
CLAIMS = [
    ("approaching: both handles and the neighbour's base", ("S0", "S1"), {
        "both handles": ("object/handles[", "object/handles_from_ee["),
        "neighbour's base": ("neighbour/base_xy", "neighbour/yaw_sincos")}),
    ("grasping and lifting: own gripper, own handle, neighbour's gripper", ("S1", "S2"), {
        "own gripper": OWN_GRIPPER,
        "own handle": ("object/handles[listed 2nd]", "object/handles_from_ee[listed 2nd]"),
        "neighbour's gripper": ("neighbour/ee_pos", "neighbour/gripper_opening", "neighbour/pad_touch")}),
    ("transporting: own gripper and the goal", ("S3", "S4"), {"own gripper": OWN_GRIPPER, "goal": ("goal/",)}),
]
RELEASE = ("near release: the partner's handle more than the partner", ("S5", "S6"))


def _group(shares: dict[str, float], prefixes) -> float:
    return sum(v for k, v in shares.items() if k.startswith(prefixes))


def claims(result: dict) -> list[dict]:
    """Each claim's measured saliency shares against the inputs' share of the observation
    (attention above uniform); a claim holds when every part of it is above uniform (the
    release claim: when the partner's handle draws more than the whole neighbour block)."""
    by_stage, uniform = result["by_stage"], result["uniform_share"]

    def pooled(stages):
        rows = [by_stage[s] for s in stages if s in by_stage]
        n = sum(r["robot_steps"] for r in rows)
        return {k: sum(r["fields"][k] * r["robot_steps"] for r in rows) / n for k in uniform} if n else None

    table = []
    for text, stages, parts in CLAIMS:
        shares = pooled(stages)
        if shares is None:
            continue
        measured = {p: {"share": round(_group(shares, pre), 4), "uniform": round(_group(uniform, pre), 4)}
                    for p, pre in parts.items()}
        table.append({"claim": text, "stages": list(stages), "parts": measured,
                      "holds": all(m["share"] > m["uniform"] for m in measured.values())})
    shares = pooled(RELEASE[1])
    if shares is not None:
        handle = _group(shares, ("object/handles[listed 1st]", "object/handles_from_ee[listed 1st]"))
        partner = _group(shares, ("neighbour/",))
        table.append({"claim": RELEASE[0], "stages": list(RELEASE[1]), "holds": handle > partner,
                      "parts": {"partner's handle": {"share": round(handle, 4)}, "partner": {"share": round(partner, 4)}}})
    return table


def saliency(checkpoint: str, episodes: int, seed: int, nthread: int | None,
             max_episode_steps: int | None = None) -> dict:
    pol = load_policy(checkpoint, episodes, seed, backend="mujoco", nthread=nthread,
                      max_episode_steps=max_episode_steps)
    env, actor, n = pol.env, pol.actor, episodes
    fields = field_slices()
    sums = np.zeros((len(STAGES), len(fields)))
    counts = np.zeros(len(STAGES))
    live = torch.ones(n, dtype=torch.bool)  # world's first episode still running
    trace, stages0 = [], []  # world 0's episode
    td, t0 = env.reset(), time.monotonic()
    while bool(live.any()):
        grad = mean_action_saliency(actor, td[OBS], td[STAGE_ONE_HOT])
        share = grad / grad.sum(-1, keepdim=True).clamp(min=1e-12)
        per_field = torch.stack([share[..., sl].sum(-1) for sl in fields.values()], -1)  # [N, A, F]
        stage = td[STAGE].reshape(n, -1)
        for w in live.nonzero().view(-1).tolist():
            for a in range(stage.shape[1]):
                sums[int(stage[w, a])] += per_field[w, a].numpy()
                counts[int(stage[w, a])] += 1
        if bool(live[0]):
            trace.append(per_field[0].numpy())
            stages0.append(stage[0].tolist())
        with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
            out, td = env.step_and_maybe_reset(actor(td))
        live &= ~out["next", "done"].view(n)
    env.close()
    names = list(fields)
    dims = {k: (sl.stop - sl.start) / sum(OBS_BLOCKS.values()) for k, sl in fields.items()}
    by_stage = {}
    for s, name in enumerate(STAGES):
        if counts[s]:
            f = dict(zip(names, (sums[s] / counts[s]).round(5).tolist()))
            by_stage[f"S{s}"] = {"robot_steps": int(counts[s]), "fields": f,
                                 "blocks": {b: round(sum(v for k, v in f.items() if k.startswith(b + "/")), 5)
                                            for b in OBS_BLOCKS}}
    return {"checkpoint": str(checkpoint), "num_robots": int(pol.cfg.env.num_robots),
            "handle_order": pol.cfg.env.handle_order, "episodes": episodes, "seed": seed,
            "uniform_share": {k: round(v, 5) for k, v in dims.items()}, "by_stage": by_stage,
            "episode0": {"fields": names, "shares": np.stack(trace).round(5).tolist(), "stages": stages0},
            "wall_s": time.monotonic() - t0}


def plot(result: dict, out: Path) -> list[Path]:
    stages = list(result["by_stage"])
    blocks = list(OBS_BLOCKS)
    fig, ax = plt.subplots(figsize=(8, 4))
    bottom = np.zeros(len(stages))
    for b in blocks:
        v = np.array([result["by_stage"][s]["blocks"][b] for s in stages])
        ax.bar(stages, v, bottom=bottom, label=f"{b} ({100 * sum(result['uniform_share'][k] for k in result['uniform_share'] if k.startswith(b + '/')):.0f} % of inputs)")
        bottom += v
    ax.set(ylabel="share of saliency", ylim=(0, 1), title=f"{result['num_robots']} robot(s): saliency by stage")
    ax.set_xticks(range(len(stages)), [f"{s} {STAGES[int(s[1:])]}" for s in stages], fontsize=7, rotation=25,
                  ha="right")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.tight_layout()
    p1 = out.with_name(out.name + ".png")
    fig.savefig(p1, dpi=120)
    plt.close(fig)

    ep = result["episode0"]
    shares, stages0 = np.array(ep["shares"]), np.array(ep["stages"])
    n_rob = shares.shape[1]
    fig, axes = plt.subplots(2 * n_rob, 1, figsize=(9, 2.2 + 3.2 * n_rob),
                             gridspec_kw={"height_ratios": [6, 1] * n_rob}, sharex=True)
    for a in range(n_rob):
        ax, sx = axes[2 * a], axes[2 * a + 1]
        ax.imshow(shares[:, a].T, aspect="auto", cmap="viridis", interpolation="nearest")
        ax.set_yticks(range(len(ep["fields"])), ep["fields"], fontsize=5)
        ax.set_title(f"robot {a}: share of saliency per field (world 0)", fontsize=8)
        sx.step(np.arange(len(stages0)), stages0[:, a], where="post")
        sx.set(ylabel="stage", ylim=(-0.5, 6.5))
    axes[-1].set_xlabel("step (0.1 s)")
    fig.tight_layout()
    p2 = out.with_name(out.name + "_episode.png")
    fig.savefig(p2, dpi=120)
    plt.close(fig)
    return [p1, p2]


def main(argv: list[str]) -> dict:
    cfg = settings(argv, DEFAULTS, __doc__)
    out = Path(cfg.out)
    if cfg.replot:
        result = json.loads(out.with_suffix(".json").read_text())
        plot(result, out)
        return result
    torch.set_num_threads(1)
    result = saliency(cfg.checkpoint, int(cfg.episodes), int(cfg.seed), cfg.nthread, cfg.max_episode_steps)
    out.parent.mkdir(parents=True, exist_ok=True)
    result["plots"] = [str(p) for p in plot(result, out)]
    if result["num_robots"] == 2:
        result["claims"] = claims(result)
    result.update(provenance())
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    print({s: v["blocks"] for s, v in result["by_stage"].items()})
    return result
