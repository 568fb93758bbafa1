"""Timing of the self-calibration: milliseconds per solve, 30 frames x 13 joints.

Usage::

    .venv/bin/python bench/bench_selfcal.py [--runs 300] [--mocap ../shared/data/mocap/16_15.amc]

Prints the median (and quartiles) over ``--runs`` solves of noisy 2-camera
tracks for the closed form (§4.2), the same with 10 % missing joints, three
cameras (least squares), the baselines, the closed form on denoised tracks,
and the bundle-adjustment variants (with and without the temporal prior),
whose runs are fewer. The target is <= 5 ms for the closed form.
"""

from __future__ import annotations

import os

# Small matrices: BLAS threads only add overhead (and thrash on a shared 2-core box).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from estimator.camera import world_to_camera_rotation  # noqa: E402
from estimator.joints import N_JOINTS  # noqa: E402
from estimator.selfcal import self_calibrate  # noqa: E402
from estimator.selfcal_baselines import liebowitz_carlsson, tresadern_reid  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MOCAP = ROOT.parent / "shared" / "data" / "mocap" / "16_15.amc"




def walk(path: Path) -> np.ndarray:
    if path.exists():
        from estimator.mocap import read_motion

        return read_motion(path).person_frame()[20:140:4, :N_JOINTS]
    # Fallback (no mocap): a random rigid-ish point cloud moving in 3D.
    rng = np.random.default_rng(0)
    base = rng.normal(size=(N_JOINTS, 3))
    rots = Rotation.from_rotvec(np.linspace(0, 1, 30)[:, None] * [0.3, 0.8, 0.2]).as_matrix()
    return np.einsum("tij,kj->tki", rots, base)


def timeit(fn, tracks: list[np.ndarray]) -> np.ndarray:
    fn(tracks[0])  # warm-up
    out = np.empty(len(tracks))
    for i, y in enumerate(tracks):
        t0 = time.perf_counter()
        fn(y)
        out[i] = (time.perf_counter() - t0) * 1e3
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=300)
    p.add_argument("--mocap", type=Path, default=DEFAULT_MOCAP)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--write", type=Path, default=None,
                   help="also put the table in this Markdown file (e.g. docs/BENCHMARKS.md), "
                        "replacing an earlier self-calibration section")
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    x = walk(args.mocap)
    rel = Rotation.from_euler("xyz", [-10, -60, 20], degrees=True).as_matrix()
    rots = np.stack([world_to_camera_rotation(45, 10), rel @ world_to_camera_rotation(45, 10), world_to_camera_rotation(200, 15)])
    clean = np.einsum("cij,tkj->ctki", rots[:, :2], x) * 130.0
    h = 130.0 * float(np.mean(x[..., 2].max(1) - x[..., 2].min(1)))

    def noisy(n: int, cams: int = 2, missing: float = 0.0) -> list[np.ndarray]:
        out = []
        for _ in range(n):
            y = clean[:cams] + rng.uniform(-0.05 * h, 0.05 * h, clean[:cams].shape)
            if missing:
                y[rng.random(y.shape[:3]) < missing] = np.nan
            out.append(y)
        return out

    n = args.runs
    few = max(5, n // 30)
    cases = [
        ("closed form, 2 cameras (sec. 4.2)", self_calibrate, noisy(n)),
        ("closed form, 2 cameras, 10% missing", self_calibrate, noisy(n, missing=0.1)),
        ("least squares, 3 cameras", self_calibrate, noisy(n, cams=3)),
        ("Liebowitz-Carlsson", lambda y: liebowitz_carlsson(y, on_indefinite="clip"), noisy(n)),
        ("Tresadern-Reid", tresadern_reid, noisy(n)),
        ("closed form, denoised (temporal prior + noise model)",
         lambda y: self_calibrate(y, temporal_prior=True, noise_model=True), noisy(n)),
        ("closed form + bundle adjustment, no temporal prior",
         lambda y: self_calibrate(y, refine=True, temporal_prior=False, noise_model=False), noisy(few)),
        ("closed form + bundle adjustment (refine=True)", lambda y: self_calibrate(y, refine=True),
         noisy(few)),
        ("varying scales (sec. 4.3), no temporal prior",
         lambda y: self_calibrate(y, scales="varying", temporal_prior=False), noisy(few)),
        ("varying scales (sec. 4.3)", lambda y: self_calibrate(y, scales="varying"), noisy(few)),
    ]
    title = (f"self-calibration timing: {x.shape[0]} frames x {N_JOINTS} joints, noise 5% of height; "
             "the bundle-adjustment rows include the posterior covariance (dense Cholesky with the temporal prior, ~50 ms; sparse LU without)")
    print(title)
    print(f"{'case':52s} {'runs':>5s} {'median ms':>10s} {'q25':>8s} {'q75':>8s}")
    rows = []
    for name, fn, data in cases:
        ms = timeit(fn, data)
        q25, med, q75 = np.percentile(ms, [25, 50, 75])
        print(f"{name:52s} {len(data):5d} {med:10.2f} {q25:8.2f} {q75:8.2f}", flush=True)
        rows.append(f"| {name} | {len(data)} | {med:.2f} | {q25:.2f} | {q75:.2f} |")
    if args.write is not None:
        write_section(args.write, title, rows)
    return 0


START, END = "<!-- selfcal:start -->", "<!-- selfcal:end -->"


def write_section(path: Path, title: str, rows: list[str]) -> None:
    """Put the table between the self-calibration markers of ``path``."""
    import platform

    body = "\n".join([
        START,
        "## Self-calibration (issue 5, `bench/bench_selfcal.py`)",
        "",
        f"{title}; {time.strftime('%Y-%m-%d', time.gmtime())}, Python {platform.python_version()}, "
        f"numpy {np.__version__}, {platform.machine()} (2 shared cores). Target: closed form "
        "<= 5 ms per solve.",
        "",
        "| case | runs | median ms | q25 | q75 |",
        "|---|---|---|---|---|",
        *rows,
        "",
        "Command: `.venv/bin/python bench/bench_selfcal.py --write docs/BENCHMARKS.md`",
        END,
    ])
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    if START in text and END in text:
        head, rest = text.split(START, 1)
        text = head + body + rest.split(END, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + body + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
