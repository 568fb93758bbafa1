"""``posecal selfcal`` on a real lab's keypoints: the Pose2Sim demo, against its Qualisys calibration.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_real_keypoints.py [--plot docs/img/real_keypoints_rig.png]

The input is ``tests/fixtures/pose2sim_balancing`` (its README: OpenPose
BODY_25B keypoints of a person balancing on a beam, 4 cameras 1088x1920 about
3-4.5 m away, a second person at the edge of two views; BSD 3-Clause), the
truth its Qualisys calibration. Nothing of posecal's made these keypoints or
was tuned on them. ``python -m service.cli selfcal`` runs on them as a user
would, through the real command line (:func:`eval_keypoints_import.run_cli`):

- with the 4 cameras: the default (``--image-size 1088,1920``), known
  intrinsics (``--intrinsics`` the Qualisys file itself, matched to the
  keypoint folders by name: ``cam_01`` is ``cam01``), no image size
  (scaled-orthographic cameras) and ``--method closed-form``;
- the default on every 3-camera subset and every camera pair (the camera
  folders linked into a temporary folder), to see how the error grows as
  cameras are taken away.

Reported per run: the geodesic error of every camera pair's relative
rotation (median, max), the focal lengths' relative errors, the camera
centres' errors in the reference camera's frame (metres at the demo's
stature, 1.72 m) and the translation directions' errors; the seconds per run
(with the interpreter's start). ``--plot`` draws the rig from above, true
and estimated.

``--damage N`` adds, on top of the detector's own errors, more of the same
kind to N damaged copies of the keypoints (seeded): each keypoint missed
with probability ``--drop``, displaced by 6-17 % of the person's image height
with probability ``--outliers`` (its confidence then 0.3-0.7), each left/right
pair of a person swapped with probability ``--swaps``; and reports the
default's errors over the copies.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import eval_keypoints_import as ev  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "pose2sim_balancing"
CALIBRATION = FIXTURE / "calibration" / "Calib_qualisys.toml"
SIZE = (1088, 1920)
STATURE_M = 1.72  # the demo's participant (its Config.toml)


def true_rig(names: list[str]) -> dict:
    """The Qualisys calibration as :mod:`eval_keypoints_import`'s rig: per camera (in file order, named
    as the keypoint folders) the world-to-camera rotation ``R``, the centre ``C`` and the focal ``f``."""
    doc = tomllib.loads(CALIBRATION.read_text())
    tables = [t for t in doc.values() if isinstance(t, dict) and "rotation" in t]
    cams = []
    for name, t in zip(names, tables):
        rot = Rotation.from_rotvec(np.ravel(t["rotation"])).as_matrix()
        k = np.array(t["matrix"], float)
        cams.append({"name": name, "R": rot, "C": -rot.T @ np.ravel(t["translation"]),
                     "f": (k[0, 0] + k[1, 1]) / 2, "size": SIZE})
    return {"cameras": cams, "size": SIZE}


# BODY_25B's left/right pairs (eyes, ears, shoulders, elbows, wrists, hips, knees, ankles; big toes,
# small toes, heels), as OpenPose's body_25b model numbers them.
PAIRS_25B = ((1, 2), (3, 4), (5, 6), (7, 8), (9, 10), (11, 12), (13, 14), (15, 16), (19, 22), (20, 23), (21, 24))


def damage(src: Path, dst: Path, rng: np.random.Generator, drop: float, outliers: float, swaps: float) -> None:
    """A copy of the OpenPose folders ``src`` with more detector errors (``--damage`` in the module's
    docstring): every person of every file, keypoints as OpenPose writes them (``0, 0, 0`` missed)."""
    shutil.copytree(src, dst)
    for path in sorted(dst.glob("*_json/*.json")):
        doc = json.loads(path.read_text())
        for person in doc["people"]:
            kp = np.array(person["pose_keypoints_2d"], float).reshape(-1, 3)
            seen = kp[:, 2] > 0
            if seen.sum() < 2:
                continue
            height = np.ptp(kp[seen, 1])
            for a, b in PAIRS_25B:
                if rng.random() < swaps:
                    kp[[a, b]] = kp[[b, a]]
            moved = seen & (rng.random(len(kp)) < outliers)
            ang = rng.uniform(0, 2 * np.pi, len(kp))
            shift = rng.uniform(0.06, 0.17, len(kp)) * height
            kp[moved, :2] += (shift[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1))[moved]
            kp[moved, 2] = rng.uniform(0.3, 0.7, moved.sum())
            kp[rng.random(len(kp)) < drop] = 0.0
            person["pose_keypoints_2d"] = [round(float(v), 3) for v in kp.ravel()]
        path.write_text(json.dumps(doc))


def run(cameras: list[str], *extra: str, source: Path = FIXTURE / "pose") -> dict:
    """``posecal selfcal`` on the ``cameras`` of ``source`` (a temporary folder of links to their keypoint
    folders) with ``extra`` arguments; its errors against the Qualisys rig."""
    with tempfile.TemporaryDirectory() as tmp:
        pose = Path(tmp) / "pose"
        pose.mkdir()
        for cam in cameras:
            (pose / f"{cam}_json").symlink_to(source / f"{cam}_json")
        doc, seconds, failure = ev.run_cli(Path(tmp), "--height", str(STATURE_M), *extra)
    row = {"cameras": cameras, "args": " ".join(extra), "seconds": seconds, "failure": failure, "doc": doc}
    if doc is None:
        return row
    rig = _subset(true_rig(ALL), cameras)
    row["rotation"], row["focal"] = ev.errors(doc, rig)
    if "centre_m" in next(iter(doc["cameras"].values())):
        row["centre"], _, row["direction"] = ev.centre_errors(doc, rig)
    row["frames"] = len(doc["frames"])
    return row


def _subset(rig: dict, cameras: list[str]) -> dict:
    return dict(rig, cameras=[c for c in rig["cameras"] if c["name"] in cameras])


ALL = sorted(p.name[: -len("_json")] for p in (FIXTURE / "pose").iterdir() if p.name.endswith("_json"))


def _fmt(values: list[float] | None, scale: float = 1.0, unit: str = "") -> str:
    if not values:
        return "—"
    v = np.asarray(values) * scale
    return f"{np.median(v):.2f} / {v.max():.2f}{unit}"


def plot(rows: list[dict], path: Path) -> None:
    """The rig from above (camera 0's x-z plane, metres): true centres and optical axes, and each
    4-camera run's estimate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rig = true_rig(ALL)
    r0, c0 = rig["cameras"][0]["R"], rig["cameras"][0]["C"]
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    styles = [("true (Qualisys)", "k", "o")] + [(r["label"], col, m) for r, col, m in
                                                zip(rows, ("tab:blue", "tab:orange"), ("x", "+"))]
    for i, (label, colour, marker) in enumerate(styles):
        if i == 0:
            cen = [r0 @ (c["C"] - c0) for c in rig["cameras"]]
            axes = [r0 @ c["R"][2] for c in rig["cameras"]]
        else:
            doc = rows[i - 1]["doc"]
            cen = [np.zeros(3)] + [np.array(doc["cameras"][n]["centre_m"]) for n in ALL[1:]]
            axes = [np.array([0.0, 0.0, 1.0])] + [np.array(doc["cameras"][n]["rotation"])[2] for n in ALL[1:]]
        for name, c, a in zip(ALL, cen, axes):
            ax.plot(c[0], c[2], marker, color=colour, ms=9, label=label if name == ALL[0] else None)
            ax.annotate("", xy=(c[0] + 0.8 * a[0], c[2] + 0.8 * a[2]), xytext=(c[0], c[2]),
                        arrowprops={"arrowstyle": "->", "color": colour})
            if i == 0:
                ax.annotate(name, (c[0], c[2]), textcoords="offset points", xytext=(8, -12))
    ax.set_aspect("equal")
    ax.set_xlabel(f"x (m, {ALL[0]}'s frame: right)")
    ax.set_ylabel(f"z (m, {ALL[0]}'s optical axis)")
    ax.set_title("Pose2Sim demo: rig from its OpenPose keypoints, from above")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    print(f"plot: {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plot", type=Path, help="PNG of the rig from above, true and estimated")
    ap.add_argument("--damage", type=int, default=0, metavar="N",
                    help="instead: the default on N damaged copies of the keypoints")
    ap.add_argument("--drop", type=float, default=0.1)
    ap.add_argument("--outliers", type=float, default=0.05)
    ap.add_argument("--swaps", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    size = f"{SIZE[0]},{SIZE[1]}"
    if args.damage:
        damaged(args, size)
        return
    runs = [("default (--image-size)", ALL, ("--image-size", size)),
            ("--intrinsics (the Qualisys file)", ALL, ("--intrinsics", str(CALIBRATION))),
            ("no --image-size (scaled orthographic)", ALL, ()),
            ("--method closed-form", ALL, ("--method", "closed-form"))]
    runs += [(f"default, {len(s)} cameras {'+'.join(s)}", list(s), ("--image-size", size))
             for n in (3, 2) for s in itertools.combinations(ALL, n)]
    rows = []
    print("| run | frames | rotation error median / max (deg) | focal error median / max | centre error "
          "median / max (m) | translation direction median / max (deg) | s |")
    print("|---|---|---|---|---|---|---|")
    for label, cams, extra in runs:
        row = dict(run(cams, *extra), label=label)
        rows.append(row)
        if row["doc"] is None:
            print(f"| {label} | — | failed: {row['failure']} | | | | {row['seconds']:.1f} |")
            continue
        flag = " (flagged unreliable)" if row["failure"] else ""
        print(f"| {label}{flag} | {row['frames']} | {_fmt(row['rotation'])} | {_fmt(row.get('focal'), 100, ' %')} | "
              f"{_fmt(row.get('centre'))} | {_fmt(row.get('direction'))} | {row['seconds']:.1f} |", flush=True)
    for n in (3, 2):
        errs = [e for r in rows if len(r["cameras"]) == n and r.get("rotation") and r["args"].startswith("--image")
                for e in r["rotation"]]
        if errs:
            print(f"default, all {n}-camera subsets: camera pairs median {np.median(errs):.2f}, "
                  f"p90 {np.percentile(errs, 90):.2f}, max {max(errs):.2f} deg ({len(errs)} pairs)")
    if args.plot:
        plot([r for r in rows[:2] if r["doc"] is not None], args.plot)


def damaged(args: argparse.Namespace, size: str) -> None:
    """The default on ``args.damage`` damaged copies of the 4 cameras' keypoints."""
    rng = np.random.default_rng(args.seed)
    rot, foc, fails = [], [], 0
    for k in range(args.damage):
        with tempfile.TemporaryDirectory() as tmp:
            damage(FIXTURE / "pose", Path(tmp) / "pose", rng, args.drop, args.outliers, args.swaps)
            row = run(ALL, "--image-size", size, source=Path(tmp) / "pose")
        if row["doc"] is None or row["failure"]:
            fails += 1
            print(f"copy {k}: {row['failure'] or 'failed'}")
            continue
        rot += row["rotation"]
        foc += row["focal"]
        print(f"copy {k}: pairs {np.round(row['rotation'], 2).tolist()} focal {np.round(100 * np.array(row['focal']), 1).tolist()} %",
              flush=True)
    print(f"\n{args.damage} copies, keypoints missed {args.drop:.0%} more, outliers {args.outliers:.0%}, "
          f"left/right swaps {args.swaps:.0%} (seed {args.seed}): camera pairs median {np.median(rot):.2f}, "
          f"p90 {np.percentile(rot, 90):.2f}, max {max(rot):.2f} deg; focal median {100 * np.median(foc):.1f} %, "
          f"p90 {100 * np.percentile(foc, 90):.1f} %; failed or flagged {fails}")


if __name__ == "__main__":
    main()
