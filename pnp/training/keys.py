"""TensorDict keys shared by the models, the losses and the trainer (multi-agent layout:
per-robot entries under ``"agents"`` with batch ``[*B, A]``)."""
from __future__ import annotations

OBS = ("agents", "observation")
STAGE_ONE_HOT = ("agents", "stage_one_hot")
ACTION = ("agents", "action")
LOG_PROB = ("agents", "action_log_prob")
VALUE = ("agents", "state_value")
LOC, SCALE = ("agents", "loc"), ("agents", "scale")
REWARD = ("agents", "reward")
ADVANTAGE = ("agents", "advantage")
VALUE_TARGET = ("agents", "value_target")
STAGE = ("agents", "stage")
EPISODE_STAGE = ("agents", "episode_stage")
PEAK = ("agents", "stage_peak")  # written under curriculum.episode_stage=peak
ROLL_IN = "roll_in"  # bool [N, 1] per step: the action was the policy's mean (a roll-in step)
# Teacher-student distillation (pnp.distill.student): the student's noisy observation with
# arm-joint history (beside the clean one the teacher and the critic read), and the frozen
# teacher's distribution parameters on the same states.
STUDENT_OBS = ("agents", "student_observation")
TEACHER_LOC, TEACHER_SCALE = ("agents", "teacher_loc"), ("agents", "teacher_scale")
