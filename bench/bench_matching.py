"""Matching one silhouette against all cluster means (target: <= 1 ms).

usage: python bench/bench_matching.py [--source auto|body|stick] [--clusters N] [--size H,W]
                                      [--repeats N]

Pins the process to one CPU and BLAS to one thread, then times
``AppearanceModel.match`` (registration + eq. 8 against every cluster) on fresh
rendered silhouettes, one call per silhouette, and split into its two stages.
Also times a batch of 100 silhouettes in one call.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(__file__))

from threadpoolctl import threadpool_limits  # noqa: E402

from _appearance_data import fresh_examples, model_for  # noqa: E402
from _onecore import pin  # noqa: E402
from estimator.registration import distance  # noqa: E402

TARGET_MS = 1.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default="auto")
    parser.add_argument("--clusters", type=int, default=100)
    parser.add_argument("--size", default="64,48")
    parser.add_argument("--repeats", type=int, default=2000)
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split(","))
    pin()
    model, _, src = model_for(source=args.source, n_clusters=args.clusters, size=size)
    fresh = fresh_examples(200, seed=101, source="stick" if args.source == "stick" else "body")
    sils = fresh.silhouettes
    n = args.repeats
    with threadpool_limits(1):
        for i in range(50):  # warm-up
            model.match(sils[i % len(sils) : i % len(sils) + 1])
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(n):
            model.match(sils[i % len(sils) : i % len(sils) + 1])
        per_call = (time.perf_counter() - t0) / n * 1e3
        per_call_cpu = (time.process_time() - c0) / n * 1e3
        t0 = time.perf_counter()
        for i in range(n):
            reg, _ = model.register(sils[i % len(sils) : i % len(sils) + 1])
        t_reg = (time.perf_counter() - t0) / n * 1e3
        t0 = time.perf_counter()
        for i in range(n):
            distance(reg, model.means)
        t_dist = (time.perf_counter() - t0) / n * 1e3
        t0 = time.perf_counter()
        reps = max(1, n // 100)
        for _ in range(reps):
            model.match(sils[:100])
        batch = (time.perf_counter() - t0) / (reps * 100) * 1e3
    h, w = sils.shape[1:]
    print(f"model: {model.n_clusters} clusters, canvas {model.size[0]}x{model.size[1]}, "
          f"examples from {src}")
    print(f"match one {h}x{w} silhouette vs all clusters: {per_call:.3f} ms wall, "
          f"{per_call_cpu:.3f} ms CPU (register {t_reg:.3f} ms + eq. 8 {t_dist:.3f} ms wall), "
          f"{n} calls, one core")
    print(f"  batch of 100 in one call: {batch:.3f} ms per silhouette")
    print(f"  target <= {TARGET_MS:.1f} ms: ratio {per_call / TARGET_MS:.2f} wall, "
          f"{per_call_cpu / TARGET_MS:.2f} CPU ({'met' if per_call <= TARGET_MS else 'MISSED'})")
    print(f"  (load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")


if __name__ == "__main__":
    main()
