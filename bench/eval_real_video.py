"""The capture segmenter on real footage (vtest.avi): bootstrap default vs the old warm-up.

Clips are crops of ``/work/shared/data/video/vtest.avi`` (480x360, 10 fps,
795 frames, outdoor, several pedestrians with shadows): ``lawn`` (nobody in
view for long stretches, walkers entering after the start) and ``path``
(walkers in view from frame 0, often several). Each clip is segmented with
DEFAULT settings the way the agent does a file (background bootstrapped from
frames sampled over the first seconds, then every frame from 0), and with the
old default (``background="warmup"``: MOG2 learned from the first 100 frames).

"Walker in view" / "nobody in view" come from offline masks: the difference to
the temporal median of the WHOLE video (max channel > 25 grey levels), shadow
pixels removed (ratio to the median in [0.4, 0.95], chromaticity distortion
< 0.1), opened (3 px) and closed (5 px), components >= 80 px. A clip frame is
"in view" with >= 150 such pixels in the crop, "empty" with < 10; frames in
between (a sliver at the border) are in neither set. Reference masks
(``tests/fixtures/vtest``, made by ``--make-fixtures`` from the same offline
masks and checked by eye) give IoU of the tracked walker.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_real_video.py [--montage docs/img/real_video_segment.png]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import cv2
import numpy as np

from capture.live import segment_recording
from capture.scene import iou
from capture.segment import SegmentSettings

VIDEO = Path("/work/shared/data/video/vtest.avi")
FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "vtest"
CLIPS = {"lawn": (80, 200, 320, 160), "path": (0, 80, 240, 160)}  # x, y, w, h in vtest
FPS = 10.0


def load_video(path: Path = VIDEO) -> np.ndarray:
    """All frames, (N, H, W, 3) uint8 BGR."""
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, image = cap.read()
        if not ok:
            break
        frames.append(image)
    cap.release()
    return np.stack(frames)


def offline_masks(video: np.ndarray, drop_shadows: bool = True) -> np.ndarray:
    """Foreground of every frame against the whole video's median (module docstring);
    ``drop_shadows=False`` keeps every changed pixel (for "nobody in view")."""
    median = np.median(video, axis=0).astype(np.float32)
    bb = (median ** 2).sum(axis=2) + 1.0
    close, opening = (cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (n, n)) for n in (5, 3))
    out = np.zeros(video.shape[:3], np.uint8)
    for k, image in enumerate(video):
        f = image.astype(np.float32)
        r = (f * median).sum(axis=2) / bb
        chroma = ((f - r[..., None] * median) ** 2).sum(axis=2) / bb
        shadow = (r >= 0.4) & (r <= 0.95) & (chroma < 0.01)
        fg = ((np.abs(f - median).max(axis=2) > 25) & ~(shadow & drop_shadows)).astype(np.uint8) * 255
        fg = cv2.morphologyEx(cv2.morphologyEx(fg, cv2.MORPH_OPEN, opening), cv2.MORPH_CLOSE, close)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
        keep = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= 80)
        out[k] = np.isin(labels, keep[keep > 0]).astype(np.uint8) * 255
    return out


def crop(a: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    x, y, w, h = box
    return a[:, y:y + h, x:x + w]


def segment(frames: np.ndarray, settings: SegmentSettings) -> tuple[list, float]:
    """Segment a clip as the agent segments a file (:func:`capture.live.segment_recording`: the
    background bootstrapped, the look back, the join test): (the tracked walker's ``Segmentation``
    per frame, None where there is none; ms per frame, the bootstrap included)."""
    t = time.perf_counter()
    found = segment_recording(frames, settings, FPS)
    return [None if s is None or s.box.empty else s for s in found], (time.perf_counter() - t) * 1e3 / len(frames)


def run(frames: np.ndarray, settings: SegmentSettings) -> tuple[list, float]:
    """:func:`segment` as full-frame masks (or None); ms per frame."""
    found, ms = segment(frames, settings)
    return [None if s is None else s.full_mask() for s in found], ms


def load_fixtures() -> list[dict]:
    """Reference masks: dicts with clip, frame, box (in the clip) and mask."""
    out = []
    for meta in sorted(FIXTURES.glob("*.json")):
        d = json.loads(meta.read_text())
        d["mask"] = cv2.imread(str(meta.with_suffix(".png")), cv2.IMREAD_GRAYSCALE)
        out.append(d)
    return out


def fixture_ious(clip: str, masks: list) -> list[float]:
    """IoU of the silhouette with each reference mask of ``clip``, inside its box."""
    out = []
    for d in load_fixtures():
        if d["clip"] != clip:
            continue
        x, y, w, h = d["box"]
        got = masks[d["frame"]]
        got = np.zeros((h, w), np.uint8) if got is None else got[y:y + h, x:x + w]
        out.append(iou(got, d["mask"]))
    return out


def make_fixtures(video: np.ndarray, offline: np.ndarray, changed: np.ndarray,
                  picks: dict[str, list[int]]) -> None:
    """Write one reference mask per (clip, frame), by GrabCut on the frame.

    Seeds: sure foreground = the offline mask's component of the person, eroded
    by 3 px; probable region = that component and the components of
    ``changed`` (no shadow test) touching it, dilated by 5 px (everything else
    is sure background); inside it, pixels
    more than 15 grey levels from the whole video's median are probably
    foreground. GrabCut's colour models then put the edge where the colours
    change, which neither threshold does: dark jeans on a grey path (which
    the offline shadow test takes for shadow) are kept, a shadow on the grass
    (same colour as the grass, darker) is not. Opened by 3 px (GrabCut leaks
    along thin lines into the background), holes filled, cropped to the
    box plus 6 px; overlays for checking by eye go to /tmp/vtest_fixtures
    (frame | reference).
    """
    FIXTURES.mkdir(parents=True, exist_ok=True)
    check = Path("/tmp/vtest_fixtures")
    check.mkdir(exist_ok=True)
    median = np.median(video, axis=0).astype(np.float32)
    for clip, frames in picks.items():
        box = CLIPS[clip]
        for k in frames:
            image = crop(video[k:k + 1], box)[0]
            m = crop(offline[k:k + 1], box)[0]
            n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
            person = cv2.compare(labels, 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])), cv2.CMP_EQ)
            n, labels = cv2.connectedComponents(crop(changed[k:k + 1], box)[0], connectivity=8)
            touching = np.unique(labels[(person > 0) & (labels > 0)])
            region = cv2.dilate(person | np.isin(labels, touching).astype(np.uint8) * 255,
                                np.ones((5, 5), np.uint8))
            far = np.abs(image.astype(np.float32) - crop(median[None], box)[0]).max(axis=2) > 15
            seeds = np.full(person.shape, cv2.GC_BGD, np.uint8)
            seeds[region > 0] = cv2.GC_PR_BGD
            seeds[(region > 0) & far] = cv2.GC_PR_FGD
            seeds[cv2.erode(person, np.ones((3, 3), np.uint8)) > 0] = cv2.GC_FGD
            cv2.grabCut(image, seeds, None, np.zeros((1, 65)), np.zeros((1, 65)), 8,
                        cv2.GC_INIT_WITH_MASK)
            ref = np.isin(seeds, (cv2.GC_FGD, cv2.GC_PR_FGD)).astype(np.uint8) * 255
            ref = cv2.morphologyEx(ref, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))  # 1-2 px leaks
            n, labels, stats, _ = cv2.connectedComponentsWithStats(ref, connectivity=8)
            best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
            ref = cv2.compare(labels, best, cv2.CMP_EQ)
            contours, _ = cv2.findContours(ref, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(ref, contours, -1, 255, -1)  # fill holes
            x, y, w, h = stats[best, :4]
            x0, y0 = max(0, x - 6), max(0, y - 6)
            x1, y1 = min(ref.shape[1], x + w + 6), min(ref.shape[0], y + h + 6)
            name = f"{clip}_{k:03d}"
            cv2.imwrite(str(FIXTURES / f"{name}.png"), ref[y0:y1, x0:x1])
            (FIXTURES / f"{name}.json").write_text(json.dumps(
                {"clip": clip, "clip_box": list(box), "frame": k,
                 "box": [int(x0), int(y0), int(x1 - x0), int(y1 - y0)],
                 "method": "grabcut (bench/eval_real_video.py --make-fixtures), checked by eye"}) + "\n")
            patch = image[y0:y1, x0:x1]
            over = patch.copy()
            over[ref[y0:y1, x0:x1] > 0] = (0, 0, 255)
            cv2.imwrite(str(check / f"{name}.png"),
                        cv2.resize(np.hstack([patch, cv2.addWeighted(patch, 0.5, over, 0.5, 0)]),
                                   None, fx=4, fy=4, interpolation=cv2.INTER_NEAREST))


def montage(path: Path, clips: dict, results: dict, frames: list[tuple[str, int]]) -> None:
    """Frames with the default's silhouette (red) and the old warm-up's (blue outline)."""
    tiles = []
    for clip, k in frames:
        image = clips[clip][k].copy()
        new, old = results[clip]["bootstrap (default)"][0][k], results[clip]["warmup"][0][k]
        if new is not None:
            image[new > 0] = (0.5 * image[new > 0] + (0, 0, 127)).astype(np.uint8)
        if old is not None:
            contours, _ = cv2.findContours(old, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(image, contours, -1, (255, 128, 0), 1)
        cv2.putText(image, f"{clip} {k}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
        tiles.append(cv2.resize(image, (320, 160)))
    while len(tiles) % 3:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + 3]) for i in range(0, len(tiles), 3)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack(rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--montage", type=Path, default=None)
    parser.add_argument("--make-fixtures", action="store_true")
    parser.add_argument("--core", type=int, default=0)
    args = parser.parse_args()
    os.sched_setaffinity(0, {args.core})
    cv2.setNumThreads(1)
    video = load_video()
    offline, changed = offline_masks(video), offline_masks(video, drop_shadows=False)
    clips = {name: crop(video, box) for name, box in CLIPS.items()}
    variants = {"bootstrap (default)": SegmentSettings(),
                "bootstrap, colour split off": SegmentSettings(colour_split=False),
                "warmup": SegmentSettings(background="warmup")}
    results = {clip: {name: run(frames, settings) for name, settings in variants.items()}
               for clip, frames in clips.items()}
    if args.make_fixtures:
        make_fixtures(video, offline, changed, {"lawn": [655, 665, 675], "path": [4, 162, 377, 401]})
    print(f"vtest.avi crops, {FPS:.0f} fps; load avg {os.getloadavg()[0]:.2f}\n")
    print("| clip | background | in view: silhouette | nobody: silhouette | IoU reference (n) | ms/frame |")
    print("|---|---|---|---|---|---|")
    for clip, frames in clips.items():
        inview = (crop(offline, CLIPS[clip]) > 0).reshape(len(frames), -1).sum(axis=1) >= 150
        empty = (crop(changed, CLIPS[clip]) > 0).reshape(len(frames), -1).sum(axis=1) < 10
        for mode, (masks, ms) in results[clip].items():
            got = np.array([m is not None for m in masks])
            ious = fixture_ious(clip, masks)
            ref = f"{np.mean(ious):.3f} (min {np.min(ious):.3f}, {len(ious)})" if ious else "-"
            print(f"| {clip} | {mode} | "
                  f"{got[inview].mean():.1%} of {inview.sum()} | {got[empty].mean():.1%} of {empty.sum()} | "
                  f"{ref} | {ms:.2f} |")
    if args.montage:
        montage(args.montage, clips, results,
                [("path", 0), ("path", 5), ("path", 300), ("lawn", 20), ("lawn", 560), ("lawn", 680)])


if __name__ == "__main__":
    main()
