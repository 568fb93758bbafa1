"""Perspective bundle adjustment of a rig from 2D joint tracks, after the scaled-orthographic one.

Wang–Leow §4 models each camera as scaled orthographic: one scale per camera
(or per frame) and no depth within the body. Real cameras (and posecal's
renders) are pinholes: the walker's image grows as they approach, the near
shoulder is larger than the far one. Even on the *true* 2D joints of
rendered walks (cameras 8-12 m away, 24 deg field of view) the refined
scaled-orthographic self-calibration leaves camera-pair rotations 2.8 deg off
in the median and 7.2 at the 90th percentile. This module starts from its
result and adjusts pinhole cameras: per camera a rotation, a centre and a
focal length (principal point at the image centre), per frame the 13 joints
in metres, with constant bone lengths: Levenberg–Marquardt with the analytic
Jacobian, each step solved by eliminating the frames' joints first (the Schur
complement, :mod:`estimator.bundle`); optionally rounds of Cauchy reweighting
(``PerspectiveConfig.reweight``) for sparse gross errors such as a detector's.
The metric scale comes from the walker's stature (the chain
ankle-knee-hip-shoulder-head of the model's body at ``height_m``).

Choices where nothing constrains them: the focal length has a weak
log-normal prior around its start (``focal_sigma``: a walker 10 m away shows
little perspective, so focal length and distance trade off), the start puts
the walker at the depth where camera 0's start focal length gives the
orthographic scale, and the bone lengths are free per link and shared over
frames. Where the walker shows too little perspective to hold its body's
shape, the upright walker's perpendicularities can hold it, frame by frame
(``PerspectiveConfig.upright``; Wang–Leow's scaled-orthographic adjustment
has them on the frames' means, :data:`estimator.selfcal.UPRIGHT_PRIORS`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial.transform import Rotation

from ._selfcal_core import triangulate
from .selfcal import UPRIGHT_PRIORS, _angle_prior, cosine_gradients
from .bundle import levenberg_marquardt
from .pinhole import PinholeCameras

__all__ = ["KEYPOINT_REWEIGHT", "KEYPOINT_SETTINGS", "KEYPOINT_SMOOTH", "KEYPOINT_UPRIGHT", "UPRIGHT_FRAME_PRIORS", "WEAK_PERSPECTIVE",
           "PerspectiveConfig", "PerspectiveRig", "perspective_refine"]


WEAK_PERSPECTIVE = 0.4
"""Free focal lengths are reported as poorly determined when no camera sees the walker's depth vary by
this share of its distance (:meth:`PerspectiveRig.depth_spread`): 0.6-0.9 at 3 m (focal lengths within
1 %), 0.15 at 15 m (3-12 % off), 0.03-0.04 at 40-60 m (6-32 % off), and 0.21-0.32 on the Pose2Sim demo's
real keypoints (a person balancing in place 3-4.5 m away: 4-13 % off, posterior 1.3-2.3 %; 0.3 until
session 19 let that pass). The posterior alone missed the far cases once the scene's scale was held (1-2 %
for focal lengths 30 % off). Below it the upright walker's priors hold the body's shape, where they are
asked for (:attr:`PerspectiveConfig.upright`; ``posecal selfcal`` does, :data:`KEYPOINT_UPRIGHT`)."""


@dataclass(frozen=True)
class PerspectiveConfig:
    """Settings of :func:`perspective_refine`.

    Attributes
    ----------
    focal_px : float, sequence of float (one per camera), or None
        Known focal length in pixels, the same for every camera (a float) or
        per camera; None: free per camera, started at ``focal_start`` x that
        camera's image width.
    principal_px : sequence of (float, float), or None
        Known principal point per camera, pixels; None: the image centre.
    focal_start : float
        Start of a free focal length, in image widths (1.5: a 37 deg field of view).
    focal_sigma : float
        Standard deviation of the log focal length's prior (free focal only).
    depth_start : {"fixed", "frames"}
        Where the start from the scaled-orthographic rig places the walker
        (:func:`_start`): at one depth from camera 0 in every frame, the
        focal lengths at their start; or at the depth its image size gives
        in each frame, the focal lengths solved with the positions.
    bone_weight : float
        Weight of a bone's change of length against a pixel of reprojection
        (lengths are in camera 0's pixels at the walker).
    max_nfev : int
        At most this many evaluations of the residuals (Levenberg–Marquardt
        steps tried, :func:`estimator.bundle.levenberg_marquardt`), per round.
        Most adjustments converge in 20-40; one walk of the evaluation on
        exact joints needed 94 (at 60 it stopped 2.8 deg off, at 94 0.4).
    reweight, robust_scale : int, float
        Rounds of iteratively reweighted least squares after the first
        adjustment: each joint's residual weighted by Cauchy's
        ``1 / sqrt(1 + (d / (robust_scale sigma))^2)``, ``d`` its reprojection
        distance, ``sigma`` the noise read from their median (a 2D Gaussian's
        median distance is 1.1774 sigma). For a detector's keypoints, whose
        gross errors are sparse (``posecal selfcal`` uses 2 rounds). Off (0)
        for mNBP postures: their errors are systematic, not sparse, and 2
        rounds took the tuning walks' rotations from 2.46 / 5.98 deg to
        2.52 / 6.40 (CMU) and from 3.79 / 9.02 to 4.83 / 9.86 (stylised).
    upright, upright_spread : float
        Strength of the upright walker's perpendicularities in every frame
        (:data:`UPRIGHT_FRAME_PRIORS`; 0: off), used when the first adjustment
        finds that no camera sees the walker's depth vary by ``upright_spread``
        of its distance (:meth:`PerspectiveRig.depth_spread`: a walker 15 m
        away, or a person nearly still 3-4.5 m away; not a walk 3 m away):
        each frame's ``cos`` of each pair's angle then becomes a residual
        weighted ``upright * sigma / tol`` (``sigma`` the pixel noise, from the
        median reprojection distance as 2D Gaussian), in the reweighting
        rounds, or in one more adjustment when there are none. (The depth
        spread is read from the first adjustment; the result's
        :meth:`PerspectiveRig.depth_spread`, from the last, can fall on the
        other side of the threshold.) The scaled-orthographic adjustment has
        the same priors on the frames' means; here they hold the body's shape
        where the perspective is too weak to (docs/SELFCAL.md, "15 m").
    smooth : float
        Strength of the walker's smooth motion over frames (0: off): in each
        camera, the acceleration of each joint's *predicted* image track (its
        projection's second difference over three frames in a row) is a
        residual weighted ``smooth * sigma / a_cj``, ``a_cj`` that camera's and
        joint's acceleration as the tracks show it with the noise taken off
        (:func:`_acceleration_power`), ``sigma`` the pixel noise: the MAP prior
        of a motion whose accelerations have that spread, measured, not
        assumed, so the frame rate and the joint (an ankle accelerates more
        than the neck) set it. On the image tracks, as the scaled-orthographic
        adjustment's temporal prior (:func:`estimator.selfcal._temporal_prior`),
        not on the 3D joints: there it pulled two-camera rigs 11-26 deg (a rig
        that flattens the noise in depth makes a smoother walk). In the
        reweighting rounds, or in one more adjustment when there are none;
        only across frames one step apart (``frame_times``); exact tracks
        (``sigma`` at its floor) are left as they are. ``posecal selfcal`` uses
        :data:`KEYPOINT_SMOOTH`.
    """

    focal_px: float | tuple[float, ...] | None = None
    principal_px: tuple[tuple[float, float], ...] | None = None
    focal_start: float = 1.5
    focal_sigma: float = 0.5
    depth_start: Literal["fixed", "frames"] = "fixed"
    bone_weight: float = 1.0
    max_nfev: int = 100
    reweight: int = 0
    robust_scale: float = 2.5
    upright: float = 0.0
    upright_spread: float = WEAK_PERSPECTIVE
    smooth: float = 0.0


UPRIGHT_FRAME_PRIORS = tuple((a, b, 3.0) for a, b, _ in UPRIGHT_PRIORS)
"""The upright walker's perpendicularities (:data:`estimator.selfcal.UPRIGHT_PRIORS`) in each frame,
each within 3 deg: the per-frame angles of the CMU walks are 90.1 +- 3.1, 88.3 +- 0.7 and 91.0 +- 3.2
deg (16_15; 07_05: 91.0 +- 2.9, 88.1 +- 1.0, 89.0 +- 1.6)."""


@dataclass
class PerspectiveRig:
    """Pinhole cameras in camera 0's frame (x right, y down, z forward), metres.

    Attributes
    ----------
    rotations : ndarray of shape (C, 3, 3)
        World-to-camera rotations; ``rotations[0]`` is the identity, so they are
        also ``R_c R_0^T``.
    centres : ndarray of shape (C, 3)
        Camera centres; ``centres[0]`` is the origin.
    focal_px : ndarray of shape (C,)
    joints3d : ndarray of shape (T, 13, 3)
        The walker's joints per frame (not centred: the walk is in it).
    rmse_px : float
        Root mean square reprojection error over the observed joints.
    scales : ndarray of shape (C,)
        Each camera's pixels per unit at the walker (focal length over the
        walker's mean depth) relative to camera 0's.
    focal_log_std : ndarray of shape (C,) or None
        Posterior standard deviation of each free focal length's logarithm
        (about its relative error; Laplace approximation at the optimum, image
        noise = the rms of the reprojection residuals as weighted, the focal prior included); None
        when the focal lengths were given.
    principal_px : ndarray of shape (C, 2) or None
        The principal points the cameras were adjusted with.
    median_px : float
        Median reprojection distance over the observed joints: unlike
        ``rmse_px``, blind to the few gross errors reweighting set aside.
    upright : bool
        The upright walker's per-frame priors were used (:attr:`PerspectiveConfig.upright`: the
        perspective was weak).
    cost : float
        The adjustment's objective where it ended: half the sum of its squared residuals (pixels as
        weighted, bone lengths, priors), to compare the ends of two starts on the same data and
        settings (NaN when not adjusted).
    """

    rotations: np.ndarray
    centres: np.ndarray
    focal_px: np.ndarray
    joints3d: np.ndarray
    rmse_px: float
    scales: np.ndarray
    focal_log_std: np.ndarray | None = None
    principal_px: np.ndarray | None = None
    median_px: float = float("nan")
    upright: bool = False
    cost: float = float("nan")

    def depth_spread(self) -> np.ndarray:
        """Per camera, how far the joints' depths spread over the walk (5th to 95th percentile) over
        their median: the perspective the tracks show, without which focal length and distance
        trade off (about 0.8 for a walk 3 m away, 0.2 at 15 m, 0.04 at 60 m)."""
        return _depth_spread(self.rotations, self.centres, self.joints3d)

    def cameras(self, scale: float = 1.0) -> PinholeCameras:
        """These cameras as matrices (:class:`estimator.pinhole.PinholeCameras`), their centres
        times ``scale`` (e.g. metres per unit)."""
        return PinholeCameras.from_centres(self.focal_px, self.principal_px, self.rotations, self.centres * scale)


def _depth_spread(rotations: np.ndarray, centres: np.ndarray, joints3d: np.ndarray) -> np.ndarray:
    """:meth:`PerspectiveRig.depth_spread` of these cameras and joints."""
    x = joints3d.reshape(-1, 3)
    z = np.einsum("ca,nca->cn", rotations[:, 2], x[:, None, :] - centres[None])
    lo, mid, hi = np.nanpercentile(np.where(np.isfinite(z), z, np.nan), [5, 50, 95], axis=1)
    return (hi - lo) / mid


def _project(x: np.ndarray, rotvec: np.ndarray, centre: np.ndarray, focal: np.ndarray,
             principal: np.ndarray) -> np.ndarray:
    """Pixels (C, T, J, 2) of joints ``x`` (T, J, 3) through C pinhole cameras."""
    r = Rotation.from_rotvec(rotvec).as_matrix()  # (C, 3, 3)
    cam = np.einsum("cab,tjb->ctja", r, x) - np.einsum("cab,cb->ca", r, centre)[:, None, None, :]
    z = np.maximum(cam[..., 2:3], 1e-6)
    return focal[:, None, None, None] * cam[..., :2] / z + principal[:, None, None, :]


def perspective_refine(tracks: np.ndarray, image_sizes: np.ndarray, rotations: np.ndarray, scales: np.ndarray,
                       links: list[tuple[int, int]], *, config: PerspectiveConfig = PerspectiveConfig(),
                       initial: PerspectiveRig | None = None, weights: np.ndarray | None = None,
                       rotation_prior: tuple[np.ndarray, float | np.ndarray] | None = None,
                       frame_times: np.ndarray | None = None) -> PerspectiveRig:
    """Adjust pinhole cameras and 3D joints to 2D joint tracks, from a scaled-orthographic rig.

    Parameters
    ----------
    tracks : ndarray of shape (C, T, 13, 2)
        Full-frame pixels, NaN where missing.
    image_sizes : ndarray of shape (C, 2)
        (width, height) per camera: the principal point is the image centre
        unless ``config.principal_px`` gives it.
    rotations, scales : ndarray of shape (C, 3, 3), (C,)
        The scaled-orthographic result (``R_c R_0^T`` and relative scales);
        not used (may be None) when ``initial`` is given.
    links : list of (int, int)
        Joint pairs of constant length.
    initial : PerspectiveRig, optional
        Start from these pinhole cameras and joints (a previous round's
        result) instead of from the scaled-orthographic rig; the focal
        lengths' prior stays centred where ``config`` puts it.
    weights : ndarray of shape (C, T, 13), optional
        Each observation's reprojection residual is multiplied by this
        (e.g. a detector's confidence); default 1.
    rotation_prior : (ndarray of shape (C, 3, 3), float or ndarray of shape (C,)), optional
        Rotations ``R_c R_0^T`` known roughly and a weight (one, or per camera):
        a camera's turn away from its prior (rotation vector, radians) times
        its weight is a residual beside the pixels (pixels per radian).
    frame_times : ndarray of shape (T,), optional
        When each frame was taken (frame numbers, not jittered timestamps:
        gaps are matched to the commonest one), for ``config.smooth``: its
        prior joins only three frames in a row at the recording's commonest
        step (a gap in the frames breaks the chain there). Default: evenly spaced.
    """
    y = np.asarray(tracks, float)
    n_cam, t, j, _ = y.shape
    principal = _per_camera(config.principal_px, (n_cam, 2), "principal_px", np.asarray(image_sizes, float) / 2.0)
    observed = np.all(np.isfinite(y), axis=-1)
    f0 = _per_camera(config.focal_px, (n_cam,), "focal_px",
                     config.focal_start * np.asarray(image_sizes, float)[:, 0])
    if initial is not None:
        rotations, centres, x0, focal = initial.rotations, initial.centres, initial.joints3d, initial.focal_px
    else:
        centres, x0, focal = _start(y, observed, rotations, scales, f0, principal, config.depth_start)
    ln = np.asarray(links, int).reshape(-1, 2)
    lengths0 = np.nanmedian(np.linalg.norm(x0[:, ln[:, 0]] - x0[:, ln[:, 1]], axis=-1), axis=0)
    scale0 = float(np.nanmean(lengths0)) if len(ln) else 1.0
    free_focal = config.focal_px is None
    rv0 = Rotation.from_matrix(rotations[1:]).as_rotvec()
    p0 = np.concatenate([rv0.ravel(), centres[1:].ravel(), np.log(focal) if free_focal else [], x0.ravel(),
                         lengths0])
    n_r, n_c, n_f = 3 * (n_cam - 1), 3 * (n_cam - 1), n_cam if free_focal else 0
    o_c, o_f, o_x = n_r, n_r + n_c, n_r + n_c + n_f
    o_l = o_x + 3 * t * j
    obs_c, obs_t, obs_j = np.nonzero(observed)
    y_obs = y[obs_c, obs_t, obs_j]
    w_obs = np.ones(len(obs_c)) if weights is None else \
        np.broadcast_to(np.asarray(weights, float), y.shape[:3])[obs_c, obs_t, obs_j]
    w_obs = np.repeat(w_obs, 2)  # per residual: u and v
    bone_w = config.bone_weight  # a unit is a pixel of camera 0 at the walker
    if rotation_prior is not None:
        prior_rot = np.asarray(rotation_prior[0], float)[1:]
        prior_w = np.broadcast_to(np.asarray(rotation_prior[1], float), (n_cam,))[1:, None]
    a_up, b_up, per_tol = _angle_prior(UPRIGHT_FRAME_PRIORS, 1.0)  # per_tol: 1 / tolerance (radians)
    n_up = t * len(per_tol) if config.upright > 0 else 0
    up_w = np.zeros(len(per_tol))  # set once the first adjustment has read the noise
    if frame_times is not None and np.shape(frame_times) != (t,):
        raise ValueError(f"frame_times must give one time per frame ({t}), got shape {np.shape(frame_times)}")
    mids = _evenly_timed(np.arange(t) if frame_times is None else frame_times) if config.smooth > 0 else []
    n_sm = 2 * n_cam * len(mids) * j
    sm_w = np.zeros((n_cam, j))  # per camera and joint, set once the first adjustment has read the noise

    def _upright_cosines(x):
        return cosine_gradients(np.einsum("kj,tjd->tkd", a_up, x), np.einsum("kj,tjd->tkd", b_up, x))

    def unpack(p):
        rv = np.concatenate([np.zeros((1, 3)), p[:o_c].reshape(-1, 3)])
        ce = np.concatenate([np.zeros((1, 3)), p[o_c:o_f].reshape(-1, 3)])
        fo = np.exp(p[o_f:o_x]) if free_focal else f0
        return rv, ce, fo, p[o_x:o_l].reshape(t, j, 3), p[o_l:]

    def gap(rv, ce, fo, x):
        """Reprojection error (N, 2) of each observed joint, unweighted."""
        return _project(x, rv, ce, fo, principal)[obs_c, obs_t, obs_j] - y_obs

    def residuals(p):
        rv, ce, fo, x, lk = unpack(p)
        res = [w_obs * gap(rv, ce, fo, x).ravel()]
        if len(ln):
            res.append(bone_w * (np.linalg.norm(x[:, ln[:, 0]] - x[:, ln[:, 1]], axis=-1) - lk).ravel())
        if free_focal:
            res.append((np.log(fo) - np.log(f0)) / config.focal_sigma)
        if rotation_prior is not None:
            res.append((prior_w * _rotation_gap(rv[1:], prior_rot)).ravel())
        if len(ln):
            res.append([GAUGE_WEIGHT * (lk.mean() / scale0 - 1.0)])
        if n_up:
            res.append((up_w * _upright_cosines(x)[0]).ravel())
        if n_sm:
            uv = _project(x, rv, ce, fo, principal)  # (C, T, J, 2)
            res.append((sm_w[:, None, :, None] * (uv[:, mids - 1] - 2.0 * uv[:, mids] + uv[:, mids + 1])).ravel())
        return np.concatenate(res)

    n_obs = len(obs_c)
    grid = [a.ravel() for a in np.meshgrid(np.arange(n_cam), np.arange(t), np.arange(j), indexing="ij")]
    obs_flat = (obs_c * t + obs_t) * j + obs_j

    def projection_entries(at, first_row):
        """Rows and columns of the projection's derivatives (:func:`_projection_derivatives`) at grid
        indices ``at`` (camera, frame, joint), residual rows ``first_row + 2 i`` (u) and ``+ 1`` (v), in
        the order ``projected`` gives their values."""
        cc, tt, jj = (g[at] for g in grid)
        rows = first_row + 2 * np.arange(len(at))[:, None] + np.arange(2)  # (N, 2) u then v
        moved = cc > 0  # camera 0 is the frame: no rotation or centre of its own
        cam_cols = 3 * (cc[moved] - 1)[:, None, None] + np.zeros((1, 2, 1), int) + np.arange(3)
        cam_rows = np.repeat(rows[moved].ravel(), 3)  # the rotation's and the centre's
        return ([np.repeat(rows.ravel(), 3), *([rows.ravel()] if free_focal else []), cam_rows, cam_rows],
                [(o_x + 3 * (tt * j + jj))[:, None, None] + np.zeros((1, 2, 1), int) + np.arange(3),
                 *([o_f + cc[:, None] + np.zeros((1, 2), int)] if free_focal else []), cam_cols, o_c + cam_cols])

    jac_rows, jac_cols = projection_entries(obs_flat, 0)
    tt, kk = np.divmod(np.arange(t * len(ln)), max(len(ln), 1))
    bone_rows = 2 * n_obs + np.arange(t * len(ln))
    if len(ln):
        jac_rows += [np.repeat(bone_rows, 3)] * 2 + [bone_rows]
        jac_cols += [o_x + 3 * (tt * j + ln[kk, 0])[:, None] + np.arange(3),
                     o_x + 3 * (tt * j + ln[kk, 1])[:, None] + np.arange(3), o_l + kk]
    n_res = 2 * n_obs + t * len(ln)
    if free_focal:
        jac_rows.append(n_res + np.arange(n_cam))
        jac_cols.append(o_f + np.arange(n_cam))
        n_res += n_cam
    if rotation_prior is not None:
        jac_rows.append(np.repeat(n_res + np.arange(n_r), 3))
        jac_cols.append(np.repeat(np.arange(n_r).reshape(-1, 3), 3, axis=0))
        n_res += n_r
    if len(ln):
        jac_rows.append(np.full(len(ln), n_res))
        jac_cols.append(o_l + np.arange(len(ln)))
        n_res += 1
    if n_up:  # frame t's prior k touches that frame's joints in either vector
        kk_up, jj_up = np.nonzero((a_up != 0) | (b_up != 0))
        tt_up = np.repeat(np.arange(t), len(kk_up))
        jac_rows.append(np.repeat(n_res + tt_up * len(per_tol) + np.tile(kk_up, t), 3))
        jac_cols.append((o_x + 3 * (tt_up * j + np.tile(jj_up, t)))[:, None] + np.arange(3))
        n_res += n_up
    if n_sm:  # camera c's image of joint j at frame t accelerates with frames t - 1, t and t + 1
        sm_c, sm_m, sm_j = (a.ravel() for a in np.meshgrid(np.arange(n_cam), np.arange(len(mids)), np.arange(j),
                                                           indexing="ij"))
        sm_at = [(sm_c * t + mids[sm_m] + k) * j + sm_j for k in (-1, 0, 1)]
        for at in sm_at:
            rows, cols = projection_entries(at, n_res)
            jac_rows += rows
            jac_cols += cols
        n_res += n_sm
    jac_rows = np.concatenate(jac_rows)
    jac_cols = np.concatenate([c.ravel() for c in jac_cols])
    shape = (n_res, o_l + len(ln))

    def jacobian(p):
        """Analytic Jacobian of :func:`residuals` (sparse): the chain rule through the projection,
        d R(r) q / d r = -[R q]x J_l(r) for the rotation vector r (J_l: SO(3)'s left Jacobian)."""
        rv, ce, fo, x, lk = unpack(p)
        rot = Rotation.from_rotvec(rv).as_matrix()
        deriv = _projection_derivatives(rot, rv, ce, fo, x, *grid)  # every camera, frame and joint

        def projected(at, scale):
            """The projection's derivatives at grid indices ``at``, times ``scale``, as
            ``projection_entries`` places them."""
            d_x, d_f, d_rot = (d[at] * scale.reshape(-1, *([1] * (d.ndim - 1))) for d in deriv)
            moved = grid[0][at] > 0
            return [d_x.ravel(), *([d_f.ravel()] if free_focal else []), d_rot[moved].ravel(), -d_x[moved].ravel()]

        vals = projected(obs_flat, w_obs[::2])
        if len(ln):
            d = x[:, ln[:, 0]] - x[:, ln[:, 1]]
            unit = bone_w * d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
            vals += [unit.ravel(), -unit.ravel(), np.full(t * len(ln), -bone_w)]
        if free_focal:
            vals.append(np.full(n_cam, 1.0 / config.focal_sigma))
        if rotation_prior is not None:
            gap = _rotation_gap(rv[1:], prior_rot)
            vals.append((prior_w[..., None] * np.linalg.inv(_left_jacobian(gap)) @ _left_jacobian(rv[1:])).ravel())
        if len(ln):
            vals.append(np.full(len(ln), GAUGE_WEIGHT / (len(ln) * scale0)))
        if n_up:
            _, ga, gb = _upright_cosines(x)  # (T, K, 3) each
            vals.append((up_w[kk_up, None] * (a_up[kk_up, jj_up, None] * ga[:, kk_up]
                                              + b_up[kk_up, jj_up, None] * gb[:, kk_up])).ravel())
        if n_sm:
            for at, coef in zip(sm_at, (1.0, -2.0, 1.0)):
                vals += projected(at, coef * sm_w[sm_c, sm_j])
        return scipy.sparse.csr_matrix((np.concatenate(vals), (jac_rows, jac_cols)), shape=shape)

    sol = levenberg_marquardt(residuals, jacobian, p0, block_start=o_x, block_size=3 * j, n_blocks=t,
                              max_nfev=config.max_nfev)
    base = w_obs.copy()
    upright = False
    if n_up:  # only where the perspective is weak
        rv, ce, _, x, _ = unpack(sol.x)
        upright = np.nanmax(_depth_spread(Rotation.from_rotvec(rv).as_matrix(), ce, x)) < config.upright_spread
    for k in range(max(config.reweight, 1 if upright or n_sm else 0)):
        dist = np.linalg.norm(gap(*unpack(sol.x)[:4]), axis=-1)
        noise = max(np.median(dist) / 1.1774, 1e-6)  # 2D Gaussian: median 1.1774 sigma
        if k < config.reweight:
            w_obs[:] = base * np.repeat(1.0 / np.sqrt(1.0 + (dist / (config.robust_scale * noise)) ** 2), 2)  # Cauchy
        if upright:
            up_w[:] = config.upright * noise * per_tol
        if n_sm:
            power = _acceleration_power(y, mids, noise)
            ok = np.isfinite(power) & (power > 0)
            sm_w[:] = np.where(ok, config.smooth * noise / np.sqrt(np.where(ok, power, 1.0)), 0.0)
        sol = levenberg_marquardt(residuals, jacobian, sol.x, block_start=o_x, block_size=3 * j, n_blocks=t,
                                  max_nfev=config.max_nfev)
    rv, ce, fo, x, _ = unpack(sol.x)
    dist = np.linalg.norm(gap(rv, ce, fo, x), axis=-1)  # reprojection, unweighted
    rmse, median = float(np.sqrt(np.mean(dist**2))), float(np.median(dist))
    rots = Rotation.from_rotvec(rv).as_matrix()
    depth = np.einsum("ca,ca->c", rots[:, 2], x.reshape(-1, 3).mean(axis=0)[None] - ce)  # walker's mean depth
    size = fo / depth
    sigma = float(np.sqrt(np.mean(sol.fun[:y_obs.size] ** 2)))  # per coordinate, as weighted in the Jacobian
    # The posterior from the pixels and the focal prior: the bone and scale rows are constraints whose
    # weights are not a noise level (with them it said 1-2 % for focal lengths 30-160 % off at 60 m).
    data = np.concatenate([np.arange(y_obs.size), 2 * n_obs + t * len(ln) + np.arange(n_f)])
    log_std = _focal_log_std(sol.jac[data], sigma, o_f, n_f) if free_focal else None
    return PerspectiveRig(rots, ce, fo, x, rmse, size / size[0], log_std, principal, median, bool(upright),
                          sol.cost)


KEYPOINT_REWEIGHT = 2
"""Rounds of Cauchy reweighting (:attr:`PerspectiveConfig.reweight`) for a pose detector's keypoints
(``posecal selfcal``, :meth:`estimator.rig.RigConfig.for_keypoints`): their gross errors are sparse (a
joint on the wrong limb); on the issue's noise (1-3 % of the walker's height, 5 % outliers, 2 % swaps;
10 rigs 2.5-4 m away) two rounds took the camera pairs from 0.99 / 3.30 deg (median / p90) to 0.59 /
2.61, at 15 m from 3.4 / 12.8 to 1.5 / 8.1 (docs/SELFCAL.md)."""


KEYPOINT_UPRIGHT = 1.0
"""Strength of the upright walker's per-frame priors (:attr:`PerspectiveConfig.upright`) for a pose
detector's keypoints (``posecal selfcal``, and :meth:`estimator.rig.RigConfig.for_keypoints` since session
26), used where the perspective is weak: on the issue's noise at 15 m
(20 rigs of seed 4, not used to choose) the camera pairs went from 1.41 / 6.20 deg (median / p90) to 1.07 /
3.96; a walk 2.5-4 m away is not held by them (docs/SELFCAL.md, "15 m"). Not for mNBP's postures, whose
errors are systematic (the rig from silhouettes lost with them: docs/POSTURE.md)."""


KEYPOINT_SMOOTH = 1.0
"""Strength of the walker's smooth motion (:attr:`PerspectiveConfig.smooth`) for a pose detector's keypoints
(``posecal selfcal``, :meth:`estimator.rig.RigConfig.for_keypoints`): a detector's errors are independent
from frame to frame, a walker's joints are not (docs/SELFCAL.md, "A walker moves smoothly")."""


KEYPOINT_SETTINGS = {"reweight": KEYPOINT_REWEIGHT, "upright": KEYPOINT_UPRIGHT, "smooth": KEYPOINT_SMOOTH}
"""The :class:`PerspectiveConfig` fields for a pose detector's keypoints, one place for ``posecal selfcal``
and :meth:`estimator.rig.RigConfig.for_keypoints`."""


GAUGE_WEIGHT = 1e4
"""Weight of the residual that holds the mean bone length at its start. Scaling the joints, the
centres and the bone lengths together leaves every reprojection unchanged (camera 0 at the origin),
but shrinks the bone residuals: unpinned, the exact solver let the whole scene shrink towards zero
(from about 960 units to 0.18 on a test walk) and the bone constraint faded with it."""


def _projection_derivatives(rot: np.ndarray, rotvec: np.ndarray, centres: np.ndarray, focal: np.ndarray,
                            x: np.ndarray, cc: np.ndarray, tt: np.ndarray, jj: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Derivatives of the pixels of joint ``jj`` at frame ``tt`` in camera ``cc`` (N each): by the
    joint (N, 2, 3), by the log focal length (N, 2), by the camera's rotation vector (N, 2, 3; by its
    centre: minus the first). d R(r) q / d r = -[R q]x J_l(r)."""
    cam = np.einsum("nab,nb->na", rot[cc], x[tt, jj] - centres[cc])  # (N, 3)
    z = np.maximum(cam[:, 2], 1e-6)
    g = (focal[cc] / z)[:, None]
    d_cam = np.zeros((len(cc), 2, 3))  # d (u, v) / d camera coordinates
    d_cam[:, 0, 0] = d_cam[:, 1, 1] = g[:, 0]
    d_cam[:, :, 2] = -g * cam[:, :2] / z[:, None]
    return d_cam @ rot[cc], g * cam[:, :2], -d_cam @ _hat(cam) @ _left_jacobian(rotvec)[cc]


def _evenly_timed(times: np.ndarray) -> np.ndarray:
    """Indices of the frames whose neighbours on both sides are one step away, the step being the
    commonest between the frames ``times`` (T,)."""
    gaps = np.diff(np.asarray(times, float))
    if len(gaps) < 2:
        return np.zeros(0, int)
    values, counts = np.unique(gaps[gaps > 0], return_counts=True)
    if not len(values):
        return np.zeros(0, int)
    even = np.isclose(gaps, values[np.argmax(counts)])
    return np.flatnonzero(even[:-1] & even[1:]) + 1


def _acceleration_power(tracks: np.ndarray, mids: np.ndarray, noise_px: float) -> np.ndarray:
    """Each camera's and joint's mean squared acceleration (C, J), pixels squared per coordinate: the
    tracks' (C, T, J, 2) second differences over the frames ``mids`` and their neighbours, the noise's
    share taken off.

    A second difference of a track carries ``6 noise^2`` of independent noise per coordinate; what is
    above is the motion's. Robust to sparse gross errors: the median of the squares over frames and
    coordinates, read as a Gaussian's (median of chi-square(1) = 0.455). Floored at the standard error
    of the measured power, so that a joint whose motion drowns in the noise (a detector's 1-3 % of the
    walker's height: most joints) is held, not frozen."""
    d2 = tracks[:, mids - 1] - 2.0 * tracks[:, mids] + tracks[:, mids + 1]  # (C, M, J, 2) pixels
    samples = np.sum(np.isfinite(d2[..., 0]), axis=1) * 2  # per camera and joint
    with warnings.catch_warnings():  # a joint a camera never saw in three frames in a row: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        power = np.nanmedian(np.moveaxis(d2, 2, 1).reshape(*samples.shape, -1) ** 2, axis=-1) / 0.455
        return np.maximum(power - 6.0 * noise_px**2, power * np.sqrt(2.0 / np.maximum(samples, 1)))


def _per_camera(value, shape: tuple[int, ...], name: str, default: np.ndarray | None) -> np.ndarray | None:
    """A setting given for every camera at once or per camera, as an array of ``shape``."""
    if value is None:
        return default
    try:
        out = np.broadcast_to(np.asarray(value, float), shape).copy()
    except ValueError:
        raise ValueError(f"{name} must be one value or one per camera ({shape[0]}), got {value!r}") from None
    if not np.all(np.isfinite(out)) or (name == "focal_px" and not np.all(out > 0)):
        raise ValueError(f"{name} must be finite{' and positive' if name == 'focal_px' else ''}, got {value!r}")
    return out


def _focal_log_std(jac, sigma_px: float, start: int, n: int) -> np.ndarray:
    """Posterior standard deviation of the ``n`` log focal lengths at ``start`` (Laplace approximation:
    covariance ``sigma^2 (J^T J)^-1`` of the reprojection residuals, in pixels; the focal prior's rows are
    in the same units, so ``sigma`` scales them too, which keeps the estimate conservative)."""
    h = scipy.sparse.csc_matrix(jac.T @ jac)
    h = h + scipy.sparse.identity(h.shape[0], format="csc") * (1e-12 * h.diagonal().max())
    rhs = np.zeros((h.shape[0], n))
    rhs[start + np.arange(n), np.arange(n)] = 1.0
    cov = scipy.sparse.linalg.splu(h).solve(rhs)[start:start + n]
    return sigma_px * np.sqrt(np.clip(np.diag(cov), 0.0, None))


def _start(y: np.ndarray, observed: np.ndarray, rotations: np.ndarray, scales: np.ndarray, f0: np.ndarray,
           principal: np.ndarray, depth: str = "fixed") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera centres (C, 3), joints (T, J, 3) and focal lengths (C,) from the scaled-orthographic rig.

    ``depth="fixed"``: each camera's pixels per unit ``s_c`` (camera 0: 1), the walker at depth
    ``f_0`` in camera 0 in every frame (1 unit = 1 pixel of camera 0 at the walker), centred
    where camera 0 sees its centroid; the focal lengths ``f0``. ``depth="frames"``: each frame
    seen through weak-perspective cameras, camera c showing frame t's walker at ``s_ct`` pixels
    per unit (:func:`_magnification`), so at depth ``f_c / s_ct``; given the rotations, the
    walker's positions, the centres and the focal lengths solve one linear least-squares problem
    (:func:`_weak_perspective_positions`): a walker who nears and recedes tells the focal
    lengths (1 unit = 1 pixel of camera 0 at the walker's median depth)."""
    if depth not in ("fixed", "frames"):
        raise ValueError(f"depth_start must be 'fixed' or 'frames', got {depth!r}")
    n_cam, t = y.shape[:2]
    count = observed.sum(axis=2)[..., None]  # (C, T, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        centroid = np.where(observed[..., None], y, 0.0).sum(axis=2) / count  # (C, T, 2), NaN where none
    filled = np.where(np.isfinite(centroid), centroid, np.nanmean(centroid, axis=1, keepdims=True))
    rel = rotations @ rotations[0].T
    if depth == "frames":
        s = _magnification(y, observed)  # (C, T)
        body = triangulate(y, observed, rel, s, filled)  # (T, J, 3) about each frame's centroid
        where, centres, focal = _weak_perspective_positions(filled - principal[:, None], s, rel,
                                                            observed.sum(axis=2) >= _MIN_JOINTS, f0)
        return centres, where[:, None, :] + body, focal
    ray0 = np.concatenate([(filled[0] - principal[0]) / f0[0], np.ones((t, 1))], axis=1) * f0[0]  # (T, 3)
    # The body about its centroid through the scaled-orthographic cameras, placed on camera 0's ray.
    x0 = ray0[:, None, :] + triangulate(y, observed, rel, scales, filled)
    walker = x0.reshape(-1, 3).mean(axis=0)
    centres = np.zeros((n_cam, 3))
    for c in range(1, n_cam):
        d = f0[c] / scales[c]  # depth at which camera c sees 1 unit as s_c pixels
        p_cam = np.append((np.nanmean(filled[c], axis=0) - principal[c]) / f0[c], 1.0) * d
        centres[c] = walker - rotations[c].T @ p_cam
    return centres, x0, f0


_MIN_JOINTS = 4  # joints a camera-frame shows for its walker's size and place to count in the per-frame start


def _magnification(y: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(C, T) each camera-frame's rms vertical spread of the joints about their centroid over camera
    0's median: pixels per unit of an upright walker, whatever the view (the median where fewer
    than ``_MIN_JOINTS`` joints are seen)."""
    v = np.where(observed, y[..., 1], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames or cameras with nothing seen
        spread = np.sqrt(np.nanmean((v - np.nanmean(v, axis=2, keepdims=True)) ** 2, axis=2))
        spread = np.where(observed.sum(axis=2) >= _MIN_JOINTS, spread, np.nan)
        m = spread / np.nanmedian(spread[0])
        m = np.where(np.isfinite(m) & (m > 0), m, np.nanmedian(m, axis=1, keepdims=True))
    return np.where(np.isfinite(m), m, 1.0)


_FOCAL_HOLD = 1e-2  # weight of a focal length's start (per pixel) where the walk does not determine it


def _weak_perspective_positions(offsets: np.ndarray, s: np.ndarray, rotations: np.ndarray, seen: np.ndarray,
                                f0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The walker's positions (T, 3), camera centres (C, 3; camera 0 at the origin) and focal
    lengths (C,) that place each frame as every camera sees it: camera c at frame t, the walker's
    image ``offsets[c, t]`` (pixels from the principal point) at ``s[c, t]`` pixels per unit, says
    ``W_t = C_c + R_c^T ((u, v) / s, f_c / s)`` -- linear in W, C and f. ``seen`` (C, T): the
    camera-frames that count. Each focal length is held weakly at ``f0`` (``_FOCAL_HOLD``) for a
    walk that does not determine it; where one falls outside 0.2-33 times ``f0`` (0.3-50 image
    widths from the default start) all are held at ``f0`` and the rest solved again."""
    n_cam, t = s.shape
    n_w, n_c = 3 * t, 3 * (n_cam - 1)
    cc, tt = np.nonzero(seen)
    rt = np.swapaxes(rotations, 1, 2)[cc]  # (N, 3, 3): R_c^T
    a = np.zeros((len(cc), 3, n_w + n_c + n_cam))
    a[np.arange(len(cc))[:, None], np.arange(3), 3 * tt[:, None] + np.arange(3)] = 1.0
    moved = cc > 0
    a[np.flatnonzero(moved)[:, None], np.arange(3), n_w + 3 * (cc[moved] - 1)[:, None] + np.arange(3)] = -1.0
    a[np.arange(len(cc)), :, n_w + n_c + cc] = -rt[:, :, 2] / s[cc, tt][:, None]
    b = np.einsum("nab,nb->na", rt[:, :, :2], offsets[cc, tt] / s[cc, tt][:, None]).ravel()
    rows = a.reshape(-1, a.shape[2])
    hold = np.zeros((n_cam, a.shape[2]))
    hold[np.arange(n_cam), n_w + n_c + np.arange(n_cam)] = 1.0

    def solve(weight: float) -> np.ndarray:
        """The least-squares solution with each focal length held at ``f0`` by ``weight`` per pixel."""
        return np.linalg.lstsq(np.concatenate([rows, weight * hold]), np.concatenate([b, weight * f0]),
                               rcond=None)[0]

    sol = solve(_FOCAL_HOLD)
    focal = sol[n_w + n_c:]
    ok = np.isfinite(focal) & (focal > 0.2 * f0) & (focal < 33.0 * f0)
    if not ok.all():
        focal = f0
        sol = solve(1.0)
    where = sol[:n_w].reshape(t, 3)
    where[~seen.any(axis=0)] = np.nanmean(where[seen.any(axis=0)], axis=0)
    centres = np.concatenate([np.zeros((1, 3)), sol[n_w:n_w + n_c].reshape(-1, 3)])
    return where, centres, np.asarray(focal, float)


def _rotation_gap(rotvec: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Rotation vectors (C, 3) of ``R(rotvec) rotations^T``: how far each camera turned from a prior."""
    return (Rotation.from_rotvec(rotvec) * Rotation.from_matrix(rotations).inv()).as_rotvec()


def _hat(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x of vectors (..., 3)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return out - np.swapaxes(out, -1, -2)


def _left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian J_l(r) (..., 3, 3): R(r + d) = R(J_l(r) d) R(r) to first order."""
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = _hat(rotvec)
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + a * k + b * (k @ k)
