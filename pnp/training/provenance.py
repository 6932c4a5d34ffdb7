"""Who, where and how a result was produced: stored beside every figure in results/."""
from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from pnp.training.protocol import REPORTING_SEED, seed_role


# Written figures, not inputs: a batch of evaluations rewriting results/*.json is still the
# committed code (checkpoints in results/ are inputs and do count).
_OUTPUT_SUFFIXES = (".json", ".md", ".png", ".gif")


def _counts_as_dirty(porcelain_line: str) -> bool:
    path = porcelain_line[3:].strip()
    return not (path.startswith("results/") and path.endswith(_OUTPUT_SUFFIXES))


def _tree() -> tuple[str, list[str]]:
    """The short commit and the tracked files changed since (written figures in results/ aside)."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True)
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True).stdout
        return out.stdout.strip(), [x[3:].strip() for x in status.splitlines() if _counts_as_dirty(x)]
    except (OSError, subprocess.CalledProcessError):  # a copy without .git (a lent GPU machine) says its commit
        return os.environ.get("PNP_COMMIT", "unknown"), []


def commit() -> str:
    head, changed = _tree()
    return head + ("-dirty" if changed else "")


# The tree the process started from: a script that writes over a tracked file in results/
# (a re-rendered GIF) would otherwise call its own output a dirty tree.
_HEAD_AT_START, _CHANGED_AT_START = _tree()
_COMMIT_AT_START = _HEAD_AT_START + ("-dirty" if _CHANGED_AT_START else "")


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return f"{platform.system()} {platform.machine()}, {os.cpu_count()} cores, {cpu}"


def provenance(**extra) -> dict:
    """Command, commit (``-dirty`` with uncommitted code, and then ``dirty_files``), machine, date."""
    record = {
        "command": " ".join([os.path.relpath(sys.executable) if "venv" in sys.executable else "python", *sys.argv]),
        "commit": _COMMIT_AT_START,
        "machine": machine(),
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if _CHANGED_AT_START:
        record["dirty_files"] = list(_CHANGED_AT_START)
    return {**record, **extra}


def launch_record() -> dict:
    """A training launch's provenance; from a dirty tree it says which files were uncommitted."""
    record = provenance()
    if "dirty_files" in record:
        record["dirty_reason"] = "launched with uncommitted changes to " + ", ".join(record["dirty_files"])
    return record


def check_clean(out, dirty_reason: str | None) -> None:
    """Refuse to write a figure into results/ from a tree with uncommitted code or checkpoints,
    unless ``dirty_reason`` says why; called before the work, not after it."""
    if _CHANGED_AT_START and dirty_reason is None and Path(str(out or "")).parts[:1] == ("results",):
        raise ValueError(f"a figure for results/ from a dirty tree ({_COMMIT_AT_START}: "
                         f"{', '.join(_CHANGED_AT_START)}): commit first, or say why with dirty_reason=...")


def evaluation_record(ckpt: dict, seed: int, dirty_reason: str | None) -> dict:
    """What every evaluation result records beside its figures: the seed and its role, the
    pairing, the experiment and configuration hash of the checkpoint, and the provenance."""
    source = launch_source(ckpt.get("launches", []))
    record = {"seed": seed, "seed_role": seed_role(seed), "reporting_seed": REPORTING_SEED, "paired": True,
              "experiment": source["experiment"], "launch_overrides": source["launch_overrides"],
              "config_sha": config_sha(ckpt["cfg"]), **provenance()}
    if _CHANGED_AT_START:
        record["dirty_reason"] = dirty_reason
    return record


def write_result(result: dict, out, markdown: str) -> dict:
    """``result`` as JSON at ``out`` and ``markdown`` beside it (``.md``); returns ``result``
    with both paths added. A figure for results/ from a dirty tree needs its ``dirty_reason``
    (the recipes check before the work; this is the last line)."""
    out = Path(out)
    check_clean(out, result.get("dirty_reason"))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown)
    result["json"], result["markdown"] = str(out), str(out.with_suffix(".md"))
    return result


# Where a run lives or how it is watched, not what it trains: left out of the config hash.
_LOCATION_KEYS = ("out_dir", "resume", "runs_root", "progress", "logger", "checkpoint_every_min", "branch_from")


def config_sha(cfg) -> str:
    """Short SHA-256 of a resolved training configuration, without the run's location keys."""
    from omegaconf import OmegaConf

    data = OmegaConf.to_container(cfg, resolve=True) if not isinstance(cfg, dict) else dict(cfg)
    data = {k: v for k, v in data.items() if k not in _LOCATION_KEYS}
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:12]


def launch_source(launches: list[dict]) -> dict:
    """The experiment a checkpoint's last launch named (``experiment=`` or ``distill_experiment=``)
    and its other command-line overrides; ``None`` where the launch named none."""
    if not launches:
        return {"experiment": None, "launch_overrides": []}
    args = launches[-1]["command"].split()[2:]
    name = next((a.split("=", 1)[1] for a in args if a.split("=", 1)[0] in ("experiment", "distill_experiment")), None)
    rest = [a for a in args if a.split("=", 1)[0] not in ("experiment", "distill_experiment", "out_dir")]
    return {"experiment": name, "launch_overrides": rest}
