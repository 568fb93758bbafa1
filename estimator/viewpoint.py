"""Camera viewpoint from the cloud of matched examples' viewpoints (Izo–Grimson §3 step 4).

The viewpoints (azimuth, elevation) of all examples in the clusters matched
over a window form a cloud; a 2D Gaussian (the paper's ellipse) fitted to it,
with azimuth on the circle, gives the estimate (its centre) and a spread.

Silhouettes seen from azimuth ``a`` and ``180 - a`` are nearly the same shape
(the body's left/right mirror symmetry plus projection from the opposite side),
so the cloud may have two modes: ahead-left vs behind-left. The walker's motion
in the full frame tells them apart (§3 step 4): a walker who grows is
approaching (``cos a > 0``), one moving towards the image's left is seen from
their left (``sin a > 0``). Each sample is folded onto the side the motion
indicates before the fit; without a motion cue (cropped silhouettes) the larger
mode wins and the result says the flip was not resolved.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

__all__ = ["MotionCue", "Viewpoint", "azimuth_difference_deg", "circular_mean_deg", "elevation_from_path",
           "estimate_viewpoint", "head_points", "motion_cue", "with_path_elevation"]


def azimuth_difference_deg(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Signed difference ``a - b`` of azimuths on the circle, in [-180, 180)."""
    return (np.asarray(a, dtype=float) - b + 180.0) % 360.0 - 180.0


FALL_MIN_ELEVATION_DEG = 5.0
"""Default of :func:`estimate_viewpoint`'s ``fall_min_elevation_deg``: the feet's path settles
ahead/behind (:meth:`MotionCue.fall_sign`) only where the viewpoint's cloud is at least this far above the
walker; a camera below the walker's centroid may be below its feet too (the synthetic grid goes down to
-20 deg), where the feet's path reads the other way."""


@dataclass(frozen=True)
class MotionCue:
    """How the walker moves in one camera's full frame over a window.

    Attributes
    ----------
    growth : float
        Relative change of the walker's image size per frame (> 0: approaching).
    travel : float
        Horizontal motion per frame, in body heights (> 0: towards the image's right).
    n_frames : int
        Frames with a box.
    growth_se : float
        Standard error of ``growth`` (0: taken as exact).
    source : str
        What ``growth`` was measured from: ``"head"`` (the perspective curvature
        of the head's image path), ``"height"`` (the silhouette's height), or
        ``"head+height"`` (both, weighted by their errors); where the heights
        end on a fixed edge, ``"head width"`` (the head's size) or ``"head+head
        width"``, and ``"none"`` when nothing could be measured (``growth_se``
        is infinite).
    conflict : bool
        The head's path and the height (or the head's width) disagreed (by
        more than ``motion_cue``'s ``conflict`` errors) and one was dropped.
        Where the head's path is what was kept, the sign of ``growth`` is
        contested, and :func:`estimator.pipeline.estimate_walk` lets the other
        cameras settle ahead/behind.
    fall, fall_se : float
        The foot point's motion down the image per frame, in body heights
        (> 0: approaching, for a camera above the ground), and its standard
        error (inf: not measured, e.g. feet cut by the clean-up).
    head_velocity, head_velocity_cov : tuple
        The head's image velocity (u right, v down) at the window's middle, in
        body heights per frame, from the same perspective fit as the head's
        growth, and its 2 x 2 covariance (NaN and inf: not measured). Its
        direction tells the elevation (:func:`elevation_from_path`).
    """

    growth: float
    travel: float
    n_frames: int
    growth_se: float = 0.0
    source: str = "height"
    conflict: bool = False
    fall: float = 0.0
    fall_se: float = float("inf")
    head_velocity: tuple[float, float] = (float("nan"), float("nan"))
    head_velocity_cov: tuple[tuple[float, float], tuple[float, float]] = ((float("inf"), 0.0), (0.0, float("inf")))

    def signs(self, *, z: float = 3.0, min_travel: float = 0.01) -> tuple[int, int]:
        """(sign of cos azimuth, sign of sin azimuth) the motion implies; 0 = no evidence.

        Growth is evidence when it is ``z`` standard errors from zero.
        """
        cos_sign = int(np.sign(self.growth)) if abs(self.growth) > z * self.growth_se else 0
        sin_sign = int(-np.sign(self.travel)) if abs(self.travel) >= min_travel else 0
        return cos_sign, sin_sign

    def fall_sign(self, *, z: float = 3.0) -> int:
        """The sign of cos azimuth the feet's motion down the image implies (0: no evidence).

        Any camera above the ground sees a receding walker's feet rise towards
        the horizon: for a level camera at height ``H_c`` the foot point lies
        ``h H_c / H_p`` pixels below the horizon (``h`` the walker's image
        height, ``H_p`` its stature), so its fall in heights per frame is
        ``H_c / H_p`` times ``growth``: on a camera above a walker's head, a
        larger signal than the size change (vtest.avi: 2-4 times). Only for
        cameras that look down on the walker (:func:`estimate_viewpoint`).
        """
        return int(np.sign(self.fall)) if abs(self.fall) > z * self.fall_se else 0


class HeadBand(NamedTuple):
    """:func:`head_band`'s measures per frame, NaN where the frame has no silhouette."""

    points: np.ndarray  # (T, 2): the band's centroid in the full frame
    widths: np.ndarray  # (T,): the band's mean width in pixels


def head_band(silhouettes: list[np.ndarray | None], boxes: np.ndarray, *, depth: float = 0.08) -> HeadBand:
    """The top of the head per frame: the silhouette's top ``depth`` of the window's median height.

    Its centroid is a point of the body that shadows, reflections, cut limbs and
    walls, all at the feet, leave alone (a raised arm or something carried
    overhead moves it: those frames are the robust fit's outliers,
    :func:`motion_cue`). Its mean width is the head's size: the band holds the
    head from the crown to about the eyes, so it grows and shrinks with the
    walker's image while the pixels' depth stays fixed.
    ``silhouettes`` are tight crops whose boxes ``(x, y, w, h)`` are ``boxes``.
    """
    boxes = np.asarray(boxes, dtype=float)
    points, widths = np.full((len(silhouettes), 2), np.nan), np.full(len(silhouettes), np.nan)
    ok = [t for t, s in enumerate(silhouettes) if s is not None and np.isfinite(boxes[t, 3])]
    if not ok:
        return HeadBand(points, widths)
    rows = max(2, int(round(depth * np.median(boxes[ok, 3]))))
    for t in ok:
        v, u = np.nonzero(silhouettes[t][:rows])
        if u.size:
            points[t] = boxes[t, 0] + u.mean(), boxes[t, 1] + v.mean()
            if silhouettes[t].shape[0] >= rows:
                widths[t] = u.size / rows
    return HeadBand(points, widths)


def head_points(silhouettes: list[np.ndarray | None], boxes: np.ndarray, *, depth: float = 0.08) -> np.ndarray:
    """The top of the head per frame in the full frame: (T, 2), NaN where no silhouette
    (:func:`head_band`'s centroids)."""
    return head_band(silhouettes, boxes, depth=depth).points


class _HeadPath(NamedTuple):
    """:func:`_head_path`'s fit: growth per frame and its standard error, the image velocity (px per
    frame) at the window's middle and its covariance."""

    growth: float
    growth_se: float
    velocity: np.ndarray  # (2,)
    velocity_cov: np.ndarray  # (2, 2)


def _head_path(t: np.ndarray, points: np.ndarray, *, floor_px: float = 0.3) -> _HeadPath:
    """The image path of a point moving steadily along a straight line: in homogeneous
    coordinates the path is linear in time, so ``x(t) = (a + b t) / (1 + c t)`` in both image
    axes with one ``c``, and the walker's image size goes as ``1 / (1 + c t)``: growth ``-c`` at
    the window's middle, velocity ``b - a c`` there. Linear least squares in
    ``(a_x, b_x, a_y, b_y, c)`` from ``x = a + b t - c t x`` (each axis shifted by its median
    first, which keeps ``c``, and weighted by its own robust noise, at least ``floor_px``:
    whole-pixel positions); frames 3 sigmas off on either axis are dropped, then it is refitted.
    """
    tc = t - t.mean()
    n = len(tc)
    p = points - np.median(points, axis=0)
    one, zero = np.ones(n), np.zeros(n)
    A = np.concatenate([np.stack([one, tc, zero, zero, -tc * p[:, 0]], 1),
                        np.stack([zero, zero, one, tc, -tc * p[:, 1]], 1)])
    b = p.T.ravel()
    keep = np.ones(n, bool)
    for last in (False, True):
        sol = np.linalg.lstsq(A[np.tile(keep, 2)], b[np.tile(keep, 2)], rcond=None)[0]
        resid = (b - A @ sol).reshape(2, n)
        sigma = np.maximum(1.4826 * np.median(np.abs(resid[:, keep]), axis=1), floor_px)  # per axis
        if last:
            break
        keep = np.all(np.abs(resid) <= 3 * sigma[:, None], axis=0)
        if keep.sum() < 6:
            return _HeadPath(0.0, np.inf, np.full(2, np.nan), np.diag([np.inf, np.inf]))
    rows = np.tile(keep, 2)
    w = np.repeat(1.0 / sigma, n)[rows]
    aw, bw = A[rows] * w[:, None], b[rows] * w
    sol = np.linalg.lstsq(aw, bw, rcond=None)[0]
    dof = max(aw.shape[0] - aw.shape[1], 1)
    s2 = float(np.sum((bw - aw @ sol) ** 2)) / dof  # the axes' weights are relative; their scale is fitted
    r_inv = np.linalg.pinv(np.linalg.qr(aw, mode="r"))
    cov = s2 * (r_inv @ r_inv.T)
    ax, bx, ay, by, c = sol
    jac = np.array([[-c, 1.0, 0.0, 0.0, -ax], [0.0, 0.0, -c, 1.0, -ay]])  # of (b - a c) in each axis
    return _HeadPath(float(-c), float(np.sqrt(cov[4, 4])), np.array([bx - ax * c, by - ay * c]), jac @ cov @ jac.T)


def _theil_sen(t: np.ndarray, y: np.ndarray, *, floor: float = 0.0) -> tuple[float, float]:
    """Median of pairwise slopes, and its standard error from the residuals' MAD (at least ``floor``)."""
    i, j = np.triu_indices(len(t), 1)
    slope = float(np.median((y[j] - y[i]) / (t[j] - t[i])))
    resid = y - slope * t
    sigma = max(1.4826 * np.median(np.abs(resid - np.median(resid))), floor)
    return slope, float(sigma / np.sqrt(np.sum((t - t.mean()) ** 2)))


def motion_cue(boxes: np.ndarray, heads: np.ndarray | None = None, *, feet_cut: bool = False,
               heights: bool | np.ndarray = True, head_widths: np.ndarray | None = None,
               conflict: float = 3.0) -> MotionCue | None:
    """Fit the walker's motion from full-frame boxes (and head points).

    Parameters
    ----------
    boxes : ndarray of shape (T, 4)
        ``(x, y, width, height)`` of the silhouette in the full frame per frame;
        NaN rows where the camera has no silhouette.
    heads : ndarray of shape (T, 2), optional
        The head's image position per frame (:func:`head_points`). Its path's
        perspective curvature gives the growth independently of the feet,
        which shadows, reflections and cut limbs corrupt; the silhouette's
        height gives it too. Both are combined by their standard errors.
    feet_cut : bool
        The clean-up cut something off below the feet (a shadow or a
        reflection): the heights then carry the cut's error, which drifts over
        the window. When the two growths disagree by more than ``conflict``
        errors, the head alone counts if the feet were cut, the height alone
        otherwise (a walker who speeds up or slows down bends the head's path
        as approaching would: CMU 07_05).
    heights : bool or ndarray of shape (T,), bool
        The frames whose silhouette's height is the walker's size (all: True).
        Not those that end on an edge fixed in the image
        (:func:`estimator.cleanup.fixed_edge`): the visible part shrinks as
        the walker nears a camera that looks over a wall. The heights and the
        feet's fall are read on the others; with fewer than 3 of them the
        growth is the head's: from ``head_widths`` and the head's path, and 0
        with an infinite error (no evidence) without either.
    head_widths : ndarray of shape (T,), optional
        The head's width per frame (:func:`head_band`), for the growth where no
        height tells it (fewer than 3 ``heights`` frames). Its log's slope is
        combined with the head path's by their errors; where the two disagree
        by more than ``conflict`` errors the width alone counts: a walker who
        slows down bends the head's path as approaching would (CMU 07_05),
        and only their distance changes the head's size.

    Returns
    -------
    MotionCue or None
        None when fewer than 3 frames have a box.
    """
    boxes = np.asarray(boxes, dtype=float)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"boxes must have shape (T, 4), got {boxes.shape}")
    ok = np.all(np.isfinite(boxes), axis=1) & (boxes[:, 3] > 0)
    if ok.sum() < 3:
        return None
    t = np.flatnonzero(ok).astype(float)
    x, y, w, h = boxes[ok].T
    sized = np.broadcast_to(np.asarray(heights, bool), (len(boxes),))[ok]
    sized = sized if sized.sum() >= 3 else np.zeros_like(sized)
    # Robust slopes (Theil-Sen: median of pairwise slopes) resist a bad frame.
    # Heights are whole pixels: their log is known to 1 / (sqrt(12) h) at best.
    pixel = 1.0 / (np.sqrt(12.0) * np.median(h))  # a whole-pixel edge, in walker heights
    unknown = (0.0, float("inf"))
    growth, se = _theil_sen(t[sized], np.log(h[sized]), floor=pixel) if sized.any() else unknown
    travel, _ = _theil_sen(t, (x + w / 2) / np.median(h))
    fall, fall_se = unknown if feet_cut or not sized.any() else \
        _theil_sen(t[sized], (y + h)[sized] / np.median(h), floor=pixel)
    source, conflict_seen = "height" if sized.any() else "none", False
    if not sized.any() and head_widths is not None:  # a wall across the window: the head's size instead
        widths = np.asarray(head_widths, dtype=float)
        if widths.shape != (len(boxes),):
            raise ValueError(f"head_widths must have shape ({len(boxes)},), got {widths.shape}")
        wk = ok & np.isfinite(widths) & (widths > 0)
        if wk.sum() >= 6:
            growth, se = _theil_sen(np.flatnonzero(wk).astype(float), np.log(widths[wk]),
                                    floor=1.0 / (np.sqrt(12.0) * np.median(widths[wk])))
            source = "head width"
    velocity, velocity_cov = MotionCue.head_velocity, MotionCue.head_velocity_cov
    if heads is not None:
        heads = np.asarray(heads, dtype=float)
        if heads.shape != (len(boxes), 2):
            raise ValueError(f"heads must have shape ({len(boxes)}, 2), got {heads.shape}")
        hk = ok & np.all(np.isfinite(heads), axis=1)
        if hk.sum() >= 6:
            th = np.flatnonzero(hk).astype(float)
            path = _head_path(th, heads[hk])
            g_head, se_head = path.growth, path.growth_se
            travel, _ = _theil_sen(th, heads[hk, 0] / np.median(h))
            velocity = (float(path.velocity[0] / np.median(h)), float(path.velocity[1] / np.median(h)))
            velocity_cov = tuple(map(tuple, path.velocity_cov / np.median(h) ** 2))
            if source == "none":
                growth, se, source = g_head, se_head, "head"
            elif np.isfinite(se_head):
                if abs(growth - g_head) > conflict * np.hypot(se, se_head):
                    conflict_seen = True
                    if feet_cut and source == "height":
                        growth, se, source = g_head, se_head, "head"
                else:
                    wa, wb = 1 / se**2, 1 / se_head**2
                    growth, se, source = (wa * growth + wb * g_head) / (wa + wb), float(np.sqrt(1 / (wa + wb))), \
                        f"head+{source}"
    return MotionCue(growth=growth, travel=travel, n_frames=int(ok.sum()), growth_se=se, source=source,
                     conflict=conflict_seen, fall=fall, fall_se=fall_se, head_velocity=velocity,
                     head_velocity_cov=velocity_cov)


HEAD_ABOVE_CENTROID = 0.45
"""The head point (:func:`head_points`) above the body's centroid, in statures: the model's body
(the 13 joints' mean at 0.90 m of 1.75 m, the top 8 %'s centroid at about 1.68 m)."""


def elevation_from_path(cue: MotionCue, azimuth_deg: float, azimuth_se_deg: float, *,
                        head_above: float = HEAD_ABOVE_CENTROID) -> tuple[float, float]:
    """The elevation (deg) that the walker's straight image path implies at ``azimuth_deg``, and its
    standard error; (NaN, inf) when the path was not measured.

    The elevation is read from the silhouettes' shape (§3 step 4), mostly from the legs; this
    reads it from where the walker goes in the image instead. Walking along x, the walker moves
    in the image of a camera at azimuth ``a`` and elevation ``e`` along the first two rows of
    :func:`estimator.camera.world_to_camera_rotation` applied to x, ``(-sin a, sin e cos a)``
    (scaled orthographic), so ``sin e = -(v / u) tan a`` for the body's centroid's image velocity
    ``(u, v)``. The head's is measured (:attr:`MotionCue.head_velocity`, nothing at the feet
    touches it): the head lies ``head_above`` of the height over the centroid, so as the walker's
    image grows by ``growth`` per frame it rises over the centroid by ``head_above * growth``
    heights. Side views move across the image whatever the elevation and a frontal view hardly
    sideways; the error (the velocity's, the growth's and ``azimuth_se_deg``) says how little
    they tell.
    """
    (u, v), cov = cue.head_velocity, np.asarray(cue.head_velocity_cov, float)
    if not (np.isfinite(u) and np.isfinite(v) and np.all(np.isfinite(cov)) and u != 0.0):
        return float("nan"), float("inf")
    growth_se = cue.growth_se if np.isfinite(cue.growth_se) else 0.0
    vc = v + head_above * cue.growth
    if abs(azimuth_deg % 180.0 - 90.0) < 2.0 * azimuth_se_deg:  # within 2 errors of a side view,
        return float("nan"), float("inf")  # where tan a changes sign: the elevation's sign is not known
    a = np.radians(azimuth_deg)
    tan_a = np.tan(a)
    sin_e = -vc / u * tan_a
    grad = np.array([vc * tan_a / u**2, -tan_a / u])  # d sin_e / d (u, v)
    var = grad @ cov @ grad + (tan_a / u * head_above * growth_se) ** 2 \
        + (vc / u / np.cos(a) ** 2 * np.radians(azimuth_se_deg)) ** 2
    if abs(sin_e) - 1.0 > 2.0 * np.sqrt(var):  # no elevation moves so: the azimuth or the path is wrong
        return float("nan"), float("inf")
    e = float(np.degrees(np.arcsin(np.clip(sin_e, -1.0, 1.0))))
    return e, float(np.degrees(np.sqrt(var) / np.sqrt(max(1.0 - sin_e**2, 0.01))))


def with_path_elevation(vp: Viewpoint, cue: MotionCue | None) -> Viewpoint:
    """The viewpoint with its elevation and the path's (:func:`elevation_from_path`, at its own
    azimuth and the azimuth's spread) joined by their variances; unchanged without a path.

    On the held-out walks of ``bench/eval_damage.py --seed 13`` the shape's elevation is 2.6 / 6.4
    deg off (median / p90) and the joined one 1.3 / 5.0; behind a low wall (the legs hidden)
    7.1 / 18.1 and 4.0 / 15.8.
    """
    if cue is None or not (np.isfinite(vp.azimuth_deg) and np.isfinite(vp.elevation_deg)):
        return vp
    cov = np.asarray(vp.covariance, float)
    if not np.all(np.isfinite(cov)) or cov[1, 1] <= 0:
        return vp
    e, se = elevation_from_path(cue, vp.azimuth_deg, float(np.sqrt(max(cov[0, 0], 0.0))))
    if not np.isfinite(e):
        return vp
    w_shape, w_path = 1.0 / cov[1, 1], 1.0 / max(se, 1e-3) ** 2
    var = 1.0 / (w_shape + w_path)
    joined = cov.copy()
    joined[1, 1] = var
    joined[0, 1] = joined[1, 0] = cov[0, 1] * np.sqrt(var / cov[1, 1])
    return replace(vp, elevation_deg=float((w_shape * vp.elevation_deg + w_path * e) * var), covariance=joined,
                   elevation_from="shape+path")


@dataclass(frozen=True)
class Viewpoint:
    """An estimated camera viewpoint (DESIGN.md convention, degrees).

    Attributes
    ----------
    azimuth_deg, elevation_deg : float
        Centre of the fitted ellipse.
    covariance : ndarray of shape (2, 2)
        Covariance of (azimuth, elevation) of the folded cloud, degrees^2.
    spread_deg : float
        Square root of the larger eigenvalue: the ellipse's semi-major axis.
    flip : str
        How the ahead/behind ambiguity was settled: ``"motion"`` (by the motion
        cue), ``"cameras"`` (by the phase the other cameras see, when this
        camera's cue was contested or absent), ``"earlier"`` (the side a fixed
        camera's earlier windows found, :func:`estimator.pipeline.decode_walk`;
        this window alone found its mirror), ``"majority"`` (no motion cue:
        the larger mode) or ``"none"`` (the cloud had one clear mode, or a cue
        too weak to decide).
    flip_margin : float
        ``|w_ahead - w_behind|``: how unevenly the cloud's weight lies on the two
        sides before folding (1 = all on one side).
    n_samples : int
    elevation_from : str
        ``"shape"`` (the matched examples' cloud) or ``"shape+path"`` (joined with
        the walker's image path, :func:`with_path_elevation`).
    """

    azimuth_deg: float
    elevation_deg: float
    covariance: np.ndarray
    spread_deg: float
    flip: str
    flip_margin: float
    n_samples: int
    elevation_from: str = "shape"

    def to_dict(self) -> dict:
        """JSON-able (strict JSON: an undefined viewpoint's numbers are None)."""

        def num(x: float) -> float | None:
            return round(float(x), 3) if np.isfinite(x) else None

        return {
            "azimuth_deg": num(self.azimuth_deg),
            "elevation_deg": num(self.elevation_deg),
            "spread_deg": num(self.spread_deg),
            "covariance_deg2": [[num(v) for v in row] for row in np.asarray(self.covariance)],
            "flip": self.flip,
            "flip_margin": num(self.flip_margin),
            "n_samples": self.n_samples,
            "elevation_from": self.elevation_from,
        }


def circular_mean_deg(a: np.ndarray, w: np.ndarray | None = None) -> float:
    """Weighted mean of angles on the circle (degrees, in [0, 360)); equal weights by default."""
    w = np.ones(np.shape(a)) if w is None else w
    r = np.deg2rad(a)
    return float(np.rad2deg(np.arctan2(np.sum(w * np.sin(r)), np.sum(w * np.cos(r)))) % 360.0)


def estimate_viewpoint(
    azimuth_deg: np.ndarray,
    elevation_deg: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    cue: MotionCue | None = None,
    ahead: bool | None = None,
    fall_min_elevation_deg: float = FALL_MIN_ELEVATION_DEG,
) -> Viewpoint:
    """Fit the viewpoint ellipse to a cloud of example viewpoints.

    Parameters
    ----------
    azimuth_deg, elevation_deg : ndarray of shape (N,)
        Viewpoints of the matched clusters' members over the window.
    weights : ndarray of shape (N,), optional
        Per-sample weights (e.g. 1 / cluster size, or match quality).
    cue : MotionCue, optional
        The walker's motion in this camera's full frame, to settle ahead/behind.
    ahead : bool, optional
        Ahead/behind settled elsewhere (by the other cameras' phase,
        :func:`estimator.pipeline.estimate_walk`): the cloud is folded onto
        the side in front of the walker (``cos(azimuth) > 0``) if True,
        behind it if False, whatever the cue says; ``flip`` is ``"cameras"``.
    fall_min_elevation_deg : float
        Where the cue's growth is no evidence, its feet's path decides
        (:meth:`MotionCue.fall_sign`) if the cloud is at least this far above
        the walker; ``inf`` never.
    """
    az = np.asarray(azimuth_deg, dtype=float) % 360.0
    el = np.asarray(elevation_deg, dtype=float)
    if az.ndim != 1 or az.shape != el.shape or az.size == 0:
        raise ValueError(f"azimuth_deg and elevation_deg must be non-empty (N,) arrays, got {az.shape}, {el.shape}")
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
        raise ValueError("azimuth_deg and elevation_deg must be finite")
    w = np.ones_like(az) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != az.shape or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be non-negative, one per sample, not all zero")
    w = w / w.sum()
    cos_sign, sin_sign = cue.signs() if cue is not None else (0, 0)
    if cos_sign == 0 and cue is not None and float(np.sum(w * el)) >= fall_min_elevation_deg:
        cos_sign = cue.fall_sign()  # the size hardly changes (a walker crossing the view): the feet's path
    r = np.deg2rad(az)
    in_front = np.cos(r) >= 0
    share_ahead = float(w[in_front].sum())
    if ahead is not None:
        side, flip = bool(ahead), "cameras"
    elif cos_sign != 0:
        side, flip = cos_sign > 0, "motion"
    else:
        side, flip = share_ahead >= 0.5, "majority" if cue is None else "none"
    margin = abs(2 * share_ahead - 1)
    # Fold a -> 180 - a onto the chosen side (ahead: cos > 0).
    folded = np.where(in_front == side, az, (180.0 - az) % 360.0)
    if sin_sign != 0:
        # Near-frontal views: the image's travel direction says which side.
        wrong = np.sign(np.sin(np.deg2rad(folded))) == -sin_sign
        near_axis = np.abs(np.sin(np.deg2rad(folded))) < np.sin(np.deg2rad(30))
        folded = np.where(wrong & near_axis, (-folded) % 360.0, folded)
    if flip == "majority" and margin > 0.8:
        flip = "none"
    centre = circular_mean_deg(folded, w)
    d_az = azimuth_difference_deg(folded, centre)
    mean_el = float(np.sum(w * el))
    X = np.stack([d_az, el - mean_el])
    cov = (X * w) @ X.T
    centre = (centre + float(np.sum(w * d_az))) % 360.0
    spread = float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0)))
    return Viewpoint(
        azimuth_deg=centre,
        elevation_deg=mean_el,
        covariance=cov,
        spread_deg=spread,
        flip=flip,
        flip_margin=margin,
        n_samples=int(az.size),
    )
