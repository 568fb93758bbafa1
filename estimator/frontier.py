"""Pinhole cameras refined on the silhouettes' epipolar tangents (frontier points).

The rig from silhouettes (:mod:`estimator.rig`) adjusts pinhole cameras to the
2D postures mNBP measures; their errors are systematic (the torso is the
model's, the capsules are not the person's body), and with exact joints the
same adjustment is within 0.05 deg of the truth, so the postures, not the
cameras' model, limit the rig. A silhouette carries a constraint of its own
that no body model enters: the two epipolar lines tangent to one camera's
silhouette (the lines through the epipole that touch its outline) see the
same two *frontier points* on the body as the tangent lines in the other
camera, so each tangent line, carried across by the fundamental matrix,
must again touch the other silhouette (Cipolla, Åström & Giblin 1995; Wong
& Cipolla 2001; Sinha, Pollefeys & McMillan 2004, who calibrate camera
networks from walkers' silhouettes this way). This module adjusts each
camera's rotation, centre and focal length to those tangency conditions,
starting from the pinhole rig, with a weak prior that holds the rotations
near it.

Choices (none of the cited papers fixes them for this case):

- **Outlines as convex hulls** in full-frame pixels, the hull of the
  boundary pixels' corners (a pixel covers +-0.5 px about its centre, the
  coordinates' integers): an epipolar tangent touches the outline where it
  touches its hull. Frames whose walker touches the image border are left
  out (the border, not the body, would make the tangent). On frames the
  clean-up cut below the feet (a shadow removed) the vertices within a tenth
  of the walker's height above the cut are *loose* (the cut, and what is
  left of the shadow beside the feet): a tangent that touches one, at
  either end, is not used. Chosen on the tuning walks with a shadow (seed
  11): without it the tangents pulled 1 of 12 rigs 2 deg further off (5.99
  -> 7.98 deg); with the cut's own row only, or 3 % or 6 % of the height,
  some walks lost 0.5-1.2 deg; with 10 % none lost more than 0.5.
- **The residual** of a tangent line carried into the other image is its
  signed distance to the other hull's supporting line parallel to it: the
  lesser of the hull's largest signed distance and minus its smallest, in
  pixels (0 when it touches, positive when it cuts the hull, negative when
  it misses). It needs no matching of the two tangents, is continuous in
  the cameras (the tangent point jumps from vertex to vertex, the line does
  not), and is taken both ways (camera a's tangents in b, b's in a).
- **Left out**: a frame where an epipole lies in or near the hull (the
  tangents then span more than ``max_span_deg`` about it: cameras facing
  each other across the walker), and camera pairs with fewer than
  ``min_frames`` such frames.
- **Gauge**: the reference camera (index 0) fixed; the distance of camera 1
  from it held (a residual of weight 100 per unit of relative change), since
  tangency fixes no scale. Every focal length is free with a log-normal
  prior (``focal_sigma``) about its start: the pinhole adjustment on mNBP
  postures leaves focal lengths off by factors of 2 and more, and with them
  fixed the tangents pull the rotations the wrong way.
- **Robust, in two stages**: the ``soft_l1`` loss (a smooth L1, quadratic
  below ``f_scale`` pixels; scipy's trust-region least squares) brings the
  cameras near from the pinhole rig's 1-3 px; the ``cauchy`` loss, from
  there, sets aside frames whose outline the body did not make. A segmenter
  that loses a shin loses the foot with it, and the lowest tangent moves by
  tens of pixels on half the frames: soft L1 still follows them (seed 23
  with holes and cut limbs: 4 of 12 walks refused at 0.51-0.70 px), Cauchy
  alone from the start falls into other minima on clean walks (one of 12
  went 0.87 -> 3.3 deg); in turn they moved no clean walk by more than
  0.1 deg and brought the cut-limb walks' worst cameras from 4-18 deg to
  0.4-3.3 (docs/POSTURE.md).
- **Numerical Jacobian, batched**: the tangent points are vertices chosen by
  ``argmax``, so the residuals are piecewise smooth; their derivatives are
  taken by forward differences, each camera's parameters in one array
  evaluation over the pairs that camera is in (the others do not move).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .perspective import _hat
from .pinhole import PinholeCameras

__all__ = ["FrontierConfig", "FrontierResult", "Outlines", "outlines", "paired", "refine_on_tangents",
           "tangent_residuals"]

_CORNERS = np.array([[-0.5, -0.5], [-0.5, 0.5], [0.5, -0.5], [0.5, 0.5]])


@dataclass(frozen=True)
class FrontierConfig:
    """Settings of :func:`refine_on_tangents`.

    Attributes
    ----------
    prior_px_per_deg : float
        A camera's turn away from its start costs as much as this many pixels of
        tangent residual per degree. Chosen on the tuning walks (seed 11 of
        ``bench/eval_rig_from_silhouettes.py``; docs/POSTURE.md).
    losses : tuple of str
        The robust losses of scipy's ``least_squares``, one adjustment each, each
        from where the last ended: ``soft_l1`` (quadratic below ``f_scale``, then
        linear: a wide basin) brings the cameras near, ``cauchy`` (whose weight
        falls off with the residual) then sets aside the frames whose outline
        the body did not make (a foot cut off the silhouette moves the lowest
        tangent by tens of pixels on half the frames).
    f_scale : float
        Pixels where the loss leaves its quadratic part.
    focal_sigma : float
        Standard deviation of each log focal length's prior about its start.
    max_span_deg : float
        A frame's tangents are used only when the outline spans less than this
        angle about the epipole.
    min_frames : int
        A camera pair is used with at least this many frames of tangents.
    cut_band : float
        On frames cut below the feet, the outline this share of the walker's
        height above the cut is not used (:func:`outlines`).
    hold_std_deg, hold_px_per_deg : float
        When the tangents alone leave a camera's rotation less well determined
        than ``hold_std_deg`` (``FrontierResult.rotation_std_deg``; two cameras
        on a straight walk, 1.6-22 deg), the adjustment is run again with each
        direction of the rotations' posterior wider than that held where it
        started, at ``hold_px_per_deg`` pixels of residual per degree.
    max_nfev : int
        Evaluations of the residuals at most (scipy's ``least_squares``).
    ftol : float
        Relative change of the cost (and of the parameters) at which the
        adjustment stops (``least_squares``' ``ftol`` and ``xtol``).
    """

    prior_px_per_deg: float = 0.1
    losses: tuple[str, ...] = ("soft_l1", "cauchy")
    f_scale: float = 1.0
    focal_sigma: float = 1.0
    max_span_deg: float = 150.0
    min_frames: int = 8
    cut_band: float = 0.1
    max_nfev: int = 200
    ftol: float = 1e-5
    hold_std_deg: float = 1.5
    hold_px_per_deg: float = 10.0


@dataclass
class Outlines:
    """One camera's silhouette outlines as convex hulls.

    Attributes
    ----------
    vertices : ndarray of shape (T, V, 2)
        Hull vertices in full-frame pixels, padded by repeating the first one.
    valid : ndarray of shape (T,), bool
        Frames with an outline (a silhouette clear of the image border).
    loose : ndarray of shape (T, V), bool
        Vertices not on the body's outline (on a cut below the feet): a
        tangent touching one is not used.
    """

    vertices: np.ndarray
    valid: np.ndarray
    loose: np.ndarray


@dataclass
class FrontierResult:
    """Cameras after :func:`refine_on_tangents`, in the reference camera's frame.

    Attributes
    ----------
    rotations, centres, focal_px : ndarray of shape (C, 3, 3), (C, 3), (C,)
    residual_px : (float, float)
        Median absolute tangent residual at the start and at the end (inf at the
        end when the adjusted cameras leave no outline pair to measure).
    pairs : list of (int, int)
        Camera pairs that had enough frames of tangents.
    frames : int
        Frames of tangents over those pairs.
    rotation_std_deg : ndarray of shape (C,)
        How well the tangents alone determine each camera's rotation: the
        largest posterior standard deviation of its rotation vector's
        components (Laplace approximation without the prior), degrees; 0 for
        the reference (inf where no tangent was left to measure it). Two
        cameras on a straight walk are often poorly determined (3-8 deg on
        the tuning walks): see ``held``.
    held : int
        Directions of the rotations held at the start (``hold_std_deg``).
    """

    rotations: np.ndarray
    centres: np.ndarray
    focal_px: np.ndarray
    residual_px: tuple[float, float]
    pairs: list[tuple[int, int]]
    frames: int
    rotation_std_deg: np.ndarray
    held: int = 0


def outlines(silhouettes: list[np.ndarray | None], boxes: np.ndarray, image_size: tuple[int, int],
             cut: np.ndarray | None = None, cut_band: float = 0.1) -> Outlines:
    """The convex hull of each frame's silhouette crop, in full-frame pixels (``boxes``: ``x, y, w, h``).

    ``cut`` (T,) marks frames the clean-up cut below the feet: their vertices
    within ``cut_band`` of the crop's height above its bottom (the cut, and
    what is left of the shadow beside the feet) are marked ``loose``.
    """
    width, height = image_size
    boxes = np.asarray(boxes, float)
    hulls: list[np.ndarray | None] = []
    for s, box in zip(silhouettes, boxes):
        hull = None
        if s is not None and np.all(np.isfinite(box)) and box[0] > 0 and box[1] > 0 \
                and box[0] + box[2] < width and box[1] + box[3] < height:
            contours, _ = cv2.findContours((s > 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            if contours:
                inner = cv2.convexHull(np.concatenate(contours)).reshape(-1, 2).astype(np.float32)
                corners = (inner[:, None] + _CORNERS.astype(np.float32)).reshape(-1, 2)
                hull = cv2.convexHull(corners).reshape(-1, 2).astype(float) + box[:2]
        hulls.append(hull)
    n = max([len(h) for h in hulls if h is not None] + [1])
    vertices = np.zeros((len(hulls), n, 2))
    for t, h in enumerate(hulls):
        if h is not None:
            vertices[t] = np.concatenate([h, np.repeat(h[:1], n - len(h), axis=0)])
    bottom = boxes[:, 1] + boxes[:, 3] - 0.5  # the bottom row's lower edge (pixel centres are integers)
    was_cut = np.zeros(len(hulls), bool) if cut is None else np.asarray(cut, bool)
    loose = was_cut[:, None] & (vertices[..., 1] > bottom[:, None] - 1.0 - cut_band * boxes[:, 3:4])
    return Outlines(vertices, np.array([h is not None for h in hulls]), loose)


def paired(shapes: list[Outlines], pairs: np.ndarray) -> tuple[np.ndarray, ...]:
    """The outlines of camera pairs (P, 2) as :func:`tangent_residuals` takes them: the first and the
    second camera's vertices (P, T, V, 2), padded to one V, the frames where both exist (P, T), and
    the first and the second camera's loose vertices (P, T, V)."""
    n = max(s.vertices.shape[1] for s in shapes)

    def pad(a: np.ndarray) -> np.ndarray:
        return np.concatenate([a, np.repeat(a[:, :1], n - a.shape[1], axis=1)], axis=1)

    vertices = [pad(s.vertices) for s in shapes]
    loose = [pad(s.loose) for s in shapes]
    a, b = pairs[:, 0], pairs[:, 1]
    return (np.stack([vertices[i] for i in a]), np.stack([vertices[i] for i in b]),
            np.stack([shapes[i].valid & shapes[j].valid for i, j in pairs]),
            np.stack([loose[i] for i in a]), np.stack([loose[i] for i in b]))


def _pick(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``a`` (P, T, V, ...) at vertex ``index`` (..., P, T, K): (..., P, T, K, ...)."""
    extra = a.shape[3:]
    every = np.broadcast_to(a, index.shape[:-3] + a.shape)
    idx = index.reshape(index.shape + (1,) * len(extra))
    return np.take_along_axis(every, np.broadcast_to(idx, index.shape + extra), axis=-1 - len(extra))


def _tangent_points(hull: np.ndarray, epipole: np.ndarray, max_span: float) -> tuple[np.ndarray, ...]:
    """The two hull vertices of extreme angle about the epipole: points (..., P, T, 2, 2), their
    indices (..., P, T, 2) and whether they exist (..., P, T).

    ``hull`` (P, T, V, 2), ``epipole`` (..., P, 2), finite (a far one is far, not at infinity).
    """
    v = hull - epipole[..., None, None, :]  # (..., P, T, V, 2)
    r = hull.mean(axis=-2) - epipole[..., None, :]  # the centroid's direction (..., P, T, 2)
    angle = np.arctan2(r[..., None, 0] * v[..., 1] - r[..., None, 1] * v[..., 0],
                       r[..., None, 0] * v[..., 0] + r[..., None, 1] * v[..., 1])
    index = np.stack([angle.argmin(axis=-1), angle.argmax(axis=-1)], axis=-1)
    ends = np.take_along_axis(angle, index, -1)
    return _pick(hull, index), index, ends[..., 1] - ends[..., 0] < max_span


def _carried(points: np.ndarray, fundamental: np.ndarray, hull: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed gap (..., P, T, 2) between each point's epipolar line ``F p`` and the other hull's tangent
    parallel to it, and the index of the vertex that tangent touches (..., P, T, 2)."""
    lines = np.einsum("...pij,...ptkj->...ptki", fundamental,
                      np.concatenate([points, np.ones(points.shape[:-1] + (1,))], axis=-1))
    lines = lines / np.linalg.norm(lines[..., :2], axis=-1, keepdims=True)
    d = np.einsum("...ptkj,ptvj->...ptkv", lines[..., :2], hull) + lines[..., 2:3]
    high, low = d.max(axis=-1), -d.min(axis=-1)
    return np.minimum(high, low), np.where(high <= low, d.argmax(axis=-1), d.argmin(axis=-1))


def tangent_residuals(matrices: np.ndarray, rotations: np.ndarray, centres: np.ndarray, hulls: tuple,
                      pairs: np.ndarray, max_span_deg: float = 150.0) -> tuple[np.ndarray, np.ndarray]:
    """Tangent residuals (..., P, T, 4) in pixels of batches of rigs, and which exist (..., P, T, 4).

    ``matrices``, ``rotations`` (..., C, 3, 3) and ``centres`` (..., C, 3) are
    pinhole cameras ``x = K R (X - C)``; ``hulls`` are the pairs' outlines as
    :func:`paired` gives them; ``pairs`` (P, 2) camera indices. A residual
    does not exist (and is 0) on a frame without both outlines, where an
    epipole lies in or near an outline, or where either end of it touches a
    loose vertex (on a cut below the feet).
    """
    first, second, valid, loose_first, loose_second = hulls
    a, b = pairs[:, 0], pairs[:, 1]
    ka, kb, ra, rb, ca, cb = (matrices[..., a, :, :], matrices[..., b, :, :], rotations[..., a, :, :],
                              rotations[..., b, :, :], centres[..., a, :], centres[..., b, :])
    e_a = np.einsum("...ij,...jk,...k->...i", ka, ra, cb - ca)  # b's centre seen by a (homogeneous)
    e_b = np.einsum("...ij,...jk,...k->...i", kb, rb, ca - cb)

    def finite(e):
        w = e[..., 2:3]
        return e[..., :2] / np.where(np.abs(w) < 1e-12, np.copysign(1e-12, w), w)

    max_span = np.radians(max_span_deg)
    pa, ia, ok_a = _tangent_points(first, finite(e_a), max_span)
    pb, ib, ok_b = _tangent_points(second, finite(e_b), max_span)
    # F with x_b^T F x_a = 0 (Hartley & Zisserman eq. 9.2, cameras K [R | -R C])
    relative = rb @ np.swapaxes(ra, -1, -2)
    f = np.swapaxes(np.linalg.inv(kb), -1, -2) @ _hat(np.einsum("...ij,...j->...i", rb, ca - cb)) \
        @ relative @ np.linalg.inv(ka)
    gap_ab, touch_b = _carried(pa, f, second)
    gap_ba, touch_a = _carried(pb, np.swapaxes(f, -1, -2), first)
    res = np.concatenate([gap_ab, gap_ba], axis=-1)
    firm = ~np.concatenate([_pick(loose_first, ia) | _pick(loose_second, touch_b),
                            _pick(loose_second, ib) | _pick(loose_first, touch_a)], axis=-1)
    ok = (valid & ok_a & ok_b)[..., None] & firm
    return np.where(ok, res, 0.0), ok


def refine_on_tangents(focal_px: np.ndarray, principal_px: np.ndarray, rotations: np.ndarray, centres: np.ndarray,
                       shapes: list[Outlines], config: FrontierConfig = FrontierConfig()) -> FrontierResult | None:
    """Pinhole cameras adjusted to their silhouettes' epipolar tangents (this stage's entry).

    ``rotations`` (C, 3, 3) world-to-camera with ``rotations[0]`` the
    identity, ``centres`` (C, 3) with ``centres[0]`` the origin (any unit:
    the result keeps camera 1's distance), ``focal_px`` (C,), ``principal_px``
    (C, 2), one :class:`Outlines` per camera over the same frames. None when
    no camera pair has ``config.min_frames`` frames of tangents.
    """
    n_cam = len(rotations)
    rotations, centres = np.asarray(rotations, float), np.asarray(centres, float)
    k0 = PinholeCameras.from_centres(np.asarray(focal_px, float), np.asarray(principal_px, float), rotations,
                                     centres).matrices
    all_pairs = np.array([(a, b) for a in range(n_cam) for b in range(a + 1, n_cam)], int).reshape(-1, 2)
    hulls = paired(shapes, all_pairs)
    start, started = tangent_residuals(k0, rotations, centres, hulls, all_pairs, config.max_span_deg)
    keep = started.any(axis=-1).sum(axis=1) >= config.min_frames
    if not keep.any():
        return None
    pairs, start, started = all_pairs[keep], start[keep], started[keep]
    hulls = tuple(h[keep] for h in hulls)
    distance = float(np.linalg.norm(centres[1]))
    n_rot = 3 * (n_cam - 1)

    def cameras(x: np.ndarray):
        """Batches of parameter vectors (B, n) -> K, R, C of shape (B, C, ...)."""
        rv = x[:, :n_rot].reshape(len(x), n_cam - 1, 3)
        turn = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(len(x), n_cam - 1, 3, 3)
        r = np.concatenate([np.broadcast_to(rotations[:1], (len(x), 1, 3, 3)), turn @ rotations[1:]], axis=1)
        c = np.concatenate([np.broadcast_to(centres[:1], (len(x), 1, 3)),
                            centres[1:] + x[:, n_rot:2 * n_rot].reshape(len(x), n_cam - 1, 3)], axis=1)
        k = np.repeat(k0[None], len(x), axis=0)
        k[..., 0, 0] = k[..., 1, 1] = k0[:, 0, 0] * np.exp(x[:, 2 * n_rot:])
        return k, r, c, rv

    def tangents(x: np.ndarray, sel: slice | np.ndarray = slice(None)) -> np.ndarray:
        """(B, P', T, 4) tangent residuals of a batch of parameter vectors, on the pairs ``sel``."""
        k, r, c, _ = cameras(x)
        return tangent_residuals(k, r, c, tuple(h[sel] for h in hulls), pairs[sel], config.max_span_deg)[0]

    hold = np.zeros((0, n_rot))  # rotation directions held at the start (rows), set after a first solve

    def priors(x: np.ndarray) -> np.ndarray:
        """(B, n_rot + 1 + C + H) rows of the rotation prior, the gauge, the focal lengths' prior and the
        held directions."""
        moved = centres[1] + x[:, n_rot:n_rot + 3]
        gauge = 100.0 * (np.linalg.norm(moved, axis=-1) - distance) / distance
        return np.concatenate([config.prior_px_per_deg * np.degrees(x[:, :n_rot]), gauge[:, None],
                               x[:, 2 * n_rot:] / config.focal_sigma,
                               config.hold_px_per_deg * np.degrees(x[:, :n_rot] @ hold.T)], axis=1)

    def residuals(x: np.ndarray) -> np.ndarray:
        """(B, m) residuals of a batch of parameter vectors."""
        return np.concatenate([tangents(x).reshape(len(x), -1), priors(x)], axis=1)

    step = 1e-6
    # each camera's parameters (rotation, centre, log focal length) move only the pairs it is in
    owner = np.r_[np.repeat(np.arange(1, n_cam), 3), np.repeat(np.arange(1, n_cam), 3), np.arange(n_cam)]
    n_tan = start.size

    def jacobian(x: np.ndarray) -> np.ndarray:
        """Forward differences, each camera's parameters evaluated on its own pairs only."""
        moved = x + step * np.eye(len(x))
        prior = priors(x[None])
        jac = np.zeros((n_tan + prior.shape[1], len(x)))
        base = tangents(x[None])[0]
        for cam in range(n_cam):
            cols, sel = np.flatnonzero(owner == cam), (pairs == cam).any(axis=1)
            if not sel.any():  # a camera in no pair with tangents: its priors alone hold it
                continue
            diff = (tangents(moved[cols], sel) - base[sel]) / step  # (k, P', T, 4)
            jac[:n_tan].reshape(len(pairs), -1, len(x))[np.ix_(sel, np.arange(base[0].size), cols)] = \
                diff.reshape(len(cols), sel.sum(), -1).transpose(1, 2, 0)
        jac[n_tan:] = ((priors(moved) - prior) / step).T
        return jac

    def solve() -> np.ndarray:
        x = np.zeros(2 * n_rot + n_cam)
        for loss in config.losses:
            x = least_squares(lambda x: residuals(x[None])[0], x, jac=jacobian, loss=loss, f_scale=config.f_scale,
                              x_scale="jac", max_nfev=config.max_nfev, ftol=config.ftol, xtol=config.ftol).x
        return x

    x = solve()
    k, r, c, _ = cameras(x[None])
    res, used = tangent_residuals(k[0], r[0], c[0], hulls, pairs, config.max_span_deg)
    # Laplace approximation from the tangents alone (the rotation prior's rows left out), the noise
    # read from the residuals' median (robust: 1.4826 x the median absolute value)
    jac = jacobian(x)
    tangent_rows = np.r_[np.arange(res.size), np.arange(res.size + n_rot, n_tan + n_rot + 1 + n_cam)]
    sigma = 1.4826 * _median_abs(res[used])
    info = jac[tangent_rows].T @ jac[tangent_rows]
    with np.errstate(invalid="ignore"):
        cov = np.linalg.pinv(info)[:n_rot, :n_rot] * sigma ** 2
    spread = np.degrees(np.sqrt(np.clip(np.diag(cov), 0.0, None))).reshape(-1, 3).max(axis=1)
    if spread.max() > config.hold_std_deg and np.all(np.isfinite(cov)):
        # the directions the tangents hardly see follow the outlines' faults: held where they started
        value, vector = np.linalg.eigh(cov)
        hold = vector[:, value > np.radians(config.hold_std_deg) ** 2].T
        if len(hold):
            x = solve()
            k, r, c, _ = cameras(x[None])
            res, used = tangent_residuals(k[0], r[0], c[0], hulls, pairs, config.max_span_deg)
    return FrontierResult(r[0], c[0], k[0, :, 0, 0], (_median_abs(start[started]), _median_abs(res[used])),
                          [tuple(int(i) for i in p) for p in pairs], int(used.any(axis=-1).sum()), np.r_[0.0, spread],
                          len(hold))


def _median_abs(residuals: np.ndarray) -> float:
    """Median absolute residual (px); inf when no tangent is left to measure (the cameras moved so
    that no outline pair faces the other camera any more)."""
    return float(np.median(np.abs(residuals))) if residuals.size else np.inf
