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
    X, Y = T.OBS_FIELDS["object"]["box_x_axis"], T.OBS_FIELDS["object"]["box_y_axis"]
    assert torch.equal(own[0, X], -ident[0, X]) and torch.equal(own[0, Y], -ident[0, Y])  # box turned half a turn
    P = T.OBS_FIELDS["object"]["box_pos"]
    for o in (own, ident):  # the first handle lies along the (listed) box x axis from its centre
        assert ((o[:, first] - o[:, P]) * o[:, X]).sum(-1).gt(0).all()
    flipped = set(range(H.start, F.stop)) | set(range(X.start, Y.stop))
    rest = [i for i in range(own.shape[-1]) if i not in flipped]
    assert torch.equal(own[:, rest], ident[:, rest]) and torch.equal(own[1], ident[1])
    last = T.observations(s, g, act, handle_order="own_last")["object"][0]
    assert torch.equal(last[0], ident[0])  # robot 0's handle is 1: already last
    assert torch.equal(last[1, first], ident[1, second]) and torch.equal(last[1, X], -ident[1, X])
    with pytest.raises(ValueError, match="nearest"):
        T.observations(s, g, act, handle_order="nearest")




def test_a_claimed_handle_stays_its_claimers():
    _, h = _handles_of([[0.0, 0.0, 0.0]])
    x, z = float(h[0, 0]), float(h[0, 2])
    s = _state([[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]], (0.0, 0.0, 0.0))
    s.ee_pos = torch.tensor([[[x + 0.1, 0.0, z + 0.1], [x + 0.3, 0.0, z]]])  # robot 0 nearer to handle 0
    none = torch.full((1, 2), -1)
    claim = T.update_claims(none, T.geometry(s, none))
    assert claim.tolist() == [[0, 1]]  # the farther of two at one handle takes the other
    s.ee_pos = torch.tensor([[[x + 0.1, 0.0, z + 0.1], [x + 0.01, 0.0, z]]])  # robot 1 now nearer to handle 0
    assert T.geometry(s).own.tolist() == [[True, False]]  # without claims it would take handle 0
    g = T.geometry(s, claim)
    assert g.own.tolist() == [[False, True]]  # with them each keeps its own
    assert torch.equal(T.update_claims(claim, g), claim)
    one = _state([[-3.0, 0.0, 0.0]], (0.0, 0.0, 0.0))
    one.ee_pos = torch.tensor([[[-x + 0.1, 0.0, z]]])  # one robot: its handle is fixed too
    assert T.geometry(one, torch.tensor([[0]])).own.tolist() == [[False]] and T.geometry(one).own.tolist() == [[True]]


def test_env_claims_stay_distinct_under_the_scripted_pair():
    from envs.pnp_env import PnPEnv
    from pnp.task.scripted import ScriptedPnP

    env = PnPEnv(num_worlds=4, num_robots=2, backend="kinematic", seed=0, nthread=1, handle_claim=True)
    pol, td = ScriptedPnP(4, 2), env.reset()
    claimed = torch.zeros(4, 2, dtype=torch.bool)
    for _ in range(250):
        td = env.step(pol(td))
        c = env._claim
        claimed |= c >= 0
        assert ((c >= -1) & (c <= 1)).all() and not ((c[:, 0] >= 0) & (c[:, 0] == c[:, 1])).any()
        td = env.step_mdp(td)
    assert claimed.all()
    st = env.get_state()
    env.set_state(st)
    assert torch.equal(env._claim, st["_claim"])
