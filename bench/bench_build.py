"""Build time, peak memory and artifact size of the appearance model.

usage: python bench/bench_build.py [--source auto|body|stick] [--clusters N] [--out PATH]

Targets (issue 3): full build (render + cluster + means) <= 120 s on the 2-core
machine with peak memory <= 2 GB; clustering + means <= 30 s on one core;
artifact <= 25 MB. With ``--source auto`` the examples come from
``estimator.examples.render_examples`` (timed here) when it exists; otherwise
from a cached render, and only the model part is timed.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(__file__))

from threadpoolctl import threadpool_limits  # noqa: E402

from _appearance_data import training_examples  # noqa: E402
from _onecore import pin  # noqa: E402
from estimator.appearance import build_model, save_model  # noqa: E402


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default="auto")
    parser.add_argument("--clusters", type=int, default=100)
    parser.add_argument("--one-core", action="store_true", help="pin to one CPU, BLAS 1 thread")
    parser.add_argument("--out", default=None)
    parser.add_argument("--cached", action="store_true",
                        help="reuse cached examples (time the model part only)")
    args = parser.parse_args()
    if args.one_core:
        pin()
    t0 = time.perf_counter()
    ex, src = training_examples(source=args.source, cache=args.cached)
    t_examples = time.perf_counter() - t0
    mb_examples = _peak_mb()
    t1, c1 = time.perf_counter(), time.process_time()
    with threadpool_limits(1 if args.one_core else None):
        model = build_model(ex, n_clusters=args.clusters, rng=0, provenance={"source": src})
    t_model = time.perf_counter() - t1
    cpu_model = time.process_time() - c1
    out = args.out or os.path.join(tempfile.mkdtemp(), "appearance.npz")
    t2 = time.perf_counter()
    save_model(model, out)
    t_save = time.perf_counter() - t2
    size_mb = os.path.getsize(out) / 1e6
    tm = model.provenance["timings"]
    em = model.provenance["em"]
    print(f"examples: {len(ex)} from {src}: {t_examples:.1f} s")
    print(f"model ({model.n_clusters} clusters{', one core' if args.one_core else ''}): {t_model:.1f} s "
          f"= register {tm['register_s']:.1f} s + EM {tm['em_s']:.1f} s ({em['n_iter']} iterations, "
          f"converged {em['converged']}) + means {tm['means_s']:.2f} s; CPU {cpu_model:.1f} s; "
          f"save {t_save:.2f} s")
    print(f"  target clustering + means <= 30 s: {'met' if t_model <= 30 else 'MISSED'}")
    print(f"total (examples + model + save): {t_examples + t_model + t_save:.1f} s; "
          f"peak RSS {_peak_mb():.0f} MB (after examples {mb_examples:.0f} MB)")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    print(f"artifact: {out} {size_mb:.2f} MB; target <= 25 MB: {'met' if size_mb <= 25 else 'MISSED'}")


if __name__ == "__main__":
    main()
