"""Checkpoints, RNG state, and warm starts across set-ups (a single-robot policy into the
dual-robot task, a curriculum state into a different number of worlds).

The actor (decentralised, shared parameters) has the same shapes for one or two robots.
The dual critic's first layer sees [own block | neighbour's block]; a single-robot
critic is widened with zero weights on the neighbour's block, so it starts out predicting
what it predicted alone.
"""
from __future__ import annotations

import json
import os
import pickle
import random
import zipfile
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase

_FIRST = "mlp.params.0.weight"


def rng_state() -> dict:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():  # a policy on the GPU samples there
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(state["cuda"])  # elsewhere (a CPU resume) nothing samples there


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


def save_checkpoint(path: Path, payload: dict) -> None:
    """Atomic: a run killed while writing keeps its previous checkpoint."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path) -> dict:
    try:
        ckpt = torch.load(path, weights_only=False, map_location="cpu")  # our own files
    except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile) as e:
        raise ValueError(f"checkpoint {path} is unreadable (truncated or not a torch file): {e}") from e
    missing = {"cfg", "actor", "counters"} - set(ckpt if isinstance(ckpt, dict) else ())
    if missing:
        raise ValueError(f"checkpoint {path} lacks {sorted(missing)}: not a checkpoint of recipes/train.py")
    return ckpt


def resolve_checkpoint(spec, runs_root: str | Path) -> Path:
    """``true``/``latest``: the newest ``checkpoint.pt`` under ``runs_root``; a run folder (a
    pipeline's: its last finished phase's); or a file."""
    if spec is True or str(spec).lower() in ("true", "latest"):
        found = sorted(Path(runs_root).glob("**/checkpoint.pt"), key=lambda p: p.stat().st_mtime)
        if not found:
            raise FileNotFoundError(f"no checkpoint.pt under {Path(runs_root).resolve()}")
        return found[-1]
    path = Path(str(spec))
    if path.is_dir() and not (path / "checkpoint.pt").is_file() and (path / "pipeline.json").is_file():
        phases = json.loads((path / "pipeline.json").read_text())["phases"]  # a pipeline: its last phase's
        if phases:
            return Path(phases[-1]["checkpoint"])
    if path.is_dir():
        path = path / "checkpoint.pt"
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    return path


def _widen(old: torch.Tensor, shape: torch.Size, key: str) -> torch.Tensor:
    if old.shape == shape:
        return old
    if not key.endswith(_FIRST) or old.shape[:-1] != shape[:-1] or shape[-1] % old.shape[-1]:
        raise ValueError(f"warm start: {key} has shape {tuple(old.shape)} in the checkpoint and {tuple(shape)} here; "
                         "only the critic's first layer may widen (single -> dual robots)")
    new = old.new_zeros(shape)
    new[..., : old.shape[-1]] = old
    return new


def load_module(module: torch.nn.Module, state: dict) -> list[str]:
    """``module.load_state_dict(state)`` with first layers widened; returns the widened keys."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    if missing:
        raise KeyError(f"warm start: the checkpoint lacks {missing}")
    widened = [k for k in own if own[k].shape != state[k].shape]
    module.load_state_dict({k: _widen(state[k], own[k].shape, k) for k in own})
    return widened


def load_optimiser(optim: torch.optim.Optimizer, state: dict) -> None:
    """Adam's moments and lr; moments of a widened parameter are zero-padded like it."""
    optim.load_state_dict(state)
    for group in optim.param_groups:
        for p in group["params"]:
            for name, v in optim.state.get(p, {}).items():
                if torch.is_tensor(v) and v.dim() and v.shape != p.shape:
                    optim.state[p][name] = _widen(v, p.shape, _FIRST)


def adapt_curriculum(state: dict, num_worlds: int, num_robots: int) -> dict:
    """Per-world curriculum tensors ([N, A, ...]) resized to ``num_worlds`` (rows reused
    cyclically) and, from one robot, repeated for each of ``num_robots``."""
    out = {}
    for k, v in state.items():
        if v.dim() >= 2:
            v = v[torch.arange(num_worlds) % v.shape[0]]
            if v.shape[1] != num_robots:
                if v.shape[1] != 1:
                    raise ValueError(f"warm start: curriculum {k} has {v.shape[1]} robots, this run {num_robots}")
                v = v.expand(num_worlds, num_robots, *v.shape[2:])
            v = v.clone()
        out[k] = v
    return out


def conform_to_spec(carried: TensorDictBase, spec) -> list:
    """Entries of ``carried`` whose shape differs from ``spec``'s set to the spec's zeros, in
    place; returns their keys. A checkpoint's carried step holds every observation entry,
    and one that grew since (a reward term added) could not be stacked with new steps."""
    zero, stale = spec.zero(), []
    have = set(carried.keys(True, True))
    for key in zero.keys(True, True):
        if key in have and carried[key].shape != zero[key].shape:
            carried[key] = zero[key]
            stale.append(key)
    return stale


def restore_training_state(ckpt: dict, env, models, optim: torch.optim.Optimizer):
    """A run's state where its checkpoint left it: weights, Adam, curriculum, every world's
    physics and the carried step the next collection starts from (returned)."""
    models.actor.load_state_dict(ckpt["actor"])
    models.critic.load_state_dict(ckpt["critic"])
    optim.load_state_dict(ckpt["optim"])
    env.transform.load_state_dict(ckpt["curriculum"])
    env.base_env.set_state(ckpt["env"])
    carried = ckpt["carried"]
    stale = conform_to_spec(carried, env.observation_spec)
    if stale:
        print(f"resume: the checkpoint's last step has {stale} in another shape (an entry added since): zeros")
    return carried
