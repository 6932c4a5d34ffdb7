"""Per-world box resizing against the compiler, and episode randomisation ranges."""
import math

import mujoco
import numpy as np
import pytest
import torch

from pnp.sim.box import DUAL_ROBOT_BOXES, SINGLE_ROBOT_BOXES, BoxAsset
from pnp.sim.layout import MIN_ROBOT_BOX, MIN_ROBOT_ROBOT, SCALE_RANGE, START_RANGE, sample_layout
from pnp.sim.physics import BatchedPhysics
from pnp.sim.scene import build_scene


def _inertia_matrix(m, b):
    q = m.body_iquat[b]
    r = np.zeros(9)
    mujoco.mju_quat2Mat(r, q)
    r = r.reshape(3, 3)
    return r @ np.diag(m.body_inertia[b]) @ r.T


@pytest.mark.parametrize("target", [SINGLE_ROBOT_BOXES[2], BoxAsset((0.25, 0.3, 0.2), 1.1)])
def test_set_box_matches_a_compiled_model(target):
    _, m, idx = build_scene(1, SINGLE_ROBOT_BOXES[0])
    ph = BatchedPhysics(m, 2, idx.box_body, idx.box_geoms, nthread=1)
    ph.set_box(1, target)
    _, ref, ridx = build_scene(1, target)
    got, b = ph.models[1], idx.box_body
    np.testing.assert_allclose(got.geom_size[idx.box_geoms], ref.geom_size[ridx.box_geoms], atol=1e-9)
    np.testing.assert_allclose(got.geom_pos[idx.box_geoms], ref.geom_pos[ridx.box_geoms], atol=1e-9)
    np.testing.assert_allclose(got.body_mass[b], ref.body_mass[ridx.box_body], rtol=1e-9)
    np.testing.assert_allclose(got.body_ipos[b], ref.body_ipos[ridx.box_body], atol=1e-6)
    np.testing.assert_allclose(_inertia_matrix(got, b), _inertia_matrix(ref, ridx.box_body), rtol=0.02, atol=1e-6)
    # World 0 keeps the original asset.
    np.testing.assert_allclose(ph.models[0].geom_size[idx.box_geoms], m.geom_size[idx.box_geoms])
    ph.close()


@pytest.mark.parametrize("robots,assets", [(1, SINGLE_ROBOT_BOXES), (2, DUAL_ROBOT_BOXES)])
def test_layout_ranges(robots, assets):
    rng = torch.Generator().manual_seed(0)
    lay = sample_layout(rng, 2000, robots, assets)
    box_d = lay.box_xy_yaw[:, :2].norm(dim=-1)
    base_d = lay.base[..., :2].norm(dim=-1)
    for d in (box_d, base_d):
        assert d.min() >= START_RANGE[0] - 1e-5 and d.max() <= START_RANGE[1] + 1e-5
    edges = torch.tensor([a.size for a in assets])
    # Each edge is some asset's edge scaled by U(0.8, 1.2): check against the asset set.
    ratio = lay.box_size[:, None, :] / edges[None]
    ok = ((ratio >= SCALE_RANGE[0] - 1e-5) & (ratio <= SCALE_RANGE[1] + 1e-5)).all(-1).any(-1)
    assert ok.all()
    masses = torch.tensor([a.mass for a in assets])
    assert torch.isclose(lay.box_mass[:, None], masses[None]).any(-1).all()
    sep = (lay.base[..., :2] - lay.box_xy_yaw[:, None, :2]).norm(dim=-1)
    assert (sep > MIN_ROBOT_BOX).float().mean() > 0.99  # rejection sampling: rare fallbacks allowed
    if robots == 2:
        assert ((lay.base[:, 0, :2] - lay.base[:, 1, :2]).norm(dim=-1) > MIN_ROBOT_ROBOT).float().mean() > 0.99
    assert lay.base[..., 2].abs().max() <= math.pi


def test_layout_scales_cover_the_range():
    asset = SINGLE_ROBOT_BOXES[1]
    lay = sample_layout(torch.Generator().manual_seed(1), 2000, 1, (asset,))
    ratio = lay.box_size / torch.tensor(asset.size)
    assert ratio.min() < SCALE_RANGE[0] + 0.01 and ratio.max() > SCALE_RANGE[1] - 0.01
    assert abs(ratio.mean().item() - 1.0) < 0.01


def test_start_range_narrows_the_layout_and_is_validated():
    lay = sample_layout(torch.Generator().manual_seed(2), 500, 1, SINGLE_ROBOT_BOXES, start_range=(0.6, 1.5))
    d = torch.cat([lay.box_xy_yaw[:, :2].norm(dim=-1), lay.base[:, 0, :2].norm(dim=-1)])
    assert d.min() >= 0.6 - 1e-5 and d.max() <= 1.5 + 1e-5
    with pytest.raises(ValueError, match=r"start_range.*\(2.0, 1.0\)"):
        sample_layout(torch.Generator(), 4, 1, SINGLE_ROBOT_BOXES, start_range=(2.0, 1.0))
