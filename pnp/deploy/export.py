"""The distilled student as one function a robot runs: observation, GRU state and an
episode-start flag in; the deterministic action and the next GRU state out. Exported to
ONNX for onnxruntime (``export_onnx``), so a robot needs neither torch nor this package.

    python -m pnp.deploy.export --checkpoint results/eval_student_single_checkpoint.pt --out runs/student.onnx

Per robot, not per team: the student's parameters are shared over robots and each robot's
action depends on its own observation and GRU state only, so a dual student exports as the
same one-robot function (batch ``N`` for several robots in one process).
"""
from __future__ import annotations

import argparse
import copy
import logging
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from pnp.task import ACTION_HIGH, ACTION_LOW, ACTION_NAMES
from pnp.training.recurrent import RecurrentStudentNet, recurrent_net
from pnp.training.stage_ensemble import call_head

GRIPPER = ACTION_NAMES.index("grasp")
# The ONNX graph's names: what a client feeds and reads.
INPUTS = ("observation", "hidden", "first_step")
OUTPUTS = ("action", "hidden_next")
# torchrl's SafeTanhTransform keeps tanh inside +-(1 - eps) (float32's resolution).
_TANH_EPS = float(torch.finfo(torch.float32).resolution)


def _shared_mlp(mlp: nn.Module) -> nn.Module:
    """The one network a share_params MultiAgentMLP applies to every agent, with its
    parameters, callable on any number of robots (the MultiAgentMLP insists on its own)."""
    net = copy.deepcopy(mlp._empty_net)
    for name, value in mlp.params.flatten_keys(".").items():
        *path, leaf = name.split(".")
        owner = net.get_submodule(".".join(path)) if path else net
        setattr(owner, leaf, nn.Parameter(value.detach().clone(), requires_grad=False))
    return net


class DeployedStudent(nn.Module):
    """``forward(observation [N, D], hidden [N, H], first_step [N, 1]) -> (action [N, 8],
    hidden_next [N, H])``: the recurrent student's deterministic action, as its
    ProbabilisticActor gives it in evaluation (the TanhNormal's transformed mean; the
    gripper closed iff its logit > 0). ``first_step`` 1 zeroes the state, as the env's
    step count 0 does in training."""

    def __init__(self, net: RecurrentStudentNet, low: torch.Tensor | None = None, high: torch.Tensor | None = None):
        """``low``/``high``: the actor's action bounds (default: the paper's, pnp.task)."""
        super().__init__()
        if not isinstance(net, RecurrentStudentNet):
            raise TypeError(f"DeployedStudent needs a RecurrentStudentNet (student.recurrent_cells > 0), "
                            f"got {type(net).__name__}")
        self.obs_norm = copy.deepcopy(net.obs_norm)
        self.gru = copy.deepcopy(net.gru)
        self.mlp = _shared_mlp(net.mlp)
        self.head = copy.deepcopy(net.head)
        self.hidden_size, self.n_obs = net.hidden_size, net.gru.input_size
        low = torch.tensor(ACTION_LOW) if low is None else low
        high = torch.tensor(ACTION_HIGH) if high is None else high
        low, high = (b.reshape(-1, len(ACTION_NAMES))[0].float() for b in (low, high))  # a spec's [R, 8]: robots alike
        self.register_buffer("mid", (high + low) / 2)
        self.register_buffer("half_range", (high - low) / 2)
        is_grip = torch.zeros(len(ACTION_NAMES), dtype=torch.bool)
        is_grip[GRIPPER] = True
        self.register_buffer("is_grip", is_grip)
        self.eval().requires_grad_(False)

    def forward(self, observation: torch.Tensor, hidden: torch.Tensor, first_step: torch.Tensor):
        x = self.obs_norm(observation)
        h = self.gru(x, hidden * (1.0 - first_step))
        loc, _ = call_head(self.head, self.mlp(torch.cat([x, h], -1)), observation[..., :0])
        arm = self.mid + self.half_range * torch.tanh(loc).clamp(-1.0 + _TANH_EPS, 1.0 - _TANH_EPS)
        return torch.where(self.is_grip, (loc > 0).to(loc.dtype), arm), h


def deployed_student(actor) -> DeployedStudent:
    """The :class:`DeployedStudent` of a loaded student actor (``load_student_actor``)."""
    net = recurrent_net(actor)
    if net is None:
        raise TypeError("this actor has no GRU (a student trained with student.recurrent_cells=0 or a teacher): "
                        "only the recurrent student is exported")
    bounds = actor.module[-1].distribution_kwargs  # the env's action spec it was built on (env.action_bounds)
    return DeployedStudent(net, bounds["low"], bounds["high"])


def export_onnx(student: DeployedStudent, path: str | Path) -> Path:
    """Writes ``student`` as an ONNX graph with a dynamic batch (robots) dimension."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A batch of 2: torch.export specialises a size-1 dimension to a constant.
    example = (torch.zeros(2, student.n_obs), torch.zeros(2, student.hidden_size), torch.ones(2, 1))
    batch = torch.export.Dim("robots", min=1, max=1024)
    quiet = logging.getLogger("torch.onnx")
    level, quiet.level = quiet.level, logging.ERROR  # its registry lists every torchvision op it skips
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(student, example, str(path), input_names=list(INPUTS), output_names=list(OUTPUTS),
                              dynamic_shapes={"observation": {0: batch}, "hidden": {0: batch}, "first_step": {0: batch}},
                              dynamo=True, external_data=False, verbose=False)
    finally:
        quiet.setLevel(level)
    return path


@dataclass
class OnnxStudent:
    """An exported student under onnxruntime: ``step(obs [N, D], first [N, 1])`` carries
    the GRU state itself; ``reset()`` zeroes it (a restarted client starts from zeros)."""

    path: Path
    n_robots: int = 1

    def __post_init__(self):
        import onnxruntime as ort  # the [deploy] extra

        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1  # one robot's 10 Hz loop
        self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        shapes = {i.name: i.shape for i in self.session.get_inputs()}
        self.n_obs, self.hidden_size = int(shapes["observation"][-1]), int(shapes["hidden"][-1])
        self.reset()

    def reset(self) -> None:
        self.hidden = np.zeros((self.n_robots, self.hidden_size), np.float32)

    def step(self, observation: np.ndarray, first_step: np.ndarray) -> np.ndarray:
        obs = np.asarray(observation, np.float32)
        if obs.shape != (self.n_robots, self.n_obs):
            raise ValueError(f"observation shape {obs.shape}: this student takes ({self.n_robots}, {self.n_obs})")
        if not np.isfinite(obs).all():
            raise ValueError(f"observation has non-finite entries at columns {np.flatnonzero(~np.isfinite(obs).all(0)).tolist()}")
        feed = {"observation": obs, "hidden": self.hidden,
                "first_step": np.asarray(first_step, np.float32).reshape(self.n_robots, 1)}
        action, self.hidden = self.session.run(list(OUTPUTS), feed)
        return action


def time_inference(fn, n: int = 200) -> dict:
    """Wall time per call of ``fn()`` over ``n`` calls after 10 warm-up ones: median and p99 (ms)."""
    for _ in range(10):
        fn()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t0))
    return {"calls": n, "median_ms": float(np.median(times)), "p99_ms": float(np.percentile(times, 99))}


def main(argv=None) -> None:
    from pnp.deploy.student_io import load_student

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, help="a recurrent student's checkpoint (distill run)")
    parser.add_argument("--out", required=True, help="the .onnx file to write")
    args = parser.parse_args(argv)
    student = deployed_student(load_student(args.checkpoint).actor)
    print(f"wrote {export_onnx(student, args.out)}")


if __name__ == "__main__":
    main()
