"""The deployment's configuration, declared once: what ``python -m pnp.deploy.run`` and each
process read (``key=value`` overrides, unknown keys refused by OmegaConf's schema)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from omegaconf import DictConfig, OmegaConf

PROTOCOL_VERSION = 1


@dataclass
class LinkFaults:
    """One direction of a network link, per message: dropped with probability ``loss``,
    else delivered after ``delay_s`` + U[0, ``jitter_s``] (world seconds); with probability
    ``reorder`` held back a further ``reorder_s``, so that later messages overtake it."""

    delay_s: float = 0.0
    jitter_s: float = 0.0
    loss: float = 0.0
    reorder: float = 0.0
    reorder_s: float = 0.2


@dataclass
class MocapFaults:
    """Markers lost per world: a dropout starts with probability ``rate_hz`` x 0.1 each tick
    and lasts U[``min_s``, ``max_s``]; meanwhile that world's box pose is not sent."""

    rate_hz: float = 0.0
    min_s: float = 0.5
    max_s: float = 0.5


@dataclass
class RestartFault:
    """Robot ``robot``'s client killed at world time ``at_s`` and started again ``down_s``
    later (a fresh process: GRU state from zeros). ``robot`` -1: none."""

    robot: int = -1
    at_s: float = 5.0
    down_s: float = 1.0


@dataclass
class FaultConfig:
    # Robot states and the mocap stream on their way through the coordinator (the radio).
    link: LinkFaults = field(default_factory=LinkFaults)
    # A robot's command on its way to its low level (late or missing commands).
    command: LinkFaults = field(default_factory=LinkFaults)
    mocap: MocapFaults = field(default_factory=MocapFaults)
    restart: RestartFault = field(default_factory=RestartFault)


@dataclass
class DeployConfig:
    checkpoint: str = "results/eval_student_single_checkpoint.pt"
    robots: Optional[int] = None  # None: the checkpoint's (a standalone coordinator needs it)
    trials: int = 100
    worlds: int = 50             # trials run W at a time, one process per robot for all W
    seed: str = "reporting"      # the evaluation protocol's seed role, or an integer
    backend: Optional[str] = None  # the world's physics (None: the student's training backend)
    low_level: Optional[str] = None  # ideal | learned (None: the student's)
    time_scale: float = 1.0      # world seconds per real second (1: real time)
    # A command answering tick k counts if it arrives by this share of the tick (later: late);
    # the rest of the tick is the physics' (50 worlds: ~20-40 ms here).
    deadline_share: float = 0.6
    # The low level holds (zero base velocity, its last EE target and gripper) when its newest
    # command is older than this (world s); a watchdog time-out is logged.
    command_timeout_s: float = 0.1
    relay_freshest: bool = False  # the coordinator keeps the newest by sequence number, not the last to arrive
    # The student's training noise model on its observation (simulated sensors): its Gaussian
    # noise, and its own box dropouts (p 0.01 per step, 0.2-2 s) beside any mocap faults.
    sensor_noise: bool = True
    sensor_dropouts: bool = True
    faults: FaultConfig = field(default_factory=FaultConfig)
    host: str = "127.0.0.1"       # where this machine's servers listen
    coordinator_port: int = 0     # 0: a free port
    world_port: int = 0
    # Each piece started alone: where the others are, and which robot a client is.
    coordinator_address: Optional[str] = None  # host:port
    world_address: Optional[str] = None
    robot_id: int = 0
    onnx: Optional[str] = None   # a client's exported student (None: exported from the checkpoint at start)
    max_message_bytes: int = 1 << 20
    out: Optional[str] = None     # the result JSON (None: print only)
    progress: bool = True


def deploy_config(overrides: list[str] | None = None, base: DictConfig | dict | None = None) -> DictConfig:
    """The schema, then ``base``, then ``key=value`` ``overrides``; an unknown key raises."""
    cfg = OmegaConf.structured(DeployConfig)
    if base is not None:
        cfg = OmegaConf.merge(cfg, base)
    if overrides:
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    check(cfg)
    return cfg


def check(cfg: DictConfig) -> None:
    if not cfg.time_scale > 0:
        raise ValueError(f"time_scale={cfg.time_scale}: must be > 0")
    if not 0 < cfg.deadline_share <= 1:
        raise ValueError(f"deadline_share={cfg.deadline_share}: must be in (0, 1]")
    for name in ("link", "command"):
        f = cfg.faults[name]
        for key in ("loss", "reorder"):
            if not 0 <= f[key] <= 1:
                raise ValueError(f"faults.{name}.{key}={f[key]}: a probability in [0, 1]")
        for key in ("delay_s", "jitter_s", "reorder_s"):
            if f[key] < 0:
                raise ValueError(f"faults.{name}.{key}={f[key]}: must be >= 0")
    m = cfg.faults.mocap
    if m.rate_hz < 0 or not 0 <= m.min_s <= m.max_s:
        raise ValueError(f"faults.mocap: need rate_hz >= 0 and 0 <= min_s <= max_s, got {OmegaConf.to_container(m)}")
    if cfg.command_timeout_s < 0 or cfg.faults.restart.at_s < 0 or cfg.faults.restart.down_s < 0:
        raise ValueError(f"command_timeout_s={cfg.command_timeout_s}, faults.restart.at_s={cfg.faults.restart.at_s}, "
                         f"faults.restart.down_s={cfg.faults.restart.down_s}: each must be >= 0")
    if cfg.trials < 1 or cfg.worlds < 1:
        raise ValueError(f"trials={cfg.trials}, worlds={cfg.worlds}: both must be >= 1")
