"""Offscreen rendering on the CPU (skipped where EGL/Mesa is not installed)."""

import numpy as np
import pytest

from pnp.envs.pnp_env import PnPEnv
from tests.training._tiny import tiny_train
from pnp.analysis import render_gif as render_recipe


def test_render_frame_shows_the_scene():
    try:
        from pnp.sim.render import WorldRenderer

        env = PnPEnv(num_worlds=1, nthread=1)
        r = WorldRenderer(env.backend, 0, width=96, height=64)
    except Exception as e:  # noqa: BLE001 - any GL failure means no offscreen context here
        pytest.skip(f"no offscreen GL context: {e}")
    img = r.frame()
    r.close()
    assert img.shape == (64, 96, 3) and img.dtype == np.uint8
    assert img.std() > 5  # not a blank frame


def test_render_a_trained_checkpoint(tmp_path):
    pytest.importorskip("imageio")
    try:
        from pnp.sim.render import WorldRenderer

        WorldRenderer(PnPEnv(num_worlds=1, nthread=1).backend, 0, width=32, height=32).close()
    except Exception as e:  # noqa: BLE001
        pytest.skip(f"no offscreen GL context: {e}")
    tiny_train(tmp_path / "run", "total_iterations=1")
    out = tmp_path / "teacher.gif"
    info = render_recipe.main(["--checkpoint", str(tmp_path / "run"), "--out", str(out), "--tries", "2",
                               "--max-steps", "4", "--every", "2"])
    assert out.stat().st_size > 0 and info["checkpoint_iteration"] == 1 and info["episodes_tried"] == 2
    assert info["steps"] == 4 and not info["success"]  # 0.4 s: no policy succeeds that fast
    assert info["outcome_wanted"] == "success" and not info["outcome_found"]
    info = render_recipe.main(["--checkpoint", str(tmp_path / "run"), "--out", str(out), "--tries", "2",
                               "--max-steps", "4", "--outcome", "failure"])
    assert info["episodes_tried"] == 1 and info["outcome_found"] and not info["success"]
