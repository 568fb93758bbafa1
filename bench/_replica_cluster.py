"""Several ``posecal serve`` replicas on one ``posecal router``, live rigs, and who estimates them.

Shared by ``tests/test_replicas.py`` and ``bench/bench_failover.py``:

- :class:`Replica`: ``posecal serve`` in a process of its own (``POSECAL_REPLICA_ID``), a Zenoh
  peer of the router with a listener of its own, small windows, feedback and the live rig
  off, no job workers, so that three replicas and their estimates fit on two shared cores;
- :class:`Traffic`: one Zenoh client session of the router that publishes the rigs'
  silhouettes (pre-rendered crops, index-synchronised, as agents publish them) from a
  thread, and records every estimate on ``posecal/*/estimate`` with the replica named in
  its attachment and its arrival time;
- :meth:`Traffic.failover`: after a replica is killed, per rig it estimated, the time to
  the first estimate another replica publishes; :meth:`Traffic.handback`: once it is back,
  the gap between the interim owner's last estimate and its first.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import zenoh

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
from bench_service_live import render  # noqa: E402
from soak_live import Router  # noqa: E402

from capture.wire import SilhouetteMessage, encode, silhouette_key  # noqa: E402
from capture.zconfig import build_config  # noqa: E402
from service.server import free_port  # noqa: E402

__all__ = ["Estimate", "Replica", "Router", "Traffic", "render", "shutdown", "wait_until"]


def wait_until(predicate, *, timeout: float, what: str):
    """Poll ``predicate()`` every 50 ms until truthy (its value); TimeoutError after ``timeout``."""
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)
    return value


class Replica:
    """``posecal serve`` as replica ``name``, connected to ``router``; its log under ``workdir``."""

    def __init__(self, name: str, workdir: Path, router: str, *, model: str | None, window: int, hop: int,
                 lease_s: float = 2.0) -> None:
        self.name, self.router, self.proc = name, router, None
        self.dir = workdir / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.extra = ["--model", model] if model else []
        self.window, self.hop, self.lease_s = window, hop, lease_s
        self.client: httpx.Client | None = None

    def start(self) -> None:
        """Start the process (without waiting: see :meth:`wait_ready`)."""
        port = free_port()
        cmd = [sys.executable, "-m", "service.cli", "serve", "--port", str(port),
               "--connect", self.router, "--listen", f"tcp/127.0.0.1:{free_port()}",
               "--db", str(self.dir / "jobs.db"), "--data-dir", str(self.dir / "data"), "--job-workers", "0",
               "--window", str(self.window), "--hop", str(self.hop), "--no-feedback", "--no-live-rig", *self.extra]
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYOPENGL_PLATFORM": "egl", "PYTHONUNBUFFERED": "1",
               "POSECAL_REPLICA_ID": self.name, "POSECAL_REPLICA_LEASE_S": str(self.lease_s),
               "POSECAL_DATA": str(self.dir)}
        self.proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=open(self.dir / "serve.log", "ab"),
                                     stderr=subprocess.STDOUT)
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30)

    def wait_ready(self, timeout: float = 180.0) -> float:
        """Wait until ``/healthz`` answers (the replica has joined); its monotonic time."""
        deadline = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"replica {self.name} exited with {self.proc.returncode}; "
                                   f"see {self.dir / 'serve.log'}")
            try:
                if self.client.get("/healthz").status_code == 200:
                    return time.monotonic()
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"replica {self.name} did not start in {timeout} s")
            time.sleep(0.1)

    def get(self, path: str) -> httpx.Response:
        return self.client.get(path)

    def rigs(self) -> list[str]:
        """The rigs this replica lists in ``/v1/rigs`` (those it estimates)."""
        return sorted(r["rig"] for r in self.get("/v1/rigs").json()["rigs"])

    def send(self, sig: int) -> float:
        """Send ``sig`` (SIGKILL: a crash; SIGSTOP: a host that vanished with its links open);
        the monotonic time just before."""
        t = time.monotonic()
        os.kill(self.proc.pid, sig)
        return t

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None and self.proc.poll() is None:
            if sig != signal.SIGKILL:
                os.kill(self.proc.pid, signal.SIGCONT)  # a stopped process cannot handle SIGTERM
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.client is not None:
            self.client.close()


@dataclass(frozen=True)
class Estimate:
    t: float  # monotonic arrival time here
    rig: str
    replica: str | None  # the estimate's attachment
    seq: int


class Traffic:
    """Publish ``rigs`` x the rendered cameras at ``fps`` through ``router`` and record the estimates."""

    def __init__(self, router: str, rigs: list[str], *, fps: float, frames: int = 40, seed: int = 7) -> None:
        scene = render(2, frames, seed)
        cams, crops, size = scene.cameras, scene.crops, scene.size
        self.rigs, self.fps, self.size = rigs, fps, size
        self.crops = dict(zip(cams, crops))
        self.estimates: list[Estimate] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.session = zenoh.open(build_config(mode="client", connect=[router]))
        self._sub = self.session.declare_subscriber("posecal/*/estimate", self._on_estimate)
        self._pubs = {(rig, cam): self.session.declare_publisher(
            silhouette_key(rig, cam), congestion_control=zenoh.CongestionControl.BLOCK, express=True)
            for rig in rigs for cam in self.crops}
        self._thread = threading.Thread(target=self._publish, name="traffic", daemon=True)
        self._thread.start()

    def _on_estimate(self, sample: zenoh.Sample) -> None:
        t = time.monotonic()
        rig = str(sample.key_expr).split("/")[1]
        att = sample.attachment
        seq = json.loads(sample.payload.to_bytes())["window"]["seq"]
        with self._lock:
            self.estimates.append(Estimate(t, rig, None if att is None else att.to_string(), seq))

    def _publish(self) -> None:
        epoch, t0 = time.time_ns(), time.monotonic()
        k = 0
        while not self._stop.wait(max(0.0, t0 + k / self.fps - time.monotonic())):
            now = time.time_ns()
            for (rig, cam), pub in self._pubs.items():
                mask, box = self.crops[cam][k % len(self.crops[cam])]
                pub.put(encode(SilhouetteMessage(
                    rig=rig, camera=cam, frame_index=k, capture_ns=now, box=box, image_size=self.size,
                    epoch_ns=epoch, seq=k, mask=mask, sync="index", publish_ns=now)))
            k += 1

    def since(self, t: float) -> list[Estimate]:
        """Estimates that arrived after monotonic time ``t``."""
        with self._lock:
            return [e for e in self.estimates if e.t > t]

    def estimated_by(self, t: float) -> dict[str, set[str | None]]:
        """Per rig, the replicas whose estimates arrived after ``t``."""
        out: dict[str, set[str | None]] = {r: set() for r in self.rigs}
        for e in self.since(t):
            out[e.rig].add(e.replica)
        return out

    def first_windows(self, rigs: list[str], t: float, by, *, timeout: float, what: str) -> dict[str, float]:
        """Per rig of ``rigs``, the arrival time of its first estimate after ``t`` from a replica
        ``by(replica)`` accepts; TimeoutError if one has none after ``timeout``."""
        def firsts() -> dict[str, float] | None:
            first: dict[str, float] = {}
            for e in self.since(t):
                if e.rig in rigs and by(e.replica):
                    first.setdefault(e.rig, e.t)
            return first if len(first) == len(rigs) else None
        return wait_until(firsts, timeout=timeout, what=what)

    def failover(self, rigs: list[str], dead: str, t_kill: float, *, timeout: float) -> dict[str, float]:
        """Per rig of ``rigs`` (the dead replica's), seconds from ``t_kill`` to the first estimate
        of it published by another replica."""
        first = self.first_windows(rigs, t_kill, lambda r: r != dead, timeout=timeout,
                                   what=f"other replicas to estimate {rigs} after {dead} died")
        return {rig: t - t_kill for rig, t in first.items()}

    def handback(self, rigs: list[str], back: str, t_back: float, *, timeout: float) -> dict[str, float]:
        """Per rig of ``rigs`` (those of ``back``, which joined at ``t_back``), the gap between the
        interim owner's last estimate and ``back``'s first."""
        first = self.first_windows(rigs, t_back, lambda r: r == back, timeout=timeout,
                                   what=f"{back} to estimate {rigs} again")
        with self._lock:
            last = {rig: max((e.t for e in self.estimates if e.rig == rig and e.replica != back and e.t < t),
                             default=float("nan")) for rig, t in first.items()}
        return {rig: t - last[rig] for rig, t in first.items()}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        for entity in (self._sub, *self._pubs.values()):
            entity.undeclare()
        self.session.close()


def shutdown(traffic: "Traffic | None", replicas: dict[str, "Replica"], *routers: Router) -> None:
    """Stop the rigs' traffic, every replica and the routers (the end of a cluster's run)."""
    if traffic is not None:
        traffic.close()
    for r in replicas.values():
        r.stop()
    for router in routers:
        router.kill(signal.SIGTERM)
