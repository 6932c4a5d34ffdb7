"""Which handle each robot's terms refer to (pnp.task.geometry): the nearest, and with two
robots near one handle, the farther one gets the other handle."""
import torch

import pnp.task as T
from tests.pnp.test_collisions import _state


def _handles_of(ee):
    s = _state([[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]][: len(ee)], (0.0, 0.0, 0.0))
    s.ee_pos = torch.tensor([ee], dtype=torch.float32)
    h = T.handles(s)[0]  # [2, 3]: +x, -x
    g = T.geometry(s)
    return [int(torch.argmin((h - g.handle[0, r]).norm(dim=-1))) for r in range(len(ee))], h


def test_nearest_handle_for_each_robot():
    _, h = _handles_of([[0.0, 0.0, 0.0]])
    z = float(h[0, 2])
    assert _handles_of([[0.5, 0.0, z]])[0] == [0] and _handles_of([[-0.5, 0.0, z]])[0] == [1]
    assert _handles_of([[0.5, 0.0, z], [-0.6, 0.1, z]])[0] == [0, 1]


def test_two_robots_at_one_handle_split():
    _, h = _handles_of([[0.0, 0.0, 0.0]])
    x, z = float(h[0, 0]), float(h[0, 2])
    assert _handles_of([[x + 0.3, 0.0, z], [x + 0.1, 0.0, z]])[0] == [1, 0]  # robot 1 is nearer: it keeps it
    assert _handles_of([[x + 0.1, 0.0, z], [x + 0.3, 0.0, z]])[0] == [0, 1]
    assert _handles_of([[x, 0.2, z], [x, -0.2, z]])[0] == [0, 1]  # a tie: robot 0 keeps it
