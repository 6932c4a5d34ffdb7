"""Bad messages get a clear gRPC status and a log line; the servers and the other robot carry on."""
from __future__ import annotations

import numpy as np
import pytest

grpc = pytest.importorskip("grpc")

from pnp.deploy.config import deploy_config  # noqa: E402
from pnp.deploy.coordinator import start  # noqa: E402
from pnp.deploy.messages import ROBOT_FIELDS, header, robot_state  # noqa: E402
from pnp.deploy.proto import deploy_pb2 as pb  # noqa: E402
from pnp.deploy.proto import deploy_pb2_grpc as pb_grpc  # noqa: E402
from pnp.deploy.server import WorldClock, channel  # noqa: E402
from pnp.deploy.world import start_robots  # noqa: E402

WORLDS = 2


def _state(robot: int, **change) -> pb.RobotState:
    arrays = {k: np.zeros((WORLDS, w), np.float32) for k, w in ROBOT_FIELDS.items()}
    arrays.update(change)
    return robot_state(robot, arrays, np.zeros(WORLDS, np.int64), np.zeros(WORLDS, np.int64), 0, 0.0, 1)


@pytest.fixture(scope="module")
def servers():
    cfg = deploy_config([f"worlds={WORLDS}", "max_message_bytes=65536"])
    clock = WorldClock(1.0)
    coord_server, coord_port, coordinator = start(cfg, 2, WORLDS, clock)
    robot_server, robot_port, robots = start_robots(cfg, 2, WORLDS, clock, seed=0)
    yield (pb_grpc.CoordinatorStub(channel(f"127.0.0.1:{coord_port}", 1 << 22)), coordinator,
           pb_grpc.RobotStub(channel(f"127.0.0.1:{robot_port}", 1 << 22)), robots, coord_port)
    coord_server.stop(0)
    robot_server.stop(0)


def _refused(call, request, code, match):
    with pytest.raises(grpc.RpcError) as info:
        call(request, timeout=10)
    assert info.value.code() == code
    assert match in info.value.details()


def test_refusals_name_what_is_wrong(servers, caplog):
    stub, coordinator, robot_stub, _, _ = servers
    bad_version = _state(0)
    bad_version.header.protocol_version = 7
    _refused(stub.PublishState, bad_version, grpc.StatusCode.FAILED_PRECONDITION, "protocol_version=7")
    _refused(stub.Join, pb.JoinRequest(header=header(5, 0.0, 1)), grpc.StatusCode.NOT_FOUND, "robot_id=5 does not exist")
    short = _state(0)
    del short.arm_q[-1]
    _refused(stub.PublishState, short, grpc.StatusCode.INVALID_ARGUMENT, "RobotState.arm_q: 11 values, expected 12")
    _refused(stub.PublishState, _state(1, base=np.full((WORLDS, 3), np.nan, np.float32)),
             grpc.StatusCode.INVALID_ARGUMENT, "RobotState.base: non-finite")
    _refused(robot_stub.Act, pb.Command(header=header(3, 0.0, 1), worlds=WORLDS), grpc.StatusCode.NOT_FOUND,
             "robot_id=3")
    _refused(robot_stub.Act, pb.Command(header=header(0, 0.0, 1), worlds=WORLDS, action=[0.0] * 5),
             grpc.StatusCode.INVALID_ARGUMENT, "Command.action: 5 values, expected 16")
    _refused(robot_stub.Act, pb.Command(header=header(0, 0.0, 1), worlds=WORLDS, action=[0.0] * 16, hold=[False] * 2,
                                        tick=9), grpc.StatusCode.INVALID_ARGUMENT, "Command.tick=9 answers a state not yet")
    assert coordinator.refused == {"FAILED_PRECONDITION": 1, "NOT_FOUND": 1, "INVALID_ARGUMENT": 2}
    assert any("refused PublishState" in r.getMessage() for r in caplog.records)


def test_oversized_and_malformed_messages_do_not_stop_the_server(servers):
    stub, _, _, _, port = servers
    big = pb.RobotState(header=header(0, 0.0, 1), worlds=WORLDS)
    big.base.extend([0.0] * 40000)  # 160 kB against the server's 64 kB
    _refused(stub.PublishState, big, grpc.StatusCode.RESOURCE_EXHAUSTED, "")
    raw = grpc.insecure_channel(f"127.0.0.1:{port}").unary_unary("/pnp.deploy.v1.Coordinator/PublishState")
    with pytest.raises(grpc.RpcError) as info:
        raw(b"\xff\xff\xff\x0f not a protobuf", timeout=10)
    assert info.value.code() in (grpc.StatusCode.INTERNAL, grpc.StatusCode.INVALID_ARGUMENT)
    # The other robot's traffic still flows.
    assert stub.PublishState(_state(1), timeout=10).ok
    relay = stub.Fetch(pb.Poll(header=header(0, 0.0, 2)), timeout=10)
    assert [m.header.robot_id for m in relay.neighbours] == [1]
