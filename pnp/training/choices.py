"""The closed choices of the training configuration's schema (``pnp.training.config``), and
where the recipes' hydra configs live."""
from __future__ import annotations

from enum import StrEnum
from pathlib import Path

# Closed choices are enums, so hydra refuses another value when it composes (a StrEnum
# member equals, formats and hashes as its string; checkpoints store the strings). Choices
# that a registry extends (env.task, curriculum.schedule, model.per_stage) stay strings,
# checked where the registry is read.
Backend = StrEnum("Backend", ["mujoco", "kinematic"])
HandleOrder = StrEnum("HandleOrder", ["identity", "own_first", "own_last"])
GraspPose = StrEnum("GraspPose", ["height", "bar"])
LowLevel = StrEnum("LowLevel", ["ideal", "learned"])
EpisodeStage = StrEnum("EpisodeStage", ["peak", "final"])
GraspDist = StrEnum("GraspDist", ["bernoulli", "tanh_normal"])
ValueNorm = StrEnum("ValueNorm", ["popart", "none"])
LrSchedule = StrEnum("LrSchedule", ["adaptive", "fixed"])
LoggerBackend = StrEnum("LoggerBackend", ["wandb", "csv"])


# The recipes' hydra configs (a checkout's; the studies and tools compose from them).
RECIPES_CONFIG = str(Path(__file__).resolve().parents[2] / "recipes" / "config")
