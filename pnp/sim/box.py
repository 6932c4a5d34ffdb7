"""A box with two handles on its top face, and the paper's box assets.

Handles are horizontal bars along the box's y axis at x = +-(a/2 - HANDLE_INSET), held
by two posts; a downward gripper grasps a bar from above. Box sizes are
``(a, b, c)`` full edge lengths in metres. Assets follow the paper (Sec. IV): single
robot, three boxes of 1.0-1.3 kg with edges 0.22-0.45 m; dual robot, 1.9 and 2.2 kg
boxes with edges 0.3-1.5 m. The exact edges per asset are ours, inside those ranges.
"""
from __future__ import annotations

from dataclasses import dataclass

from pnp.sim import _offscreen  # noqa: F401  # sets MUJOCO_GL before dm_control loads

import numpy as np
from dm_control import composer, mjcf

HANDLE_RADIUS = 0.015  # m, ours: inside the 2F-140 stroke with margin
HANDLE_HEIGHT = 0.06  # m, bar axis above the top face
HANDLE_INSET = 0.05  # m, bar axis from the box's x edge
HANDLE_LEN = 0.10  # m, bar length (capped at 60 % of the box's y edge)
HANDLE_MASS = 0.05  # kg per handle (bar and posts)
BOX_CONTYPE, BOX_CONAFFINITY = 5, 3  # collides with floor (1) and robots (2)


@dataclass(frozen=True)
class BoxAsset:
    size: tuple[float, float, float]  # full edges (a, b, c), m
    mass: float  # kg


SINGLE_ROBOT_BOXES = (
    BoxAsset((0.30, 0.22, 0.22), 1.0),
    BoxAsset((0.38, 0.28, 0.25), 1.15),
    BoxAsset((0.45, 0.32, 0.30), 1.3),
)
DUAL_ROBOT_BOXES = (
    BoxAsset((1.2, 0.4, 0.3), 1.9),
    BoxAsset((1.5, 0.45, 0.35), 2.2),
)


def handle_layout(size) -> dict[str, np.ndarray]:
    """Geometry of the handles for full edges ``size``: bar centres, half length, posts."""
    a, b, c = (float(s) for s in size)
    half_len = min(HANDLE_LEN, 0.6 * b) / 2
    x = a / 2 - HANDLE_INSET
    z = c / 2 + HANDLE_HEIGHT
    return {
        "centres": np.array([[x, 0.0, z], [-x, 0.0, z]]),
        "half_len": half_len,
        "post_half_h": HANDLE_HEIGHT / 2,
        "post_z": c / 2 + HANDLE_HEIGHT / 2,
    }


class HandleBox(composer.Entity):
    """Box with handles ``handle0`` (+x) and ``handle1`` (-x)."""

    def _build(self, asset: BoxAsset, name: str = "box"):
        self._mjcf_root = root = mjcf.RootElement(model=name)
        root.default.geom.set_attributes(contype=BOX_CONTYPE, conaffinity=BOX_CONAFFINITY, friction=(1.0, 0.005, 0.0001))
        # Geoms go straight into the worldbody: the scene attaches this entity with a free
        # joint on its attachment frame (body ``box/``), as composer's free entities do.
        body = root.worldbody
        a, b, c = asset.size
        body_mass = asset.mass - 2 * HANDLE_MASS
        body.add("geom", name="shell", type="box", size=(a / 2, b / 2, c / 2), mass=body_mass, rgba=(0.6, 0.45, 0.3, 1))
        body.add("site", name="box_site", size=(0.01,), rgba=(0, 0, 0, 0))
        lay = handle_layout(asset.size)
        for i, centre in enumerate(lay["centres"]):
            hl = lay["half_len"]
            body.add(
                "geom", name=f"handle{i}", type="capsule", size=(HANDLE_RADIUS, hl), pos=centre,
                quat=(np.sqrt(0.5), np.sqrt(0.5), 0, 0),  # capsule z -> box y
                mass=HANDLE_MASS * 0.6, friction=(1.5, 0.01, 0.001), condim=4, rgba=(0.9, 0.8, 0.1, 1),
            )
            for k, sy in enumerate((1, -1)):
                body.add(
                    "geom", name=f"handle{i}_post{k}", type="box", size=(0.008, 0.008, lay["post_half_h"]),
                    pos=(centre[0], sy * (hl + 0.008), lay["post_z"]), mass=HANDLE_MASS * 0.2, rgba=(0.3, 0.3, 0.3, 1),
                )
            body.add("site", name=f"handle{i}_site", pos=centre, size=(0.01,), rgba=(0, 0, 1, 0.5))

    @property
    def mjcf_model(self):
        return self._mjcf_root


def _box_inertia(m, half):
    a, b, c = half
    return m / 3.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])


def _capsule_y_inertia(m, r, hl):
    # Capsule along y approximated as a solid cylinder of length 2 (hl + r): 1 mm-scale error.
    length = 2 * (hl + r)
    ax = 0.5 * m * r * r
    tr = m * (3 * r * r + length * length) / 12
    return np.array([tr, ax, tr])


def box_geometry(asset: BoxAsset, geom_names: list[str]) -> dict[str, np.ndarray]:
    """Per-geom size, pos, rbound, aabb and the body's mass, com and inertia for ``asset``.

    Lets one compiled model be resized per world (``pnp.sim.physics``) without recompiling;
    the tests compare it with a model compiled from that asset.
    """
    a, b, c = asset.size
    lay = handle_layout(asset.size)
    hl, ph = lay["half_len"], lay["post_half_h"]
    geoms = {"shell": (np.array([a / 2, b / 2, c / 2]), np.zeros(3), asset.mass - 2 * HANDLE_MASS, "box")}
    for i, centre in enumerate(lay["centres"]):
        geoms[f"handle{i}"] = (np.array([HANDLE_RADIUS, hl, 0.0]), centre, HANDLE_MASS * 0.6, "capsule")
        for k, sy in enumerate((1, -1)):
            pos = np.array([centre[0], sy * (hl + 0.008), lay["post_z"]])
            geoms[f"handle{i}_post{k}"] = (np.array([0.008, 0.008, ph]), pos, HANDLE_MASS * 0.2, "box")
    size, pos, rbound, aabb = [], [], [], []
    total, com, inertia = 0.0, np.zeros(3), np.zeros(3)
    for name in geom_names:
        s, p, m, kind = geoms[name.split("/")[-1]]
        size.append(s)
        pos.append(p)
        if kind == "box":
            rbound.append(np.linalg.norm(s))
            aabb.append(np.concatenate([np.zeros(3), s]))
        else:
            rbound.append(s[0] + s[1])
            aabb.append(np.array([0, 0, 0, s[0], s[0], s[0] + s[1]]))
        total += m
        com += m * p
    com /= total
    for name in geom_names:
        s, p, m, kind = geoms[name.split("/")[-1]]
        own = _box_inertia(m, s) if kind == "box" else _capsule_y_inertia(m, s[0], s[1])
        d = p - com
        inertia += own + m * (d @ d - d * d)  # parallel axis, diagonal part (symmetric body)
    return {
        "size": np.array(size), "pos": np.array(pos), "rbound": np.array(rbound), "aabb": np.array(aabb),
        "mass": total, "com": com, "inertia": inertia,
    }
