"""Run a benchmark on one core: single-threaded libraries, process pinned to one CPU."""

from __future__ import annotations

import os


def single_threaded() -> None:
    """One thread for BLAS, OpenMP and Mesa's llvmpipe; call before numpy or pyrender is imported."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "LP_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def pin() -> int | None:
    """Pin this process to the first CPU it may use; return that CPU (None where unsupported)."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    core = sorted(os.sched_getaffinity(0))[0]
    os.sched_setaffinity(0, {core})
    return core
