"""Where a training iteration's time goes: policy forward, env step (physics + task terms +
TorchRL transforms) and the PPO update, for any training configuration.

    python recipes/analyze/profile_iteration.py experiment=single_pnp_pipeline iterations=3 out=runs/profile.json
    python recipes/analyze/profile_iteration.py backend=mujoco env.num_worlds=1024 collect.frames_per_batch=16384

The work is :mod:`pnp.analysis.profile_iteration` (its docstring says what and how).
"""
import sys

from pnp.analysis.profile_iteration import main


if __name__ == "__main__":
    main(sys.argv[1:])
