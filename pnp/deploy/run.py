"""One command for a deployment's trial set: the student exported, then a coordinator, the
simulated world and one client per robot, each its own process on this machine (loopback),
and the client-restart fault if configured. Writes one JSON result.

    python -m pnp.deploy.run --checkpoint results/eval_student_dual_checkpoint.pt --trials 100 \\
        faults.link.delay_s=0.1 faults.link.loss=0.05 out=runs/deploy/dual_d100.json

Across machines, start the pieces alone (``python -m pnp.deploy.coordinator|world|client``
with ``host=0.0.0.0`` and the others' addresses).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from omegaconf import OmegaConf

from pnp.deploy.config import deploy_config


def _start(module: str, args: list[str], log_path: Path) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    with open(log_path, "w") as log:  # the child keeps its own handle
        return subprocess.Popen([sys.executable, "-m", f"pnp.deploy.{module}", *args], stdout=subprocess.PIPE,
                                stderr=log, text=True, env=env)


def _address(proc: subprocess.Popen, what: str, timeout_s: float = 120.0) -> str:
    """The ``host:port`` a started server prints on its first line."""
    result = {}

    def read():
        result["line"] = proc.stdout.readline()
    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(timeout_s)
    line = result.get("line", "")
    if "listening on" not in line:
        raise RuntimeError(f"the {what} did not start (exit code {proc.poll()}, first line {line!r}); see its log")
    return line.strip().rsplit(" ", 1)[-1]


class _Restart:
    """The client-restart fault: kill robot r's client at world time at_s (from the world's
    first tick), start it again down_s later; never after ``stop``."""

    def __init__(self, cfg, clients: dict, client_args, logs: Path, world: subprocess.Popen):
        self.cfg, self.clients, self.client_args, self.logs, self.world = cfg, clients, client_args, logs, world
        self.events: list[dict] = []
        self.stopped = threading.Event()
        self.lock = threading.Lock()
        if cfg.faults.restart.robot >= 0:
            threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        fault, scale = self.cfg.faults.restart, self.cfg.time_scale
        while "ticking" not in self.world.stdout.readline():
            if self.world.poll() is not None:
                return
        started = time.monotonic()
        for wait, act in ((fault.at_s / scale, "killed"), (fault.down_s / scale, "restarted")):
            if self.stopped.wait(wait):
                return
            with self.lock:
                if self.stopped.is_set():
                    return
                r = int(fault.robot)
                if act == "killed":
                    self.clients[r].kill()
                else:
                    self.clients[r] = _start("client", self.client_args(r), self.logs / f"client{r}_restarted.log")
                self.events.append({"event": act, "robot": r, "real_s": round(time.monotonic() - started, 3)})

    def stop(self):
        with self.lock:
            self.stopped.set()


def run(cfg, workdir: Path) -> dict:
    """Runs the trial set with every process; returns the world's result with the others' reports."""
    from pnp.deploy.export import deployed_student, export_onnx
    from pnp.deploy.student_io import load_student

    student = load_student(cfg.checkpoint)
    robots = int(student.cfg.env.num_robots)
    if cfg.robots is not None and int(cfg.robots) != robots:
        raise ValueError(f"robots={cfg.robots}, but {cfg.checkpoint} is a {robots}-robot student")
    student.env.close()
    onnx = export_onnx(deployed_student(student.actor), workdir / "student.onnx")
    worlds = min(int(cfg.worlds), int(cfg.trials))
    common = [f"{k}={v}" for k, v in OmegaConf.to_container(cfg, resolve=True).items()
              if k not in ("faults", "out", "robots", "worlds", "coordinator_address", "world_address", "onnx",
                           "robot_id", "progress") and v is not None]
    common += [f"faults.{a}.{k}={v}" for a, f in OmegaConf.to_container(cfg.faults).items() for k, v in f.items()]
    common += [f"worlds={worlds}", f"robots={robots}"]
    if cfg.faults.restart.robot >= robots:
        raise ValueError(f"faults.restart.robot={cfg.faults.restart.robot}: this student has robots 0..{robots - 1}")
    procs, clients, restart = {}, {}, None
    try:
        procs["coordinator"] = _start("coordinator", [*common, f"out={workdir / 'coordinator.json'}"],
                                      workdir / "coordinator.log")
        coordinator = _address(procs["coordinator"], "coordinator")
        procs["world"] = _start("world", [*common, f"coordinator_address={coordinator}", f"progress={cfg.progress}",
                                          f"out={workdir / 'world.json'}"], workdir / "world.log")
        world = _address(procs["world"], "world")

        def client_args(r):
            return [*common, f"robot_id={r}", f"coordinator_address={coordinator}", f"world_address={world}",
                    f"onnx={onnx}", f"out={workdir / f'client{r}.json'}"]
        clients.update({r: _start("client", client_args(r), workdir / f"client{r}.log") for r in range(robots)})
        restart = _Restart(cfg, clients, client_args, workdir, procs["world"])
        if procs["world"].wait() != 0:
            raise RuntimeError(f"the world failed (exit {procs['world'].returncode}): {workdir / 'world.log'}")
        restart.stop()
        for proc in list(clients.values()):
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.terminate()  # the client writes its counters on SIGTERM (below, else killed)
    finally:
        if restart is not None:
            restart.stop()
        for proc in [*procs.values(), *clients.values()]:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
    result = json.loads((workdir / "world.json").read_text())
    result["coordinator"] = json.loads((workdir / "coordinator.json").read_text())
    result["clients"] = {f"robot_{r}": (json.loads(p.read_text()) if (p := workdir / f"client{r}.json").exists() else None)
                         for r in range(robots)}
    result["restart_events"] = restart.events
    result["config"] = OmegaConf.to_container(cfg)
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     epilog="key=value overrides: pnp.deploy.config.DeployConfig")
    parser.add_argument("--checkpoint", help="a recurrent student's checkpoint")
    parser.add_argument("--robots", type=int, help="checked against the checkpoint's")
    parser.add_argument("--trials", type=int)
    parser.add_argument("--worlds", type=int)
    parser.add_argument("overrides", nargs="*", help="key=value (faults.link.delay_s=0.1, time_scale=1, ...)")
    args = parser.parse_args(argv)
    given = {k: v for k, v in (("checkpoint", args.checkpoint), ("robots", args.robots), ("trials", args.trials),
                               ("worlds", args.worlds)) if v is not None}
    cfg = deploy_config(args.overrides, given)
    with tempfile.TemporaryDirectory(prefix="deploy_") as tmp:
        workdir = Path(cfg.out).with_suffix("") if cfg.out else Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        result = run(cfg, workdir)
        result["launcher_wall_s"] = time.monotonic() - t0
    s = result["summary"]
    print(f"{s['trials']} trials: success {100 * s['success_rate']:.1f} %, latency {result['latency']}")
    if cfg.out:
        Path(cfg.out).write_text(json.dumps(result, indent=1, default=str))
        print(f"wrote {cfg.out} (process logs in {workdir})")


if __name__ == "__main__":
    main()
