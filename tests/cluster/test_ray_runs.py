"""A local Ray cluster runs a two-run multirun of a tiny experiment to the end, each run in
its own folder with its threads set to its declared CPUs; rerunning it resumes (nothing left to do)."""
from __future__ import annotations

import json

import pytest

ray = pytest.importorskip("ray")

from pnp.cluster.ray_runs import command, launch, ray_runs_config, run_points  # noqa: E402
from tests.training._tiny import TINY  # noqa: E402

TRAIN = [o for o in TINY if not o.startswith(("logger.", "progress="))] + ["total_iterations=2"]


def test_points_and_commands():
    cfg = ray_runs_config(["seeds=[0,1]", "grid={optim.lr: [0.001, 0.0003]}", "cpus_per_run=3", "out_root=/tmp/r"])
    points = run_points(cfg)
    assert [p["name"] for p in points] == ["optim.lr_0.001-seed_0", "optim.lr_0.001-seed_1",
                                           "optim.lr_0.0003-seed_0", "optim.lr_0.0003-seed_1"]
    cmd = command(cfg, points[1])
    assert "seed=1" in cmd and "optim.lr=0.001" in cmd and "threads.update=3" in cmd and "env.nthread=3" in cmd
    assert "out_dir=/tmp/r/optim.lr_0.001-seed_1" in cmd


@pytest.mark.timeout(600)
def test_local_cluster_runs_two_seeds_to_the_end(tmp_path):
    overrides = "[" + ",".join(f"'{o}'" for o in TRAIN) + "]"
    cfg = ray_runs_config([f"overrides={overrides}", "seeds=[0,1]", "cpus_per_run=1", f"out_root={tmp_path}"])
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        runs = launch(cfg)
        assert [r["error"] for r in runs] == [None, None]
        for seed, r in enumerate(runs):
            rows = [json.loads(x) for x in (tmp_path / f"seed_{seed}" / "metrics.jsonl").read_text().splitlines()]
            assert [row["iteration"] for row in rows] == [1, 2]
            assert r["metrics"]["iteration"] == 2
        cfg.seeds = [0]
        again = launch(cfg)  # the same run again: its folder resumes, already at its end
        assert [r["error"] for r in again] == [None]
        rows = (tmp_path / "seed_0" / "metrics.jsonl").read_text().splitlines()
        assert len(rows) == 2
    finally:
        ray.shutdown()
