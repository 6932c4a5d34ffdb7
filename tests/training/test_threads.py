"""torch's thread counts are the trainer's decision (cfg.threads), set per part of an iteration."""
from __future__ import annotations

import sys

import pytest
import torch
from omegaconf import OmegaConf

import pnp.training.trainer as trainer_module
from pnp.training.threads import available_cores, torch_threads
from tests.training._tiny import tiny_train


def test_null_means_the_available_cores_and_a_bad_count_is_named():
    assert torch_threads(OmegaConf.create({"collect": 1, "update": None})) == {"collect": 1, "update": available_cores()}
    with pytest.raises(ValueError, match=r"threads.update=0: expected a positive thread count"):
        torch_threads(OmegaConf.create({"collect": 1, "update": 0}))


def test_the_trainer_sets_the_collect_and_update_counts(tmp_path, monkeypatch):
    calls, real = [], torch.set_num_threads

    def recording(n):  # the env also runs its steps on one thread and restores the count: not counted
        if sys._getframe(1).f_code.co_filename == trainer_module.__file__:
            calls.append(n)
        real(n)

    before = torch.get_num_threads()
    monkeypatch.setattr(trainer_module.torch, "set_num_threads", recording)
    try:
        tiny_train(tmp_path / "run", "total_iterations=2", "threads.collect=1", "threads.update=2")
    finally:
        real(before)
    assert calls == [1, 2, 1, 2]


def test_mujocos_pool_defaults_to_the_cores_this_process_may_use(monkeypatch):
    from pnp.sim.backend import MujocoBackend
    from pnp.sim.box import SINGLE_ROBOT_BOXES
    from pnp.training.config import EnvConfig

    assert OmegaConf.structured(EnvConfig).nthread is None  # the schema leaves it to the machine
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 3, 5}, raising=False)
    backend = MujocoBackend(2, 1, SINGLE_ROBOT_BOXES[0])
    assert backend.physics.nthread == available_cores() == 3  # a job pinned to 3 cores gets 3 threads
    backend.close()
