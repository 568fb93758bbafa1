"""The live path end to end on walkers composited into real footage, against ground truth.

``bench/eval_composite.py`` runs ``posecal estimate`` on each walk's videos: a
file, looked at whole. This runs what a live rig runs on the same walks (the
same seed draws the same walks): ``posecal serve`` on loopback, and per walk
one ``posecal capture`` agent per camera on the camera's video (its image of
the empty scene as ``--background-image`` when ``--plates``; the frames
numbered as recorded, so the cameras are synchronised by index), publishing
silhouettes over Zenoh while the service estimates windows (20 frames every
10) and calibrates the rig from them. Each walk is a rig of its own
(``walk<i>``). Then, from the REST API:

- every window's viewpoint per camera (``GET /v1/rigs/<rig>/estimates``:
  ``cameras``, the window's own, and ``smoothed``, over the windows so far)
  against the truth: azimuth and elevation errors, median / p90 over windows
  and cameras;
- every window's 2D joints per frame and camera divided by the walker's
  image height, and the phase;
- the live rig (``GET /v1/rigs/<rig>/calibration`` after the walk's last
  window): each camera's rotation to the reference camera against the
  truth's, and the rig from the last window's smoothed viewpoints;
- the windows estimated, and on how many walks the live rig was
  self-calibrated (the others: the viewpoints' rig, its notes say why);
- how many windows x cameras left frames out because the agent's track
  was on another person there until a look back moved it (``window.other_person``),
  and how many windows were estimated again because the move came after
  their first estimate (``window.revision``).

The agents' silhouettes on the same walks are measured against the exact
ones by ``eval_composite.py --segment-only`` (the live agent's path in
process).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_live_composite.py [--sequences 12] [--seed 5] \\
        [--walker-scale 0.5] [--plates] [--keep DIR] [--json FILE]

A walk is 45 frames (3 s) as in ``eval_composite.py``, where the walker
crosses the view: 3 windows per camera. The live rig measures postures on
``live_rig_frames`` frames per window (default 2) and needs 8 seen by two
cameras, which 3 windows do not give: the service runs with
``POSECAL_LIVE_RIG_FRAMES=4`` and ``POSECAL_LIVE_RIG_EVERY=1`` (set
``--rig-frames``), so the rig is calibrated from the 12 frames of the 3
windows; a live rig that runs for minutes rests on many more. The first
window holds the frames before the agent's first look back (docs/CAPTURE.md,
"Live, the agent looks back") and may miss a camera's first frames (the
agents start within a second of each other). All of it runs on this
machine's 2 cores: the agents (one per camera host in a real rig) and the
service.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _service_proc import ServiceProcess  # noqa: E402
from eval_composite import Optics, cell, composite_walks, score  # noqa: E402

from estimator.sequence import Sequence, read_sequence  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("azimuth", "elevation", "joints2d", "phase")


def run_walk(svc: ServiceProcess, rig: str, folder: Path, cams: list[str], timeout: float = 300.0) -> str:
    """One agent per camera on ``folder/<cam>.avi``; waits for them to end; returns their logs' last
    lines."""
    procs = []
    for cam in cams:
        cmd = [sys.executable, "-m", "service.cli", "capture", "--rig", rig, "--camera", cam,
               "--source", str(folder / f"{cam}.avi"), "--connect", svc.zenoh, "--stats-interval", "600"]
        plate = folder / f"{cam}.background.png"
        if plate.exists():
            cmd += ["--background-image", str(plate)]
        procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
                                      env={**os.environ, "PYTHONUNBUFFERED": "1"}))
    tails = []
    for cam, proc in zip(cams, procs):
        try:
            out, _ = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"agent {rig}/{cam} exited {proc.returncode}:\n{out[-2000:]}")
        tails.append(f"{cam}: " + (out.strip().splitlines() or [""])[-1])
    return "\n".join(tails)


def _settled(fetch, settle_s: float, timeout_s: float):
    """``fetch()`` once it has returned the same value for ``settle_s`` (or at ``timeout_s``)."""
    deadline, value, since = time.monotonic() + timeout_s, None, time.monotonic()
    while time.monotonic() < deadline:
        new = fetch()
        if new != value:
            value, since = new, time.monotonic()
        elif time.monotonic() - since > settle_s:
            break
        time.sleep(0.5)
    return value


def collect(svc: ServiceProcess, rig: str) -> tuple[list[dict], dict]:
    """The rig's windows once no new one has come for 3 s, and its calibration (or {}) once it has not
    changed for 8 s: the live rig is measured in a low-priority process and lags the windows."""
    def windows() -> list[dict]:
        r = svc.client.get(f"/v1/rigs/{rig}/estimates", params={"limit": 1000})
        return r.json()["estimates"] if r.status_code == 200 else []

    def calibration() -> dict:
        r = svc.client.get(f"/v1/rigs/{rig}/calibration")
        return r.json() if r.status_code == 200 else {}

    return _settled(windows, 3.0, 60.0) or [], _settled(calibration, 8.0, 120.0) or {}


def score_live(windows: list[dict], cal: dict, seq: Sequence) -> dict[str, list[float]]:
    """Errors of one walk's live results (module docstring)."""
    out: dict[str, list[float]] = {k: [] for k in (*KEYS, "smoothed_azimuth", "smoothed_elevation", "rig",
                                                   "rig_viewpoints")}
    for w in windows:
        for k, v in score({**w, "rig": None, "sync": None}, seq).items():
            if k in KEYS:
                out[k] += v
        smoothed = w.get("smoothed") or {}
        if smoothed:
            s = score({"cameras": smoothed, "frames": [], "rig": None}, seq)
            out["smoothed_azimuth"] += s["azimuth"]
            out["smoothed_elevation"] += s["elevation"]
    if windows:
        last = windows[-1]
        rig = cal.get("calibration") or {}  # a live estimate's "rig" is the rig's name
        views = last.get("smoothed") or last["cameras"]
        s = score({"cameras": views, "frames": [], "rig": rig}, seq)
        out["rig"] += s["rig"]
        out["rig_viewpoints"] += s["rig_viewpoints"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=12)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--walker-scale", type=float, default=1.0)
    parser.add_argument("--plates", action="store_true")
    parser.add_argument("--rig-frames", type=int, default=4,
                        help="frames per window whose postures the live rig measures (the service's "
                             "live_rig_frames, default 2 there): 8 are needed, from the 3 windows of a walk")
    parser.add_argument("--keep", type=Path, help="keep the videos, the service's files and the results here")
    parser.add_argument("--json", type=Path, help="write every walk's windows, calibration and errors here")
    parser.add_argument("--reuse", action="store_true",
                        help="the walks are in --keep DIR already (written by this script or by eval_composite.py "
                             "--keep with the same --seed, --walker-scale and --plates): read, not rendered again")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="posecal-live-composite-"))
    rows: dict[str, list[float]] = {}
    counts = {"windows": 0, "walks without a window": 0, "calibrated": 0, "self-calibrated": 0, "other person": 0,
              "frames on another person": 0, "revised": 0, "set aside": 0}
    dump = []
    if args.reuse and not args.keep:
        parser.error("--reuse reads the walks from --keep DIR")
    walks = ((i, read_sequence(work / f"walk{i}" / "exact"), None) for i in range(args.sequences)) if args.reuse \
        else composite_walks(work, sequences=args.sequences, seed=args.seed, walker_scale=args.walker_scale,
                             plates=args.plates, optics=Optics())
    os.environ.update(POSECAL_LIVE_RIG_FRAMES=str(args.rig_frames), POSECAL_LIVE_RIG_EVERY="1")
    with ServiceProcess(work / "service") as svc:
        for i, seq, _ in tqdm(walks, total=args.sequences, desc="walks", file=sys.stderr):
            rig = f"walk{i}"
            agents = run_walk(svc, rig, work / rig / "videos", list(seq.cameras))
            windows, cal = collect(svc, rig)
            counts["windows"] += len(windows)
            counts["walks without a window"] += not windows
            counts["calibrated"] += bool(cal)
            counts["self-calibrated"] += cal.get("source") == "self-calibration"
            others = [f for w in windows for f in (w["window"].get("other_person") or {}).values()]
            counts["other person"] += len(others)
            counts["frames on another person"] += sum(map(len, others))
            counts["revised"] += sum(w["window"].get("revision", 0) > 0 for w in windows)
            counts["set aside"] += sum(any("too few for a viewpoint" in n for n in c.get("notes", ()))
                                       for w in windows for c in w["cameras"].values())
            errors = score_live(windows, cal, seq)
            for k, v in errors.items():
                rows.setdefault(k, []).extend(v)
            dump.append({"walk": i, "cameras": list(seq.cameras), "agents": agents, "windows": windows,
                         "calibration": cal, "errors": errors})
    n_cams = sum(len(d["cameras"]) for d in dump)
    print(f"\n{args.sequences} walks ({n_cams} cameras, 45 frames at 15 Hz, walker scale {args.walker_scale:g}, "
          f"{'plates' if args.plates else 'no plates'}), seed {args.seed}: agents -> Zenoh -> `posecal serve`, "
          f"{counts['windows']} windows ({counts['walks without a window']} walks without one); live rig "
          f"calibrated on {counts['calibrated']} walks, self-calibrated on {counts['self-calibrated']}; "
          f"{counts['other person']} windows x cameras left {counts['frames on another person']} frames out, the "
          "agent's track on another person there (`window.other_person`); "
          f"{counts['revised']} windows estimated again after a later move said so (`window.revision`); "
          f"{counts['set aside']} windows x cameras set aside on too few frames (`EstimateConfig.min_frames`)\n")
    labels = [("azimuth error per window and camera (deg)", "azimuth"),
              ("elevation error per window and camera (deg)", "elevation"),
              ("smoothed azimuth error (deg)", "smoothed_azimuth"),
              ("smoothed elevation error (deg)", "smoothed_elevation"),
              ("phase error (cycles)", "phase"),
              ("2D joint error / image height", "joints2d"),
              ("live rig rotation error per camera (deg)", "rig"),
              ("the same, rotations from the smoothed viewpoints (deg)", "rig_viewpoints")]
    print("| median / p90 | live |\n|---|---|")
    for label, key in labels:
        print(f"| {label} | {cell(rows.get(key, []))} |")
    if args.json:
        args.json.write_text(json.dumps(dump, indent=1, default=float))
    if not args.keep:
        import shutil

        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
