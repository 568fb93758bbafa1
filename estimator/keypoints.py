"""2D keypoints of common pose detectors onto posecal's 13 joints.

OpenPose (BODY_25, BODY_25B, COCO-18), MMPose / RTMPose (COCO-17, HALPE-26,
COCO-WholeBody 133) and MediaPipe Pose (33 landmarks) each number their
keypoints their own way. :data:`SKELETONS` holds one table per layout: every
posecal joint (:data:`estimator.joints.JOINT_NAMES`) is the mean of one or more
source keypoints, and is missing unless all of them are confident.

posecal's ``head`` is the middle of the skull (the mean of the CMU skeleton's
head base and head top, :mod:`estimator.mocap`), not the face. The detectors'
nearest point to it is the midpoint of the two ears: on the head's axis, about
5 cm below it (half the CMU head bone, 9.5 cm, which starts near the ear
line), where the nose is about 10 cm in front of the ears and the eyes about
8 cm. A point fixed on the head is what the rigid-body factorization needs;
an offset along the head's axis only shortens the neck. So ``head`` = midpoint
of the ears, missing when either ear is missing: one ear alone is 7-8 cm to
the side, which in the other views is a bias, not noise.

Pure arrays in and out: file layouts are read in :mod:`service.keypoints_io`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .joints import JOINT_NAMES, N_JOINTS

__all__ = ["SKELETONS", "Skeleton", "detect_skeleton", "keypoints_to_joints", "track_person"]


@dataclass(frozen=True)
class Skeleton:
    """A detector's keypoint layout and its map onto the 13 joints.

    Attributes
    ----------
    name : str
    n_keypoints : int
    sources : tuple of tuple of int
        Per posecal joint (DESIGN.md order), the keypoint indices averaged to make it.
    """

    name: str
    n_keypoints: int
    sources: tuple[tuple[int, ...], ...]

    def __post_init__(self) -> None:
        if len(self.sources) != N_JOINTS:
            raise ValueError(f"{self.name}: need {N_JOINTS} joint sources, got {len(self.sources)}")
        if not all(s and all(0 <= i < self.n_keypoints for i in s) for s in self.sources):
            raise ValueError(f"{self.name}: source indices must lie in [0, {self.n_keypoints})")


def _table(name: str, n: int, mapping: dict[str, tuple[int, ...]]) -> Skeleton:
    return Skeleton(name, n, tuple(mapping[j] for j in JOINT_NAMES))


# COCO-17 order: 0 nose, 1-2 eyes (L, R), 3-4 ears (L, R), 5-6 shoulders, 7-8 elbows,
# 9-10 wrists, 11-12 hips, 13-14 knees, 15-16 ankles. HALPE-26, COCO-WholeBody and
# OpenPose BODY_25B start with these 17 (Pose2Sim's skeletons.py, MMPose's dataset metainfo).
_COCO17 = {
    "head": (3, 4), "left_shoulder": (5,), "right_shoulder": (6,), "left_elbow": (7,), "right_elbow": (8,),
    "left_wrist": (9,), "right_wrist": (10,), "left_hip": (11,), "right_hip": (12,), "left_knee": (13,),
    "right_knee": (14,), "left_ankle": (15,), "right_ankle": (16,),
}
# OpenPose BODY_25: 0 nose, 1 neck, 2-4 right arm, 5-7 left arm, 8 mid hip, 9-11 right leg,
# 12-14 left leg, 15-16 eyes (R, L), 17-18 ears (R, L), 19-24 feet.
_BODY25 = {
    "head": (18, 17), "left_shoulder": (5,), "right_shoulder": (2,), "left_elbow": (6,), "right_elbow": (3,),
    "left_wrist": (7,), "right_wrist": (4,), "left_hip": (12,), "right_hip": (9,), "left_knee": (13,),
    "right_knee": (10,), "left_ankle": (14,), "right_ankle": (11,),
}
# OpenPose COCO (18): as BODY_25 without mid hip and feet: 8-10 right leg, 11-13 left leg,
# 14-15 eyes (R, L), 16-17 ears (R, L).
_COCO18 = {
    "head": (17, 16), "left_shoulder": (5,), "right_shoulder": (2,), "left_elbow": (6,), "right_elbow": (3,),
    "left_wrist": (7,), "right_wrist": (4,), "left_hip": (11,), "right_hip": (8,), "left_knee": (12,),
    "right_knee": (9,), "left_ankle": (13,), "right_ankle": (10,),
}
# MediaPipe Pose: 0 nose, 1-6 eyes, 7-8 ears (L, R), 9-10 mouth, 11-12 shoulders,
# 13-14 elbows, 15-16 wrists, 17-22 hands, 23-24 hips, 25-26 knees, 27-28 ankles, 29-32 feet.
_MEDIAPIPE33 = {
    "head": (7, 8), "left_shoulder": (11,), "right_shoulder": (12,), "left_elbow": (13,), "right_elbow": (14,),
    "left_wrist": (15,), "right_wrist": (16,), "left_hip": (23,), "right_hip": (24,), "left_knee": (25,),
    "right_knee": (26,), "left_ankle": (27,), "right_ankle": (28,),
}

SKELETONS: dict[str, Skeleton] = {s.name: s for s in (
    _table("COCO_17", 17, _COCO17),
    _table("COCO_18", 18, _COCO18),
    _table("BODY_25", 25, _BODY25),
    _table("BODY_25B", 25, _COCO17),
    _table("HALPE_26", 26, _COCO17),
    _table("MEDIAPIPE_33", 33, _MEDIAPIPE33),
    _table("COCO_133", 133, _COCO17),
)}
"""The supported layouts by name (docs/SELFCAL.md has the same map as one table)."""

_BY_COUNT = {17: "COCO_17", 18: "COCO_18", 26: "HALPE_26", 33: "MEDIAPIPE_33", 133: "COCO_133"}


def detect_skeleton(keypoints: np.ndarray, scores: np.ndarray | None = None, *,
                    min_confidence: float = 0.3) -> Skeleton:
    """The layout of detections from their keypoint count.

    Parameters
    ----------
    keypoints : ndarray of shape (N, K, 2)
        Some detections (any frames, cameras, people) of one layout.
    scores : ndarray of shape (N, K), optional
        Their confidences (keypoints below ``min_confidence`` are not used).

    Returns
    -------
    Skeleton

    Raises
    ------
    ValueError
        For a count no layout has, or 25 keypoints that cannot be told apart.

    Notes
    -----
    BODY_25 and BODY_25B both have 25 keypoints. In BODY_25, keypoint 1 (neck)
    is the midpoint of 2 and 5 (the shoulders) and 8 (mid hip) that of 9 and 12
    (the hips); in BODY_25B they are an eye between an eye and a shoulder, and
    an elbow between a wrist and a hip: about 0.07 and 0.12 of the stature above
    those midpoints in an upright person, whatever the view. Each offset is a
    signed 2D vector in units of the person's size (the larger side of the box of
    their confident keypoints); its median over the detections cancels the
    detector's noise, and the sum of the two medians' lengths decides: below
    ``BODY25_OFFSET`` (0.06), BODY_25. Where no detection shows one of the two
    triples (BODY_25B's eyes are not seen from behind), the other's length is
    doubled: the Pose2Sim demo's two rear cameras show no eye and give 0.36
    and 0.47 from the elbows alone. Two earlier rules failed on a 4-camera
    rig: offsets over the shoulders' and hips' widths (a side view has none),
    then the median of the offsets' lengths (noise of 3 % of the height alone
    makes that 0.07).
    """
    kp = np.asarray(keypoints, float)
    if kp.ndim != 3 or kp.shape[-1] != 2:
        raise ValueError(f"keypoints must have shape (N, K, 2), got {kp.shape}")
    k = kp.shape[1]
    if k in _BY_COUNT:
        return SKELETONS[_BY_COUNT[k]]
    if k != 25:
        raise ValueError(f"unknown keypoint count {k}: expected 17 (COCO-17), 18 (OpenPose COCO), "
                         f"25 (BODY_25, BODY_25B), 26 (HALPE-26), 33 (MediaPipe) or 133 (COCO-WholeBody)")
    ok = np.isfinite(kp).all(axis=-1)
    if scores is not None:
        ok &= np.asarray(scores, float) >= min_confidence
    enough = ok.sum(axis=1) >= 8
    lo = np.where(ok[..., None], kp, np.inf).min(axis=1)
    hi = np.where(ok[..., None], kp, -np.inf).max(axis=1)
    unit = 1.0 / np.maximum((hi - lo).max(axis=-1), 1e-9)[:, None]  # over the person's size
    offsets = []
    for mid, a, b in ((1, 2, 5), (8, 9, 12)):  # neck or eye; mid hip or elbow
        use = ok[:, [mid, a, b]].all(axis=1) & enough
        if use.any():
            offsets.append(np.linalg.norm(np.median((kp[use, mid] - (kp[use, a] + kp[use, b]) / 2) * unit[use],
                                                    axis=0)))
    if not offsets:
        raise ValueError("25 keypoints, but no detection shows keypoints 1, 2 and 5 or 8, 9 and 12 "
                         "to tell BODY_25 from BODY_25B (give the skeleton: --skeleton)")
    offset = float(np.sum(offsets)) * 2 / len(offsets)
    return SKELETONS["BODY_25" if offset < BODY25_OFFSET else "BODY_25B"]


BODY25_OFFSET = 0.06
"""Length of the median offset of the neck from the shoulders' midpoint plus that of the mid hip from the
hips', over the person's size, below which 25 keypoints are BODY_25 (:func:`detect_skeleton`)."""


def keypoints_to_joints(keypoints: np.ndarray, scores: np.ndarray, skeleton: Skeleton, *,
                        min_confidence: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Map detector keypoints onto the 13 joints.

    Parameters
    ----------
    keypoints : ndarray of shape (..., K, 2)
        Pixels; NaN where the detector gave nothing.
    scores : ndarray of shape (..., K)
        Confidences in [0, 1].
    skeleton : Skeleton
        The layout (``K = skeleton.n_keypoints``).
    min_confidence : float
        Keypoints below this are missing.

    Returns
    -------
    joints : ndarray of shape (..., 13, 2)
        NaN where missing (a joint is missing unless all its source keypoints are seen).
    confidence : ndarray of shape (..., 13)
        The least confidence of the sources; 0 where missing.
    """
    kp = np.asarray(keypoints, float)
    sc = np.asarray(scores, float)
    if kp.shape[-2:] != (skeleton.n_keypoints, 2) or sc.shape != kp.shape[:-1]:
        raise ValueError(f"{skeleton.name}: keypoints must have shape (..., {skeleton.n_keypoints}, 2) and "
                         f"scores (..., {skeleton.n_keypoints}), got {kp.shape} and {sc.shape}")
    if not 0.0 <= min_confidence <= 1.0:
        raise ValueError(f"min_confidence must lie in [0, 1], got {min_confidence}")
    seen = np.isfinite(kp).all(axis=-1) & np.isfinite(sc) & (sc >= min_confidence)
    joints = np.full(kp.shape[:-2] + (N_JOINTS, 2), np.nan)
    conf = np.zeros(kp.shape[:-2] + (N_JOINTS,))
    for j, src in enumerate(skeleton.sources):
        idx = list(src)
        ok = seen[..., idx].all(axis=-1)
        joints[..., j, :] = np.where(ok[..., None], kp[..., idx, :].mean(axis=-2), np.nan)
        conf[..., j] = np.where(ok, np.where(seen[..., idx], sc[..., idx], 1.0).min(axis=-1), 0.0)
    return joints, conf


def _box(joints: np.ndarray) -> np.ndarray | None:
    """(x0, y0, x1, y1) of the seen joints (13, 2), None when fewer than 2 are seen."""
    p = joints[np.isfinite(joints).all(axis=-1)]
    if len(p) < 2:
        return None
    return np.concatenate([p.min(axis=0), p.max(axis=0)])


def track_person(people: Sequence[np.ndarray], *, gate: float = 0.5) -> np.ndarray:
    """Follow one person through the frames of one camera.

    Parameters
    ----------
    people : sequence of ndarray of shape (P_t, 13, 2)
        Per frame, the joints of every detected person (NaN = missing); P_t may be 0.
    gate : float
        Largest distance between box centres from one chosen box to the next,
        in units of the previous box's diagonal.

    Returns
    -------
    ndarray of shape (T,), int
        The chosen person per frame, -1 where none.

    Notes
    -----
    Every person of the first frame with anyone starts a track; frame by
    frame, a track takes the person whose box centre is nearest its last
    box's, if within ``gate`` diagonals (else none in that frame, and the last
    box is kept; the diagonal is the larger of the last box's and the median
    of the track's, so one box of a few joints does not narrow the gate for
    good). The track with the largest sum of box diagonals over its
    frames is kept: the person seen longest and largest, so a passer-by who
    is nearer the camera on the first frame and then leaves is not followed
    (the largest box on the first frame was the rule until session 19). Each
    camera is tracked on its own, so in a crowd the subject must be the most
    present person in every camera.
    """
    boxes = [[_box(p) for p in persons] for persons in people]
    first = next((t for t, bs in enumerate(boxes) if any(b is not None for b in bs)), None)
    if first is None:
        return np.full(len(people), -1, dtype=int)
    tracks = [_follow(boxes, first, i, gate) for i, b in enumerate(boxes[first]) if b is not None]
    support = [sum(float(np.linalg.norm(boxes[t][i][2:] - boxes[t][i][:2])) for t, i in enumerate(tr) if i >= 0)
               for tr in tracks]
    return tracks[int(np.argmax(support))]


def _follow(boxes: list[list[np.ndarray | None]], first: int, start: int, gate: float) -> np.ndarray:
    """The track of :func:`track_person` started at person ``start`` of frame ``first``."""
    out = np.full(len(boxes), -1, dtype=int)
    out[first], last = start, boxes[first][start]
    diags = [float(np.linalg.norm(last[2:] - last[:2]))]
    for t in range(first + 1, len(boxes)):
        cand = [(i, b) for i, b in enumerate(boxes[t]) if b is not None]
        if not cand:
            continue
        centre = (last[:2] + last[2:]) / 2
        dist = [float(np.linalg.norm((b[:2] + b[2:]) / 2 - centre)) for _, b in cand]
        k = int(np.argmin(dist))
        if dist[k] > gate * max(diags[-1], float(np.median(diags)), 1e-9):
            continue
        out[t], last = cand[k]
        diags.append(float(np.linalg.norm(last[2:] - last[:2])))
    return out
