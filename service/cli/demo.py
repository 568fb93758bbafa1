"""``posecal demo``: the whole product on one machine, no hardware, no external server.

Starts the service (REST on 127.0.0.1, Zenoh on a free loopback port, Rerun to
``demo.rrd``), starts two or more synthetic capture agents (``posecal capture
--source synthetic:...``, one process per camera, same walker seen from
different viewpoints), streams a walk for a few seconds, then prints the
estimated viewpoints next to the truth and the REST URL.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import CliError, CliFailure

# Viewpoints of the demo cameras (azimuth, elevation), docs/FORMATS.md convention.
CAMERAS = ((60.0, 10.0), (150.0, 15.0), (240.0, 5.0), (330.0, 20.0), (105.0, 25.0), (285.0, 0.0))
FPS = 15.0
EMPTY = 30  # empty frames first: the agents learn the background from them
WARMUP = 28


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="service + synthetic agents on loopback; prints "
                              "estimated viewpoints vs truth; writes demo.rrd",
                              description=__doc__.splitlines()[0])
    p.add_argument("--cameras", type=int, default=3, help=f"synthetic cameras, 2..{len(CAMERAS)} (default: 3)")
    p.add_argument("--seconds", type=float, default=10.0, help="walking time to stream (default: 10)")
    p.add_argument("--port", type=int, default=8000, help="HTTP port (0 = any free port; default: 8000)")
    p.add_argument("--rrd", default="demo.rrd", metavar="PATH", help="Rerun recording (default: demo.rrd)")
    p.add_argument("--model", metavar="PATH", help="appearance model (default: the cached default "
                   "model, built on first use in about 2 minutes)")
    p.add_argument("--workdir", metavar="DIR", help="database and uploads (default: a temporary folder)")
    p.add_argument("--seed", type=int, default=3, help="the walker (default: 3)")
    p.add_argument("--keep", action="store_true", help="keep serving after the walk until Ctrl-C")
    p.set_defaults(func=run_demo)


def _agent(k: int, az: float, el: float, args: argparse.Namespace, endpoint: str, frames: int,
           log_dir: Path) -> subprocess.Popen:
    spec = (f"synthetic:seed={args.seed},azimuth={az:g},elevation={el:g},fps={FPS:g},"
            f"empty={EMPTY},pass=40,gap=10")
    cmd = [sys.executable, "-m", "service.cli", "capture", "--rig", "demo", "--camera", f"c{k}",
           "--source", spec, "--warmup", str(WARMUP), "--max-frames", str(frames),
           "--connect", endpoint, "--stats-interval", "60"]
    log = open(log_dir / f"agent-c{k}.log", "w")
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)


def _angle(a: float | None, b: float) -> str:
    from estimator.viewpoint import azimuth_difference_deg

    return "   n/a" if a is None else f"{float(azimuth_difference_deg(a, b)):+6.1f}"


def run_demo(args: argparse.Namespace) -> int:
    import logging

    import httpx

    from service.server import BackgroundServer, free_port
    from service.settings import Settings

    logging.getLogger("httpx").setLevel(logging.WARNING)
    if not 2 <= args.cameras <= len(CAMERAS):
        raise CliError(f"--cameras must be between 2 and {len(CAMERAS)}")
    if args.seconds <= 0:
        raise CliError("--seconds must be positive")
    if args.model and not Path(args.model).is_file():
        raise CliError(f"no appearance model at {args.model}")
    workdir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="posecal-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rrd = Path(args.rrd).resolve()
    settings = Settings(db=str(workdir / "jobs.db"), data_dir=workdir / "data",
                        model_path=Path(args.model) if args.model else None,
                        live=True, zenoh_listen=[endpoint], zenoh_connect=[], rerun=f"save:{rrd}")
    cams = CAMERAS[:args.cameras]
    frames = EMPTY + int(round(args.seconds * FPS))
    print(f"starting the service (model: {args.model or 'default, built on first use'}) ...", flush=True)
    try:
        server = BackgroundServer(settings, port=args.port or None)
    except (RuntimeError, OSError) as exc:
        if not args.workdir:  # nothing was written there worth keeping
            shutil.rmtree(workdir, ignore_errors=True)
        raise CliFailure(f"the service did not start: {exc}") from None
    with server:
        url = server.url
        print(f"service at {url}  (Zenoh {endpoint}); {len(cams)} synthetic agents, "
              f"{frames} frames at {FPS:g} fps; agent logs in {workdir}", flush=True)
        agents = [_agent(k, az, el, args, endpoint, frames, workdir) for k, (az, el) in enumerate(cams)]
        client = httpx.Client(base_url=url, timeout=10.0)
        try:
            deadline = time.monotonic() + frames / FPS + 120.0
            while any(a.poll() is None for a in agents) and time.monotonic() < deadline:
                time.sleep(1.0)
                rig = client.get("/v1/rigs/demo")
                if rig.status_code == 200:
                    w = rig.json()["windows"]
                    print(f"\r  windows estimated {w['estimated']}, skipped (no walker) {w['skipped']}",
                          end="", flush=True)
            for a in agents:
                if a.poll() is None:
                    a.terminate()
                if a.wait(timeout=10) not in (0, -15):
                    print(f"\nwarning: agent {a.args[6]} exited with {a.returncode}", file=sys.stderr)
            time.sleep(1.0)  # the last windows
            print()
            rig = client.get("/v1/rigs/demo")
            if rig.status_code != 200:
                raise CliFailure(f"no silhouettes reached the service; see the agent logs in {workdir}")
            summary = rig.json()
            estimates = client.get("/v1/rigs/demo/estimates", params={"limit": 1000}).json()["estimates"]
            # The live rig lags the windows (its postures run at low priority): give it a few
            # seconds to catch up, as long as it still does.
            calibration, waited = None, 0
            while waited < 10:
                got = client.get("/v1/rigs/demo/calibration")
                latest = got.json() if got.status_code == 200 else None
                if latest is not None and calibration is not None and latest["lag_windows"] in (
                        0, calibration["lag_windows"]) and waited >= 3:
                    calibration = latest
                    break
                calibration = latest or calibration
                time.sleep(1.0)
                waited += 1
        finally:
            client.close()
            for a in agents:
                if a.poll() is None:
                    a.kill()
        _report(summary, estimates, cams)
        _report_rig(calibration, cams)
        print(f"\nREST: {url}/v1/rigs/demo/estimate, /v1/rigs/demo/calibration   (API docs: {url}/docs)")
        if args.keep:
            print("serving until Ctrl-C ...", flush=True)
            try:
                while True:
                    time.sleep(3600)
            except KeyboardInterrupt:
                pass
    print(f"Rerun recording: {rrd}   (view: rerun {rrd})")
    if not summary["windows"]["estimated"]:
        raise CliFailure(f"no window was estimated (skipped without a walker: {summary['windows']['skipped']}, "
                         f"failed: {summary['windows']['failed']}); see the agent logs in {workdir}")
    return 0


def _report(summary: dict, estimates: list[dict], cams) -> None:
    import numpy as np

    w = summary["windows"]
    f = summary["frames"]
    print(f"windows: {w['estimated']} estimated, {w['skipped']} skipped (walker absent), "
          f"{w['failed']} failed, {w['dropped']} dropped; frames late {f['late']}, missing {f['missing']}")
    lat = [e["latency_ms"]["last_frame_to_result"] for e in estimates]
    if lat:
        print(f"latency, last frame -> estimate: p50 {np.percentile(lat, 50):.0f} ms, "
              f"p95 {np.percentile(lat, 95):.0f} ms")
    print("\ncamera   truth az/el     estimated az/el (smoothed)   error az/el   windows")
    for k, (az, el) in enumerate(cams):
        sm = summary["viewpoints"].get(f"c{k}", {})
        eaz, eel = sm.get("azimuth_deg"), sm.get("elevation_deg")
        est = "     not estimated       " if eaz is None else f"{eaz:7.1f} / {eel:5.1f}           "
        print(f"c{k}      {az:6.1f} / {el:5.1f}    {est}   {_angle(eaz, az)} / "
              f"{'n/a' if eel is None else f'{eel - el:+5.1f}'}    {sm.get('windows', 0)}")


def _report_rig(calibration: dict | None, cams) -> None:
    """The live rig: each camera's rotation from the reference and its error against the truth."""
    import numpy as np

    from estimator._selfcal_core import geodesic_deg
    from estimator.rig import rotations_from_viewpoints

    if calibration is None:
        print("\nlive rig: not calibrated yet (too few windows with postures)")
        return
    rig = calibration["calibration"]
    ref = int(rig["reference"][1:])
    truth = rotations_from_viewpoints([cams[ref]] + list(cams))[1:]
    print(f"\nlive rig ({calibration['source']}, postures on {calibration['frames']} frames of "
          f"{calibration['windows']} windows, {calibration['lag_windows']} windows behind), rotations from "
          f"{rig['reference']}:")
    for k in range(len(cams)):
        cam = rig["cameras"].get(f"c{k}", {})
        if k == ref or cam.get("rotation") is None:
            continue
        r = np.array(cam["rotation"])
        extra = f", focal {cam['focal_px']:.0f} px" if cam.get("focal_px") else ""
        print(f"  c{k}: {geodesic_deg(r, np.eye(3)):6.1f} deg{extra}   off the truth by "
              f"{geodesic_deg(r, truth[k]):.1f} deg")
    if calibration.get("body"):
        thigh = calibration["body"]["segments"].get("left_thigh", {})
        print(f"  body at a stature of {calibration['body']['stature_m']} m: left thigh "
              f"{thigh.get('metres', float('nan')):.2f} m")
