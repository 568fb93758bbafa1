"""Live feedback benchmark (§7.1): do the priors reach the agents before their frames?

Runs ``posecal serve`` (live windows with feedback on) and N real capture
agents (``posecal capture``) on synthetic cameras at F fps, all on loopback
Zenoh. Each agent counts, for every frame after the first prior arrived,
whether the prior predicted *for that frame index* had arrived before the
frame's capture time, and how many priors it used or rejected (its own
evidence check). The service reports windows and priors sent.

    .venv/bin/python bench/bench_feedback_live.py [--agents 2] [--fps 15] [--seconds 60]
        [--contrast 0.8] [--noise 3] [--compare]

With ``--compare`` it runs a second time without feedback and compares the
agents' silhouette IoU against the synthetic cameras' ground truth.

Target (issue 8): with 2 agents at 15 fps, the prior for frame t reaches its
agent before frame t is captured in >= 95 % of frames.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _service_proc import ServiceProcess  # noqa: E402

TARGET = 0.95
WARMUP = 30
_FINAL = re.compile(r"stopped after (\d+) frames: .* published (\d+) .*priors (\d+) \(used (\d+), "
                    r"rejected (\d+), stale (\d+), late (\d+), in time for (\d+)/(\d+) frames\)"
                    r"(?:, IoU vs ground truth ([0-9.]+))?")


def _spawn(k: int, endpoint: str, args: argparse.Namespace) -> subprocess.Popen:
    azimuth = (60.0 + 90.0 * k) % 360.0
    spec = (f"synthetic:seed={k + 1},azimuth={azimuth:g},elevation=10,fps={args.fps:g},"
            f"empty={WARMUP},pass={args.pass_frames},gap=0,contrast={args.contrast:g},"
            f"noise={args.noise:g}")
    frames = WARMUP + int(args.seconds * args.fps)
    cmd = [sys.executable, "-m", "service.cli", "capture", "--rig", "bench", "--camera", f"c{k}",
           "--source", spec, "--fps", f"{args.fps:g}", "--max-frames", str(frames),
           "--warmup", str(WARMUP), "--connect", endpoint, "--stats-interval", "15"]
    env = {**os.environ, "POSECAL_CAPTURE_OPENCV_THREADS": "1", "POSECAL_CAPTURE_SCORE_TRUTH": "1",
           "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=Path(__file__).parents[1], env=env)


def _means(text: str) -> dict[str, float]:
    """Mean of each service histogram of interest, from the Prometheus text."""
    values = dict(re.findall(r"^(posecal_\w+_(?:sum|count)) ([0-9.e+-]+)$", text, re.M))
    out = {}
    for name, label in (("posecal_window_estimate_seconds", "estimate"),
                        ("posecal_window_latency_seconds", "last frame -> estimate"),
                        ("posecal_feedback_seconds", "priors (render + publish)")):
        n = float(values.get(f"{name}_count", 0))
        if n:
            out[label] = float(values[f"{name}_sum"]) / n
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, default=2)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--pass-frames", type=int, default=150, help="frames per walk across the view")
    ap.add_argument("--contrast", type=float, default=0.8, help="clothing vs background (synthetic)")
    ap.add_argument("--noise", type=float, default=3.0, help="sensor noise sigma (synthetic)")
    ap.add_argument("--compare", action="store_true",
                    help="run again without feedback and compare the silhouette IoU")
    ap.add_argument("--model", help="appearance model (default: the service's default model)")
    args = ap.parse_args()
    ok, iou_fb = run(args, feedback=True)
    if args.compare:
        _, iou_raw = run(args, feedback=False)
        print(f"live silhouette IoU vs ground truth: without feedback {iou_raw:.3f}, with feedback "
              f"{iou_fb:.3f} (gain {iou_fb - iou_raw:+.3f})")
    return 0 if ok else 1


def run(args: argparse.Namespace, *, feedback: bool) -> tuple[bool, float]:
    """One run; returns (target met, mean IoU over agents)."""
    load_before = os.getloadavg()[0]
    workdir = Path(tempfile.mkdtemp(prefix="posecal-bench-feedback-"))
    extra = ["--job-workers", "0"] + ([] if feedback else ["--no-feedback"])
    with ServiceProcess(workdir, *extra, model=args.model) as svc:
        time.sleep(0.5)
        agents = [_spawn(k, svc.zenoh, args) for k in range(args.agents)]
        outputs = []
        for p in agents:
            try:
                outputs.append(p.communicate(timeout=args.seconds + 180)[0])
            except subprocess.TimeoutExpired:
                p.kill()
                outputs.append(p.communicate()[0])
        time.sleep(1.0)
        rig = svc.client.get("/v1/rigs/bench").json()
        metrics = _means(svc.client.get("/metrics").text)
    print(f"feedback {'on' if feedback else 'off'}: {args.agents} agents x {args.fps:g} fps x "
          f"{args.seconds:g} s (synthetic cameras 640x480, contrast {args.contrast:g}, noise "
          f"{args.noise:g}, walks of {args.pass_frames} frames), {rig.get('windows', {}).get('seq')} windows cut, "
          f"{os.cpu_count()} cores, load avg before {load_before:.2f} after {os.getloadavg()[0]:.2f}")
    w = rig["windows"]
    print(f"service: windows estimated {w['estimated']}, skipped {w['skipped']}, failed {w['failed']}, "
          f"dropped {w['dropped']}; priors sent {rig['feedback']['priors_sent']}")
    print("service means: " + ", ".join(f"{k} {1e3 * v:.0f} ms" for k, v in metrics.items()))
    ahead = total = 0
    ious = []
    for k, out in enumerate(outputs):
        m = _FINAL.search(out)
        if m is None:
            print(f"c{k}: no final statistics; output:\n{out[-2000:]}")
            return False, float("nan")
        frames, published, priors, used, rejected, stale, late, a, n = (int(v) for v in m.groups()[:9])
        ious.append(float(m.group(10) or "nan"))
        ahead, total = ahead + a, total + n
        print(f"  c{k}: published {published}, priors received {priors}, frames segmented with a "
              f"prior {used}, rejected by the agent's check {rejected}, stale {stale}, arrived after "
              f"their frame {late}; prior in time for {a}/{n} frames ({100 * a / max(n, 1):.1f} %); "
              f"IoU vs ground truth {ious[-1]:.3f}")
    if not feedback:
        return True, float(np.mean(ious))
    share = ahead / max(total, 1)
    ok = share >= TARGET
    print(f"prior for frame t before frame t was captured: {ahead}/{total} = {100 * share:.1f} % "
          f"(target >= {100 * TARGET:.0f} %, ratio {share / TARGET:.3f}): {'MET' if ok else 'NOT MET'}")
    return ok, float(np.mean(ious))


if __name__ == "__main__":
    raise SystemExit(main())
