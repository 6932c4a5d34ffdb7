"""``device``: where the networks and the PPO update run; the env stays on the CPU. The CUDA
case runs only where torch sees a GPU (it is skipped on the CPU machines of CI)."""
from __future__ import annotations

import json

import pytest
import torch

from pnp.training.checkpoint import load_checkpoint
from pnp.training.device import training_device
from pnp.training.trainer import Trainer
from tests.training._tiny import TINY, compose_cfg, tiny_train

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]


def test_a_device_this_machine_lacks_is_refused_by_name():
    assert training_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match=r"device='tpu'"):
        training_device("tpu")
    with pytest.raises(ValueError, match=r"device='gpu0' is not a device name"):
        training_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"device='cuda': this machine has no CUDA device"):
            training_device("cuda")


@pytest.mark.parametrize("device", DEVICES)
def test_the_networks_and_the_update_run_on_the_device_and_resume_on_the_cpu(tmp_path, device):
    run = tmp_path / "run"
    trainer = Trainer(compose_cfg("train", [*TINY, f"out_dir={run}", "total_iterations=2", f"device={device}"]))
    on = {t.device.type for t in [*trainer.loss.parameters(), *trainer.loss.buffers()]}
    assert on == {device}, f"parameters and buffers on {on}, expected {device}"
    assert trainer.env.device == torch.device("cpu")  # the env stays on the CPU
    trainer.run()
    ckpt = load_checkpoint(run / "checkpoint.pt")  # readable on a CPU machine
    assert ckpt["counters"]["iteration"] == 2 and ckpt["cfg"]["device"] == device
    # A GPU run goes on on a CPU machine (device may change on a resume).
    out = tiny_train(run, f"resume={run}", "total_iterations=3", "device=cpu")
    assert out["iteration"] == 3
    rows = [json.loads(r) for r in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3] and all(torch.isfinite(torch.tensor(r["train/entropy"]))
                                                             for r in rows)
