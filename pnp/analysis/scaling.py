"""What a bigger machine buys: iteration time and frames/s of `make train`'s MuJoCo and
kinematic iterations against the thread count and the device, each row profiled in this one
process (:func:`pnp.analysis.profile_iteration.profile`) with its ratio to the first row of
its backend.

    python recipes/analyze/scaling.py threads=1,2 out=results/scaling.json
    python recipes/analyze/scaling.py threads=1,4,8,16 devices=cpu,cuda out=$OUT/scaling.json   # a GPU machine

``threads=n`` gives MuJoCo's pool and torch's update n threads (the policy's forward keeps
one, the trainer's default); ``devices``: where the networks and the update run. Other
arguments are hydra overrides of recipes/train.py, added to every row.
"""
from __future__ import annotations

import json
import shlex
from pathlib import Path

from hydra import compose, initialize_config_dir
from tqdm import tqdm

from pnp.analysis.profile_iteration import profile
from pnp.training.choices import RECIPES_CONFIG
from pnp.training.config import register
from pnp.training.provenance import check_clean, provenance

# The iterations of `make train` (experiment=single_pnp_pipeline): its MuJoCo phases and its
# kinematic ones, episodes cut to 300 steps as in results/profile_iteration_mujoco.json.
BACKENDS = {
    "mujoco": ["experiment=single_pnp_pipeline", "env.backend=mujoco", "env.max_episode_steps=300"],
    "kinematic": ["experiment=single_pnp_pipeline", "env.backend=kinematic"],
}
OPTIONS = ("threads", "devices", "backends", "iterations", "out")


def _ints(text: str, key: str) -> list[int]:
    items = text.split(",")
    if not all(t.isdigit() and int(t) >= 1 for t in items):
        raise ValueError(f"{key}={text!r}: expected positive integers separated by commas, e.g. 1,4,8,16")
    return [int(t) for t in items]


def parse(argv: list[str]) -> tuple[dict, list[str]]:
    opts = {"threads": "1,2", "devices": "cpu", "backends": ",".join(BACKENDS), "iterations": "3",
            "out": "runs/scaling.json"}
    extra = []
    for arg in argv:
        key, _, value = arg.partition("=")
        if key in OPTIONS:
            opts[key] = value
        else:
            extra.append(arg)
    unknown = set(opts["backends"].split(",")) - set(BACKENDS)
    if unknown:
        raise ValueError(f"backends={opts['backends']!r}: {sorted(unknown)} not among {sorted(BACKENDS)}")
    return opts, extra


def main(argv: list[str]) -> dict:
    opts, extra = parse(argv)
    out = Path(opts["out"])
    check_clean(out, None)
    threads, iterations = _ints(opts["threads"], "threads"), _ints(opts["iterations"], "iterations")[0]
    grid = [(b, d, n) for b in opts["backends"].split(",") for d in opts["devices"].split(",") for n in threads]
    rows = []
    for backend, device, n in tqdm(grid, desc="scaling", unit="row"):
        overrides = [*BACKENDS[backend], f"env.nthread={n}", f"device={device}", *extra]
        with initialize_config_dir(config_dir=RECIPES_CONFIG, version_base="1.3"):
            cfg = compose("train", overrides=overrides)
        alone = [f"backends={backend}", f"devices={device}", f"threads={n}", f"iterations={iterations}", *extra]
        row = {"threads": n, **profile(cfg, iterations, 1, n), "overrides": overrides,
               "command": shlex.join(["python", "recipes/analyze/scaling.py", *alone])}
        first = next(r for r in rows + [row] if r["backend"] == backend)
        row["frames_per_s_ratio_to_first"] = row["frames_per_s"] / first["frames_per_s"]
        tqdm.write(f"{backend} {device} {n} threads: {row['seconds_per_iteration']:.2f} s per iteration, "
                   f"{row['frames_per_s']:.0f} frames/s (x{row['frames_per_s_ratio_to_first']:.2f} of "
                   f"{first['device']} {first['threads']} threads)")
        rows.append(row)
        # Written after every row: a device lease that ends mid-grid still returns the rows it measured.
        result = {"rows": rows, "rows_planned": len(grid), **provenance()}
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1) + "\n")
    plot(rows, out.with_suffix(".png"))
    return result


def plot(rows: list[dict], path: Path, title: str = "") -> None:
    """Frames/s against threads, one line per backend and device."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for key in sorted({(r["backend"], r["device"]) for r in rows}):
        mine = sorted((r["threads"], r["frames_per_s"]) for r in rows if (r["backend"], r["device"]) == key)
        ax.plot(*zip(*mine), marker="o", label=f"{key[0]}, update on {key[1]}")
    ax.set(xlabel="threads (MuJoCo pool and torch update)", ylabel="training frames/s", title=title)
    ax.set_xscale("log", base=2)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


register()
