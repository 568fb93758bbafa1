"""A pinhole start for the rig from epipolar geometry: essential matrices, triangulation, resection.

The scaled-orthographic self-calibration (Wang–Leow §4) is the start of the
pinhole bundle adjustment (:mod:`estimator.perspective`). At lab distances
(cameras 2-4 m from a walker who covers 2 m) its model is far from the
images, and on about a quarter of random 4-camera rigs it lands in a basin the
bundle adjustment does not leave (docs/SELFCAL.md). There the perspective is
strong, and that is exactly what makes the classical two-view start work:
every frame's joints are correspondences between the views (13 joints x T
frames, one rigid scene per frame, the same cameras throughout), so

1. per camera pair, the essential matrix of the normalised joints, robustly
   (the five-point algorithm in RANSAC, :func:`cv2.findEssentialMat`, Nistér
   2004), and the relative pose with the points in front of both cameras
   (:func:`cv2.recoverPose`);
2. the pair with the most inliers fixes the frame and the scale; its joints
   are triangulated, and each further camera is placed by resection
   (PnP in RANSAC, :func:`cv2.solvePnPRansac`) against the joints it sees,
   the camera with most of them first, and the joints triangulated again
   with every placed camera (incremental structure from motion, Hartley &
   Zisserman ch. 18);
3. free focal lengths are not known: the start is built for a few focal
   lengths (the same multiple of every camera's image width) and the one
   whose joints reproject best is kept; the bundle adjustment frees each
   camera's focal length from there.

The result is a :class:`estimator.perspective.PerspectiveRig` in that
module's units (camera 0's frame, the walker's mean depth in camera 0 equal
to its focal length), ready for ``perspective_refine(..., initial=)``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import cv2
import numpy as np

from .perspective import PerspectiveConfig, PerspectiveRig, _per_camera, perspective_refine
from .pinhole import PinholeCameras, image_height, reprojection_rmse, triangulate

__all__ = ["EpipolarConfig", "epipolar_start", "refine_from_starts"]


@dataclass(frozen=True)
class EpipolarConfig:
    """Settings of :func:`epipolar_start`.

    Attributes
    ----------
    focal_widths : tuple of float
        Focal lengths tried when they are not given, in image widths
        (0.5-2.4: fields of view from 90 to 24 deg).
    threshold_share : float
        RANSAC inlier threshold, as a share of the walker's median image
        height (1.5 %: about 3 px for a 200 px walker, above a detector's noise).
    min_points : int
        Fewest joints two cameras must both see for their essential matrix.
    seed : int
        OpenCV's RANSAC seed (the start is deterministic given it).
    """

    focal_widths: tuple[float, ...] = (0.5, 0.7, 1.0, 1.4, 2.0)
    threshold_share: float = 0.015
    min_points: int = 24
    seed: int = 0


def epipolar_start(tracks: np.ndarray, image_sizes: np.ndarray, *, focal_px: np.ndarray | None = None,
                   principal_px: np.ndarray | None = None,
                   config: EpipolarConfig = EpipolarConfig()) -> PerspectiveRig | None:
    """Pinhole cameras and 3D joints from 2D joint tracks by two-view geometry and resection.

    Parameters
    ----------
    tracks : ndarray of shape (C, T, J, 2)
        Full-frame pixels, NaN where missing.
    image_sizes : ndarray of shape (C, 2)
        (width, height) per camera.
    focal_px : ndarray of shape (C,), optional
        Known focal lengths; None: tried at ``config.focal_widths`` image widths.
    principal_px : ndarray of shape (C, 2), optional
        Known principal points; None: the image centres.

    Returns
    -------
    PerspectiveRig or None
        The start with the lowest reprojection error, or None when no camera
        pair shares enough joints or a camera cannot be placed.
    """
    y = np.asarray(tracks, float)
    sizes = np.asarray(image_sizes, float)
    principal = sizes / 2.0 if principal_px is None else np.asarray(principal_px, float)
    focals = ([np.asarray(focal_px, float)] if focal_px is not None
              else [k * sizes[:, 0] for k in config.focal_widths])
    height = image_height(y, min_joints=4)
    if not np.isfinite(height):
        return None
    best = None
    for f in focals:
        rig = _start_for(y, f, principal, config.threshold_share * height, config)
        if rig is not None and (best is None or rig.rmse_px < best.rmse_px):
            best = rig
    return best


def refine_from_starts(tracks: np.ndarray, image_sizes: np.ndarray, rotations: np.ndarray, scales: np.ndarray,
                       links: list[tuple[int, int]], *, config: PerspectiveConfig = PerspectiveConfig(),
                       epipolar: EpipolarConfig | None = EpipolarConfig(),
                       race_nfev: int | None = 15, frame_times: np.ndarray | None = None
                       ) -> tuple[PerspectiveRig, str]:
    """The pinhole bundle adjustment from the scaled-orthographic rig and from the epipolar start; the
    one whose joints reproject best is kept.

    Parameters are those of :func:`estimator.perspective.perspective_refine`; ``epipolar=None``
    skips the epipolar start. With ``race_nfev``, each start is adjusted for that many evaluations
    and only the better one runs on to ``config.max_nfev`` (the two ends are rarely close: a wrong
    basin leaves a larger error from the first iterations); None adjusts both to the end.
    Returns the rig and which start it came from (``"scaled orthographic"`` or ``"epipolar"``).

    On 20 random 4-camera rigs 2.5-4 m from a walker (detector-like keypoints,
    ``bench/eval_keypoints_import.py``) both starts end in the same basin on 19;
    on the other the scaled-orthographic start stops 4.6 deg off in the median
    pair and the epipolar one 0.3 deg off, with the lower reprojection error.
    """
    starts = {"scaled orthographic": None}
    if epipolar is not None:
        n_cam = len(tracks)
        focal = _per_camera(config.focal_px, (n_cam,), "focal_px", None)
        principal = _per_camera(config.principal_px, (n_cam, 2), "principal_px", None)
        start = epipolar_start(tracks, image_sizes, focal_px=focal, principal_px=principal, config=epipolar)
        if start is not None:
            starts["epipolar"] = start
    short = (config if race_nfev is None or len(starts) == 1
             else replace(config, max_nfev=race_nfev, reweight=0, upright=0.0, smooth=0.0))
    found = {name: perspective_refine(tracks, image_sizes, rotations, scales, links, config=short, initial=start,
                                      frame_times=frame_times)
             for name, start in starts.items()}
    name = min(found, key=lambda k: found[k].rmse_px if np.isfinite(found[k].rmse_px) else np.inf)
    if short is not config:
        found[name] = perspective_refine(tracks, image_sizes, rotations, scales, links, config=config,
                                         initial=found[name], frame_times=frame_times)
    return found[name], name


def _start_for(y: np.ndarray, focal: np.ndarray, principal: np.ndarray, threshold_px: float,
               config: EpipolarConfig) -> PerspectiveRig | None:
    """The incremental start for one set of focal lengths (steps 1-2 of the module's docstring)."""
    n_cam, t, j, _ = y.shape
    norm = (y - principal[:, None, None, :]) / focal[:, None, None, None]  # (C, T, J, 2)
    seen = np.isfinite(norm).all(axis=-1)
    thr = threshold_px / float(np.mean(focal))
    pair = _best_pair(norm, seen, thr, config)
    if pair is None:
        return None
    a, b, rot_ab, t_ab = pair
    rot = np.full((n_cam, 3, 3), np.nan)
    trans = np.full((n_cam, 3), np.nan)
    rot[a], trans[a] = np.eye(3), np.zeros(3)
    rot[b], trans[b] = rot_ab, t_ab
    placed = [a, b]
    x = _triangulate(norm, rot, trans, placed)
    while len(placed) < n_cam:
        todo = [c for c in range(n_cam) if c not in placed]
        shared = [int((seen[c] & np.isfinite(x).all(axis=-1)).sum()) for c in todo]
        c = todo[int(np.argmax(shared))]
        pose = _resect(norm[c], seen[c], x, thr, config)
        if pose is None:
            return None
        rot[c], trans[c] = pose
        placed.append(c)
        x = _triangulate(norm, rot, trans, placed)
    return _in_camera0(y, x, rot, trans, focal, principal)


def _best_pair(norm: np.ndarray, seen: np.ndarray, thr: float, config: EpipolarConfig):
    """The camera pair whose essential matrix has the most inliers in front of both cameras, with its
    relative pose ``x_b = R x_a + t`` (``|t| = 1``)."""
    best, best_count = None, 0
    n_cam = norm.shape[0]
    for a in range(n_cam):
        for b in range(a + 1, n_cam):
            both = seen[a] & seen[b]
            if both.sum() < config.min_points:
                continue
            pa, pb = norm[a][both], norm[b][both]
            cv2.setRNGSeed(config.seed)
            e, mask = cv2.findEssentialMat(pa, pb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr)
            if e is None or e.shape != (3, 3):
                continue  # degenerate, or several solutions stacked: take the pair only when it is clear
            count, r, tt, mask = cv2.recoverPose(e, pa, pb, np.eye(3), mask=mask)
            if count > best_count:
                best, best_count = (a, b, r, tt.ravel()), count
    return best


def _resect(norm: np.ndarray, seen: np.ndarray, x: np.ndarray, thr: float, config: EpipolarConfig):
    """A camera's pose ``(R, t)`` from the joints it sees (T, J, 2) and their 3D positions, by PnP."""
    ok = seen & np.isfinite(x).all(axis=-1)
    if ok.sum() < 6:
        return None
    cv2.setRNGSeed(config.seed)
    found, rvec, tvec, inliers = cv2.solvePnPRansac(x[ok].astype(np.float64), norm[ok].astype(np.float64),
                                                   np.eye(3), None, reprojectionError=thr, iterationsCount=200,
                                                   flags=cv2.SOLVEPNP_EPNP)
    if not found or inliers is None or len(inliers) < 6:
        return None
    idx = inliers.ravel()
    _, rvec, tvec = cv2.solvePnP(x[ok][idx], norm[ok][idx], np.eye(3), None, rvec, tvec, useExtrinsicGuess=True,
                                 flags=cv2.SOLVEPNP_ITERATIVE)
    return cv2.Rodrigues(rvec)[0], tvec.ravel()


def _triangulate(norm: np.ndarray, rot: np.ndarray, trans: np.ndarray, placed: list[int]) -> np.ndarray:
    """Joints (T, J, 3) from the placed cameras' normalised tracks; NaN where fewer than two see a joint."""
    cams = PinholeCameras(np.broadcast_to(np.eye(3), (len(placed), 3, 3)), rot[placed], trans[placed])
    return triangulate(cams, norm[placed])


def _in_camera0(y: np.ndarray, x: np.ndarray, rot: np.ndarray, trans: np.ndarray, focal: np.ndarray,
                principal: np.ndarray) -> PerspectiveRig | None:
    """The start in :mod:`estimator.perspective`'s units: camera 0's frame, the walker's mean depth in
    camera 0 equal to its focal length; joints no two cameras saw filled from the frame's others."""
    centres = -np.einsum("cba,cb->ca", rot, trans)  # C = -R^T t
    r0, c0 = rot[0], centres[0]
    x = (x - c0) @ r0.T
    centres = (centres - c0) @ r0.T
    rot = rot @ r0.T
    depth = float(np.nanmean(x[..., 2]))
    if not (np.isfinite(depth) and depth > 0):
        return None
    k = focal[0] / depth
    x, centres = _fill(x * k), centres * k
    if x is None:
        return None
    cams = PinholeCameras.from_centres(focal, principal, rot, centres)
    rmse = reprojection_rmse(cams, x, y)
    walker = x.reshape(-1, 3).mean(axis=0)
    scale = focal / np.einsum("ca,ca->c", rot[:, 2], walker[None] - centres)
    return PerspectiveRig(rot, centres, focal.copy(), x, rmse, scale / scale[0], None, principal)


def _fill(x: np.ndarray) -> np.ndarray | None:
    """Joints (T, J, 3) with the missing ones placed at the frame's centroid plus the joint's median
    offset from it over the frames (a frame with no joint at all: its neighbours' centroid)."""
    seen = np.isfinite(x).all(axis=-1)
    if not seen.any():
        return None
    with np.errstate(invalid="ignore"):
        centroid = np.nanmean(np.where(seen[..., None], x, np.nan), axis=1)  # (T, 3)
    have = np.isfinite(centroid).all(axis=-1)
    idx = np.arange(len(x))
    centroid = np.stack([np.interp(idx, idx[have], centroid[have, d]) for d in range(3)], axis=-1)
    with warnings.catch_warnings():  # a joint no two cameras ever saw: its offset is 0 below
        warnings.simplefilter("ignore", RuntimeWarning)
        offset = np.nanmedian(np.where(seen[..., None], x - centroid[:, None], np.nan), axis=0)  # (J, 3)
    offset = np.where(np.isfinite(offset), offset, 0.0)
    return np.where(seen[..., None], x, centroid[:, None] + offset[None])
