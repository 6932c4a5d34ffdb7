"""Old checkpoints' configurations brought to the schema (``pnp.training.config``): retired
keys dropped when they held their neutral value, missing keys given the code defaults of
their time; and the settings two configurations differ in.
"""
from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from pnp.training.config import TrainConfig


# Keys that old checkpoints hold and the schema dropped: each with the only value that
# leaves behaviour unchanged (any other value is refused, never silently dropped).
_RETIRED = {
    "env.lone_holder_pinned": False,
    "loss.reach_coeff": 0.0,
    "env.kinematic.slip": False,  # measured not to help the kinematic-to-MuJoCo transfer
    "env.kinematic.box_pushed": False,  # likewise
    "env.grasp_sampling": "threshold",  # the env sampled the gripper: stalled learning to hold
    "env.start_curriculum": {"enabled": False},  # unmeasured (archive/single_pnp_auto only)
}
_MOVED_TO_KINEMATIC = ("box_blocks_base", "grasp_holds")


def _is_neutral(value, neutral) -> bool:
    if isinstance(neutral, dict):  # a retired group: neutral while its listed keys are
        return not isinstance(value, dict) or all(value.get(k, v) == v for k, v in neutral.items())
    return value in (neutral, None)


def drop_retired(saved) -> dict:
    """A stored configuration (as a plain dict) without the keys the schema dropped; a key
    that was not at its neutral value is refused, never silently dropped."""
    saved = OmegaConf.to_container(OmegaConf.create(saved), resolve=True)
    for dotted, neutral in _RETIRED.items():
        *groups, key = dotted.split(".")
        node = saved
        for g in groups:
            node = node.get(g) if isinstance(node, dict) else None
        value = node.pop(key, neutral) if isinstance(node, dict) else neutral
        if not _is_neutral(value, neutral):
            raise ValueError(f"checkpoint config {dotted}={value!r}: that option was removed "
                             f"(only {neutral!r} is still supported)")
    return saved


def migrate(saved: dict) -> DictConfig:
    """A checkpoint's stored configuration as a validated :class:`TrainConfig`.

    Checkpoints written before the schema lack keys that have defaults now (and had other
    code defaults then: ``terminate_on_success`` True, ``episode_stage`` final,
    ``grasp_dist`` tanh_normal), hold the kinematic options at the top of ``env``, and
    may hold retired keys.
    """
    saved = drop_retired(saved)
    env, cur, model = saved.setdefault("env", {}), saved.setdefault("curriculum", {}), saved.setdefault("model", {})
    kin = {k: bool(env.pop(k)) for k in _MOVED_TO_KINEMATIC if k in env}
    if env.get("backend") == "kinematic" and "kinematic" not in env:
        env["kinematic"] = kin
    # The code defaults of the recipes before the schema, for keys such checkpoints lack.
    env.setdefault("terminate_on_success", True)
    cur.setdefault("episode_stage", "final")
    model.setdefault("grasp_dist", "tanh_normal")
    return OmegaConf.merge(OmegaConf.structured(TrainConfig), saved)


def changed_settings(now: DictConfig, then: DictConfig, resumable) -> dict:
    """``{key: (then, now)}`` for every dotted key outside ``resumable`` whose value differs:
    settings a resume from ``then``'s checkpoint would silently ignore."""
    a, b = (_flat(OmegaConf.to_container(c, resolve=True)) for c in (now, then))
    return {k: (b.get(k), a.get(k)) for k in sorted(set(a) | set(b)) if k not in resumable and a.get(k) != b.get(k)}


def _flat(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out
