"""Seeds or a sweep of recipes/train.py on a Ray cluster (Ray Tune; pnp.cluster.ray_runs).

    python recipes/ray_runs.py experiment=single_pnp_pipeline 'seeds=[0,1,2]' cpus_per_run=2 out_root=runs/seeds
    python recipes/ray_runs.py experiment=single_pnp_kinematic 'grid={optim.lr: [1e-4, 3e-4]}' address=auto
    ray start --head   # on the head node; `ray start --address=<head>:6379` on each worker; then address=auto

Rerunning the same command resumes every run's folder. Prints one line per run and writes
``<out_root>/ray_runs.json``.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from pnp.cluster.ray_runs import launch, ray_runs_config


def main() -> None:
    cfg = ray_runs_config(sys.argv[1:])
    runs = launch(cfg)
    for r in runs:
        print(f"{r['name']}: {'error ' + r['error'] if r['error'] else 'done'} {r['out_dir']}")
    out = Path(cfg.out_root) / "ray_runs.json"
    out.write_text(json.dumps(runs, indent=1, default=str))
    print(f"wrote {out}")
    if any(r["error"] for r in runs):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
