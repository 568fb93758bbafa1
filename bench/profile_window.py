"""Where a live window's estimate spends its time: stages of ``estimate_walk`` per window.

usage: python bench/profile_window.py [--cameras 16] [--frames 20] [--windows 10] [--live [--warm 3]]

One process pinned to one core (BLAS and OpenCV one thread), the default model,
synthetic walks seen from ``--cameras`` viewpoints around the walker. Each
window is a walk of its own; with ``--live``, windows are cut from one walk as
the live service cuts them (``--frames`` every ``--frames / 2``) and estimated
with a match cache, as a live worker estimates its cameras' windows (the
frames shared with the window before are in the cache); ``--warm N`` also looks
at each window's new frames N at a time before it closes, as the live service
does (``warm_every``; their CPU is printed apart). Prints the
CPU time per window and, from a cProfile run of the same windows, the
cumulative share of each stage (a stage's time includes what it calls, so
registration is also inside the shadow search's scoring; the profiler's own
overhead inflates small calls, so the shares are what to read).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

from _onecore import pin, single_threaded

single_threaded()

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from estimator.matchcache import MatchCache  # noqa: E402
from estimator.pipeline import estimate_walk, prime_cache, tracks_from_sequence  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402
from estimator.windows import window_tracks  # noqa: E402
from service.worker import WindowBefore  # noqa: E402

# (label, module path suffix, function name): the stages in the order they run.
STAGES = [
    ("clean-up: walker per frame (select_walker)", "cleanup.py", "select_walker"),
    ("clean-up: shadow search (trim_shadow)", "cleanup.py", "trim_shadow"),
    ("clean-up: plausibility (check_plausible)", "cleanup.py", "check_plausible"),
    ("clean-up: share hidden below (hidden_fraction)", "occlusion.py", "hidden_fraction"),
    ("motion cue (head points, Theil-Sen)", "viewpoint.py", "motion_cue"),
    ("registration (Izo-Grimson section 5)", "registration.py", "register"),
    ("eq. 8 to the cluster means", "registration.py", "distance"),
    ("members of the nearest clusters (_cloud_exemplars)", "pipeline.py", "_cloud_exemplars"),
    ("viewpoint vote (_vote)", "pipeline.py", "_vote"),
    ("phase evidence (_phase_evidence)", "pipeline.py", "_phase_evidence"),
    ("examples at the decoded phases (_cloud_at_phases)", "pipeline.py", "_cloud_at_phases"),
    ("HMM Viterbi + posterior", "hmm.py", None),
    ("joints placed (_place_joints)", "pipeline.py", "_place_joints"),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--windows", type=int, default=10)
    ap.add_argument("--live", action="store_true", help="overlapping windows of one walk, with a match cache")
    ap.add_argument("--warm", type=int, default=0, metavar="N",
                    help="with --live: each window's new frames looked at N at a time before it closes")
    args = ap.parse_args()
    from service.cli.model import get_default_model

    cv2.setNumThreads(1)
    model = get_default_model(progress=True)
    az = list(np.linspace(0, 360, args.cameras, endpoint=False) + 45.0)
    el = [10.0 + 5 * (k % 3) for k in range(args.cameras)]
    hop = args.frames // 2
    if args.live:
        walk = tracks_from_sequence(synthesize(SynthSpec(n_cameras=args.cameras, n_frames=args.frames + hop * (
            2 * args.windows + 1), seed=1, azimuths=az, elevations=el)))
        windows = [window_tracks(walk, k * hop, k * hop + args.frames) for k in range(2 * args.windows + 1)]
        cache = MatchCache(max_entries=1280)  # as service.worker's
    else:
        seqs = [synthesize(SynthSpec(n_cameras=args.cameras, n_frames=args.frames, seed=s, azimuths=az, elevations=el))
                for s in range(3)]
        cache = None
        windows = [tracks_from_sequence(seqs[w % len(seqs)]) for w in range(2 * args.windows + 1)]
    pin()
    step = args.warm if args.live else 0
    n_states = model.exemplars().n_phases

    def look_early(k: int, before) -> None:
        """As the live service (warm_every): window k's frames after those it shares with the
        window before, ``step`` at a time, at the window before's viewpoints and phase."""
        said = WindowBefore.of(k - 1, list(range((k - 1) * hop, (k - 1) * hop + args.frames)), before)
        for a in range(hop, args.frames, step) if step else ():
            b = min(a + step, args.frames)
            prime_cache(window_tracks(windows[k], a, b), model, cache,
                        **said.guess(np.arange(k * hop + a, k * hop + b), n_states))

    cpu, early = [], []
    before = estimate_walk(windows[0], model, cache=cache)  # warm-up
    for k in range(1, args.windows + 1):
        t0 = time.process_time()
        look_early(k, before)
        t1 = time.process_time()
        before = estimate_walk(windows[k], model, cache=cache)
        cpu.append(time.process_time() - t1)
        early.append(t1 - t0)
    cpu_ms = 1000 * np.array(cpu)
    print(f"estimate_walk, {args.cameras} cameras x {args.frames} frames, {args.windows} windows"
          f"{' cut as live (a match cache)' if args.live else ''}, one core: "
          f"CPU per window median {np.median(cpu_ms):.0f} ms, min {cpu_ms.min():.0f} ms "
          f"({np.median(cpu_ms) / (args.cameras * args.frames):.2f} ms per frame and camera)")
    if step:
        print(f"  after looking at the new frames {step} at a time before the close "
              f"(CPU {1000 * np.median(early):.0f} ms per window, not counted above)")

    prof = cProfile.Profile()
    for k in range(args.windows + 1, len(windows)):
        look_early(k, before)
        prof.enable()
        before = estimate_walk(windows[k], model, cache=cache)
        prof.disable()
    stats = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    total = sum(v[3] for k, v in stats.items() if k[2] == "estimate_walk")
    print(f"\nprofile (cProfile, cumulative per stage; total {1000 * total / args.windows:.0f} ms per window "
          "with the profiler's overhead):")
    for label, module, name in STAGES:
        ct = 0.0
        for (path, _, func), v in stats.items():
            if path.endswith(module) and (func == name if name else func in ("viterbi", "posterior")):
                if not any(c[0] == path and c[2] == func for c in v[4]):  # not a recursive count
                    ct += v[3]
        print(f"  {label:<52} {1000 * ct / args.windows:7.1f} ms  {100 * ct / total:5.1f} %")


if __name__ == "__main__":
    main()
