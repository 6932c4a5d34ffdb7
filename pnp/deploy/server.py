"""What the coordinator and the world's servers share: a gRPC server with bounded
messages, refusals that become gRPC statuses with a log line, and the world clock."""
from __future__ import annotations

import functools
import logging
import time
from concurrent import futures

import grpc

from pnp.deploy.messages import BadMessage, UnknownRobot, WrongVersion

log = logging.getLogger("pnp.deploy")


class WorldClock:
    """World seconds since ``start`` (real seconds x ``time_scale``)."""

    def __init__(self, time_scale: float, start: float | None = None):
        self.time_scale, self.start = float(time_scale), time.monotonic() if start is None else start

    def __call__(self) -> float:
        return (time.monotonic() - self.start) * self.time_scale

    def real(self, world_s: float) -> float:
        """Real seconds that ``world_s`` world seconds take."""
        return world_s / self.time_scale


def status_of(error: BadMessage) -> grpc.StatusCode:
    if isinstance(error, UnknownRobot):
        return grpc.StatusCode.NOT_FOUND
    if isinstance(error, WrongVersion):
        return grpc.StatusCode.FAILED_PRECONDITION
    return grpc.StatusCode.INVALID_ARGUMENT


def refusing(method):
    """A servicer method whose ``BadMessage`` becomes a gRPC status and a log line; the
    server and every other caller carry on."""
    @functools.wraps(method)
    def wrapper(self, request, context):
        try:
            return method(self, request, context)
        except BadMessage as error:
            code = status_of(error)
            log.warning("%s refused %s from %s: %s (%s)", type(self).__name__, method.__name__, context.peer(),
                        error, code.name)
            self.refused[code.name] = self.refused.get(code.name, 0) + 1
            context.abort(code, str(error))
    return wrapper


def serve(add_servicer, servicer, host: str, port: int, max_message_bytes: int, workers: int = 8):
    """A started server with ``servicer``; returns (server, bound port)."""
    options = [("grpc.max_receive_message_length", max_message_bytes),
               ("grpc.max_send_message_length", max_message_bytes)]
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=workers), options=options)
    add_servicer(servicer, server)
    bound = server.add_insecure_port(f"{host}:{port}")
    if bound == 0:
        raise OSError(f"could not bind {host}:{port}")
    server.start()
    return server, bound


def channel(address: str, max_message_bytes: int) -> grpc.Channel:
    return grpc.insecure_channel(address, options=[("grpc.max_receive_message_length", max_message_bytes),
                                                   ("grpc.max_send_message_length", max_message_bytes)])
