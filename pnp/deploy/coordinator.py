"""The coordinator (paper Sec. IV-E: robots talk through a gRPC server): robots publish their
states, the mocap its box poses, the world its episodes; each robot fetches the others'
freshest states, the box and the episodes. The link faults act here, on the way in.

    python -m pnp.deploy.coordinator robots=2 worlds=50 coordinator_port=50051
"""
from __future__ import annotations

import json
import logging
import signal
import sys
import threading
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from pnp.deploy.config import PROTOCOL_VERSION, deploy_config
from pnp.deploy.faults import DelayLine
from pnp.deploy.messages import BOX_FIELDS, box_pose, check_header, read_box_pose, read_episode_info, read_robot_state
from pnp.deploy.proto import deploy_pb2 as pb
from pnp.deploy.proto import deploy_pb2_grpc as pb_grpc
from pnp.deploy.server import WorldClock, refusing, serve
from pnp.task import HL_DT

log = logging.getLogger("pnp.deploy.coordinator")


class _Box:
    """The mocap's poses merged per world: a world whose markers were lost keeps its last pose."""

    def __init__(self, worlds: int):
        self.arrays = {name: np.zeros((worlds, w), np.float32) for name, w in BOX_FIELDS.items()}
        self.episode = np.zeros(worlds, np.int64)
        self.seen = np.zeros(worlds, bool)
        self.seq = np.full(worlds, -1, np.int64)
        self.tick, self.stamp = 0, 0.0

    def merge(self, msg: pb.BoxPose, arrays: dict, freshest: bool) -> None:
        take = arrays["visible"] & ((msg.header.seq > self.seq) if freshest else True)
        for name in BOX_FIELDS:
            self.arrays[name][take] = arrays[name][take]
        self.episode[take], self.seq[take] = arrays["episode"][take], msg.header.seq
        self.seen |= take
        self.tick, self.stamp = max(self.tick, msg.tick), max(self.stamp, msg.header.stamp_s)

    def message(self) -> pb.BoxPose:
        return box_pose(self.arrays, self.seen, self.episode, self.tick, self.stamp, int(self.seq.max()))


class Coordinator(pb_grpc.CoordinatorServicer):
    def __init__(self, cfg: DictConfig, num_robots: int, worlds: int, clock: WorldClock, seed: int = 0):
        self.cfg, self.num_robots, self.worlds, self.clock = cfg, num_robots, worlds, clock
        self.lines = {r: DelayLine(cfg.faults.link, clock, seed + r) for r in range(num_robots)}
        self.mocap_line = DelayLine(cfg.faults.link, clock, seed + 100)
        self.states: dict[int, pb.RobotState] = {}
        self.box = _Box(worlds)
        self.episodes: pb.EpisodeInfo | None = None
        self.joins: list[dict] = []
        self.refused: dict[str, int] = {}
        self._lock = threading.Lock()

    @refusing
    def Join(self, request, context):
        check_header(request.header, self.num_robots, "Join")
        rid = request.header.robot_id
        with self._lock:
            again = any(j["robot"] == rid for j in self.joins)
            self.joins.append({"robot": rid, "world_s": round(self.clock(), 3), "rejoin": again})
        log.info("robot %d %s at world time %.2f s", rid, "rejoined" if again else "joined", self.clock())
        return pb.JoinReply(num_robots=self.num_robots, worlds=self.worlds, protocol_version=PROTOCOL_VERSION,
                            tick_s=self.clock.real(HL_DT), time_scale=self.clock.time_scale)

    @refusing
    def PublishState(self, request, context):
        check_header(request.header, self.num_robots, "PublishState")
        read_robot_state(request, self.worlds)  # refuse before it enters the line
        self.lines[request.header.robot_id].push(request)
        return pb.Ack(ok=True)

    @refusing
    def PublishMocap(self, request, context):
        check_header(request.header, 1, "PublishMocap")  # the mocap system is sender 0
        self.mocap_line.push((request, read_box_pose(request, self.worlds)))
        return pb.Ack(ok=True)

    @refusing
    def PublishEpisodes(self, request, context):
        check_header(request.header, 1, "PublishEpisodes")
        read_episode_info(request, self.worlds, self.num_robots)
        with self._lock:  # episode control is reliable: no faults on it
            self.episodes = request
        return pb.Ack(ok=True)

    @refusing
    def Fetch(self, request, context):
        check_header(request.header, self.num_robots, "Fetch")
        rid = request.header.robot_id
        with self._lock:
            self._deliver()
            relay = pb.Relay(neighbours=[m for r, m in sorted(self.states.items()) if r != rid])
            if self.box.seen.any():
                relay.box.CopyFrom(self.box.message())
            if self.episodes is not None:
                relay.episodes.CopyFrom(self.episodes)
        return relay

    def _deliver(self) -> None:
        """Messages due by now, in arrival order: the last to arrive is relayed, or with
        ``relay_freshest`` the newest by sequence number."""
        freshest = bool(self.cfg.relay_freshest)
        for rid, line in self.lines.items():
            for msg in line.pop_due():
                old = self.states.get(rid)
                if not (freshest and old is not None and msg.header.seq <= old.header.seq):
                    self.states[rid] = msg
        for msg, arrays in self.mocap_line.pop_due():
            self.box.merge(msg, arrays, freshest)

    def report(self) -> dict:
        return {"joins": self.joins, "refused": self.refused,
                "links": {f"robot_{r}": line.stats() for r, line in self.lines.items()},
                "mocap_link": self.mocap_line.stats()}


def start(cfg: DictConfig, num_robots: int, worlds: int, clock: WorldClock, seed: int = 0):
    """A running coordinator: (server, port, servicer)."""
    servicer = Coordinator(cfg, num_robots, worlds, clock, seed)
    server, port = serve(pb_grpc.add_CoordinatorServicer_to_server, servicer, cfg.host, cfg.coordinator_port,
                         cfg.max_message_bytes)
    log.info("coordinator on %s:%d (%d robots, %d worlds)", cfg.host, port, num_robots, worlds)
    return server, port, servicer


def main(argv=None) -> None:
    cfg = deploy_config(list(sys.argv[1:] if argv is None else argv))
    if cfg.robots is None:
        raise SystemExit("the coordinator alone needs robots=1|2 (it does not read the checkpoint)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    server, port, servicer = start(cfg, int(cfg.robots), cfg.worlds, WorldClock(cfg.time_scale))

    def stop(*_):  # SIGTERM: the report (joins, refusals, link statistics), then exit
        if cfg.out:
            Path(cfg.out).write_text(json.dumps(servicer.report()))
        server.stop(grace=0.5)
    signal.signal(signal.SIGTERM, stop)
    print(f"coordinator listening on {cfg.host}:{port}", flush=True)
    server.wait_for_termination()


if __name__ == "__main__":
    main()
