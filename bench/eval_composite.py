"""The whole path on a walker composited into real footage, against ground truth.

``vtest.avi`` is real footage but has no truth, and posecal's renders have
truth but nothing real in them. This evaluation puts the one into the other:
a walker of random body (stature 1.5-1.95 m, proportions +-10 %) driven by
one of the two CMU walks (motion not the model's) is rendered for 2-4
synchronised cameras (5-12 m away, mounted 0.5-3.5 m above the ground,
640x480, 15 Hz), dressed (hair, skin,
shirt, trousers and shoes in colours drawn from everyday clothing, shaded
like a cylinder, edges feathered by a pixel), composited over real frames of
``vtest.avi`` (scaled to 640x480; each camera its own stretch of the video,
some mirrored: real people walking past with their shadows, real daylight
changes, real compression), given a ground shadow on every other walk (the
silhouette's ground shadow, :func:`estimator.damage.shadow`'s geometry,
darkening the real background by 25-50 % with a soft edge), taken through a
camera's optics (:class:`Optics`: since session 46 the walk is rendered at 5
instants per frame and each frame averages the 3 the shutter is open for,
40 ms, so a swinging foot or hand smears as it does on a real 15 Hz camera;
then the lens's blur, 0.7 px, and the sensor's noise, 2 grey levels;
``--shutter 0 --defocus 0 --noise 0`` gives the sharp single instant of
before), and written as MJPG videos, one per camera. Then ``posecal estimate FOLDER`` runs on the
folder exactly as a user runs it, with no flags: the agent's segmenter
(background bootstrapped with the walker in view), the tracker, the
synchronisation from the walk, the viewpoints, the phase, mNBP postures and
the rig, then the videos segmented again with the model's feedback (§7.1) and
estimated again; ``--feedback off`` shows the first estimate. The same walks' exact silhouettes (a sequence folder, no
background, no segmenter) run the same command for comparison.

Reported against the truth, for both inputs: each camera's azimuth and
elevation error; the phase (frames within 1/20 of a cycle); the rig
(geodesic error of each camera's rotation to the reference camera,
``rig.cameras``); the 2D joints (``frames[].joints2d``) per frame and camera
divided by the walker's image height; the person's 3D posture
(``frames[].person_joints3d`` after a similarity alignment, divided by the
stature); the synchronisation offsets found (the truth is 0); and the
segmenter's silhouettes against the exact ones (IoU per frame, the same
segmenter settings as the command's).

The walker is rendered 190-300 px tall, larger than anyone in ``vtest.avi``
(55-140 px at 640x480); ``--walker-scale 0.5`` makes it one of the crowd
(100-150 px: the focal length halved, the silhouettes and 2D truth scaled
about the image centre), where which person the segmenter follows matters
(docs/ROBUSTNESS.md, "People of the walker's size").

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_composite.py [--sequences 8] [--seed 5] \
        [--plot docs/img/composite_errors.png] [--montage docs/img/composite_frames.jpg] [--keep DIR] \
        [--walker-scale 0.5] [--plates] [--shutter 0.6] [--defocus 0.7] [--noise 2] \
        [--segment-only [--segment KEY=VALUE ...] [--per-camera]]

``--segment-only`` scores only the segmenter's silhouettes (the file's path and
the live agent's), ``--segment KEY=VALUE`` changes a ``SegmentSettings`` field
for both (``--segment track_colour=0``: before session 59), ``--per-camera``
prints each camera's figures.

``--plates`` puts an image of the empty scene beside each video (the median of
the whole of ``vtest.avi``, mirrored as the camera's stretch), which
``posecal estimate`` takes as the background: a walker who stays in the same
place in the image (walking towards or away from a camera) is otherwise in
the background learned from the clip (docs/ROBUSTNESS.md, "A walker held in
the background").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_estimate import az_err, ph_err  # noqa: E402
from eval_mnbp import MOCAP, body  # noqa: E402
from eval_real_video import VIDEO, load_video  # noqa: E402
from capture.live import segment_recording  # noqa: E402
from capture.refine import plate_for, segment_clip  # noqa: E402
from capture.scene import iou  # noqa: E402
from capture.segment import SegmentSettings  # noqa: E402
from estimator._selfcal_core import geodesic_deg  # noqa: E402
from estimator.damage import shadow  # noqa: E402
from estimator.joints import JOINT_INDEX  # noqa: E402
from estimator.mocap import read_motion  # noqa: E402
from estimator.rig import aligned_error, rotations_from_viewpoints  # noqa: E402
from estimator.sequence import Sequence, write_sequence  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIZE = (640, 480)
FPS = 15.0
# Everyday colours (BGR): skin, hair, shirts, trousers, shoes.
SKIN = [(160, 180, 225), (120, 150, 200), (80, 110, 160), (60, 80, 120)]
HAIR = [(20, 20, 25), (30, 45, 70), (60, 100, 150), (140, 140, 145)]
TROUSERS = [(90, 50, 30), (35, 35, 35), (120, 160, 180), (110, 110, 110), (60, 60, 50)]
SHOES = [(25, 25, 25), (200, 200, 200), (40, 50, 70)]


@dataclass(frozen=True)
class Outfit:
    """The walker's colours (BGR) and how much its shadow darkens the ground (1 = no shadow)."""

    skin: np.ndarray
    hair: np.ndarray
    shirt: np.ndarray
    trousers: np.ndarray
    shoes: np.ndarray
    shadow_gain: float
    shadow_seed: int  # the shadow's length and slant (the same in every frame: the sun does not move)

    @classmethod
    def random(cls, rng: np.random.Generator, *, shadow: bool) -> "Outfit":
        pick = lambda table: np.array(table[rng.integers(len(table))], np.float32)  # noqa: E731
        hsv = np.array([[[rng.integers(0, 180), rng.integers(0, 200), rng.integers(40, 240)]]], np.uint8)
        shirt = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0].astype(np.float32)
        gain = float(rng.uniform(0.5, 0.75)) if shadow else 1.0
        return cls(pick(SKIN), pick(HAIR), shirt, pick(TROUSERS), pick(SHOES), gain, int(rng.integers(1 << 30)))


def elevations(rng: np.random.Generator, n: int, stature: float, distance: float) -> tuple[float, ...]:
    """Camera elevations over the walker's centroid (the 13 joints' mean, about half the stature up)
    for cameras mounted 0.5-3.5 m above the ground at ``distance``: none below the floor."""
    height = rng.uniform(0.5, 3.5, n)
    return tuple(float(e) for e in np.degrees(np.arcsin((height - 0.5 * stature) / distance)))


def dress(mask: np.ndarray, joints2d: np.ndarray, outfit: Outfit) -> tuple[np.ndarray, np.ndarray]:
    """The walker's colour image (H, W, 3 float32) and feathered alpha (H, W) from its exact mask:
    bands between the projected joints (hair and skin above the shoulders, shirt to the hips,
    trousers to the ankles, shoes below), shaded as a cylinder and darker towards the feet."""
    h, w = mask.shape
    j = np.asarray(joints2d, float)
    v = np.arange(h, dtype=np.float32)[:, None]
    shoulder = j[[JOINT_INDEX["left_shoulder"], JOINT_INDEX["right_shoulder"]], 1].mean()
    hip = j[[JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]], 1].mean()
    ankle = j[[JOINT_INDEX["left_ankle"], JOINT_INDEX["right_ankle"]], 1].mean()
    head = j[JOINT_INDEX["head"], 1]
    ys, xs = np.nonzero(mask)
    top = ys.min() if ys.size else 0
    colour = np.empty((h, 1, 3), np.float32)
    bands = [(top + 0.4 * (head - top), outfit.hair), (shoulder - 0.1 * (shoulder - head), outfit.skin),
             (hip, outfit.shirt), (ankle + 0.02 * (ankle - top), outfit.trousers), (np.inf, outfit.shoes)]
    lower = -np.inf
    for upper, c in bands:
        colour[(v[:, 0] >= lower) & (v[:, 0] < upper)] = c
        lower = upper
    image = np.broadcast_to(colour, (h, w, 3)).copy()
    if xs.size:
        cx, half = xs.mean(), max(1.0, 0.5 * (xs.max() - xs.min()))
        u = (np.arange(w, dtype=np.float32) - cx) / half
        across = 1.0 - 0.25 * np.clip(u, -1, 1) ** 2
        down = 1.0 - 0.15 * np.clip((v - top) / max(1, ys.max() - top), 0, 1)
        shade = across[None, :] * down
        image *= shade[..., None]
    alpha = cv2.GaussianBlur((mask > 0).astype(np.float32), (3, 3), 0.8)
    return image, alpha


def composite(background: np.ndarray, mask: np.ndarray, joints2d: np.ndarray, outfit: Outfit) -> np.ndarray:
    """One instant of a camera frame (float32 BGR): the real ``background`` (uint8 BGR), the walker's
    shadow darkening it, the dressed walker over it."""
    frame = background.astype(np.float32)
    if outfit.shadow_gain < 1.0 and mask.any():
        cast = shadow(mask, np.random.default_rng(outfit.shadow_seed))
        cast = cv2.GaussianBlur(((cast > 0) & (mask == 0)).astype(np.float32), (5, 5), 1.5)
        frame *= (1.0 - (1.0 - outfit.shadow_gain) * cast)[..., None]
    image, alpha = dress(mask, joints2d, outfit)
    return frame * (1.0 - alpha[..., None]) + image * alpha[..., None]


SUBFRAMES = 5  # instants rendered per frame when the shutter is open for a while


@dataclass(frozen=True)
class Optics:
    """What a real camera adds to the scene in front of it.

    ``shutter``: the share of the frame interval the shutter is open; the
    frame is the scene averaged over it, so a swinging foot or hand is a
    smear (a 15 Hz camera indoors exposes 30-66 ms: 0.45-1.0); 0 renders
    one instant, as this script did before session 46. ``defocus_px``: the
    lens's blur (Gaussian sigma, pixels). ``noise``: the sensor's noise
    (Gaussian sigma, grey levels), before the MJPG compression.
    """

    shutter: float = 0.6
    defocus_px: float = 0.7
    noise: float = 2.0

    @property
    def instants(self) -> np.ndarray:
        """Offsets (in sub-frames of :data:`SUBFRAMES` per frame) of the instants rendered in one frame:
        the odd number nearest ``shutter * SUBFRAMES``, centred on the frame's time."""
        n = min(2 * int(np.floor(self.shutter * SUBFRAMES / 2)) + 1, SUBFRAMES) if self.shutter > 0 else 1
        return np.arange(n) - n // 2


def one_instant(seq: Sequence) -> tuple[dict[str, list[list]], list[list[dict]]]:
    """``seq``'s own silhouettes and truth frames as :func:`render_walk`'s instants: one per frame."""
    return {c: [[m] for m in seq.silhouettes[c]] for c in seq.cameras}, [[f] for f in seq.truth["frames"]]


def render_walk(spec: SynthSpec, motion, optics: Optics, walker_scale: float = 1.0
                ) -> tuple[Sequence, dict[str, list[list]], list[list[dict]]]:
    """The walk at ``spec.fps`` (silhouettes and truth at each frame's mid-exposure; :func:`scaled` by
    ``walker_scale``) and, per camera and frame, the masks of the instants the shutter is open, with
    each frame's instants' truth frames."""
    offsets = optics.instants
    if len(offsets) == 1:
        seq = scaled(synthesize(spec, motion=motion), walker_scale)
        return seq, *one_instant(seq)
    fast = scaled(synthesize(dataclasses.replace(spec, n_frames=spec.n_frames * SUBFRAMES, fps=spec.fps * SUBFRAMES),
                             motion=motion), walker_scale)
    mid = SUBFRAMES // 2 + SUBFRAMES * np.arange(spec.n_frames)
    instants = mid[:, None] + offsets[None, :]
    frames = [dict(fast.truth["frames"][k], index=i) for i, k in enumerate(mid)]
    seq = dataclasses.replace(fast, fps=spec.fps, silhouettes={c: [fast.silhouettes[c][k] for k in mid]
                                                              for c in fast.cameras},
                              truth=dict(fast.truth, frames=frames))
    masks = {c: [[fast.silhouettes[c][k] for k in row] for row in instants] for c in fast.cameras}
    return seq, masks, [[fast.truth["frames"][k] for k in row] for row in instants]


def exposed(background: np.ndarray, masks: list, truth_frames: list[dict], cam: str, outfit: Outfit,
            optics: Optics, rng: np.random.Generator) -> np.ndarray:
    """One camera frame as the camera takes it (uint8 BGR): the composite averaged over the instants the
    shutter is open (motion blur), blurred by the lens, with the sensor's noise."""
    empty = np.zeros(background.shape[:2], np.uint8)
    frame = np.mean([composite(background, empty if m is None else m, f["joints2d"][cam], outfit)
                     for m, f in zip(masks, truth_frames)], axis=0)
    if optics.defocus_px > 0:
        frame = cv2.GaussianBlur(frame, (0, 0), optics.defocus_px)
    if optics.noise > 0:
        frame = frame + rng.normal(0.0, optics.noise, frame.shape).astype(np.float32)
    return np.clip(frame, 0, 255).astype(np.uint8)


def backgrounds(video: np.ndarray, n_frames: int, rng: np.random.Generator) -> tuple[np.ndarray, bool]:
    """A stretch of ``n_frames`` real frames at a random start, scaled to 640x480, mirrored half the time
    (and whether it was)."""
    start = int(rng.integers(0, len(video) - n_frames))
    clip = np.stack([cv2.resize(f, SIZE, interpolation=cv2.INTER_LINEAR) for f in video[start:start + n_frames]])
    mirrored = bool(rng.random() < 0.5)
    return (clip[:, :, ::-1] if mirrored else clip), mirrored


def empty_scene(video: np.ndarray) -> np.ndarray:
    """The scene without its walkers, as a user would photograph it: the temporal median of every
    third frame of the whole video, scaled to 640x480."""
    return np.median(np.stack([cv2.resize(f, SIZE, interpolation=cv2.INTER_LINEAR) for f in video[::3]]),
                     axis=0).astype(np.uint8)


def scaled(seq: Sequence, k: float) -> Sequence:
    """``seq`` seen through ``k`` times the focal length: every silhouette and 2D joint scaled by ``k``
    about the image centre (silhouettes area-averaged, then thresholded at half), so the walker is ``k``
    times as tall among the same real people; viewpoints and 3D truth unchanged."""
    if k == 1.0:
        return seq
    w, h = SIZE
    small = (round(w * k), round(h * k))
    x0, y0 = (w - small[0]) // 2, (h - small[1]) // 2
    sils = {}
    for cam, frames in seq.silhouettes.items():
        sils[cam] = []
        for m in frames:
            if m is not None:
                canvas = np.zeros((h, w), np.float32)
                canvas[y0:y0 + small[1], x0:x0 + small[0]] = cv2.resize((m > 0).astype(np.float32), small,
                                                                         interpolation=cv2.INTER_AREA)
                m = np.where(canvas >= 0.5, 255, 0).astype(np.uint8)
            sils[cam].append(m)
    centre = np.array([x0, y0], float) + 0.5 * (k - 1.0)  # pixel centres under the area resize
    truth = json.loads(json.dumps(seq.truth))
    for frame in truth["frames"]:
        frame["joints2d"] = {c: (np.asarray(j, float) * k + centre).tolist() for c, j in frame["joints2d"].items()}
    for cam in truth["cameras"].values():
        cam["focal_px"] = cam["focal_px"] * k
    return dataclasses.replace(seq, silhouettes=sils, truth=truth)


def write_videos(folder: Path, seq: Sequence, video: np.ndarray, rng: np.random.Generator, *, cast_shadow: bool,
                 plate: np.ndarray | None = None, masks: dict[str, list[list]] | None = None,
                 instants: list[list[dict]] | None = None, optics: Optics = Optics(0.0, 0.0, 0.0)) -> Outfit:
    """Each camera's composite as ``<camera>.avi`` (MJPG, 15 fps), and ``plate`` (:func:`empty_scene`)
    as ``<camera>.background.png``, mirrored as the camera's stretch, when given; returns the outfit.

    ``masks`` and ``instants`` (:func:`render_walk`) are each frame's masks and truth frames over the
    shutter's opening (default: ``seq``'s own, one instant), taken through ``optics`` (:func:`exposed`;
    default: none)."""
    folder.mkdir(parents=True, exist_ok=True)
    outfit = Outfit.random(rng, shadow=cast_shadow)
    if masks is None:
        masks, instants = one_instant(seq)
    for cam in seq.cameras:
        bg, mirrored = backgrounds(video, len(seq.silhouettes[cam]), rng)
        if plate is not None:
            cv2.imwrite(str(folder / f"{cam}.background.png"), np.ascontiguousarray(plate[:, ::-1] if mirrored
                                                                                   else plate))
        writer = cv2.VideoWriter(str(folder / f"{cam}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), FPS, SIZE)
        noise = np.random.default_rng([int(outfit.shadow_seed), len(cam), ord(cam[-1])])
        for k in range(len(seq.silhouettes[cam])):
            writer.write(exposed(bg[k], masks[cam][k], instants[k], cam, outfit, optics, noise))
        writer.release()
    return outfit


def estimate(folder: Path, out: Path, *flags: str) -> dict:
    """``posecal estimate FOLDER --out OUT [flags]``, as a user runs it."""
    cmd = [sys.executable, "-m", "service.cli", "estimate", str(folder), "--out", str(out), *flags]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(out.read_text())


def score(result: dict, seq: Sequence) -> dict[str, list[float]]:
    """Errors of one result against the sequence's truth (see the module docstring)."""
    truth = seq.truth
    cams = seq.cameras
    out: dict[str, list[float]] = {k: [] for k in ("azimuth", "elevation", "phase", "rig", "rig_viewpoints",
                                                   "joints2d", "person3d", "sync")}
    if "error" in result:
        return out
    for c in cams:
        est, tc = result["cameras"].get(c, {}), truth["cameras"][c]
        if est.get("azimuth_deg") is None:
            out["azimuth"].append(np.nan)
            out["elevation"].append(np.nan)
            continue
        out["azimuth"].append(float(az_err(est["azimuth_deg"], tc["azimuth_deg"])))
        out["elevation"].append(abs(est["elevation_deg"] - tc["elevation_deg"]))
    # Frame i of a synchronised result is at the earliest camera's start + i / fps on the reference's
    # clock; every camera was really started with the reference, so that is the truth's frame index.
    shift = min(((result.get("sync") or {}).get("cameras") or {"_": {"offset_s": 0.0}}).values(),
                key=lambda s: s["offset_s"] if s.get("offset_s") is not None else np.inf)["offset_s"] or 0.0
    frames = {f["index"] + round(shift * FPS): f for f in result["frames"]}
    for k, tf in enumerate(truth["frames"]):
        f = frames.get(k)
        if f is not None and f.get("phase") is not None and not f.get("predicted"):
            out["phase"].append(float(ph_err(f["phase"], tf["phase"])))
        heights = {c: _image_height(seq.silhouettes[c][k]) for c in cams}
        for c, j in ((f or {}).get("joints2d") or {}).items():
            e = np.linalg.norm(np.asarray(j, float) - np.asarray(tf["joints2d"][c], float), axis=-1)
            out["joints2d"] += list(e / heights[c])
    rig = result.get("rig") or {}
    if rig.get("cameras"):
        ref = rig["reference"]
        order = [ref] + [c for c in cams if c != ref]
        true_rot = rotations_from_viewpoints([(truth["cameras"][c]["azimuth_deg"], truth["cameras"][c]["elevation_deg"])
                                              for c in order])
        seen = [result["cameras"].get(c, {}) for c in order]
        from_views = rotations_from_viewpoints([(np.nan, np.nan) if v.get("azimuth_deg") is None
                                                else (v["azimuth_deg"], v["elevation_deg"]) for v in seen])
        for c, t, v in zip(order[1:], true_rot[1:], from_views[1:]):
            r = rig["cameras"].get(c, {}).get("rotation")
            out["rig"].append(np.nan if r is None else float(geodesic_deg(np.array(r), t)))
            out["rig_viewpoints"].append(float(geodesic_deg(v, t)) if np.isfinite(v).all() else np.nan)
    idx = [k for k, f in frames.items() if f.get("person_joints3d") is not None and 0 <= k < len(truth["frames"])]
    if idx:
        est3d = np.array([[[np.nan] * 3 if q is None else q for q in frames[k]["person_joints3d"]] for k in idx],
                         float)
        true3d = np.array([truth["frames"][k]["joints3d"] for k in idx], float)
        out["person3d"] += list(aligned_error(est3d, true3d) / truth["body"]["height"])
    sync = result.get("sync") or {}
    for c, s in (sync.get("cameras") or {}).items():
        if c != sync.get("reference") and s.get("offset_frames") is not None:
            out["sync"].append(abs(float(s["offset_frames"])))
    return out


def _image_height(sil: np.ndarray | None) -> float:
    """The walker's height in the exact silhouette (pixels; NaN when out of view)."""
    if sil is None:
        return np.nan
    rows = np.nonzero(sil.any(axis=1))[0]
    return float(rows[-1] - rows[0] + 1) if rows.size else np.nan


def segmentation_iou(segs: list, seq: Sequence, cam: str) -> list[float]:
    """IoU per frame of the command's segmenter's output ``segs`` (:func:`capture.refine.segment_clip` of the
    frames as decoded, default settings) with the exact mask."""
    out = []
    for s, sil in zip(segs, seq.silhouettes[cam]):
        if sil is None or not sil.any():
            continue
        out.append(0.0 if s is None else iou(s.full_mask(), sil))
    return out


def live_segments(frames: np.ndarray, plate: np.ndarray | None, settings: SegmentSettings = SegmentSettings()) -> list:
    """The frames segmented as a live agent segments a recording (:func:`capture.live.segment_recording`:
    no look ahead; the background bootstrapped from frames sampled over the start, or ``plate``)."""
    return segment_recording(frames, settings, FPS, plate)


def segment_settings(pairs: list[str]) -> SegmentSettings:
    """``SegmentSettings`` with ``KEY=VALUE`` overrides (``--segment``); exits with code 2 on a bad one."""
    try:
        if bad := [p for p in pairs if "=" not in p]:
            raise ValueError(f"expected KEY=VALUE, got {', '.join(bad)}")
        fields = dict(p.split("=", 1) for p in pairs)
        unknown = sorted(set(fields) - set(SegmentSettings.model_fields))
        if unknown:
            raise ValueError(f"no such setting: {', '.join(unknown)}")
        return SegmentSettings(**fields)
    except ValueError as e:  # pydantic's ValidationError, or a pair without '='
        print(f"eval_composite.py: error: --segment {' '.join(pairs)}: {e}", file=sys.stderr)
        raise SystemExit(2) from None


def iou_line(what: str, ious: list[float]) -> str:
    return (f"{what}: IoU median {np.median(ious):.3f}, mean {np.mean(ious):.3f}, p10 {np.percentile(ious, 10):.3f}, "
            f"below 0.5 in {100 * np.mean(np.array(ious) < 0.5):.1f} % of {len(ious)} frames")


def cell(values: list[float]) -> str:
    """``median / p90`` of the finite values, and how many are missing."""
    v = np.asarray(values, float)
    ok = v[np.isfinite(v)]
    if not ok.size:
        return "-"
    missing = f" ({v.size - ok.size} of {v.size} missing)" if ok.size < v.size else ""
    return f"{np.median(ok):.3g} / {np.percentile(ok, 90):.3g}{missing}"


def composite_walks(work: Path, *, sequences: int, seed: int, frames: int = 45, walker_scale: float = 1.0,
                    plates: bool = False, optics: Optics = Optics()) -> Iterator[tuple[int, Sequence, Outfit]]:
    """The walks of one ``seed`` (module docstring), each written as ``work/walk<i>/videos`` (the
    composites) and ``work/walk<i>/exact`` (the exact silhouettes, a sequence folder): yields the
    walk's number, its sequence (the truth) and its outfit as each is written."""
    video = load_video(VIDEO)
    plate = empty_scene(video) if plates else None
    motions = [read_motion(MOCAP / "16_15.bvh"), read_motion(MOCAP / "07_05.amc")]
    rng = np.random.default_rng(seed)
    for i in range(sequences):
        n, shape, distance = int(rng.integers(2, 5)), body(rng), float(rng.uniform(5.0, 12.0))
        spec = SynthSpec(n_cameras=n, n_frames=frames, fps=FPS, seed=1000 * seed + i, shape=shape,
                         distance=distance, elevations=elevations(rng, n, shape.height, distance), image_size=SIZE)
        seq, masks, instants = render_walk(spec, motions[i % 2], optics, walker_scale)
        outfit = write_videos(work / f"walk{i}" / "videos", seq, video, np.random.default_rng([seed, i]),
                              cast_shadow=i % 2 == 1, plate=plate, masks=masks, instants=instants, optics=optics)
        write_sequence(work / f"walk{i}" / "exact", seq)
        yield i, seq, outfit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=8)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--frames", type=int, default=45, help="frames per walk (15 Hz; default 45 = 3 s)")
    parser.add_argument("--plot", type=Path, help="PNG: error distributions, composite against exact silhouettes")
    parser.add_argument("--montage", type=Path,
                        help="image (.jpg, .png): one frame per camera of the first walk over its segmentation")
    parser.add_argument("--keep", type=Path, help="keep the videos and results in this folder")
    parser.add_argument("--walker-scale", type=float, default=1.0,
                        help="the walker this many times as tall (the focal length scaled; 0.5: 100-150 px, "
                             "the size of the real people around them)")
    parser.add_argument("--plates", action="store_true",
                        help="give each video an image of the empty scene (<camera>.background.png), as a user "
                             "who photographed it would; the command uses it as the background")
    parser.add_argument("--shutter", type=float, default=Optics.shutter,
                        help=f"share of the frame interval the shutter is open: motion blur (default "
                             f"{Optics.shutter}; 0: one instant per frame, as before session 46)")
    parser.add_argument("--defocus", type=float, default=Optics.defocus_px,
                        help=f"the lens's blur, Gaussian sigma in pixels (default {Optics.defocus_px})")
    parser.add_argument("--segment-only", action="store_true",
                        help="only the segmenter's silhouettes (the file's path and the live agent's) against the "
                             "exact ones: no `posecal estimate` runs")
    parser.add_argument("--noise", type=float, default=Optics.noise,
                        help=f"the sensor's noise, sigma in grey levels (default {Optics.noise})")
    parser.add_argument("--segment", action="append", default=[], metavar="KEY=VALUE",
                        help="with --segment-only: a SegmentSettings field for both paths (repeat; e.g. "
                             "track_colour=0)")
    parser.add_argument("--per-camera", action="store_true",
                        help="print each camera's mean IoU and share under 0.5, the file's path and the live one")
    args = parser.parse_args()
    if args.segment and not args.segment_only:
        parser.error("--segment needs --segment-only (`posecal estimate` runs with its defaults)")
    settings = segment_settings(args.segment)
    optics = Optics(args.shutter, args.defocus, args.noise)
    runs = [("videos, no flags", "videos", ()), ("videos, --feedback off", "videos", ("--feedback", "off")),
            ("videos, --sync off", "videos", ("--sync", "off")), ("exact silhouettes", "exact", ())]
    rows: dict[str, dict[str, list[float]]] = {name: {} for name, _, _ in runs}
    ious, live_ious, failures, shadows, n_cams = [], [], [], 0, 0
    montage: list[tuple[np.ndarray, np.ndarray]] = []  # the first walk's middle frame and silhouette, per camera
    work = args.keep or Path(tempfile.mkdtemp(prefix="posecal-composite-"))
    walks = composite_walks(work, sequences=args.sequences, seed=args.seed, frames=args.frames,
                            walker_scale=args.walker_scale, plates=args.plates, optics=optics)
    for i, seq, outfit in tqdm(walks, total=args.sequences, desc="walks", file=sys.stderr):
        videos = work / f"walk{i}" / "videos"
        shadows += outfit.shadow_gain < 1.0
        n_cams += len(seq.cameras)
        for name, kind, flags in [] if args.segment_only else runs:
            result = estimate(work / f"walk{i}" / kind, work / f"walk{i}" / f"{kind}{'-'.join(flags)}.json", *flags)
            if "error" in result:
                failures.append(f"walk {i} ({name}): {result['error']}")
            for k, v in score(result, seq).items():
                rows[name].setdefault(k, []).extend(v)
        for cam in seq.cameras:
            frames, plate_image = load_video(videos / f"{cam}.avi"), plate_for(videos / f"{cam}.avi")
            segs, _ = segment_clip(lambda: list(frames), settings, fps=FPS, plate=plate_image)
            ious.extend(file_ious := segmentation_iou(segs, seq, cam))
            live_ious.extend(cam_ious := segmentation_iou(live_segments(frames, plate_image, settings), seq, cam))
            if args.per_camera and file_ious:
                tqdm.write(f"walk {i} {cam}: IoU mean / under 0.5, file {np.mean(file_ious):.3f} / "
                           f"{np.mean(np.array(file_ious) < 0.5):.1%}, live {np.mean(cam_ious):.3f} / "
                           f"{np.mean(np.array(cam_ious) < 0.5):.1%}", file=sys.stdout)
            if i == 0:
                mid = len(frames) // 2
                montage.append((frames[mid], segs[mid].full_mask() if segs[mid] is not None
                                else np.zeros(frames.shape[1:3], np.uint8)))
    print(f"\n{args.sequences} walks ({n_cams} cameras, {args.frames} frames at 15 Hz, CMU motion, random "
          f"bodies; {shadows} with a ground shadow) composited over vtest.avi through a camera's optics (shutter "
          f"{optics.shutter:g} of the frame interval, lens blur {optics.defocus_px:g} px, noise {optics.noise:g} grey "
          f"levels); `posecal estimate FOLDER`, no flags"
          + (f"; segmenter settings {' '.join(args.segment)}" if args.segment else "") + "\n")
    print(iou_line("segmenter against the exact silhouettes (the file's path, `segment_clip`)", ious))
    print(iou_line("... live, as an agent segments (`capture.live.segment_recording`)", live_ious) + "\n")
    if not args.segment_only:
        report(rows, failures)
        if args.plot:
            plot(args.plot, rows)
    if args.montage and montage:
        write_montage(args.montage, montage)
    if not args.keep:
        import shutil

        shutil.rmtree(work, ignore_errors=True)


def report(rows: dict[str, dict[str, list[float]]], failures: list[str]) -> None:
    """The table of errors per input (median / p90), and the walks that failed."""
    measures = [("azimuth error (deg)", "azimuth"), ("elevation error (deg)", "elevation"),
                ("phase error (cycles)", "phase"), ("rig rotation error per camera (deg)", "rig"),
                ("the same, rotations from the viewpoints (deg)", "rig_viewpoints"),
                ("2D joint error / image height", "joints2d"),
                ("person 3D error / stature", "person3d"),
                ("sync offset found, cameras but the reference (frames; truth 0)", "sync")]
    print("| median / p90 | " + " | ".join(rows) + " |\n|---|" + "---|" * len(rows))
    for label, key in measures:
        print(f"| {label} | " + " | ".join(cell(data.get(key, [])) for data in rows.values()) + " |")
    within = [np.mean(np.asarray(data.get("phase", []), float) <= 0.05) for data in rows.values()]
    print("| phase within 1/20 of a cycle | " + " | ".join(f"{100 * w:.1f} %" for w in within) + " |\n")
    if failures:
        print("failed:\n" + "\n".join(f"  {f}" for f in failures))


def plot(path: Path, rows: dict[str, dict[str, list[float]]]) -> None:
    """Cumulative distributions of the azimuth, rig and 2D joint errors, both inputs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("azimuth", "azimuth error (deg)"), ("rig", "rig rotation error (deg)"),
            ("joints2d", "2D joint error / image height"), ("phase", "phase error (cycles)")]
    fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 3.4))
    for ax, (key, label) in zip(axes, keys):
        right = 0.0
        for (name, data), style in zip(rows.items(), ("-", "--", ":", "-.")):
            v = np.sort(np.asarray(data.get(key, []), float))
            v = v[np.isfinite(v)]
            if v.size:
                ax.plot(v, np.arange(1, v.size + 1) / v.size, style, label=name)
                right = max(right, float(np.percentile(v, 97)))
        if right > 0:  # the few gross errors (a camera on the wrong side) would squash the rest
            ax.set_xlim(0, 1.2 * right)
            label += " (to p97)"
        ax.set_xlabel(label)
        ax.set_ylabel("fraction")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("posecal estimate on walkers composited into vtest.avi, against the same walks' exact silhouettes")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)


def write_montage(path: Path, cameras: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """A frame per camera (top row) over the segmenter's silhouette in it (bottom row)."""
    columns = []
    for frame, mask in cameras:
        bottom = cv2.cvtColor(cv2.resize(mask, (320, 240), interpolation=cv2.INTER_NEAREST), cv2.COLOR_GRAY2BGR)
        columns.append(np.vstack([cv2.resize(frame, (320, 240)), bottom]))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.hstack(columns))


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    main()
