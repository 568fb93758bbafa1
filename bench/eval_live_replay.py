"""The live windows replayed offline on the composite walks: ahead/behind with and without the side
each camera's earlier windows found.

``bench/eval_live_composite.py`` runs the live path end to end, and its runs
vary with the timing of the processes on this machine's two cores. This
replays what the service does, the same on every run: for each of
``eval_composite.py``'s walks (the same seed draws the same walks), each
camera's video is segmented as a live agent segments it
(:func:`capture.live.segment_recording`: no look ahead; the image of the empty
scene as its background with ``--plates``), cut into the service's windows (20
frames every 10), and each window estimated on its own
(:func:`estimator.pipeline.estimate_walk`), one after the other; each camera's
viewpoint is smoothed over the windows as the service smooths it
(:class:`estimator.windows.ViewpointTrack` with the service's settings, fed
the side each window found by itself, :func:`estimator.windows.own_azimuth`).
Two runs over the same silhouettes:

- ``alone``: every window on its own (``POSECAL_FOLD_WINDOWS=0``; posecal
  before session 58);
- ``earlier``: a camera whose last ``--fold-windows`` windows in a row (the
  service's ``fold_windows``, 2) agreed with its smoothed viewpoint keeps that
  side of the ahead/behind fold unless the other cameras' phase objects
  (:func:`estimator.windows.earlier_azimuths`, ``estimate_walk(earlier=)``).

Scored per window and camera against the truth: the azimuth error's median /
p90, how many are over 30 deg and how many of those are ahead/behind folds
(the mirror, ``180 - a``, within 30 deg of the truth), and every window and
camera whose error the two runs put more than 3 deg apart.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_live_replay.py [--sequences 12] [--seed 5] \\
        [--walker-scale 0.5] [--plates] [--frames 45] [--keep DIR] [--plot FILE.png]

``--synthetic N`` replays N of posecal's own walks instead, long enough for a
smoothed viewpoint to rest on many windows: three stretches of 40 frames
(11 windows), 2-4 cameras at random azimuths (the first within 20 deg of the
walking axis, where a turn and the fold look alike), 320x240, with
``--damage`` (default ``all``: every damage of :mod:`estimator.damage` at
once); ``--turn 180`` turns the walker back between stretches (a walkway
walked up and down; windows across the stretches' ends are not scored), ``--turn 0`` keeps
one heading.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_live_replay.py --synthetic 20 --turn 0 [--seed 12]

``--keep DIR`` keeps the walks and each camera's segmented track there
(``walk<i>/live_tracks.pkl``), read again by a later run with the same
arguments. A walk of 45 frames (3 s) has 3 windows per camera; the CMU walks
last 58 frames at most (``--frames 58``: 4 windows).
"""

from __future__ import annotations

import argparse
import pickle
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _onecore import single_threaded  # noqa: E402

single_threaded()

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from eval_composite import FPS, Optics, composite_walks, live_segments  # noqa: E402
from eval_real_video import load_video  # noqa: E402
from capture.refine import plate_for, track_from_segmentations  # noqa: E402
from estimator.damage import damage_sequence  # noqa: E402
from estimator.pipeline import CameraTrack, estimate_walk, tracks_from_sequence  # noqa: E402
from estimator.sequence import Sequence  # noqa: E402
from estimator.synth import SynthSpec, synthesize_turns  # noqa: E402
from estimator.viewpoint import azimuth_difference_deg  # noqa: E402
from estimator.windows import ViewpointTrack, earlier_azimuths, own_azimuth, window_tracks  # noqa: E402
from service.settings import Settings  # noqa: E402

RUNS = ("alone", "earlier")


def segmented_walks(work: Path, args) -> list[tuple[int, dict, dict[str, CameraTrack]]]:
    """Each walk's truth and its cameras' tracks as live agents segment them (cached in ``work``)."""
    out = []
    cached = [work / f"walk{i}" / "live_tracks.pkl" for i in range(args.sequences)]
    if all(p.exists() for p in cached):
        return [(i, *pickle.loads(p.read_bytes())) for i, p in enumerate(cached)]
    walks = composite_walks(work, sequences=args.sequences, seed=args.seed, frames=args.frames,
                            walker_scale=args.walker_scale, plates=args.plates, optics=Optics())
    for i, seq, _ in tqdm(walks, total=args.sequences, desc="walks (render, segment)", file=sys.stderr):
        tracks = {}
        for cam in seq.cameras:
            video = work / f"walk{i}" / "videos" / f"{cam}.avi"
            tracks[cam] = track_from_segmentations(live_segments(load_video(video), plate_for(video)))
        cached[i].write_bytes(pickle.dumps((seq.truth, tracks)))
        out.append((i, seq.truth, tracks))
    return out


def synthetic_walks(n: int, seed: int, turn: float, damage: str) -> list[tuple[int, dict, dict[str, CameraTrack]]]:
    """``n`` walks of three 40-frame stretches, the walker turning by ``turn`` deg between them (module
    docstring), with ``damage``; each stretch's viewpoints in the truth's ``segments``."""
    rng, out = np.random.default_rng(seed), []
    for k in tqdm(range(n), desc="walks (render)", file=sys.stderr):
        cams = int(rng.integers(2, 5))
        az = rng.uniform(0.0, 360.0, cams)
        az[0] = (rng.choice([0.0, 180.0]) + rng.uniform(-20.0, 20.0)) % 360.0
        elevations = tuple(rng.uniform(0.0, 20.0, cams))
        seq = synthesize_turns([SynthSpec(n_cameras=cams, n_frames=40, seed=1000 * seed + 10 * k + j,
                                          azimuths=tuple((az + turn * j) % 360.0), elevations=elevations,
                                          image_size=(320, 240)) for j in range(3)])
        if damage != "none":
            seq = Sequence(seq.fps, seq.cameras, seq.image_size,
                           damage_sequence(seq.silhouettes, damage, seed=k, truth=seq.truth), seq.truth)
        out.append((k, seq.truth, tracks_from_sequence(seq)))
    return out


def _true_azimuths(truth: dict, start: int, stop: int) -> dict[str, float] | None:
    """The cameras' azimuths over frames ``start``-``stop - 1``: the truth's, or its segment's that
    holds them all (None across a turn)."""
    if "segments" not in truth:
        return {c: v["azimuth_deg"] for c, v in truth["cameras"].items()}
    for seg in truth["segments"]:
        if seg["first_index"] <= start and stop - 1 <= seg["last_index"]:
            return {c: v["azimuth_deg"] for c, v in seg["cameras"].items()}
    return None


def replay(truth: dict, tracks: dict[str, CameraTrack], model, settings: Settings, fold_windows: int,
           walk: int) -> list[dict]:
    """One walk's windows in order, as the service estimates and smooths them: a row per window and camera."""
    smooth = {cam: ViewpointTrack(threshold_deg=settings.change_threshold_deg, confirm=settings.change_windows,
                                  settle=settings.change_windows) for cam in tracks}
    n = len(next(iter(tracks.values())).silhouettes)
    rows = []
    for start in range(0, n - settings.window_length + 1, settings.window_hop):
        stop = start + settings.window_length
        try:
            est = estimate_walk(window_tracks(tracks, start, stop), model,
                                earlier=earlier_azimuths(smooth, fold_windows))
        except ValueError:  # nothing estimable in the window: the service skips it too
            continue
        trues = _true_azimuths(truth, start, stop)
        for cam, c in est.cameras.items():
            vp = c.viewpoint
            own = own_azimuth(vp.azimuth_deg if np.isfinite(vp.azimuth_deg) else None, vp.flip)
            smooth[cam].update(own, vp.elevation_deg, stop - 1)
            if not np.isfinite(vp.azimuth_deg) or trues is None:
                continue
            true = trues[cam]
            rows.append({"walk": walk, "start": start, "camera": cam, "flip": vp.flip,
                         "error": abs(float(azimuth_difference_deg(vp.azimuth_deg, true))),
                         "mirror_error": abs(float(azimuth_difference_deg(180.0 - vp.azimuth_deg, true)))})
    return rows


def summary(rows: list[dict]) -> str:
    e = np.array([r["error"] for r in rows])
    folds = sum(r["error"] > 30 and r["mirror_error"] <= 30 for r in rows)
    held = sum(r["flip"] == "earlier" for r in rows)
    return (f"{np.median(e):.2f} / {np.percentile(e, 90):.1f} | {np.sum(e > 30)} | {folds} | {held} | {len(e)}")


def plot(path: Path, results: dict[str, list[dict]], title: str) -> None:
    """Share of windows x cameras over 30 deg off, by the window's place in its walk (the first has no
    earlier windows; from the third on, a smoothed viewpoint may rest on two)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    starts = sorted({r["start"] for rows in results.values() for r in rows})
    fig, ax = plt.subplots(figsize=(6, 3.6))
    width = 0.8 / len(results)
    for k, (run, rows) in enumerate(results.items()):
        share = [100 * np.mean([r["error"] > 30 for r in rows if r["start"] == s] or [0]) for s in starts]
        ax.bar(np.arange(len(starts)) + (k - (len(results) - 1) / 2) * width, share, width, label=run)
    ax.set_xticks(range(len(starts)), [str(s) for s in starts])
    ax.set_xlabel("the window's first frame")
    ax.set_ylabel("over 30 deg off (%)")
    ax.set_title(title, fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=12)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--walker-scale", type=float, default=0.5)
    parser.add_argument("--plates", action="store_true")
    parser.add_argument("--frames", type=int, default=45, help="frames per walk (15 Hz; at most 58)")
    parser.add_argument("--fold-windows", type=int, default=Settings().fold_windows)
    parser.add_argument("--synthetic", type=int, default=0, help="replay this many of posecal's own long walks "
                        "instead of the composites")
    parser.add_argument("--turn", type=float, default=0.0, help="--synthetic: the walker turns by this between "
                        "the stretches")
    parser.add_argument("--damage", default="all", help="--synthetic: estimator.damage kind, or none")
    parser.add_argument("--keep", type=Path, help="keep the walks and their segmented tracks here (and reuse them)")
    parser.add_argument("--plot", type=Path, help="PNG: the share over 30 deg by window, the two runs")
    args = parser.parse_args()
    if args.fold_windows < 1:
        parser.error("--fold-windows must be at least 1 (0 is the 'alone' run)")
    from service.cli.model import get_default_model

    if args.synthetic:
        walks = synthetic_walks(args.synthetic, args.seed, args.turn, args.damage)
        title = (f"seed {args.seed}: {args.synthetic} synthetic walks of 3 x 40 frames, turning {args.turn:g} deg, "
                 f"damage {args.damage}; fold_windows {args.fold_windows}")
    else:
        work = args.keep or Path(tempfile.mkdtemp(prefix="posecal-live-replay-"))
        work.mkdir(parents=True, exist_ok=True)
        walks = segmented_walks(work, args)
        title = (f"seed {args.seed}: {len(walks)} walks ({sum(len(t) for _, _, t in walks)} cameras, {args.frames} "
                 f"frames), walker scale {args.walker_scale:g}, {'plates' if args.plates else 'no plates'}; "
                 f"fold_windows {args.fold_windows}")
    model, settings = get_default_model(progress=True), Settings()
    results = {run: [] for run in RUNS}
    for i, truth, tracks in tqdm(walks, desc="walks (estimate)", file=sys.stderr):
        for run in RUNS:
            results[run] += replay(truth, tracks, model, settings, args.fold_windows if run == "earlier" else 0, i)
    print(f"\n{title}\n")
    print("| run | azimuth median / p90 (deg) | over 30 deg | of them folds | held on the earlier side "
          "| windows x cameras |")
    print("|---|---|---|---|---|---|")
    for run, rows in results.items():
        print(f"| {run} | {summary(rows)} |")
    before = {(r["walk"], r["start"], r["camera"]): r["error"] for r in results["alone"]}
    moved = [(k, before[k], r["error"]) for r in results["earlier"]
             if abs(r["error"] - before.get(k := (r["walk"], r["start"], r["camera"]), r["error"])) > 3]
    print(f"\nwindows x cameras moved more than 3 deg (walk, first frame, camera: alone -> earlier): {len(moved)}")
    for (w, s, c), a, b in moved:
        print(f"  walk {w} frame {s} {c}: {a:.1f} -> {b:.1f}")
    if args.plot:
        plot(args.plot, results, title)


if __name__ == "__main__":
    main()
