"""Network faults as a delay line: messages go in when sent and come out when due, or
never (``LinkFaults``); and the mocap's dropouts per world (``MocapDropouts``).

Times are world seconds; the line reads a clock in world seconds (real time x the time
scale), so a delay means the same in a real-time run and in a faster one.
"""
from __future__ import annotations

import heapq
import itertools
import threading
from typing import Any, Callable

import numpy as np
from omegaconf import DictConfig


class DelayLine:
    """A link's messages, each delivered after its delay or dropped (``faults``: a
    ``LinkFaults``). ``push`` at send time; ``pop_due`` returns the messages due by now in
    the order they arrive (which is not the order sent when they are reordered)."""

    def __init__(self, faults: DictConfig, clock: Callable[[], float], seed: int):
        self.faults, self.clock = faults, clock
        self.rng = np.random.default_rng(seed)
        self._heap: list = []
        self._order = itertools.count()  # ties: sending order
        self._lock = threading.Lock()
        self.sent = self.dropped = self.reordered = 0

    def delay(self) -> float | None:
        """This message's delay in world seconds, or None: lost."""
        f = self.faults
        if f.loss > 0 and self.rng.random() < f.loss:
            return None
        d = f.delay_s + (self.rng.uniform(0.0, f.jitter_s) if f.jitter_s > 0 else 0.0)
        if f.reorder > 0 and self.rng.random() < f.reorder:
            self.reordered += 1
            d += f.reorder_s
        return d

    def push(self, message: Any) -> None:
        with self._lock:
            self.sent += 1
            d = self.delay()
            if d is None:
                self.dropped += 1
                return
            heapq.heappush(self._heap, (self.clock() + d, next(self._order), message))

    def pop_due(self) -> list:
        now, out = self.clock(), []
        with self._lock:
            while self._heap and self._heap[0][0] <= now:
                out.append(heapq.heappop(self._heap)[2])
        return out

    def stats(self) -> dict:
        return {"sent": self.sent, "dropped": self.dropped, "reordered": self.reordered}


class MocapDropouts:
    """Per world, whether the markers are lost this tick: a dropout starts with probability
    ``rate_hz * dt`` after a tick where they were seen and lasts ``max(1, round(U[min_s, max_s] / dt))``
    ticks (``faults``: a ``MocapFaults``). A world whose episode restarts keeps its dropout:
    the markers do not know about episodes."""

    def __init__(self, faults: DictConfig, worlds: int, dt: float, seed: int):
        self.faults, self.dt = faults, dt
        self.rng = np.random.default_rng(seed)
        self.left = np.zeros(worlds, dtype=np.int64)
        self.started = 0

    def visible(self) -> np.ndarray:
        """This tick's visibility [W] (call once per tick)."""
        f = self.faults
        was_seen = self.left == 0  # a dropout starts after a tick where the markers were seen
        self.left = np.maximum(self.left - 1, 0)
        if f.rate_hz > 0:
            start = was_seen & (self.rng.random(self.left.shape) < f.rate_hz * self.dt)
            n = int(start.sum())
            if n:
                self.started += n
                self.left[start] = np.maximum(1, np.round(self.rng.uniform(f.min_s, f.max_s, n) / self.dt))
        return self.left == 0
