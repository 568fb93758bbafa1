"""Failover of live rigs between estimator replicas: how long a dead replica's rigs go without windows.

``--replicas`` ``posecal serve`` replicas (processes) and a ``posecal router`` on loopback;
``--rigs`` rigs of two synthetic cameras published through the router at ``--fps``
(``bench/_replica_cluster.py``). ``--kills`` times, a replica that estimates some rigs
(round-robin) is hit by ``--fault``: ``kill`` (SIGKILL: its links close at once, as for a
crash on any host whose kernel lives on) or ``stop`` (SIGSTOP: the process freezes with its
links open, as a host that lost power or network: the other replicas see it gone only
when its Zenoh lease expires, ``--lease``). Per kill it reports, for each rig that moved,
the time from the fault to the first estimate published by another replica (the
estimate's attachment names the replica), and, once the replica is started again under
the same id and takes its rigs back, the gap between the last window of the interim
owner and its first. Then median and max over all kills.

Usage: ``nice .venv/bin/python bench/bench_failover.py [--replicas 3] [--rigs 4] [--kills 5]
[--fault kill|stop] [--fps 6] [--window 8] [--hop 4] [--lease 2] [--model PATH] [--json PATH]``.
Exit code 0 when every failover took at most ``--bound`` seconds (the issue's 5 s).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _replica_cluster import Replica, Router, Traffic, shutdown, wait_until  # noqa: E402

from service.replicas import rendezvous_owner  # noqa: E402
from service.server import free_port  # noqa: E402

FAULTS = {"kill": signal.SIGKILL, "stop": signal.SIGSTOP}


def _summary(values: list[float]) -> str:
    if not values:
        return "none"
    return f"n {len(values)}, median {statistics.median(values):.2f} s, max {max(values):.2f} s"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replicas", type=int, default=3)
    ap.add_argument("--rigs", type=int, default=4)
    ap.add_argument("--kills", type=int, default=5)
    ap.add_argument("--fault", choices=sorted(FAULTS), default="kill")
    ap.add_argument("--fps", type=float, default=6.0)
    ap.add_argument("--window", type=int, default=8)
    ap.add_argument("--hop", type=int, default=4)
    ap.add_argument("--lease", type=float, default=2.0, help="the replicas' Zenoh lease (POSECAL_REPLICA_LEASE_S)")
    ap.add_argument("--bound", type=float, default=5.0, help="failover target, seconds")
    ap.add_argument("--model", help="appearance model (default: the service's default model)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()

    names = [chr(ord("a") + i) for i in range(args.replicas)]
    rigs = [f"rig{i}" for i in range(args.rigs)]
    workdir = Path(tempfile.mkdtemp(prefix="posecal-failover-"))
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    router = Router(router_ep, workdir / "router.log")
    router.start()
    reps = {n: Replica(n, workdir, router_ep, model=args.model, window=args.window, hop=args.hop,
                       lease_s=args.lease) for n in names}
    traffic = None
    kills: list[dict] = []
    print(f"{args.replicas} replicas, {args.rigs} rigs x 2 cameras at {args.fps:g} fps, window {args.window} "
          f"hop {args.hop}, fault {args.fault}, lease {args.lease:g} s; logs in {workdir}")
    try:
        for r in reps.values():
            r.start()
        for r in reps.values():
            r.wait_ready()
        traffic = Traffic(router_ep, rigs, fps=args.fps)
        owner = {rig: rendezvous_owner(rig, names) for rig in rigs}
        print("owners: " + ", ".join(f"{rig} {owner[rig]}" for rig in rigs))
        t0 = time.monotonic()
        wait_until(lambda: {e.rig for e in traffic.since(t0)} == set(rigs), timeout=120,
                   what="a window of every rig")
        victims = [n for n in names if n in owner.values()]
        for k in range(args.kills):
            victim = reps[victims[k % len(victims)]]
            moved = sorted(rig for rig in rigs if owner[rig] == victim.name)
            t_fault = victim.send(FAULTS[args.fault])
            failover = traffic.failover(moved, victim.name, t_fault, timeout=60)
            victim.stop(signal.SIGKILL)
            victim.start()
            t_back = victim.wait_ready()
            gaps = traffic.handback(moved, victim.name, t_back, timeout=60)
            kills.append({"victim": victim.name, "failover_s": failover, "rebalance_gap_s": gaps})
            print(f"kill {k + 1}: {victim.name} ({args.fault}) -> "
                  + ", ".join(f"{rig} {failover[rig]:.2f} s" for rig in moved)
                  + "; back: " + ", ".join(f"{rig} gap {gaps[rig]:.2f} s" for rig in moved))
    finally:
        shutdown(traffic, reps, router)
    failovers = [s for k in kills for s in k["failover_s"].values()]
    gaps = [s for k in kills for s in k["rebalance_gap_s"].values()]
    print(f"failover (fault -> first window elsewhere): {_summary(failovers)}")
    print(f"rebalance (interim owner's last window -> the returned replica's first): {_summary(gaps)}")
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "kills": kills}, indent=1))
    return 0 if failovers and max(failovers) <= args.bound else 1


if __name__ == "__main__":
    sys.exit(main())
