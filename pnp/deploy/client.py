"""A robot's client: its exported student at 10 Hz on its own timer, fed the freshest data
it has (its own sensors from its hardware, the others' states and the mocap box through
the coordinator, however late they are).

    python -m pnp.deploy.client checkpoint=C robot_id=1 coordinator_address=H:P world_address=H:P onnx=F

The robot's view of the world is a TorchRL env (:class:`RemoteRobotEnv`): one step sends
the command, waits for the timer's next tick with a new state, and forms the observation
from the messages with the task's own observation function; the student's observation
transforms (noise, joint history) then run on it exactly as in training.
"""
from __future__ import annotations

import logging
import time

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from pnp.deploy.messages import header, read_box_pose, read_episode_info, read_robot_state
from pnp.deploy.messages import command as command_message
from pnp.deploy.proto import deploy_pb2 as pb
from pnp.task import ACTION_HIGH, ACTION_LOW, OBS_BLOCKS, PnPState
from pnp.task.geometry import BaseFrame, geometry
from pnp.task.observations import observations

log = logging.getLogger("pnp.deploy.client")
N_OBS = sum(OBS_BLOCKS.values())


class WorldFinished(Exception):
    """The trial set is over (the world said so, or it is gone)."""


def pnp_state(own: int, states: dict[int, dict], box: dict, episodes: dict, num_robots: int) -> PnPState:
    """The task state [W, R] as robot ``own`` knows it: its own sensors, the others' relayed
    states (``states`` by robot), the mocap's box, the episodes' goal and box size."""
    def stack(name, width):
        return torch.stack([torch.as_tensor(states[r][name]).reshape(-1, *width) for r in range(num_robots)], 1)

    worlds = len(episodes["episode"])
    return PnPState(
        base=stack("base", (3,)), base_z=stack("base_z", ()), base_vel=stack("base_vel", (3,)),
        arm_q=stack("arm_q", (6,)), arm_qd=stack("arm_qd", (6,)), finger_q=stack("finger_q", (2,)),
        touch=stack("touch", (2,)) > 0.5, ee_pos=stack("ee_pos", (3,)), ee_rot=stack("ee_rot", (3, 3)),
        box_pos=torch.as_tensor(box["pos"]), box_rot=torch.as_tensor(box["rot"]).reshape(-1, 3, 3),
        box_vel=torch.as_tensor(box["vel"]), box_size=torch.as_tensor(episodes["box_size"]),
        goal=torch.as_tensor(episodes["goal"]), init_goal_dist=torch.zeros(worlds),
        grasp_cmd=torch.zeros(worlds, num_robots))


def observation(own: int, states: dict[int, dict], box: dict, episodes: dict, num_robots: int,
                handle_order: str) -> torch.Tensor:
    """Robot ``own``'s clean observation [W, 1, 74], as the env forms it."""
    s = pnp_state(own, states, box, episodes, num_robots)
    last = torch.stack([torch.as_tensor(states[r]["last_action"]) for r in range(num_robots)], 1)
    g = geometry(s, torch.as_tensor(episodes["handle"]))  # the world's claims; -1: the nearest-handle rule
    blocks = observations(s, g, last, BaseFrame(s), handle_order)
    return torch.cat([blocks[k] for k in OBS_BLOCKS], -1)[:, own : own + 1]


class RemoteRobotEnv(EnvBase):
    """Robot ``robot_id``'s view of W worlds over gRPC (``world``: its hardware's Robot stub,
    ``coordinator``: the Coordinator stub). A world whose episode changed is done; its
    reset returns the new episode's first observation. No reward: deployment only acts."""

    batch_locked = True

    def __init__(self, robot_id: int, world, coordinator, worlds: int, num_robots: int, handle_order: str,
                 tick_s: float):
        super().__init__(batch_size=torch.Size([worlds]))
        self.robot_id, self.world, self.coordinator = robot_id, world, coordinator
        self.worlds, self.num_robots, self.handle_order, self.tick_s = worlds, num_robots, handle_order, tick_s
        agents = lambda d: Composite(d, shape=(worlds, 1))  # noqa: E731
        flag = lambda: Categorical(2, shape=(worlds, 1), dtype=torch.bool)  # noqa: E731
        self.full_observation_spec = Composite({"agents": agents({"observation": Unbounded(shape=(worlds, 1, N_OBS))})},
                                               shape=(worlds,))
        self.full_action_spec = Composite({"agents": agents({"action": Bounded(
            torch.tensor(ACTION_LOW).expand(worlds, 1, 8), torch.tensor(ACTION_HIGH).expand(worlds, 1, 8),
            shape=(worlds, 1, 8))})}, shape=(worlds,))
        self.full_reward_spec = Composite({"agents": agents({"reward": Unbounded(shape=(worlds, 1, 1))})},
                                          shape=(worlds,))
        self.full_done_spec = Composite({"done": flag(), "terminated": flag(), "truncated": flag()}, shape=(worlds,))
        self.tick, self.seq, self.next_at = -1, 0, None
        self.states: dict[int, dict] = {}
        self.box = self.episodes = None
        self.episode = np.full(worlds, -1, np.int64)
        self.first_step = np.ones((worlds, 1), np.float32)
        self.waiting = self.was_waiting = np.zeros(worlds, bool)
        self.obs = None
        self.counts = {"steps": 0, "skipped_timer_ticks": 0, "missed_world_ticks": 0, "waiting_world_ticks": 0}
        self.finished = False

    def _poll(self) -> pb.Poll:
        self.seq += 1
        return pb.Poll(header=header(self.robot_id, 0.0, self.seq))

    def _wait_for_new_state(self) -> pb.RobotState:
        """The timer's next tick that shows a state newer than the last one acted on.

        The timer locks its phase to the world's: when it fires before the new state is
        out, it looks again every 1/20 of a tick and restarts its period from the moment
        the state appears (unsynchronised, a command came ~half a tick late on average)."""
        now = time.monotonic()
        if self.next_at is not None and now < self.next_at:
            time.sleep(self.next_at - now)
        polls = 0
        while True:
            state = self.world.Sense(self._poll())
            if state.worlds and state.tick != self.tick:
                # Fire again a little before the next state is due: the lock then re-forms by
                # looking, whichever clock runs faster.
                self.next_at = time.monotonic() + self.tick_s * 0.95
                self.counts["missed_world_ticks"] += max(0, int(state.tick) - self.tick - 1) if self.tick >= 0 else 0
                return state
            polls += 1
            if polls % 20 == 0:  # a whole tick without a new state
                self.counts["skipped_timer_ticks"] += 1
                self._check_finished()
            time.sleep(self.tick_s / 20)

    def _check_finished(self) -> None:
        relay = self.coordinator.Fetch(self._poll())
        if relay.HasField("episodes") and relay.episodes.finished:
            self.finished = True
            raise WorldFinished()

    def _sense(self) -> np.ndarray:
        """Reads the world and the coordinator; returns the worlds whose episode changed."""
        state = self._wait_for_new_state()
        self.tick = int(state.tick)
        own = read_robot_state(state, self.worlds)
        self.coordinator.PublishState(state)  # the robot's radio: its state to the others
        relay = self.coordinator.Fetch(self._poll())
        if relay.HasField("episodes"):
            self.episodes = read_episode_info(relay.episodes, self.worlds, self.num_robots)
            if self.episodes["finished"]:
                self.finished = True
                raise WorldFinished()
        for msg in relay.neighbours:
            self.states[msg.header.robot_id] = read_robot_state(msg, self.worlds)
        if relay.HasField("box"):
            self.box = read_box_pose(relay.box, self.worlds)
        self.states[self.robot_id] = own
        changed = own["episode"] != self.episode
        self.episode = own["episode"].copy()
        if self._ready():
            self.was_waiting, self.waiting = self.waiting, self._other_episode()
            self.counts["waiting_world_ticks"] += int(self.waiting.sum())
        return changed

    def _other_episode(self) -> np.ndarray:
        """[W]: the worlds whose relayed box or neighbour still belongs to another episode
        than the robot's own (a trial just began and the relay is late): they are held."""
        other = self.box["episode"] != self.episode
        for r in range(self.num_robots):
            other |= self.states[r]["episode"] != self.episode
        return other

    def _ready(self) -> bool:
        return (self.box is not None and self.episodes is not None
                and all(r in self.states for r in range(self.num_robots)))

    def _observe(self) -> torch.Tensor:
        return observation(self.robot_id, self.states, self.box, self.episodes, self.num_robots, self.handle_order)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None:  # a full reset: (re)start from whatever the world shows now
            self._sense()
            while not self._ready():  # the first relayed neighbour states and box pose
                self._sense()
            self.obs = self._observe()
            self.first_step[:] = 1.0
        else:
            self.first_step[reset.reshape(-1).numpy()] = 1.0
        done = torch.zeros(self.worlds, 1, dtype=torch.bool)
        return TensorDict({"agents": TensorDict({"observation": self.obs.clone()}, batch_size=(self.worlds, 1)),
                           "done": done, "terminated": done.clone(), "truncated": done.clone()},
                          batch_size=(self.worlds,))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(("agents", "action"))[:, 0].numpy()
        self.seq += 1
        self.world.Act(command_message(self.robot_id, action, self.waiting, max(self.tick, 0), 0.0, self.seq))
        self.counts["steps"] += 1
        changed = self._sense()
        # The GRU starts again on a held world's first step with data of its episode.
        self.first_step[:] = (self.waiting | self.was_waiting).astype(np.float32)[:, None]
        self.obs = self._observe()
        done = torch.as_tensor(changed).reshape(-1, 1)
        return TensorDict({"agents": TensorDict({"observation": self.obs.clone(),
                                                 "reward": torch.zeros(self.worlds, 1, 1)}, batch_size=(self.worlds, 1)),
                           "done": done, "terminated": torch.zeros_like(done), "truncated": done.clone()},
                          batch_size=(self.worlds,))

    def _set_seed(self, seed):
        return seed


def student_transforms(scfg, sensor_noise: bool, sensor_dropouts: bool, seed: int) -> list:
    """The student's observation transforms of training (``pnp.distill.student``): without
    ``sensor_noise`` no Gaussian noise, without ``sensor_dropouts`` none of the noise
    model's own box dropouts (the mocap's faults then are the only ones)."""
    from pnp.distill.student import history_transform, noise_transforms
    from pnp.training.keys import OBS, STUDENT_OBS

    noise = scfg.noise.copy()
    if not sensor_noise:
        noise.scale = 0.0
    if not sensor_dropouts:
        noise.dropout.p = 0.0
    return [*noise_transforms(noise, OBS, STUDENT_OBS, seed, int(scfg.env.num_robots)), history_transform(scfg.student)]


def run_client(cfg, onnx_path: str, stats: dict | None = None) -> dict:
    """Joins, then acts until the world says the trials are over; returns its counters, which
    ``stats["counts"]`` holds live from the join on (for an exit by error or signal)."""
    import grpc
    from torchrl.envs import Compose, TransformedEnv

    from pnp.deploy.export import OnnxStudent
    from pnp.deploy.proto import deploy_pb2_grpc as pb_grpc
    from pnp.deploy.server import channel
    from pnp.distill.config import distill_config
    from pnp.training.checkpoint import load_checkpoint
    from pnp.training.keys import ACTION, STUDENT_OBS
    from pnp.training.protocol import resolve_seed

    rid = int(cfg.robot_id)
    scfg = distill_config(load_checkpoint(cfg.checkpoint)["cfg"])
    coordinator = pb_grpc.CoordinatorStub(channel(cfg.coordinator_address, cfg.max_message_bytes))
    reply = coordinator.Join(pb.JoinRequest(header=header(rid, 0.0, 0)), wait_for_ready=True, timeout=60)
    world = pb_grpc.RobotStub(channel(cfg.world_address, cfg.max_message_bytes))
    base = RemoteRobotEnv(rid, world, coordinator, int(reply.worlds), int(reply.num_robots), scfg.env.handle_order,
                          float(reply.tick_s))
    if stats is not None:
        stats["counts"] = base.counts
    # Each robot's sensors draw their own noise: a seed per robot.
    env = TransformedEnv(base, Compose(*student_transforms(scfg, bool(cfg.sensor_noise), bool(cfg.sensor_dropouts),
                                                           resolve_seed(cfg.seed) + 1000 * (rid + 1))))
    policy = OnnxStudent(onnx_path, n_robots=int(reply.worlds))
    log.info("robot %d: %d worlds, a tick every %.3f s", rid, reply.worlds, reply.tick_s)
    try:
        td = env.reset()
        while True:
            action = policy.step(td.get(STUDENT_OBS)[:, 0].numpy(), base.first_step)
            td.set(ACTION, torch.as_tensor(action).unsqueeze(1))
            _, td = env.step_and_maybe_reset(td)
    except WorldFinished:
        pass
    except grpc.RpcError as error:  # the world gone after its last trial
        if error.code() != grpc.StatusCode.UNAVAILABLE or base.counts["steps"] == 0:
            raise
    log.info("robot %d done: %s", rid, base.counts)
    return base.counts


def main(argv=None) -> None:
    import json
    import signal
    import sys

    from pnp.deploy.config import deploy_config

    cfg = deploy_config(list(sys.argv[1:] if argv is None else argv))
    if cfg.coordinator_address is None or cfg.world_address is None:
        raise SystemExit("a client needs coordinator_address=H:P world_address=H:P (and robot_id=, onnx=)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(1)
    onnx = cfg.onnx
    if onnx is None:
        from pnp.deploy.export import deployed_student, export_onnx
        from pnp.deploy.student_io import load_student

        onnx = str(export_onnx(deployed_student(load_student(cfg.checkpoint).actor), f"student_robot{cfg.robot_id}.onnx"))
    # A runner that gives up waiting sends SIGTERM: the counters are still written, with how it ended.
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(f"robot {cfg.robot_id}: terminated"))
    stats, ended = {}, "finished"
    try:
        run_client(cfg, onnx, stats)
    except BaseException as error:
        ended = f"{type(error).__name__}: {error}"
        raise
    finally:
        if cfg.out:
            with open(cfg.out, "w") as f:
                json.dump({**stats.get("counts", {}), "ended": ended}, f)


if __name__ == "__main__":
    main()
