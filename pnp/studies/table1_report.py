"""Table I as Markdown: the paper's single-robot numbers beside ours (``recipes/table1.py``)."""
from __future__ import annotations

# Paper, Table I, single robot, 500 trials: success (%), completion time (s). It has one
# row for Liu et al. (which variant is not said), shown against both of ours.
PAPER = {"dynamic": (93.6, "10.78 ± 0.34"), "liu_max": (0.0, None), "liu_min": (0.0, None),
         "bendikas": (91.2, "13.25 ± 0.41"), "erskine": (52.8, "16.00 ± 0.87")}
NAMES = {"dynamic": "ours (dynamic curriculum)", "liu_max": "Liu et al. (max)", "liu_min": "Liu et al. (min)",
         "bendikas": "Bendikas et al.", "erskine": "Erskine et al."}


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def _time(mean, std) -> str:
    return "-" if mean is None else f"{mean:.2f} ± {std:.2f}"


def _frames(seeds: dict, key: str) -> str:
    return ", ".join("never" if s[key] is None else f"{s[key] / 1e6:.1f}M" for s in seeds.values())


def _num(x) -> str:
    return "-" if x is None else f"{x:.2f}"


def _ci(doc: dict, key: str) -> str:
    ci = doc.get(key)
    return "" if ci is None else f" (95 % over seeds: {ci[0]:.2f}-{ci[1]:.2f})"


def markdown(doc: dict) -> str:
    """The comparison ``doc`` (``recipes/table1.py``'s JSON) as Markdown tables."""
    first = next(iter(doc["methods"].values()))
    keys = [k for k in next(iter(first["seeds"].values())) if k.startswith("frames_to_")]
    out = [f"Table I, single robot ({first['trials']} deterministic trials per seed; MuJoCo: seeds "
           f"{first['mujoco_seeds']}; kinematic: {first['kinematic']['seeds_evaluated']} seeds; budget "
           f"{first['budget_frames'] / 1e6:g}M frames, {first['kinematic_budget_frames'] / 1e6:g}M of them kinematic).",
           "", "| method | paper: success (%) | paper: time (s) | ours, MuJoCo: success (%) | time (s) "
           "| ours, kinematic: success (%), mean over seeds | time (s) |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for method, m in doc["methods"].items():
        paper, kin = PAPER.get(method, (None, None)), m["kinematic"]
        sd = kin["success_rate_std_over_seeds"]
        out.append(f"| {NAMES.get(method, method)} | {'-' if paper[0] is None else paper[0]} | {paper[1] or '-'} "
                   f"| {_pct(m['success_rate'])} | {_time(m['completion_time_mean_s'], m['completion_time_std_s'])} "
                   f"| {_pct(kin['success_rate'])}{'' if sd is None else f' (sd {100 * sd:.1f})'} "
                   f"| {_time(kin['completion_time_mean_s'], kin['completion_time_std_s'])} |")
    out += ["", f"Training frames until the training mean over {doc['window_iterations']} iterations reaches "
                "each threshold, per seed (kinematic phases):", "",
            "| method | " + " | ".join(k.removeprefix("frames_to_") for k in keys) + " |",
            "| --- |" + " --- |" * len(keys)]
    for method, m in doc["methods"].items():
        out.append(f"| {NAMES.get(method, method)} | " + " | ".join(_frames(m["seeds"], k) for k in keys) + " |")
    least = doc["efficiency_ratios_at_least"]
    out += ["", f"Efficiency ratio (the best baseline's frames over ours, first threshold): "
                f"{_num(doc['efficiency_ratio'])}{_ci(doc, 'efficiency_ratio_ci95')}; counting a seed that never got there as the kinematic "
                f"budget, at least " + " and ".join(f"{_num(least[k])} ({k.removeprefix('frames_to_')})" for k in keys)
            + f"; execution time ratio (ours over the most successful "
                f"baseline's, MuJoCo): {_num(doc['execution_time_ratio'])}{_ci(doc, 'execution_time_ratio_ci95')}, "
                f"kinematic: "
                f"{_num(doc['execution_time_ratio_kinematic'])}."]
    tuned = {m: v["tuning"] for m, v in doc["methods"].items() if v.get("tuning", {}).get("configs_tried", 1) > 1}
    if tuned:
        out += ["", "Tuning: each method's configuration chosen from the same candidates on selection trials "
                    "(kinematic success rate per candidate):", ""]
        out += [f"- {NAMES.get(m, m)}: chose {t['chosen']} of " + ", ".join(
                    f"{name} {_pct(c['success_rate'])} %" for name, c in t["candidates"].items())
                + f" (seed {t['selection_seed']}, {t['trials']} trials)" for m, t in tuned.items()]
    return "\n".join(out) + "\n"
