"""Registration of silhouettes and the silhouette-to-cluster distance (Izo–Grimson §5).

Before a binary input silhouette is compared with a cluster's mean silhouette,
both are brought to a common frame: isotropic scaling to a common height,
centroid at a fixed point of the canvas, principal axis vertical. The distance
is then eq. 8, computed for many silhouettes against many means as one matrix
product.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import math

import cv2
import numpy as np

__all__ = ["DEFAULT_SIZE", "Transforms", "register", "register_shares", "distance", "transform_points"]

DEFAULT_SIZE: tuple[int, int] = (64, 48)
"""Registered canvas (height, width) in pixels; see docs/APPEARANCE.md for the measurement."""

_DEFAULT_HEIGHT_FRACTION = 0.8


@dataclass(frozen=True)
class Transforms:
    """How each input silhouette was registered.

    Attributes
    ----------
    matrix : ndarray of shape (T, 2, 3)
        Affine map from input pixel coordinates ``(u, v)`` to canvas coordinates:
        ``canvas = matrix[:, :2] @ (u, v) + matrix[:, 2]``. A similarity (rotation,
        isotropic scale, translation).
    scale : ndarray of shape (T,)
        Canvas pixels per input pixel (the paper's "scaling factor" to keep track of).
    angle_deg : ndarray of shape (T,)
        Angle of the input's principal axis from the image vertical, in degrees, in
        [-45, 45); the registration rotates by ``-angle_deg``. 0 when ``rotate=False``.
    centroid : ndarray of shape (T, 2)
        Foreground centroid ``(u, v)`` in input pixels.
    height : ndarray of shape (T,)
        Extent of the foreground along the principal axis, in input pixels.
    valid : ndarray of shape (T,), bool
        False for empty silhouettes (their registered image is all zeros and their
        matrix is NaN).
    """

    matrix: np.ndarray
    scale: np.ndarray
    angle_deg: np.ndarray
    centroid: np.ndarray
    height: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return len(self.valid)


def register(
    silhouettes: np.ndarray | Sequence[np.ndarray],
    *,
    size: tuple[int, int] = DEFAULT_SIZE,
    height_fraction: float = _DEFAULT_HEIGHT_FRACTION,
    rotate: bool = True,
    binary: bool = True,
    hidden: float = 0.0,
    top: float | None = None,
) -> tuple[np.ndarray, Transforms]:
    """Register silhouettes to a common canvas (Izo–Grimson §5).

    Each silhouette is scaled isotropically so that its extent along its principal
    axis is ``height_fraction * size[0]`` canvas pixels, rotated so that this axis
    is vertical, and translated so that its centroid is at the canvas centre.

    Parameters
    ----------
    silhouettes : ndarray of shape (T, H, W), or sequence of T arrays of shape (H_i, W_i)
        Silhouettes; any non-zero pixel is foreground (DESIGN.md: uint8 0/255).
        A sequence may hold crops of different sizes.
    size : (int, int), keyword-only
        Canvas ``(height, width)`` in pixels.
    height_fraction : float, keyword-only
        Fraction of the canvas height that the silhouette's height fills, in (0, 1].
    rotate : bool, keyword-only
        Align principal axes. The axis (major or minor) closest to the image
        vertical is made vertical, so the rotation is always within +-45 degrees.
    binary : bool, keyword-only
        Threshold the resampled silhouette at 0.5 (values 0/1). If False, return the
        area-resampled fraction of foreground in each canvas pixel, in [0, 1].
    hidden : float, keyword-only
        Fraction of the walker's height hidden below the silhouettes (a low
        wall, the image's bottom edge; :mod:`estimator.occlusion`), in [0, 1).
        The extent is then ``1 - hidden`` of the body's and is scaled to that
        share of the target height.
    top : float, keyword-only
        Place the top of the extent at this canvas row (where a whole
        registered body's top lies; the centroid's column stays the centre's)
        rather than the centroid at the centre, which a body without its
        lowest part does not share. Required when ``hidden`` > 0.

    Returns
    -------
    registered : ndarray of shape (T, size[0], size[1]), float32
        Registered silhouettes, values in [0, 1] (0/1 when ``binary``).
    transforms : Transforms
        The similarity applied to each input, for mapping points (e.g. joints) with
        :func:`transform_points`.

    Notes
    -----
    Downscaling is done by area averaging (``cv2.INTER_AREA``, on 0/255 uint8)
    to the nearest integer size, followed by one ``cv2.warpAffine`` that applies
    the rotation, the translation and the residual (sub-pixel) scale, so the total
    map is an exact similarity. The height is the full extent of the foreground
    pixels along the principal axis: remove speckle before registering.

    References
    ----------
    Izo & Grimson, §5 ("normalize the two to be of the same height using isotropic
    scaling and then register them by aligning their centroids and principal axes").
    """
    h, w = _check_size(size)
    if not 0.0 < height_fraction <= 1.0:
        raise ValueError(f"height_fraction must be in (0, 1], got {height_fraction}")
    if not 0.0 <= hidden < 1.0 or (hidden > 0.0 and top is None):
        raise ValueError(f"hidden must be in [0, 1) and given with top, got hidden={hidden}, top={top}")
    if isinstance(silhouettes, np.ndarray):
        if silhouettes.ndim != 3:
            raise ValueError(f"silhouettes must have shape (T, H, W), got {silhouettes.shape}")
        items: Sequence[np.ndarray] = silhouettes
    else:
        items = list(silhouettes)
        for i, s in enumerate(items):
            if np.ndim(s) != 2:
                raise ValueError(f"silhouettes[{i}] must be 2-D (H, W), got shape {np.shape(s)}")
    t = len(items)
    out = np.zeros((t, h, w), np.float32)
    matrix = np.full((t, 2, 3), np.nan)
    scale = np.full(t, np.nan)
    angle = np.zeros(t)
    centroid = np.full((t, 2), np.nan)
    height = np.zeros(t)
    valid = np.zeros(t, bool)
    target = height_fraction * h * (1.0 - hidden)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    for i in range(t):
        r = _register_one(items[i], out[i], target, centre, rotate, binary, top)
        if r is not None:
            matrix[i], scale[i], angle[i], centroid[i], height[i] = r
            valid[i] = True
    return out, Transforms(matrix, scale, angle, centroid, height, valid)


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    if len(size) != 2 or min(size) < 4:
        raise ValueError(f"size must be (height, width) with both >= 4, got {size}")
    return int(size[0]), int(size[1])


def _register_one(sil, out, target, centre, rotate, binary, top=None):
    """Register one silhouette into ``out`` (float32, zeros); None if it is empty. With ``top``, the
    top of its extent goes to that canvas row (the centroid stays on the centre column)."""
    shape = _measure_one(sil, rotate)
    return None if shape is None else _place_one(shape, out, target, centre, binary, top)


@dataclass
class _Shape:
    """What registration measures on one silhouette, whatever its target size: its 0/255 crop at
    ``(x0, y0)``, centroid ``(cx, cy)`` in the crop, principal-axis ``angle`` and the extent along
    it (``along_min`` to ``along_min + extent - 1``, from the centroid)."""

    crop: np.ndarray
    x0: int
    y0: int
    cx: float
    cy: float
    angle: float
    along_min: float
    extent: float


def _measure_one(sil, rotate: bool) -> _Shape | None:
    """The :class:`_Shape` of one silhouette; None if it is empty."""
    mask = np.asarray(sil)
    if mask.dtype != np.uint8:
        mask = (mask != 0).view(np.uint8)
    mask = np.ascontiguousarray(mask)
    x0, y0, bw, bh = cv2.boundingRect(mask)
    if bw == 0 or bh == 0:
        return None
    # 0/255 copy of the bounding box (inputs may be 0/1 or 0/255).
    crop = cv2.threshold(mask[y0 : y0 + bh, x0 : x0 + bw], 0, 255, cv2.THRESH_BINARY)[1]
    m = cv2.moments(crop, binaryImage=True)
    cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]  # crop coordinates
    if rotate:
        # Angle of the major axis from +u (image coordinates, v down); then the
        # principal axis nearest the vertical, as an angle from it in [-45, 45).
        theta = 0.5 * math.degrees(math.atan2(2.0 * m["mu11"], m["mu20"] - m["mu02"]))
        angle = (theta - 90.0 + 45.0) % 90.0 - 45.0
    else:
        angle = 0.0
    a = math.radians(angle)
    c, sn = math.cos(a), math.sin(a)
    # Extent along that axis, (-sin a, cos a): attained at hull vertices, which are
    # among the leftmost and rightmost foreground pixels of the rows.
    fg = crop.view(bool)
    rows = np.flatnonzero(fg.any(1))
    left = fg[rows].argmax(1)
    right = bw - 1 - fg[rows, ::-1].argmax(1)
    yr = rows - cy
    along = np.concatenate([-sn * (left - cx) + c * yr, -sn * (right - cx) + c * yr])
    return _Shape(crop, x0, y0, cx, cy, angle, float(along.min()), float(along.max() - along.min() + 1.0))


def _place_one(shape: _Shape, out, target, centre, binary, top=None):
    """Scale, rotate and translate a measured silhouette into ``out`` (see :func:`_register_one`)."""
    crop, cx, cy, angle = shape.crop, shape.cx, shape.cy, shape.angle
    bh, bw = crop.shape
    a = math.radians(angle)
    c, sn = math.cos(a), math.sin(a)
    s = target / shape.extent
    if top is not None:  # the extent's first row at canvas row ``top``
        centre = np.array([centre[0], top - s * shape.along_min])
    # R(-angle) maps the axis to the vertical (0, 1).
    rot = np.array([[c, sn], [-sn, c]])
    # Area-averaged resize of the crop to the nearest integer size.
    if s < 1.0:
        rw, rh = max(1, round(bw * s)), max(1, round(bh * s))
        small = cv2.resize(crop, (rw, rh), interpolation=cv2.INTER_AREA)
        sx, sy = rw / bw, rh / bh
    else:
        small, sx, sy = crop, 1.0, 1.0
    # Wanted: canvas = s * rot @ (q - c) + centre for crop pixel q. The resize maps
    # q to r with q = (r + 0.5) / (sx, sy) - 0.5, so the warp of the resized image is
    # canvas = s * rot @ diag(1/sx, 1/sy) @ r + s * rot @ (0.5 / (sx, sy) - 0.5 - c) + centre.
    inv = np.array([1.0 / sx, 1.0 / sy])
    m2 = np.empty((2, 3))
    m2[:, :2] = s * rot * inv[None, :]
    m2[:, 2] = s * rot @ (0.5 * inv - 0.5 - np.array([cx, cy])) + centre
    warped = cv2.warpAffine(small, m2, (out.shape[1], out.shape[0]), flags=cv2.INTER_LINEAR)
    if binary:
        np.greater(warped, 127, out=out, casting="unsafe")
    else:
        np.multiply(warped, np.float32(1.0 / 255.0), out=out)
    # Total map from input pixels: canvas = s * rot @ (u - x0 - cx, v - y0 - cy) + centre.
    u0, v0 = shape.x0 + cx, shape.y0 + cy
    total = np.empty((2, 3))
    total[:, :2] = s * rot
    total[:, 2] = centre - s * rot @ np.array([u0, v0])
    return total, s, angle, (u0, v0), shape.extent


def register_shares(
    silhouettes: Sequence[np.ndarray],
    hidden: Sequence[float],
    *,
    top: float,
    size: tuple[int, int] = DEFAULT_SIZE,
    height_fraction: float = _DEFAULT_HEIGHT_FRACTION,
    rotate: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`register` (binary, with ``top``) of the same silhouettes at each share ``hidden`` of the
    walker's height hidden below: ``(len(hidden), T, size[0], size[1])`` float32 and the (T,) valid
    mask. Each silhouette is measured once (:mod:`estimator.occlusion` searches the share)."""
    h, w = _check_size(size)
    if not all(0.0 <= f < 1.0 for f in hidden):
        raise ValueError(f"hidden shares must be in [0, 1), got {list(hidden)}")
    shapes = [_measure_one(s, rotate) for s in silhouettes]
    out = np.zeros((len(hidden), len(shapes), h, w), np.float32)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    for k, f in enumerate(hidden):
        target = height_fraction * h * (1.0 - f)
        for i, shape in enumerate(shapes):
            if shape is not None:
                _place_one(shape, out[k, i], target, centre, True, top)
    return out, np.array([shape is not None for shape in shapes], bool)


def transform_points(transforms: Transforms, points: np.ndarray) -> np.ndarray:
    """Map points from input pixels to the registered canvas.

    Parameters
    ----------
    transforms : Transforms
        From :func:`register`, for T silhouettes.
    points : ndarray of shape (T, J, 2)
        Points ``(u, v)`` in each input's pixel coordinates (e.g. the 13 joints).

    Returns
    -------
    ndarray of shape (T, J, 2)
        The points in canvas pixels (NaN for invalid registrations).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[0] != len(transforms) or points.shape[2] != 2:
        raise ValueError(f"points must have shape ({len(transforms)}, J, 2), got {points.shape}")
    m = transforms.matrix
    return np.einsum("tij,tkj->tki", m[:, :, :2], points) + m[:, None, :, 2]


def distance(registered: np.ndarray, means: np.ndarray) -> np.ndarray:
    """Distance of eq. 8 between registered silhouettes and cluster means, all pairs.

    Parameters
    ----------
    registered : ndarray of shape (T, h, w) or (h, w)
        Registered input silhouettes ``s_b`` with values in {0, 1} (from
        :func:`register` with ``binary=True``).
    means : ndarray of shape (K, h, w)
        Continuous cluster means ``s_c``, per-pixel foreground probabilities in [0, 1].

    Returns
    -------
    ndarray of shape (T, K), float32
        ``d[t, k] = sum(max(s'_b * s_c, s_b * s'_c))`` (eq. 8) with ``s' = 1 - s``.

    Notes
    -----
    At a pixel where ``a = s_b`` is 0 or 1 one of the two products ``(1 - a) b``
    and ``a (1 - b)`` is zero and the other is >= 0 (``b`` in [0, 1]), so their
    maximum is their sum, ``a + b - 2 a b``. Hence, exactly for binary ``a``,

        d = sum(a) + sum(b) - 2 a . b,

    one matrix product for all pairs. For a fractional ``a`` the same expression
    is the expected number of differing pixels between independent Bernoulli(a)
    and Bernoulli(b) images (the paper's reading of eq. 8: each flipped pixel
    weighted by the fraction of cluster members that differ). The inversion is
    taken as ``1 - s``: for a continuous mean the paper's literal "non-zero -> 0"
    would ignore how many members differ, which contradicts that reading.

    References
    ----------
    Izo & Grimson, §5, eq. 8.
    """
    a = np.asarray(registered, dtype=np.float32)
    b = np.asarray(means, dtype=np.float32)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or b.ndim != 3 or a.shape[1:] != b.shape[1:]:
        raise ValueError(
            f"registered must have shape (T, h, w) and means (K, h, w) with the same (h, w), "
            f"got {np.shape(registered)} and {np.shape(means)}"
        )
    a2 = a.reshape(len(a), -1)
    b2 = b.reshape(len(b), -1)
    return _distance_flat(a2, b2, b2.sum(1))


def _distance_flat(a2: np.ndarray, b2: np.ndarray, sum_b: np.ndarray) -> np.ndarray:
    """Eq. 8 on flattened float32 arrays: (T, P), (K, P), (K,) -> (T, K)."""
    d = a2 @ b2.T
    d *= -2.0
    d += a2.sum(1)[:, None]
    d += sum_b[None, :]
    return d
