"""Soak: N agents x F fps through the real service for D minutes, with agent and router restarts.

The lab setup of deploy/: ``posecal serve`` (its own process, live windows, feedback
priors and the live rig on, as deployed) and the agents all connect to a Zenoh router
(``posecal router``, its own process); the agents are Zenoh clients
(``deploy/posecal-capture@.service``). With ``--topology direct`` the agents connect to
the service's own listener instead (the service is then the rendezvous, and the
router restart is left out: restarting the service is the fault test
``tests/test_faults_more.py::test_service_killed_during_live_windows``).

Each agent is a process of its own (``bench/_replay_agent.py``): one camera of a
hardware-triggered rig, publishing pre-rendered synthetic silhouettes as
``posecal capture`` does, on a common tick grid (so that four agents x 15 fps for
half an hour fit on two shared cores beside the service). Every ``--restart-every``
seconds a random agent is killed (SIGKILL, as a crash) and started again
``--agent-down`` seconds later: it numbers its frames from 0 again while the others
go on. At ``--router-at`` minutes the router is killed and started again
``--router-down`` seconds later on the same endpoint.

Reported (printed as tables, ``--json`` for the figures):

- per stretch where every camera was up and heard (a maximal run of ticks at which
  every agent published with a subscriber matched), the windows the grid puts inside
  it, and the ones estimated with every camera and no frame missing;
- per camera: frames published, heard, delivered (counted by the service), in
  estimated windows, and where the others went (before the first / after the last
  window; across a gap in the rig's frames where the service restarted its window;
  in windows that were not estimated; absent from a window that covers them: lost
  after delivery unless counted as late or duplicate);
- the service's memory (RSS of the main process and of each pool worker) every
  ``--sample-every`` seconds, plotted to ``--plot`` (matplotlib, Agg).

Usage: ``nice .venv/bin/python bench/soak_live.py [--agents 4] [--fps 15] [--minutes 30]
[--restart-every 120] [--router-at MIN] [--model PATH] [--plot docs/img/soak_memory.png]
[--json PATH]``. Exit code 0 when every all-up stretch got all its windows, no
delivered frame is unaccounted for, and memory is flat (the total's per-minute floor
grew less than ``--max-growth-mb`` over the second half).
"""

from __future__ import annotations

import argparse
import bisect
import collections
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import httpx
import numpy as np
import psutil

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _replay_agent import save_crops  # noqa: E402
from _service_proc import ServiceProcess  # noqa: E402
from bench_service_live import render  # noqa: E402

from service.server import free_port  # noqa: E402

RIG = "soak"


# ---------------------------------------------------------------------------- processes


def _listening(endpoint: str) -> bool:
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    with socket.socket() as s:
        return s.connect_ex((host, int(port))) == 0


class Router:
    """``posecal router --listen ENDPOINT`` in a process of its own (``--connect``: to other routers,
    a mesh)."""

    def __init__(self, endpoint: str, log: Path, connect: tuple[str, ...] = ()) -> None:
        self.endpoint, self.log, self.connect, self.proc = endpoint, log, connect, None

    def start(self) -> None:
        links = [arg for ep in self.connect for arg in ("--connect", ep)]
        self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "router", "--listen", self.endpoint,
                                      *links], stdout=open(self.log, "a"), stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30
        while not _listening(self.endpoint):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the router did not start; see {self.log}")
            time.sleep(0.05)

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=30)


class Agent:
    """One replay agent (``bench/_replay_agent.py``); its log accumulates over its runs."""

    def __init__(self, camera: str, crops: Path, connect: str, mode: str, t0_ns: int, fps: float,
                 workdir: Path) -> None:
        self.camera, self.proc = camera, None
        self.log = workdir / f"agent-{camera}.log"
        self.cmd = [sys.executable, str(HERE / "_replay_agent.py"), "--crops", str(crops), "--rig", RIG,
                    "--camera", camera, "--t0-ns", str(t0_ns), "--fps", str(fps), "--connect", connect,
                    "--mode", mode, "--log", str(self.log)]
        self.stderr = workdir / f"agent-{camera}.err"

    def start(self) -> None:
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=open(self.stderr, "a"))

    def stop(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def runs(self) -> list[dict]:
        """Per run: first tick, the ticks published and whether a subscriber matched."""
        runs: list[dict] = []
        for line in self.log.read_text().splitlines():
            parts = line.split()
            if parts[0] == "start":
                runs.append({"epoch": int(parts[2]), "first_tick": int(parts[4]), "ticks": [], "heard": [],
                             "priors": None})
            elif parts[0] == "end":
                runs[-1]["priors"] = int(parts[4])
            else:
                runs[-1]["ticks"].append(int(parts[0]))
                runs[-1]["heard"].append(parts[2] == "1")
        return runs


_ROLES: dict[int, str] = {}


def _role(svc: psutil.Process, child: psutil.Process) -> str:
    """What a child of the service is: the live rig's pool runs at nice +10, the feedback
    pool has the renderer (EGL) loaded, the live pool the model; multiprocessing's
    resource tracker."""
    if child.pid not in _ROLES:
        if "resource_tracker" in " ".join(child.cmdline()):
            role = "resource tracker"
        elif child.nice() > svc.nice():
            role = "live rig worker"
        elif any("libEGL" in m.path for m in child.memory_maps()):
            role = "feedback worker"
        else:
            role = "live window worker"
        _ROLES[child.pid] = role
    return _ROLES[child.pid]


def _memory(svc: psutil.Process) -> dict[str, float]:
    """RSS (MB) of the service's main process and of each of its children (pool workers,
    multiprocessing's resource tracker), keyed ``main`` / ``<role> <pid>``."""
    out = {"main": svc.memory_info().rss / 2**20}
    for child in svc.children(recursive=True):
        try:
            out[f"{_role(svc, child)} {child.pid}"] = child.memory_info().rss / 2**20
        except psutil.NoSuchProcess:
            pass
    return out


# ---------------------------------------------------------------------------- analysis


def _stretches(ticks_up: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of consecutive ticks in a sorted array: [(first, last), ...]."""
    if ticks_up.size == 0:
        return []
    breaks = np.nonzero(np.diff(ticks_up) != 1)[0]
    starts = np.r_[ticks_up[0], ticks_up[breaks + 1]]
    ends = np.r_[ticks_up[breaks], ticks_up[-1]]
    return list(zip(starts.tolist(), ends.tolist()))


def analyse(estimates: list[dict], runs: dict[str, list[dict]], summary: dict, length: int, hop: int) -> dict:
    cams = sorted(runs)
    published = {c: {t for r in runs[c] for t in r["ticks"]} for c in cams}
    heard = {c: {t for r in runs[c] for t, h in zip(r["ticks"], r["heard"]) if h} for c in cams}
    windows = sorted(estimates, key=lambda e: e["window"]["seq"])
    # Stretches where every camera was up and heard, and the windows inside each.
    all_up = np.array(sorted(set.intersection(*heard.values())), int) if cams else np.zeros(0, int)
    stretches = []
    for a, b in _stretches(all_up):
        inside = [w["window"] for w in windows if a <= w["window"]["first_index"] and w["window"]["last_index"] <= b]
        phases = collections.Counter(w["last_index"] % hop for w in inside)
        if phases:
            phase = phases.most_common(1)[0][0]
            expected = sum(1 for x in range(a + length - 1, b + 1) if x % hop == phase)
        else:
            expected = max(0, (b - a + 1 - length) // hop + 1)
        full = [w for w in inside if w["cameras"] == cams and not w.get("missing")]
        stretches.append({"first_tick": a, "last_tick": b, "frames": b - a + 1, "expected": expected,
                          "estimated_all_cameras": len(full), "estimated": len(inside)})
    # Frames: where every heard frame of every camera went.
    covered = sorted((w["window"]["first_index"], w["window"]["last_index"], w["window"]["seq"]) for w in windows)
    in_windows = {c: set() for c in cams}
    absent = {c: set() for c in cams}  # covered by an estimated window that lacks the camera's frame
    for w in windows:
        win = w["window"]
        indices = [f["index"] for f in w["frames"]]
        for c in cams:
            missing = set(win.get("missing", {}).get(c, ())) if c in win["cameras"] else set(indices)
            in_windows[c].update(set(indices) - missing)
            absent[c].update(missing)
    first = covered[0][0] if covered else None
    last = max((hi for _, hi, _ in covered), default=None)

    gaps = [(hi1 + 1, lo2 - 1, "across a gap (window restarted)" if s2 == s1 + 1 else "in windows not estimated")
            for (_, hi1, s1), (lo2, _, s2) in zip(covered, covered[1:]) if lo2 > hi1 + 1]
    gap_starts = [g[0] for g in gaps]

    def where(t: int) -> str:
        if first is None or t < first:
            return "before the first window"
        if t > last:
            return "after the last window"
        k = bisect.bisect_right(gap_starts, t) - 1
        if k >= 0 and gaps[k][0] <= t <= gaps[k][1]:
            return gaps[k][2]
        return "absent from a window covering it"

    frames = {}
    for c in cams:
        lost = collections.Counter(where(t) for t in heard[c] - in_windows[c])
        frames[c] = {"published": len(published[c]), "heard": len(heard[c]),
                     "delivered": summary["cameras"].get(c, {}).get("frames"),
                     "in_windows": len(in_windows[c] & heard[c]), "not_in_windows": dict(lost),
                     "runs": len(runs[c]), "priors_received": sum(r["priors"] or 0 for r in runs[c])}
    return {"stretches": stretches, "frames": frames}


def memory_figures(samples: list[tuple[float, dict]], every_s: float) -> dict:
    """Per minute, the median RSS of the main process and of each kind of worker, and the
    total's median, floor (minimum) and peak (maximum). The live rig's worker swells by a
    few hundred MB for the seconds it calibrates and gives it back: the floor is what a
    leak would raise. The trend: a line through the per-minute floors of the second half
    of the run (MB per minute; minutes with fewer than half their samples, as the last
    sample's after the agents stopped, are left out)."""
    t = np.array([s[0] for s in samples]) / 60.0
    kinds = sorted({k.rsplit(" ", 1)[0] for _, m in samples for k in m})

    def by_kind(m: dict) -> dict[str, float]:
        out = collections.Counter()
        for k, v in m.items():
            out[k.rsplit(" ", 1)[0]] += v
        return out

    rows = [by_kind(m) for _, m in samples]
    total = np.array([sum(r.values()) for r in rows])
    minutes = np.floor(t).astype(int)
    per_minute = []
    for k in range(minutes.max() + 1):
        sel = minutes == k
        if sel.any():
            per_minute.append({"minute": k, "samples": int(sel.sum()), "total": round(float(np.median(total[sel]))),
                               "total_min": round(float(total[sel].min())), "total_max": round(float(total[sel].max())),
                               **{kind: round(float(np.median([r.get(kind, 0.0) for r, s in zip(rows, sel) if s])))
                                  for kind in kinds}})
    full = {k for k in range(minutes.max() + 1) if (minutes == k).sum() >= 30.0 / every_s}
    half = [p for p in per_minute if p["minute"] in full and p["minute"] >= (minutes.max() + 1) / 2]
    slope = (float(np.polyfit([p["minute"] for p in half], [p["total_min"] for p in half], 1)[0])
             if len(half) >= 3 else float("nan"))
    return {"samples": len(samples), "per_minute_mb": per_minute,
            "max_mb": {"total": round(float(total.max())),
                       **{kind: round(max(r.get(kind, 0.0) for r in rows)) for kind in kinds}},
            "second_half_floor_slope_mb_per_min": round(slope, 2),
            "second_half_floor_growth_mb": round(slope * (half[-1]["minute"] - half[0]["minute"]), 1)
            if len(half) >= 3 else float("nan"),
            "series": [(round(t_s, 1), {k: round(v, 1) for k, v in m.items()}) for t_s, m in samples]}


def plot(samples: list[tuple[float, dict]], events: list[tuple[float, str]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s[0] for s in samples]) / 60.0
    keys = sorted({k for _, m in samples for k in m}, key=lambda k: (k != "main", k))
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    ax.plot(t, [sum(m.values()) for _, m in samples], color="k", lw=2, label="total (main + workers)")
    for k in keys:
        ax.plot(t, [m.get(k, np.nan) for _, m in samples], lw=1.2, label="main process" if k == "main" else k)
    for when, what in events:
        ax.axvline(when / 60.0, color="tab:red" if "router" in what else "0.7", lw=0.8,
                   ls="--" if "router" in what else ":")
    ax.set_xlabel("minutes (dotted: an agent killed; dashed: the router killed)")
    ax.set_ylabel("RSS, MB")
    ax.set_ylim(bottom=0)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="center right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


# ---------------------------------------------------------------------------- main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agents", type=int, default=4)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--restart-every", type=float, default=120.0, help="seconds between agent restarts")
    ap.add_argument("--agent-down", type=float, default=2.0, help="seconds a killed agent stays down")
    ap.add_argument("--router-at", type=float, help="minutes into the run the router is killed (default: half)")
    ap.add_argument("--router-down", type=float, default=2.0, help="seconds the router stays down")
    ap.add_argument("--topology", choices=("router", "direct"), default="router")
    ap.add_argument("--sample-every", type=float, default=10.0, help="seconds between memory samples")
    ap.add_argument("--loop-frames", type=int, default=60, help="rendered frames, replayed in a loop")
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--model", help="appearance model (default: the service's default model)")
    ap.add_argument("--plot", default=str(HERE.parent / "docs" / "img" / "soak_memory.png"))
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--max-growth-mb", type=float, default=50.0,
                    help="memory is flat if the total's floor grew less than this over the second half")
    ap.add_argument("--from-json", metavar="PATH", help="print the tables of a run saved with --json again, "
                    "and plot its memory (no run)")
    args = ap.parse_args()
    if args.from_json:
        return _from_json(Path(args.from_json), Path(args.plot))
    duration = args.minutes * 60.0
    router_at = (args.router_at if args.router_at is not None else args.minutes / 2) * 60.0
    rng = random.Random(args.seed)
    length, hop = 20, 10  # the service's defaults (posecal serve without --window/--hop)

    t = time.perf_counter()
    scene = render(args.agents, args.loop_frames, seed=5)
    cams, crops, size = scene.cameras, scene.crops, scene.size
    workdir = Path(tempfile.mkdtemp(prefix="posecal-soak-"))
    crops_path = workdir / "crops.pkl"
    save_crops(crops_path, dict(zip(cams, crops)), size)
    print(f"rendered {len(cams)} x {args.loop_frames} silhouettes in {time.perf_counter() - t:.1f} s; "
          f"files in {workdir}", flush=True)
    router = None
    if args.topology == "router":
        router = Router(f"tcp/127.0.0.1:{free_port()}", workdir / "router.log")
        router.start()
    extra = ["--job-workers", "0"] + (["--connect", router.endpoint] if router else [])
    load_before = os.getloadavg()
    events: list[tuple[float, str]] = []
    samples: list[tuple[float, dict]] = []
    estimates: dict[int, dict] = {}
    svc = ServiceProcess(workdir / "service", *extra, model=args.model)
    try:
        proc = psutil.Process(svc.proc.pid)
        connect, mode = (router.endpoint, "client") if router else (svc.zenoh, "client")
        t0_ns = time.time_ns() + 3_000_000_000
        agents = {c: Agent(c, crops_path, connect, mode, t0_ns, args.fps, workdir) for c in cams}
        for a in agents.values():
            a.start()
        start = time.monotonic() + (t0_ns - time.time_ns()) / 1e9  # tick 0
        restarts = [k * args.restart_every for k in range(1, int(duration // args.restart_every) + 1)
                    if k * args.restart_every < duration]
        pending: list[tuple[float, str, str]] = [(r, "kill agent", "") for r in restarts]
        if router is not None and router_at < duration:
            pending.append((router_at, "kill router", ""))
        pending.sort()
        next_sample = next_poll = 0.0
        since = 0
        while True:
            now = time.monotonic() - start
            if now >= duration:
                break
            while pending and pending[0][0] <= now:
                _, what, who = pending.pop(0)
                if what == "kill agent":
                    cam = rng.choice(cams)
                    agents[cam].stop(signal.SIGKILL)
                    events.append((now, f"agent {cam} killed"))
                    pending.append((now + args.agent_down, "start agent", cam))
                elif what == "start agent":
                    agents[who].start()
                    events.append((now, f"agent {who} started"))
                elif what == "kill router":
                    router.kill()
                    events.append((now, "router killed"))
                    pending.append((now + args.router_down, "start router", ""))
                elif what == "start router":
                    router.start()
                    events.append((now, "router started"))
                pending.sort()
                print(f"{now / 60:6.2f} min  {events[-1][1]}", flush=True)
            if svc.proc.poll() is not None:
                raise RuntimeError(f"the service exited ({svc.proc.returncode}); see {svc.log_path}")
            if now >= next_sample:
                samples.append((now, _memory(proc)))
                next_sample += args.sample_every
            if now >= next_poll:
                since = _poll(svc.client, estimates, since)
                next_poll += 10.0
                w = svc.client.get(f"/v1/rigs/{RIG}")
                if w.status_code == 200 and int(now) % 60 < 10:
                    print(f"{now / 60:6.2f} min  windows {w.json()['windows']}  RSS total "
                          f"{sum(samples[-1][1].values()):.0f} MB", flush=True)
            time.sleep(0.2)
        for a in agents.values():
            a.stop(signal.SIGTERM)
        time.sleep(3.0)  # the last windows
        since = _poll(svc.client, estimates, since)
        samples.append((time.monotonic() - start, _memory(proc)))
        summary = svc.client.get(f"/v1/rigs/{RIG}").json()
        metrics = svc.client.get("/metrics").text
        cpu = {"main": proc.cpu_times().user + proc.cpu_times().system}
        for child in proc.children(recursive=True):
            cpu[f"{_role(proc, child)} {child.pid}"] = child.cpu_times().user + child.cpu_times().system
    finally:
        svc.close()
        if router is not None:
            router.kill(signal.SIGTERM)
    runs = {c: a.runs() for c, a in agents.items()}
    result = analyse(list(estimates.values()), runs, summary, length, hop)
    mem = memory_figures(samples, args.sample_every)
    fig = {"agents": len(cams), "fps": args.fps, "minutes": args.minutes, "topology": args.topology,
           "restart_every_s": args.restart_every, "router_at_min": router_at / 60 if router else None,
           "events": [(round(w, 1), what) for w, what in events], "windows": summary["windows"],
           "rig_frames": summary["frames"], "estimates_polled": len(estimates), **result, "memory": mem,
           "cpu_s": {k: round(v, 1) for k, v in cpu.items()}, "sample_every_s": args.sample_every,
           "load_avg": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
           "receiver_rejected": _metric(metrics, "posecal_receiver_rejected_total"),
           "latency_ms": _pct([e["latency_ms"]["last_frame_to_result"] for e in estimates.values()]),
           "workdir": str(workdir)}
    plot(samples, [e for e in events if "killed" in e[1]], Path(args.plot), _title(fig))
    ok = _report(fig, cams)
    fig["ok"] = ok
    if args.json:
        Path(args.json).write_text(json.dumps(fig, indent=1))
    print(f"memory plot: {args.plot}")
    return 0 if ok and abs(mem["second_half_floor_growth_mb"]) < args.max_growth_mb else 1


def _title(fig: dict) -> str:
    restarts = sum(1 for _, what in fig["events"] if what.startswith("agent") and "killed" in what)
    return (f"posecal serve, {fig['agents']} agents x {fig['fps']:g} fps, {fig['minutes']:g} min, "
            f"{restarts} agent restarts" + (f", router restart at {fig['router_at_min']:g} min"
                                            if fig.get("router_at_min") else ""))


def _from_json(path: Path, plot_path: Path) -> int:
    """Print the tables of a saved run again (and plot its memory), with this version's analysis."""
    fig = json.loads(path.read_text())
    samples = [(t, m) for t, m in fig["memory"]["series"]]
    fig["memory"] = memory_figures(samples, fig["sample_every_s"])
    plot(samples, [e for e in fig["events"] if "killed" in e[1]], plot_path, _title(fig))
    ok = _report(fig, sorted(fig["frames"]))
    print(f"memory plot: {plot_path}")
    return 0 if ok and abs(fig["memory"]["second_half_floor_growth_mb"]) < 50.0 else 1


def _poll(client: httpx.Client, estimates: dict[int, dict], since: int) -> int:
    """Fetch the estimates with window seq > ``since`` (the service keeps the last 500)."""
    while True:
        r = client.get(f"/v1/rigs/{RIG}/estimates", params={"since": since, "limit": 200})
        if r.status_code != 200:
            return since
        body = r.json()
        for e in body["estimates"]:
            estimates[e["window"]["seq"]] = e
        if body["next_since"] == since:
            return since
        since = body["next_since"]


def _pct(values: list[float]) -> dict:
    a = np.asarray(values, float)
    if a.size == 0:
        return {"p50": None, "p95": None, "max": None, "n": 0}
    return {"p50": round(float(np.percentile(a, 50))), "p95": round(float(np.percentile(a, 95))),
            "max": round(float(a.max())), "n": int(a.size)}


def _metric(text: str, name: str) -> float:
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(name + " "))


def _report(fig: dict, cams: list[str]) -> bool:
    fps = fig["fps"]
    print()
    print(f"soak: {fig['agents']} agents x {fps:g} fps, {fig['minutes']:g} min, topology {fig['topology']}, "
          f"load avg {fig['load_avg'][0]} -> {fig['load_avg'][1]}")
    print("events: " + "; ".join(f"{t / 60:.2f} min {what}" for t, what in fig["events"]))
    w, f = fig["windows"], fig["rig_frames"]
    print(f"windows: {w['seq']} cut, {w['estimated']} estimated, {w['skipped']} skipped, {w['failed']} failed, "
          f"{w['dropped']} dropped; frames late {f['late']}, duplicate {f['duplicate']}, ahead {f['index_ahead']}, "
          f"restarts {f['restarts']}, realigned {f['realigned']}, gaps {f['gaps']}")
    print()
    print("every camera up: stretch (min)  frames  windows expected  estimated  of which every camera in every frame")
    ok = True
    tot = collections.Counter()
    for s in fig["stretches"]:
        a, b = s["first_tick"] / fps / 60, (s["last_tick"] + 1) / fps / 60
        mark = "" if s["estimated"] >= s["expected"] else "   <- short"
        ok &= s["estimated"] >= s["expected"]
        tot.update({k: s[k] for k in ("frames", "expected", "estimated", "estimated_all_cameras")})
        print(f"{a:22.2f} - {b:5.2f}  {s['frames']:6d}  {s['expected']:16d}  {s['estimated']:9d}  "
              f"{s['estimated_all_cameras']:36d}{mark}")
    print(f"{'all':>30s}  {tot['frames']:6d}  {tot['expected']:16d}  {tot['estimated']:9d}  "
          f"{tot['estimated_all_cameras']:36d}")
    print()
    causes = sorted({k for c in cams for k in fig["frames"][c]["not_in_windows"]})
    head = "camera  runs  published  heard  delivered  in windows  " + "  ".join(causes)
    print(head)
    lost = 0
    for c in cams:
        r = fig["frames"][c]
        lost += r["not_in_windows"].get("absent from a window covering it", 0)
        cells = "  ".join(f"{r['not_in_windows'].get(k, 0):{len(k)}d}" for k in causes)
        print(f"{c:6s}  {r['runs']:4d}  {r['published']:9d}  {r['heard']:5d}  {r['delivered'] or 0:9d}  "
              f"{r['in_windows']:10d}  {cells}")
    counted = f["late"] + f["duplicate"] + f["index_ahead"]
    print(f"heard but absent from a window covering them: {lost}; dropped with a count (late, duplicate, "
          f"ahead): {counted}")
    ok &= lost <= counted
    m = fig["memory"]
    print()
    kinds = [k for k in m["max_mb"] if k != "total"]
    print(f"memory, RSS in MB, sampled every {fig['sample_every_s']:g} s: per minute the median of each process, "
          "and the total's median / floor / peak")
    print("minute  total median  floor   peak  " + "  ".join(f"{k:>18s}" for k in kinds))
    for p in m["per_minute_mb"]:
        part = "*" if p.get("samples", 99) < 30.0 / fig["sample_every_s"] else " "
        print(f"{p['minute']:5d}{part}  {p['total']:12d}  {p['total_min']:5d}  {p['total_max']:5d}  "
              + "  ".join(f"{p.get(k, 0):18d}" for k in kinds))
    print(f"{'max':>6s}  {m['max_mb']['total']:12d}  {'':5s}  {'':5s}  "
          + "  ".join(f"{m['max_mb'][k]:18d}" for k in kinds))
    print("(* fewer than half the minute's samples: left out of the trend)")
    print(f"floor over the second half: {m['second_half_floor_slope_mb_per_min']:+.1f} MB/min "
          f"({m['second_half_floor_growth_mb']:+.0f} MB)")
    lat = fig["latency_ms"]
    print(f"last frame -> estimate published (the service's figure): p50 {lat['p50']} ms, p95 {lat['p95']} ms, "
          f"max {lat['max']} ms over {lat['n']} windows")
    print(f"CPU seconds: {fig['cpu_s']}")
    return bool(ok)


if __name__ == "__main__":
    sys.exit(main())
