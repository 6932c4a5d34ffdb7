"""A start-distance curriculum (ours): robots and box start near the goal, and the upper
start distance widens as training success allows, instead of a near-start phase followed
by a far-start one. It sets the env's ``start_range`` between iterations; new layouts use
it from their next reset."""
from __future__ import annotations

from omegaconf import DictConfig

from pnp.training.collect import windowed_mean


class StartCurriculum:
    """Widens ``env.start_range`` by ``cfg.step_m`` up to ``cfg.max_m`` each time the
    episode-weighted training success over the last ``cfg.window`` iterations (counted
    since the last widening) reaches ``cfg.min_success``."""

    def __init__(self, env, cfg: DictConfig):
        low, high = env.start_range
        if not low <= high <= cfg.max_m or cfg.step_m <= 0 or cfg.window < 1:
            raise ValueError(f"env.start_curriculum needs start_range[1]={high} <= max_m={cfg.max_m}, "
                             f"step_m={cfg.step_m} > 0 and window={cfg.window} >= 1")
        self.env, self.cfg, self.rows = env, cfg, []

    @property
    def high(self) -> float:
        return float(self.env.start_range[1])

    def update(self, row: dict) -> bool:
        """Feed one iteration's metrics; returns whether the starts widened."""
        self.rows.append({k: row[k] for k in ("episodes", "success_rate") if k in row})
        success = windowed_mean(self.rows, "success_rate", int(self.cfg.window))
        if success is None or success < float(self.cfg.min_success) or self.high >= float(self.cfg.max_m):
            return False
        self.env.start_range = (self.env.start_range[0], min(self.high + float(self.cfg.step_m), float(self.cfg.max_m)))
        self.rows = []
        return True

    def state_dict(self) -> dict:
        return {"start_range": list(self.env.start_range), "rows": list(self.rows)}

    def load_state_dict(self, state: dict) -> None:
        self.env.start_range = tuple(state["start_range"])
        self.rows = list(state["rows"])
