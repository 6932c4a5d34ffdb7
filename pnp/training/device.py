"""Where a run's networks, loss and PPO update run (``cfg.device``).

The envs stay on the CPU (MuJoCo steps there; the kinematic backend so far too): each step's
tensordict goes to the policy's device for its forward and comes back for the env, and the
iteration's batch goes there once for the update. On the CPU nothing moves, so the CPU path
is the one it always was (bit-exact resume included).
"""
from __future__ import annotations

import torch

DEVICE_TYPES = ("cpu", "cuda")


def training_device(spec: str) -> torch.device:
    """``cfg.device`` as a torch device, refused with its value when this machine lacks it."""
    try:
        device = torch.device(str(spec))
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"device={spec!r} is not a device name (expected one of {DEVICE_TYPES}, or cuda:<index>)") from e
    if device.type not in DEVICE_TYPES:
        raise ValueError(f"device={spec!r}: training runs on {DEVICE_TYPES} only")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device={spec!r}: this machine has no CUDA device (torch.cuda.is_available() is "
                             f"False); use device=cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device={spec!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device


def module_device(module: torch.nn.Module) -> torch.device:
    """The device of ``module``'s parameters (a policy runs where its weights are)."""
    return next(module.parameters()).device


def policy_step(policy, carried, device: torch.device, env_device: torch.device):
    """``policy`` on the step ``carried`` (held on ``env_device``), run on ``device``: the
    step goes there and comes back with the action for the env."""
    if device == env_device:
        return policy(carried)
    return policy(carried.to(device)).to(env_device)
