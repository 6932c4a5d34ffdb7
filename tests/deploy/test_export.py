"""The exported student acts as the PyTorch student does, on observations the env produced."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from tensordict.nn import InteractionType, set_interaction_type

from pnp.deploy.export import GRIPPER, OnnxStudent, deployed_student, export_onnx
from pnp.deploy.student_io import load_student
from pnp.task import ACTION_LOW, ACTION_NAMES
from pnp.training.keys import ACTION, STUDENT_OBS
from pnp.training.recurrent import HIDDEN, HIDDEN_NEXT, carry_state, init_state
from tests.training._tiny import ROOT

pytest.importorskip("onnxruntime")
CHECKPOINT = ROOT / "results" / "eval_student_dual_checkpoint.pt"
# float32 arithmetic in another order (onnxruntime's kernels): agreement to ~1e-6 measured.
TOL = 1e-4


@pytest.fixture(scope="module")
def recorded():
    """20 deterministic steps of the dual student in 3 kinematic worlds: its inputs and outputs."""
    torch.manual_seed(0)
    s = load_student(CHECKPOINT, num_worlds=3, backend="kinematic")
    steps = []
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        td = init_state(s.env.reset(), s.actor)
        for _ in range(20):
            td = s.actor(td)
            first = (td["step_count"] == 0).float().expand(-1, td.get(STUDENT_OBS).shape[-2])
            steps.append({k: td.get(key).clone() for k, key in
                          (("obs", STUDENT_OBS), ("hidden", HIDDEN), ("next", HIDDEN_NEXT), ("action", ACTION))}
                         | {"first": first.clone()})
            out, td = s.env.step_and_maybe_reset(td)
            carry_state(out, td)
    s.env.close()
    return s, steps


@pytest.fixture(scope="module")
def onnx_path(recorded, tmp_path_factory):
    return export_onnx(deployed_student(recorded[0].actor), tmp_path_factory.mktemp("onnx") / "student.onnx")


def _flat(x: torch.Tensor) -> torch.Tensor:  # [N, A, ...] -> [N * A, ...]
    return x.reshape(-1, *x.shape[2:])


def test_deployed_module_equals_the_actor(recorded):
    s, steps = recorded
    student = deployed_student(s.actor)
    for step in steps:
        action, nxt = student(_flat(step["obs"]), _flat(step["hidden"]), _flat(step["first"]).unsqueeze(-1))
        assert torch.allclose(action, _flat(step["action"]), atol=TOL, rtol=0)
        assert torch.allclose(nxt, _flat(step["next"]), atol=TOL, rtol=0)


def test_onnx_equals_the_actor_over_an_episode(recorded, onnx_path):
    _, steps = recorded
    onnx = OnnxStudent(onnx_path, n_robots=_flat(steps[0]["obs"]).shape[0])
    grips = set()
    for step in steps:  # the runtime carries its own GRU state from step to step
        action = onnx.step(_flat(step["obs"]).numpy(), _flat(step["first"]).numpy())
        expected = _flat(step["action"]).numpy()
        assert np.abs(action - expected).max() <= TOL
        assert np.array_equal(action[:, GRIPPER], expected[:, GRIPPER])
        grips |= set(action[:, GRIPPER].tolist())
    assert grips <= {0.0, 1.0}


def test_onnx_refuses_bad_observations(onnx_path):
    onnx = OnnxStudent(onnx_path, n_robots=1)
    with pytest.raises(ValueError, match=r"shape \(1, 3\)"):
        onnx.step(np.zeros((1, 3)), np.ones((1, 1)))
    bad = np.zeros((1, onnx.n_obs))
    bad[0, 7] = np.nan
    with pytest.raises(ValueError, match=r"columns \[7\]"):
        onnx.step(bad, np.ones((1, 1)))


def test_a_teacher_is_refused():
    with pytest.raises(ValueError, match="teacher's checkpoint"):
        load_student(ROOT / "results" / "repro_dual_pnp_checkpoint.pt")


def test_deployed_module_takes_the_actors_action_bounds(recorded):
    actor = copy.deepcopy(recorded[0].actor)
    kwargs = actor.module[-1].distribution_kwargs  # env.action_bounds narrows the spec they come from
    kwargs["high"] = kwargs["high"].clone()
    kwargs["high"][..., ACTION_NAMES.index("ee_x")] = 0.85
    student = deployed_student(actor)
    i = ACTION_NAMES.index("ee_x")
    assert float(student.mid[i]) == pytest.approx((0.85 + ACTION_LOW[i]) / 2)
    assert float(student.half_range[i]) == pytest.approx((0.85 - ACTION_LOW[i]) / 2)
