"""Calibrated pinhole cameras as matrices: projection, linear triangulation, a floor frame.

What the exports of ``posecal selfcal`` need once :func:`estimator.perspective.perspective_refine`
has found the cameras: the 3D joints of every frame (not only the frames the
calibration used) by weighted linear triangulation (the DLT of Hartley &
Zisserman, §12.2, each row weighted by the keypoint's confidence, as Pose2Sim
does), and a world frame with z up for tools that expect one.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ._selfcal_core import proper_rotations
from .joints import JOINT_INDEX

__all__ = ["PinholeCameras", "floor_frame", "image_height", "project", "reprojection_rmse", "triangulate"]


@dataclass(frozen=True)
class PinholeCameras:
    """Cameras ``x_cam = R X + t``, pixels ``K x_cam`` (no distortion).

    Attributes
    ----------
    matrices : ndarray of shape (C, 3, 3)
        Intrinsics ``K``.
    rotations : ndarray of shape (C, 3, 3)
        World-to-camera rotations (rows: image u, image v, optical axis).
    translations : ndarray of shape (C, 3)
        ``t = -R C`` for the camera centre ``C``, in the world's unit.
    """

    matrices: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotations, float)
        if not proper_rotations(r):
            raise ValueError("rotations must be proper rotations")

    @classmethod
    def from_centres(cls, focal_px: np.ndarray, principal: np.ndarray, rotations: np.ndarray,
                     centres: np.ndarray) -> PinholeCameras:
        """From focal lengths (C,), principal points (C, 2), rotations (C, 3, 3) and centres (C, 3)."""
        k = np.zeros((len(focal_px), 3, 3))
        k[:, 0, 0] = k[:, 1, 1] = focal_px
        k[:, :2, 2] = principal
        k[:, 2, 2] = 1.0
        return cls(k, np.asarray(rotations, float), -np.einsum("cab,cb->ca", rotations, centres))

    def select(self, cameras) -> PinholeCameras:
        """The cameras at index (or indices) ``cameras``, as a rig of their own."""
        idx = np.atleast_1d(cameras)
        return PinholeCameras(self.matrices[idx], self.rotations[idx], self.translations[idx])

    def moved(self, rotation: np.ndarray, origin: np.ndarray) -> PinholeCameras:
        """The same cameras in the world ``X' = rotation (X - origin)``."""
        r = self.rotations @ rotation.T
        return PinholeCameras(self.matrices, r, self.translations + np.einsum("cab,b->ca", self.rotations, origin))


def project(cameras: PinholeCameras, points: np.ndarray) -> np.ndarray:
    """Pixels (C, ..., 2) of world points (..., 3); NaN behind a camera."""
    x = np.einsum("cab,...b->c...a", cameras.rotations, points)
    x = x + cameras.translations.reshape((-1,) + (1,) * (points.ndim - 1) + (3,))
    h = np.einsum("cab,c...b->c...a", cameras.matrices, x)
    z = h[..., 2:3]
    return np.where(z > 0, h[..., :2] / np.where(z > 0, z, 1.0), np.nan)


def image_height(tracks: np.ndarray, min_joints: int = 1) -> float:
    """The walker's median image height in pixels: the vertical extent of the joints of ``tracks``
    (C, T, J, 2; NaN where missing) over the cameras and frames showing at least ``min_joints``
    joints (NaN when none does)."""
    v = np.asarray(tracks, float)[..., 1]
    shown = np.isfinite(v).sum(axis=-1) >= max(min_joints, 1)
    if not shown.any():
        return float("nan")
    top = np.where(np.isfinite(v), v, np.inf).min(axis=-1)
    bottom = np.where(np.isfinite(v), v, -np.inf).max(axis=-1)
    return float(np.median((bottom - top)[shown]))


def reprojection_rmse(cameras: PinholeCameras, points: np.ndarray, tracks: np.ndarray) -> float:
    """Root mean square distance (pixels) between ``tracks`` (C, T, J, 2; NaN where missing) and the
    projections of ``points`` (T, J, 3); a point behind a camera counts as the image diagonal off."""
    y = np.asarray(tracks, float)
    seen = np.isfinite(y).all(axis=-1)
    d2 = np.sum((project(cameras, points) - y) ** 2, axis=-1)[seen]
    far = 2.0 * float(np.abs(cameras.matrices[:, :2, 2]).max()) ** 2 * 2.0  # about the diagonal, squared
    d2 = np.where(np.isfinite(d2), d2, far)
    return float(np.sqrt(d2.mean())) if d2.size else float("nan")


def triangulate(cameras: PinholeCameras, tracks: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Points (T, J, 3) seen in pixels ``tracks`` (C, T, J, 2), by weighted linear triangulation.

    ``weights`` (C, T, J), default 1, scale each camera's two rows; a point
    seen (finite, weight > 0) by fewer than two cameras is NaN.
    """
    y = np.asarray(tracks, float)
    w = np.ones(y.shape[:-1]) if weights is None else np.asarray(weights, float)
    seen = np.isfinite(y).all(axis=-1) & (w > 0)
    w = np.where(seen, w, 0.0)
    p = cameras.matrices @ np.concatenate([cameras.rotations, cameras.translations[:, :, None]], axis=2)  # (C, 3, 4)
    yy = np.where(seen[..., None], y, 0.0)
    rows = np.stack([yy[..., 0:1] * p[:, None, None, 2] - p[:, None, None, 0],
                     yy[..., 1:2] * p[:, None, None, 2] - p[:, None, None, 1]], axis=-2)  # (C, T, J, 2, 4)
    rows = rows / np.maximum(np.linalg.norm(rows, axis=-1, keepdims=True), 1e-12) * w[..., None, None]
    a = np.moveaxis(rows, 0, 2).reshape(y.shape[1], y.shape[2], -1, 4)  # (T, J, 2C, 4)
    _, _, vt = np.linalg.svd(a)
    h = vt[..., -1, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        x = h[..., :3] / h[..., 3:4]
    return np.where((seen.sum(axis=0) >= 2)[..., None], x, np.nan)


def floor_frame(joints3d: np.ndarray, forward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A world frame with z up from an upright person's joints (T, 13, 3).

    Returns ``(rotation, origin)`` for ``X_world = rotation (X - origin)``: z is
    the mean direction from the ankles' midpoint to the shoulders' midpoint
    (the body's axis; a walker's forward lean tilts it by a few degrees), x is
    ``forward`` (e.g. the reference camera's optical axis) made horizontal, y
    = z x x; the origin lies below the mean hip centre at the ankles' level
    (the median over frames of the lower ankle), about 8 cm above the floor.
    """
    j = JOINT_INDEX
    x = np.asarray(joints3d, float)
    mid = lambda a, b: (x[:, j[a]] + x[:, j[b]]) / 2  # noqa: E731
    axis = np.nanmean(mid("left_shoulder", "right_shoulder") - mid("left_ankle", "right_ankle"), axis=0)
    if not np.isfinite(axis).all() or np.linalg.norm(axis) == 0:
        raise ValueError("no frame shows both shoulders and both ankles: no up direction")
    up = axis / np.linalg.norm(axis)
    fwd = np.asarray(forward, float) - up * float(np.dot(forward, up))
    if np.linalg.norm(fwd) < 1e-6:
        raise ValueError("forward is vertical: no horizontal direction")
    fwd /= np.linalg.norm(fwd)
    rotation = np.stack([fwd, np.cross(up, fwd), up])
    hips = np.nanmean(mid("left_hip", "right_hip"), axis=0)
    ankles = np.stack([x[:, j["left_ankle"]] @ up, x[:, j["right_ankle"]] @ up])
    with warnings.catch_warnings():  # frames without ankles
        warnings.simplefilter("ignore", RuntimeWarning)
        level = float(np.nanmedian(np.nanmin(ankles, axis=0)))
    origin = hips - up * (float(hips @ up) - level)
    return rotation, origin
