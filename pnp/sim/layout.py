"""Episode randomisation (paper Sec. IV): box asset and U(0.8, 1.2) scaling of every edge,
robots and box 0.6-5 m from the goal (at the world origin), random headings.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from pnp.sim.backend import Layout
from pnp.sim.box import BoxAsset

START_RANGE = (0.6, 5.0)  # m from the goal
SCALE_RANGE = (0.8, 1.2)
MIN_ROBOT_BOX = 1.2  # m between a robot's base and the box centre at start (ours)
MIN_ROBOT_ROBOT = 1.5  # m between the two bases at start (ours)


def _ring(rng: torch.Generator, shape, start_range=START_RANGE) -> torch.Tensor:
    r = start_range[0] + (start_range[1] - start_range[0]) * torch.rand(shape, generator=rng)
    a = 2 * math.pi * torch.rand(shape, generator=rng)
    return torch.stack([r * torch.cos(a), r * torch.sin(a)], -1)


def sample_layout(rng: torch.Generator, m: int, num_robots: int, assets: tuple[BoxAsset, ...], tries: int = 16,
                  start_range: tuple[float, float] = START_RANGE, box_mass: tuple[float, float] | None = None) -> Layout:
    """Layouts for ``m`` worlds; rejection sampling (vectorised over ``tries`` candidates).

    ``start_range``: distances of robots and box from the goal (the paper's 0.6-5 m by
    default; narrower ranges make a start-distance curriculum). ``box_mass``: [lo, hi] kg
    drawn uniformly instead of the assets' masses (an evaluation condition, e.g. the paper's
    2.0 kg hardware box); drawn after every other draw, so the rest of a layout is unchanged.
    """
    if not 0 <= start_range[0] <= start_range[1]:
        raise ValueError(f"start_range must satisfy 0 <= low <= high, got {tuple(start_range)!r}")
    k = torch.randint(len(assets), (m,), generator=rng)
    edges = torch.tensor([a.size for a in assets], dtype=torch.float32)[k]
    scale = SCALE_RANGE[0] + (SCALE_RANGE[1] - SCALE_RANGE[0]) * torch.rand(m, 3, generator=rng)
    mass = torch.tensor([a.mass for a in assets], dtype=torch.float32)[k]
    box_xy = _ring(rng, (m,), start_range)
    bases = _ring(rng, (m, tries, num_robots), start_range)  # [m, tries, R, 2]
    ok = ((bases - box_xy[:, None, None]).norm(dim=-1) > MIN_ROBOT_BOX).all(-1)
    if num_robots == 2:
        ok &= (bases[:, :, 0] - bases[:, :, 1]).norm(dim=-1) > MIN_ROBOT_ROBOT
    # First valid candidate (the last one if none is valid: rare, and still a legal start).
    first = torch.where(ok.any(-1), ok.float().argmax(-1), torch.full((m,), tries - 1))
    base_xy = bases[torch.arange(m), first]
    yaw = (torch.rand(m, num_robots, generator=rng) * 2 - 1) * math.pi
    box_yaw = (torch.rand(m, generator=rng) * 2 - 1) * math.pi
    if box_mass is not None:
        lo, hi = (float(x) for x in box_mass)
        if not 0 < lo <= hi:
            raise ValueError(f"box_mass must be [lo, hi] kg with 0 < lo <= hi, got {list(box_mass)!r}")
        mass = lo + (hi - lo) * torch.rand(m, generator=rng)
    return Layout(
        base=torch.cat([base_xy, yaw.unsqueeze(-1)], -1),
        box_xy_yaw=torch.cat([box_xy, box_yaw.unsqueeze(-1)], -1),
        box_size=edges * scale,
        box_mass=mass,
    )


def trial_generator(seed: int, trial: int, *stream: int) -> torch.Generator:
    """The random stream of trial ``trial`` under evaluation seed ``seed``: a function of the
    pair alone (NumPy's SeedSequence mixes both into independent 63-bit seeds). ``stream``:
    more keys for other streams of the same trial (the layout's has none)."""
    if trial < 0:
        raise ValueError(f"trial index must be >= 0, got {trial}")
    keys = [int(seed) & (2**63 - 1), int(trial), *(int(k) for k in stream)]
    state = np.random.SeedSequence(keys).generate_state(1, np.uint64)[0]
    return torch.Generator().manual_seed(int(state) & (2**63 - 1))


def paired_layouts(seed: int, trials: torch.Tensor, num_robots: int, assets: tuple[BoxAsset, ...],
                   start_range: tuple[float, float] = START_RANGE, box_mass: tuple[float, float] | None = None) -> Layout:
    """Layouts of trials ``trials`` [m]: trial i's depends on ``(seed, i)`` only, so every policy
    meets the same trials whatever the world count or the order in which episodes end."""
    parts = [sample_layout(trial_generator(seed, int(i)), 1, num_robots, assets, start_range=start_range, box_mass=box_mass)
             for i in trials.tolist()]
    return Layout(**{f: torch.cat([getattr(p, f) for p in parts]) for f in ("base", "box_xy_yaw", "box_size", "box_mass")})
