"""Aggregate the selection evaluations of gpu_ri3 snapshots (not the reported figure) into
selection.json and selection.png beside this file.

    python results/train_single/gpu_ri3/selagg.py runs/gpu_ri3_b   # folder of sel<seed>_*.json
"""
import glob, json, sys
from pathlib import Path
import matplotlib; matplotlib.use("Agg")
import matplotlib.pyplot as plt
src, out_dir = Path(sys.argv[1]), Path(__file__).parent
rows = []
for f in glob.glob(str(src / "sel*_*.json")):
    d = json.load(open(f))
    rows.append({"iteration": d["checkpoint_iteration"], "seed": d["seed"], "trials": d["trials"],
                 "success_rate": d["success_rate"], "failure_causes": d["failure_causes"],
                 "completion_time_mean_s": d["completion_time_mean_s"], "command": d["command"],
                 "commit": d["commit"], "machine": d["machine"], "wall_s": d["wall_s"]})
rows.sort(key=lambda r: (r["seed"], r["iteration"]))
ref = json.load(open("results/eval_diagnostics/sel777_mj_ft7_1073.json"))
json.dump({"purpose": "checkpoint selection (not the reported figure): deterministic policy, 300 trials per row, MuJoCo",
           "reference_mj_ft7_1073_seed777": ref["success_rate"], "rows": rows}, open(out_dir / "selection.json", "w"), indent=1)
fig, ax = plt.subplots(figsize=(5.5, 3.4))
for seed in sorted({r["seed"] for r in rows}):
    rs = [r for r in rows if r["seed"] == seed]
    ax.plot([r["iteration"] for r in rs], [100 * r["success_rate"] for r in rs], "o-", label=f"gpu_ri3, seed {seed}")
ax.axhline(100 * ref["success_rate"], color="gray", ls="--", label="mj_ft7 @1073, seed 777")
ax.axhline(90, color="green", ls=":", label="issue target")
ax.set_xlabel("iteration"); ax.set_ylabel("deterministic success (%)"); ax.set_title("MuJoCo, 300 trials per point")
ax.legend(fontsize=7); fig.tight_layout(); fig.savefig(out_dir / "selection.png", dpi=120)
for r in rows:
    print(r["seed"], r["iteration"], round(r["success_rate"], 3), r["failure_causes"])
