"""A replay capture agent: one camera of a hardware-triggered rig, in a process of its own.

Used by ``bench/soak_live.py`` (and the fault tests) where several agents must run
for a long time on two shared cores: instead of rendering and segmenting frames
(``posecal capture --source synthetic:...``, ~10 % of a core each), it publishes
pre-rendered silhouette crops, exactly as ``capture.agent`` publishes them (one
``SilhouetteMessage`` per frame on ``posecal/<rig>/<camera>/silhouette``, the same
publisher options, ``sync="index"``, an epoch per run, ``seq`` and ``frame_index``
from 0 per run), and takes the service's priors with the agent's own validating
subscriber (counted, not used).

The rig is hardware-triggered: frames are captured on a common tick grid
(``t0_ns + tick / fps``) and the walker every camera sees is the one of the tick
(``crops[tick % loop]``). A restarted agent waits for the next tick and numbers its
frames from 0 again, as a restarted camera does, while the others go on: the
service must realign it onto the rig's indices. If the process falls behind
(stopped, starved), the ticks it missed are skipped, as a camera's frame counter
would skip them.

Every published frame is appended to ``--log`` as ``tick frame_index matching``
(flushed per line, so a SIGKILL loses nothing already published); the last line
``end published P priors R`` is written on SIGTERM/SIGINT.

Usage: ``python bench/_replay_agent.py --crops FILE.pkl --rig R --camera C --t0-ns T
--connect tcp/127.0.0.1:7447 [--mode client] [--fps 15] --log FILE``
"""

from __future__ import annotations

import argparse
import math
import pickle
import signal
import sys
import threading
import time
from pathlib import Path

import zenoh

from capture.receiver import ValidatingSubscriber
from capture.wire import Box, FeedbackMessage, SilhouetteMessage, encode, feedback_key, silhouette_key
from capture.zconfig import build_config


def save_crops(path: Path, crops: dict[str, list[tuple]], size: tuple[int, int]) -> None:
    """Write per camera a list of ``(mask uint8 crop, Box)`` and the image size for the agents."""
    rows = {c: [(m, (b.x, b.y, b.w, b.h)) for m, b in row] for c, row in crops.items()}
    with open(path, "wb") as fh:
        pickle.dump({"size": tuple(size), "crops": rows}, fh, protocol=pickle.HIGHEST_PROTOCOL)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--crops", required=True, help="pickle written by save_crops()")
    ap.add_argument("--rig", required=True)
    ap.add_argument("--camera", required=True)
    ap.add_argument("--t0-ns", type=int, required=True, help="the rig's tick 0 (time.time_ns clock)")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--connect", action="append", required=True)
    ap.add_argument("--mode", default="client", choices=("client", "peer"))
    ap.add_argument("--log", required=True)
    args = ap.parse_args(argv)

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with open(args.crops, "rb") as fh:
        data = pickle.load(fh)
    size, row = data["size"], data["crops"][args.camera]
    period_ns = 1e9 / args.fps
    epoch = time.time_ns()
    priors = 0

    def on_prior(prior: FeedbackMessage) -> None:
        nonlocal priors
        if prior.epoch_ns in (0, epoch):
            priors += 1

    published = 0
    log = open(args.log, "a", buffering=1)
    with zenoh.open(build_config(mode=args.mode, connect=args.connect)) as session:
        pub = session.declare_publisher(silhouette_key(args.rig, args.camera),
                                        congestion_control=zenoh.CongestionControl.BLOCK,
                                        reliability=zenoh.Reliability.RELIABLE, express=True)
        sub = ValidatingSubscriber(session, feedback_key(args.rig, args.camera), FeedbackMessage,
                                   on_message=on_prior, max_image_size=tuple(size))
        first = max(0, math.ceil((time.time_ns() - args.t0_ns) / period_ns))  # the next tick
        log.write(f"start epoch {epoch} first_tick {first}\n")
        tick = first
        while not stop.is_set():
            due = args.t0_ns + tick * period_ns
            wait = (due - time.time_ns()) / 1e9
            if wait > 0:
                if stop.wait(wait):
                    break
            elif -wait * args.fps > 2:  # fell behind: the ticks missed were never captured
                tick = math.ceil((time.time_ns() - args.t0_ns) / period_ns)
                continue
            mask, box = row[tick % len(row)]
            now = time.time_ns()
            pub.put(encode(SilhouetteMessage(
                rig=args.rig, camera=args.camera, frame_index=tick - first, capture_ns=int(due), box=Box(*box),
                image_size=tuple(size), epoch_ns=epoch, seq=tick - first, mask=mask, sync="index",
                publish_ns=now)))
            published += 1
            log.write(f"{tick} {tick - first} {int(pub.matching_status.matching)}\n")
            tick += 1
        sub.close()
        pub.undeclare()
    log.write(f"end published {published} priors {priors}\n")
    log.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
