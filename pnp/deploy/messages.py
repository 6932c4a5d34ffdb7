"""Arrays in and out of the protocol's messages, each checked on the way in: a message
with the wrong protocol version, an unknown robot, a field of the wrong length or a
non-finite value raises ``BadMessage`` naming it (servers turn it into a gRPC status)."""
from __future__ import annotations

import numpy as np

from pnp.deploy.config import PROTOCOL_VERSION
from pnp.deploy.proto import deploy_pb2 as pb

# Per-world widths of the array fields (world-major, flattened).
ROBOT_FIELDS = {"base": 3, "base_z": 1, "base_vel": 3, "arm_q": 6, "arm_qd": 6, "finger_q": 2, "touch": 2, "ee_pos": 3,
                "ee_rot": 9, "last_action": 8}
BOX_FIELDS = {"pos": 3, "rot": 9, "vel": 6}
ACTION_WIDTH = 8


class BadMessage(ValueError):
    """A message refused: what is wrong with it, by field."""


class UnknownRobot(BadMessage):
    """A robot id that does not exist in this run."""


class WrongVersion(BadMessage):
    """Another protocol version."""


def header(robot_id: int, stamp_s: float, seq: int) -> pb.Header:
    return pb.Header(protocol_version=PROTOCOL_VERSION, robot_id=robot_id, stamp_s=stamp_s, seq=seq)


def check_header(h: pb.Header, num_robots: int, what: str) -> None:
    if h.protocol_version != PROTOCOL_VERSION:
        raise WrongVersion(f"{what}: protocol_version={h.protocol_version}, this server speaks {PROTOCOL_VERSION}")
    if not 0 <= h.robot_id < num_robots:
        raise UnknownRobot(f"{what}: robot_id={h.robot_id} does not exist (robots 0..{num_robots - 1})")


def put(msg, name: str, array) -> None:
    getattr(msg, name).extend(np.asarray(array).ravel().tolist())


def get(msg, name: str, worlds: int, width: int | None, dtype=np.float32) -> np.ndarray:
    """Field ``name`` as ``[worlds, width]`` (``[worlds]`` for width None), checked."""
    values = getattr(msg, name)
    expected = worlds * (width or 1)
    if len(values) != expected:
        raise BadMessage(f"{type(msg).__name__}.{name}: {len(values)} values, expected {expected} "
                         f"({worlds} worlds x {width or 1})")
    out = np.asarray(values, dtype=dtype)
    if out.dtype.kind == "f" and not np.isfinite(out).all():
        raise BadMessage(f"{type(msg).__name__}.{name}: non-finite values at {np.flatnonzero(~np.isfinite(out))[:5].tolist()}")
    return out if width is None else out.reshape(worlds, width)


def check_worlds(msg, worlds: int) -> None:
    if msg.worlds != worlds:
        raise BadMessage(f"{type(msg).__name__}.worlds={msg.worlds}, this run has {worlds} worlds")


# Per-world scalar fields each message carries beside its arrays, with their types.
_ROBOT_SCALARS = {"step": np.int64, "episode": np.int64}
_BOX_SCALARS = {"visible": bool, "episode": np.int64}


def _fill(msg, widths: dict, arrays: dict, scalars: dict):
    for name in widths:
        put(msg, name, arrays[name])
    for name, values in scalars.items():
        put(msg, name, values)
    return msg


def _read(msg, worlds: int, widths: dict, scalars: dict) -> dict:
    check_worlds(msg, worlds)
    out = {name: get(msg, name, worlds, w) for name, w in widths.items()}
    out.update({name: get(msg, name, worlds, None, dtype) for name, dtype in scalars.items()})
    return out


def robot_state(robot_id: int, arrays: dict, steps, episodes, tick: int, stamp_s: float, seq: int) -> pb.RobotState:
    """A RobotState from ``arrays`` (name -> [W, width], names of ``ROBOT_FIELDS``)."""
    msg = pb.RobotState(header=header(robot_id, stamp_s, seq), worlds=len(steps), tick=tick)
    return _fill(msg, ROBOT_FIELDS, arrays, {"step": steps, "episode": episodes})


def read_robot_state(msg: pb.RobotState, worlds: int) -> dict:
    return _read(msg, worlds, ROBOT_FIELDS, _ROBOT_SCALARS)


def box_pose(arrays: dict, visible, episodes, tick: int, stamp_s: float, seq: int) -> pb.BoxPose:
    msg = pb.BoxPose(header=header(0, stamp_s, seq), worlds=len(visible), tick=tick)
    return _fill(msg, BOX_FIELDS, arrays, {"visible": visible, "episode": episodes})


def read_box_pose(msg: pb.BoxPose, worlds: int) -> dict:
    return _read(msg, worlds, BOX_FIELDS, _BOX_SCALARS)


def episode_info(episodes, goal, box_size, handle, num_robots: int, stamp_s: float, seq: int,
                 finished: bool = False) -> pb.EpisodeInfo:
    msg = pb.EpisodeInfo(header=header(0, stamp_s, seq), worlds=len(episodes), num_robots=num_robots,
                         finished=finished)
    for name, value in (("episode", episodes), ("goal", goal), ("box_size", box_size), ("handle", handle)):
        put(msg, name, value)
    return msg


def read_episode_info(msg: pb.EpisodeInfo, worlds: int, num_robots: int) -> dict:
    check_worlds(msg, worlds)
    if msg.num_robots != num_robots:
        raise BadMessage(f"EpisodeInfo.num_robots={msg.num_robots}, this run has {num_robots}")
    return {"episode": get(msg, "episode", worlds, None, np.int64), "goal": get(msg, "goal", worlds, 2),
            "box_size": get(msg, "box_size", worlds, 3), "handle": get(msg, "handle", worlds, num_robots, np.int64),
            "finished": bool(msg.finished)}


def command(robot_id: int, action, hold, tick: int, stamp_s: float, seq: int) -> pb.Command:
    msg = pb.Command(header=header(robot_id, stamp_s, seq), worlds=len(action), tick=tick)
    put(msg, "action", action)
    put(msg, "hold", hold)
    return msg


def read_command(msg: pb.Command, worlds: int) -> tuple[np.ndarray, np.ndarray]:
    """The actions [W, 8] and the worlds held [W]."""
    check_worlds(msg, worlds)
    return get(msg, "action", worlds, ACTION_WIDTH), get(msg, "hold", worlds, None, bool)
