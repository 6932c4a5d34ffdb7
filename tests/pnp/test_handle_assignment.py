"""Which handle each robot's terms refer to (pnp.task.geometry): the nearest, and with two
robots near one handle, the farther one gets the other handle."""
import pytest
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


def test_own_first_lists_the_assigned_handle_first():
    _, h = _handles_of([[0.0, 0.0, 0.0]])
    x, z = float(h[0, 0]), float(h[0, 2])
    s = _state([[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]], (0.0, 0.0, 0.0))
    s.ee_pos = torch.tensor([[[x + 0.3, 0.0, z], [x + 0.1, 0.0, z]]])  # robot 1 keeps handle 0, robot 0 gets 1
    g = T.geometry(s)
    act = torch.zeros(1, 2, 8)
    ident = T.observations(s, g, act)["object"][0]
    own = T.observations(s, g, act, handle_order="own_first")["object"][0]
    H = T.OBS_FIELDS["object"]["handles"]
    first, second = slice(H.start, H.start + 3), slice(H.start + 3, H.stop)
    assert torch.equal(own[1], ident[1])  # its handle is handle 0: order unchanged
    assert torch.equal(own[0, first], ident[0, second]) and torch.equal(own[0, second], ident[0, first])
    F = T.OBS_FIELDS["object"]["handles_from_ee"]
    assert torch.equal(own[0, F.start:F.start + 3], ident[0, F.start + 3:F.stop])
    rest = [i for i in range(own.shape[-1]) if not (H.start <= i < F.stop)]
    assert torch.equal(own[:, rest], ident[:, rest])
    with pytest.raises(ValueError, match="nearest"):
        T.observations(s, g, act, handle_order="nearest")
