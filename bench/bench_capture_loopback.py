"""Benchmark: N capture agents x F fps over Zenoh on loopback, every frame delivered?

Starts N real agents (``posecal capture`` in separate processes) on a 640x480
video of the scripted scene, looped and replayed at F fps, connecting to this
process, which listens on 127.0.0.1 and receives with the validating
:class:`capture.receiver.SilhouetteReceiver`. It counts delivered frames per
camera against what each agent reports as sent, and measures
capture-to-receive latency (the capture stamp is taken when a frame is
released at its due time, so segmentation, encoding, transport and decoding
are all inside it).

    .venv/bin/python bench/bench_capture_loopback.py [--seconds 60] [--agents 4] [--fps 30]
        [--model-width 0]

Targets (issue 6): 4 agents x 30 fps for 60 s deliver every frame; p99 latency <= 10 ms.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import zenoh

from capture.receiver import SilhouetteReceiver
from capture.scene import SceneSpec, write_video
from capture.segment import SegmentSettings, describe
from capture.zconfig import build_config
from service.server import free_port

TARGET_P99_MS = 10.0
WARMUP = 100
_SENT = re.compile(r"stopped after \d+ frames: .* published (\d+) \(unheard (\d+)\), dropped (\d+)")


def _free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def _spawn(k: int, video: Path, endpoint: str, args: argparse.Namespace) -> subprocess.Popen:
    frames = WARMUP + int(args.seconds * args.fps)
    cmd = [sys.executable, "-m", "service.cli", "capture", "--rig", "bench", "--camera", f"c{k}",
           "--source", f"{video}?loop=1", "--fps", str(args.fps), "--max-frames", str(frames),
           "--warmup", str(WARMUP), "--connect", endpoint, "--stats-interval", "10"]
    env = {**os.environ, "POSECAL_CAPTURE_OPENCV_THREADS": str(args.opencv_threads)}
    if args.model_width is not None:
        env["POSECAL_CAPTURE_SEGMENT__MODEL_WIDTH"] = str(args.model_width)
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=Path(__file__).parents[1], env=env)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--agents", type=int, default=4)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--opencv-threads", type=int, default=1, help="per agent")
    parser.add_argument("--model-width", type=int, default=None,
                        help="background-model width per agent, 0 = full resolution "
                             "(default: SegmentSettings')")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)

    with tempfile.TemporaryDirectory() as tmp:
        video = Path(tmp) / "walk.avi"
        write_video(video, SceneSpec(width=args.width, height=args.height,
                                     frames=WARMUP + 240, empty=WARMUP, fps=args.fps),
                    fourcc="XVID")  # cheap to decode, like a camera's ready frames
        endpoint = _free_endpoint()
        latencies: dict[str, list[float]] = defaultdict(list)
        transport: list[float] = []  # publish -> receive part of the latency
        load_before = os.getloadavg()
        with zenoh.open(build_config(listen=[endpoint])) as session, \
                SilhouetteReceiver(session, "bench", maxsize=100_000) as rx:
            agents = [_spawn(k, video, endpoint, args) for k in range(args.agents)]
            deadline = time.monotonic() + args.seconds + 60
            while any(p.poll() is None for p in agents) and time.monotonic() < deadline:
                item = rx.get(timeout=0.1)
                if item is not None:
                    latencies[item.message.camera].append(item.latency_ns / 1e6)
                    transport.append((item.receive_ns - item.message.publish_ns) / 1e6)
            while (item := rx.get(timeout=1.0)) is not None:  # stragglers
                latencies[item.message.camera].append(item.latency_ns / 1e6)
                transport.append((item.receive_ns - item.message.publish_ns) / 1e6)
            stats = rx.stats()
        outputs = []
        for p in agents:
            if p.poll() is None:
                p.kill()
            outputs.append(p.communicate()[0])
    load_after = os.getloadavg()

    segment = SegmentSettings(**({} if args.model_width is None
                                 else {"model_width": args.model_width}))
    print(f"{args.agents} agents x {args.fps:g} fps x {args.seconds:g} s, "
          f"{args.width}x{args.height}, {describe(segment, (args.width, args.height))}, OpenCV threads "
          f"{args.opencv_threads}/agent, Zenoh peer on 127.0.0.1, {os.cpu_count()} cores, "
          f"load avg before {load_before[0]:.2f} after {load_after[0]:.2f}")
    total_sent = total_received = 0
    all_ok = True
    for k, out in enumerate(outputs):
        cam = f"c{k}"
        m = _SENT.search(out)
        if m is None or agents[k].returncode != 0:
            print(f"  {cam}: agent failed (exit {agents[k].returncode}):\n{out[-2000:]}")
            all_ok = False
            continue
        published, unheard, dropped = map(int, m.groups())
        sent, got = published + unheard, len(latencies[cam])
        lat = np.array(latencies[cam])
        total_sent, total_received = total_sent + sent, total_received + got
        print(f"  {cam}: sent {sent} (unheard {unheard}, dropped {dropped}), received {got}, "
              f"latency p50 {np.percentile(lat, 50):.2f} ms p99 {np.percentile(lat, 99):.2f} ms "
              f"max {lat.max():.2f} ms")
        all_ok &= got == sent and unheard == 0 and dropped == 0
    lat = np.concatenate([np.array(v) for v in latencies.values()]) if latencies else np.zeros(1)
    p50, p99 = np.percentile(lat, [50, 99])
    expected = int(args.agents * args.seconds * args.fps)
    delivered_ok = all_ok and total_received == expected
    print(f"delivered {total_received}/{expected} expected ({total_sent} sent), receiver lost "
          f"{stats.lost}, rejected {stats.rejected}, overflow {stats.overflow}: "
          f"{'MET' if delivered_ok else 'NOT MET'}")
    print(f"capture->receive latency p50 {p50:.2f} ms, p99 {p99:.2f} ms (target <= "
          f"{TARGET_P99_MS:g}, ratio {p99 / TARGET_P99_MS:.2f}): "
          f"{'MET' if p99 <= TARGET_P99_MS else 'NOT MET'}; max {lat.max():.2f} ms")
    t50, t99 = np.percentile(transport, [50, 99]) if transport else (np.nan, np.nan)
    print(f"  of which publish->receive (encode done, Zenoh + decode + validation): "
          f"p50 {t50:.2f} ms, p99 {t99:.2f} ms")
    return 0 if delivered_ok and p99 <= TARGET_P99_MS else 1


if __name__ == "__main__":
    sys.exit(main())
