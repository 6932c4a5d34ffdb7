"""The simulated world of a deployment: our env plays the robots' hardware (each robot's
sensors and low level, ``Robot`` service) and the mocap system, on a 10 Hz clock of its own.
Each tick it publishes every robot's state, sends the box pose and new episodes to the
coordinator, waits for the robots' commands until the tick's deadline, and steps the
physics with them; a robot whose newest command is too old holds (watchdog).

    python -m pnp.deploy.world checkpoint=results/eval_student_dual_checkpoint.pt coordinator=127.0.0.1:50051

The trials are the evaluation protocol's paired trials (``seed``), run W worlds at a time by
``pnp.training.rollout.run_trials``, whose actor here is the robots over the wire.
"""
from __future__ import annotations

import json
import logging
import sys
import threading
import time
from pathlib import Path

import grpc
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from pnp.deploy.faults import DelayLine, MocapDropouts
from pnp.deploy.messages import BadMessage, box_pose, check_header, episode_info, read_command, robot_state
from pnp.deploy.proto import deploy_pb2 as pb
from pnp.deploy.proto import deploy_pb2_grpc as pb_grpc
from pnp.deploy.server import WorldClock, channel, refusing, serve
from pnp.deploy.student_io import student_env
from pnp.deploy.carry import CarryStrain, carry_summary
from pnp.deploy.config import deploy_config
from pnp.task import HL_DT
from pnp.training.keys import ACTION
from pnp.training.protocol import resolve_seed
from pnp.training.rollout import run_trials, summarise

log = logging.getLogger("pnp.deploy.world")
HOLD = slice(0, 3)  # base velocity commands, zeroed when the low level holds


def robot_arrays(s, last_action: torch.Tensor, r: int) -> dict[str, np.ndarray]:
    """Robot ``r``'s sensors in the task state ``s`` (a ``PnPState``), as its message carries them."""
    arrays = {"base": s.base[:, r], "base_z": s.base_z[:, r], "base_vel": s.base_vel[:, r], "arm_q": s.arm_q[:, r],
              "arm_qd": s.arm_qd[:, r], "finger_q": s.finger_q[:, r], "touch": s.touch[:, r].float(),
              "ee_pos": s.ee_pos[:, r], "ee_rot": s.ee_rot[:, r].reshape(-1, 9), "last_action": last_action[:, r]}
    return {k: v.numpy() for k, v in arrays.items()}


def box_arrays(s) -> dict[str, np.ndarray]:
    """The box as the mocap reports it (pose and velocity, world frame)."""
    return {"pos": s.box_pos.numpy(), "rot": s.box_rot.reshape(-1, 9).numpy(), "vel": s.box_vel.numpy()}


class Robots(pb_grpc.RobotServicer):
    """Each robot's hardware interface: ``Sense`` returns its state of the current tick,
    ``Act`` takes a command into the (faulty) bus to the low level."""

    def __init__(self, cfg: DictConfig, num_robots: int, worlds: int, clock: WorldClock, seed: int):
        self.num_robots, self.worlds, self.clock = num_robots, worlds, clock
        self.bus = {r: DelayLine(cfg.faults.command, clock, seed + 200 + r) for r in range(num_robots)}
        self.states: dict[int, pb.RobotState] = {}
        self.sensed = set()
        self.refused: dict[str, int] = {}
        self.published_at: dict[int, float] = {}  # tick -> real time its states were published
        self.tick = 0  # the newest tick published
        self.arrivals: dict[int, list[float]] = {r: [] for r in range(num_robots)}  # real s from state to command
        self._lock = threading.Lock()

    @refusing
    def Sense(self, request, context):
        check_header(request.header, self.num_robots, "Sense")
        rid = request.header.robot_id
        with self._lock:
            self.sensed.add(rid)
            state = self.states.get(rid)
        return state if state is not None else pb.RobotState()

    @refusing
    def Act(self, request, context):
        check_header(request.header, self.num_robots, "Act")
        action, hold = read_command(request, self.worlds)
        rid, tick = request.header.robot_id, int(request.tick)
        with self._lock:
            sent, now_tick = self.published_at.get(tick), self.tick
        if tick > now_tick:
            raise BadMessage(f"Command.tick={tick} answers a state not yet published (the world is at tick {now_tick})")
        if sent is not None:
            self.arrivals[rid].append(time.monotonic() - sent)
        self.bus[rid].push((tick, action, hold))
        return pb.Ack(ok=True)


class RemoteActor:
    """``run_trials``' actor: one call is one control tick of the world (publish, wait for
    the robots until the deadline, write their commands as the action). Ticks follow a
    fixed schedule (tick k at start + k x tick); a late tick is counted and the schedule
    moves on from it."""

    def __init__(self, cfg: DictConfig, env, robots: Robots, coordinator, seed: int):
        self.cfg, self.env, self.base, self.robots, self.coordinator = cfg, env, env.base_env, robots, coordinator
        self.worlds, self.num_robots = robots.worlds, robots.num_robots
        self.clock, self.tick_real = robots.clock, robots.clock.real(HL_DT)
        self.mocap = MocapDropouts(cfg.faults.mocap, self.worlds, HL_DT, seed + 300)
        self.tick, self.seq, self.next_at = 0, 0, None
        # Newest command delivered per robot: (tick it answers, actions [W, 8], held worlds [W]).
        self.commands = {r: (-1, None, None) for r in range(self.num_robots)}
        self.episodes = None
        self.episode_start = np.zeros(self.worlds, np.int64)  # the tick each world's episode began
        self.starts: list[float] = []
        self.counts = {"ticks": 0, "late_ticks": 0, "watchdog": [0] * self.num_robots,
                       "stale_commands": [0] * self.num_robots, "held_worlds": [0] * self.num_robots,
                       "coordinator_errors": 0}

    def _send(self, call, message) -> None:
        """A publish to the coordinator; one that fails is a lost message, not the end of the run."""
        try:
            call(message, timeout=self.tick_real)
        except grpc.RpcError as error:
            self.counts["coordinator_errors"] += 1
            if self.counts["coordinator_errors"] in (1, 10, 100):
                log.warning("coordinator unreachable (%s): %d messages lost", error.code().name,
                            self.counts["coordinator_errors"])

    def _publish(self) -> None:
        """Episodes and the box first, then the robots' states: a robot that sees its new
        state and fetches at once finds the coordinator already holding this tick's episodes."""
        s, base = self.base.physical_state(), self.base
        steps, episodes = base._steps.numpy().copy(), base.trial.numpy().copy()
        self.episode_start = np.where(steps == 0, self.tick, self.episode_start)
        stamp = self.clock()
        self.seq += 1
        if self.episodes is None or not np.array_equal(self.episodes, episodes):
            self.episodes = episodes
            claim = base._claim.numpy() if base.handle_claim else np.full((self.worlds, self.num_robots), -1)
            self._send(self.coordinator.PublishEpisodes, episode_info(
                episodes, s.goal.numpy(), s.box_size.numpy(), claim, self.num_robots, stamp, self.seq))
        visible = self.mocap.visible() | (steps == 0)  # a new episode's first pose is always sent
        self._send(self.coordinator.PublishMocap, box_pose(box_arrays(s), visible, episodes, self.tick, stamp, self.seq))
        states = {r: robot_state(r, robot_arrays(s, base._last_action, r), steps, episodes, self.tick, stamp, self.seq)
                  for r in range(self.num_robots)}
        with self.robots._lock:
            self.robots.states, self.robots.tick = states, self.tick
            self.robots.published_at[self.tick] = time.monotonic()
            self.robots.published_at.pop(self.tick - 50, None)

    def _collect(self) -> torch.Tensor:
        """[W, R, 8]: per world, each robot's newest command if it is fresh enough and of
        this episode and not held, else the hold (no base motion, the last EE target and
        gripper kept)."""
        action = self.base._last_action.clone()
        for r in range(self.num_robots):
            for tick, a, hold in self.robots.bus[r].pop_due():
                if tick > self.commands[r][0]:
                    self.commands[r] = (tick, a, hold)
            tick, a, hold = self.commands[r]
            fresh = a is not None and (self.tick - tick) * HL_DT <= self.cfg.command_timeout_s + 1e-9
            use = (torch.as_tensor(~hold & (tick >= self.episode_start)) if fresh
                   else torch.zeros(self.worlds, dtype=torch.bool))
            if fresh:
                action[:, r] = torch.where(use[:, None], torch.as_tensor(a), action[:, r])
                self.counts["stale_commands"][r] += int(tick != self.tick)
                self.counts["held_worlds"][r] += int((~use).sum())
            else:
                self.counts["watchdog"][r] += 1
                if self.counts["watchdog"][r] in (1, 10, 100) or self.counts["watchdog"][r] % 1000 == 0:
                    log.warning("watchdog: robot %d has no command younger than %.2f s at tick %d (%d holds so far)",
                                r, self.cfg.command_timeout_s, self.tick, self.counts["watchdog"][r])
            action[:, r, HOLD] = torch.where(use[:, None], action[:, r, HOLD], torch.zeros(()))
        return action

    def __call__(self, td):
        now = time.monotonic()
        if self.next_at is None:
            self.next_at = now
        elif now > self.next_at + 0.05 * self.tick_real:  # the physics ran past this tick's start
            self.counts["late_ticks"] += 1
            self.next_at = now
        time.sleep(max(0.0, self.next_at - now))
        start = self.next_at
        self.starts.append(time.monotonic())
        self._publish()
        time.sleep(max(0.0, start + self.cfg.deadline_share * self.tick_real - time.monotonic()))
        td.set(ACTION, self._collect())
        self.next_at = start + self.tick_real
        self.tick += 1
        self.counts["ticks"] += 1
        return td

    def tick_period(self) -> dict:
        """The measured real seconds between ticks (the schedule asks for ``tick_real``)."""
        gaps = np.diff(np.asarray(self.starts))
        if not len(gaps):
            return {}
        return {"asked_s": self.tick_real, "mean_s": float(gaps.mean()), "p99_s": float(np.percentile(gaps, 99)),
                "max_s": float(gaps.max())}


def wait_for_robots(robots: Robots, timeout_s: float = 120.0) -> None:
    """Blocks until every robot has sensed once (its client is up), publishing nothing."""
    t0 = time.monotonic()
    while len(robots.sensed) < robots.num_robots:
        if time.monotonic() - t0 > timeout_s:
            missing = sorted(set(range(robots.num_robots)) - robots.sensed)
            raise TimeoutError(f"robots {missing} did not connect within {timeout_s:.0f} s")
        time.sleep(0.05)


def start_robots(cfg: DictConfig, num_robots: int, worlds: int, clock: WorldClock, seed: int):
    """The robots' hardware server: (server, port, servicer)."""
    servicer = Robots(cfg, num_robots, worlds, clock, seed)
    server, port = serve(pb_grpc.add_RobotServicer_to_server, servicer, cfg.host, cfg.world_port, cfg.max_message_bytes)
    log.info("robots' hardware on %s:%d", cfg.host, port)
    return server, port, servicer


def build_world_env(cfg: DictConfig):
    """The student's evaluation env without its observation transforms (the world is the
    physics; observations are formed by each robot): (student config, env, seed)."""
    seed = resolve_seed(cfg.seed)
    scfg, _, env = student_env(cfg.checkpoint, min(int(cfg.worlds), int(cfg.trials)), seed, "clean",
                               backend=cfg.backend, low_level=cfg.low_level)
    if cfg.robots is not None and int(cfg.robots) != int(scfg.env.num_robots):
        env.close()
        raise ValueError(f"robots={cfg.robots}, but {cfg.checkpoint} is a {scfg.env.num_robots}-robot student")
    return scfg, env, seed


def latency(arrivals: dict[int, list[float]]) -> dict:
    """Per robot, real milliseconds from a tick's states to the command answering them."""
    out = {}
    for r, values in arrivals.items():
        ms = 1e3 * np.asarray(values)
        out[f"robot_{r}"] = ({"commands": len(ms), "p50_ms": float(np.percentile(ms, 50)),
                              "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())} if len(ms) else None)
    return out


def run_world(cfg: DictConfig, coordinator_address: str, on_ready=None, on_start=None) -> dict:
    """The trials, played for the robots that connect to this world's server; ``on_ready(port)``
    once it listens, ``on_start()`` when every robot is up and the clock starts. Returns the
    trial records, their summary and the world's counters."""
    scfg, env, seed = build_world_env(cfg)
    num_robots, worlds = int(scfg.env.num_robots), int(scfg.env.num_worlds)
    clock = WorldClock(cfg.time_scale)
    server, port, robots = start_robots(cfg, num_robots, worlds, clock, seed)
    coordinator = pb_grpc.CoordinatorStub(channel(coordinator_address, cfg.max_message_bytes))
    try:
        if on_ready is not None:
            on_ready(port)
        wait_for_robots(robots)
        if on_start is not None:
            on_start()
        actor = RemoteActor(cfg, env, robots, coordinator, seed)
        t0 = time.monotonic()
        strain = CarryStrain(worlds) if num_robots == 2 else None
        records = run_trials(env, actor, int(cfg.trials), bool(cfg.progress), hook=strain)
        wall = time.monotonic() - t0
        done = actor.episodes if actor.episodes is not None else np.zeros(worlds, np.int64)
        actor._send(coordinator.PublishEpisodes, episode_info(
            done, np.zeros((worlds, 2)), np.ones((worlds, 3)), np.full((worlds, num_robots), -1), num_robots, clock(),
            actor.seq + 1, finished=True))
    finally:
        env.close()
        server.stop(grace=1.0)
    summary = summarise(records) | ({"carry": carry_summary(records)} if strain is not None else {})
    return {"records": records, "summary": summary, "seed": seed, "num_robots": num_robots,
            "worlds": worlds, "world": actor.counts, "tick_period": actor.tick_period(),
            "mocap_dropouts_started": actor.mocap.started,
            "command_bus": {f"robot_{r}": line.stats() for r, line in robots.bus.items()},
            "latency": latency(robots.arrivals), "refused": robots.refused, "wall_s": wall,
            "student_config": OmegaConf.to_container(OmegaConf.masked_copy(scfg, ["noise", "student"]))}


def main(argv=None) -> None:
    cfg = deploy_config(list(sys.argv[1:] if argv is None else argv))
    if cfg.coordinator_address is None:
        raise SystemExit("the world alone needs coordinator_address=host:port")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    out = run_world(cfg, cfg.coordinator_address, lambda port: print(f"world listening on {cfg.host}:{port}", flush=True),
                    lambda: print("world ticking", flush=True))
    print({k: out["summary"][k] for k in ("trials", "success_rate", "completion_time_mean_s")}, flush=True)
    if cfg.out:
        Path(cfg.out).write_text(json.dumps(out, default=str))


if __name__ == "__main__":
    main()
