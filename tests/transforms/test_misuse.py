"""Ways a TorchRL user wrapping their own env goes wrong with the curriculum keys: a group of the
root batch (failed deep inside tensordict once stacked) and per-robot entries at the root (a bare
KeyError) are refused at the first reset with a message that names the fix; a partial reset
without the carried tensordict is TorchRL's contract, shown here as docs/guide/own_env.md states it."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Composite
from torchrl.envs import TransformedEnv

from pnp.task.stage_graph import pnp_default_stage_graph
from pnp.transforms import StageTransition

from ._toy_env import ToyStageEnv


class GroupSetEntryByEntry(ToyStageEnv):
    """Writes the ``agents`` entries with ``td.set(("agents", k), v)``: the group gets batch [*B]."""

    def _obs(self):
        good = super()._obs()
        td = TensorDict(done=good["done"], terminated=good["terminated"], batch_size=good.batch_size)
        for k, v in good["agents"].items():
            td.set(("agents", k), v)
        return td


class EntriesAtTheRoot(ToyStageEnv):
    """Per-robot entries at the root, where the transforms expect an ``agents`` group."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        group = self.observation_spec["agents"]
        self.observation_spec = Composite({k: group[k] for k in group.keys()}, shape=self.batch_size)

    def _obs(self):
        good = super()._obs()
        return TensorDict({**good["agents"].to_dict(), "done": good["done"], "terminated": good["terminated"]},
                          batch_size=good.batch_size)


def _stage(env) -> TransformedEnv:
    return TransformedEnv(env, StageTransition(pnp_default_stage_graph()))


def test_a_group_of_the_root_batch_is_refused_at_the_first_reset():
    env = _stage(GroupSetEntryByEntry(n_conditions=6))
    with pytest.raises(ValueError, match=r"'agents' group has batch \[3\], expected \[3, 2\].*set it whole"):
        env.reset()


def test_a_partial_reset_keeps_the_other_worlds_only_with_the_carried_tensordict():
    """TorchRL's contract, not the transform's: ``env.reset`` merges its output into the given
    tensordict by the mask and pads what that tensordict lacks with 0, for every entry."""
    env = _stage(ToyStageEnv(n_conditions=6))
    td = env.reset()
    for _ in range(3):
        td = env.step(td.set(("agents", "action"), torch.zeros(3, 2, 1)))["next"]
    mask = torch.tensor([[True], [False], [False]])
    out = env.reset(td.clone().set("_reset", mask))
    assert out["agents", "stage"][0].sum() == 0 and td["agents", "stage"][1:].sum() > 0
    assert torch.equal(out["agents", "stage"][1:], td["agents", "stage"][1:])
    bare = env.reset(TensorDict({"_reset": mask}, batch_size=(3,)))
    for key in (("agents", "stage"), ("agents", "observation")):  # the stage as the env's own entries
        assert bare[key][1:].eq(0).all() and not td[key][1:].eq(0).all(), key


def test_entries_at_the_root_name_the_expected_key():
    env = _stage(EntriesAtTheRoot(n_conditions=6))
    with pytest.raises(KeyError, match=r"reads agents.stage_conditions.*spec has: observation, reward_terms, "
                                       r"stage_conditions.*conditions_key="):
        env.reset()
